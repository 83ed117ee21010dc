"""Part (i): what transport security and identity cost — mTLS plus a bearer token, against plaintext.

Two gateway processes serve the same bench service, one in plaintext and one with
mutual TLS, ``[auth]`` (an HS256 secret file: every call's token is checked) and one
permitting rule (every call is decided); the same client code drives both, unary Gets
with several in flight and Gets over one Session, round after round, taking turns.
Certificates and the secret are made afresh in a temporary folder for each run.
"""

from __future__ import annotations

import datetime
import ipaddress
import tempfile
import time
from pathlib import Path
from typing import Any

import grpc
import jwt
from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import NameOID

from bench.servers import Metadata, ServerProcess
from bench.session import run_session
from bench.unary import run_unary

#: The subject of the client certificate and of the token.
SUBJECT = "bench-client"
SECRET = "a secret for the benchmark's tokens, long enough for HS256"


def _name(common_name: str) -> x509.Name:
    return x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, common_name)])


def _issue(
    subject: str,
    key: ec.EllipticCurvePrivateKey,
    issuer: tuple[x509.Name, ec.EllipticCurvePrivateKey],
    ca: bool,
) -> x509.Certificate:
    now = datetime.datetime.now(datetime.UTC)
    builder = (
        x509.CertificateBuilder()
        .subject_name(_name(subject))
        .issuer_name(issuer[0])
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(days=1))
        .add_extension(x509.BasicConstraints(ca=ca, path_length=None), critical=True)
    )
    if subject == "127.0.0.1":
        names = [x509.IPAddress(ipaddress.ip_address("127.0.0.1")), x509.DNSName("localhost")]
        builder = builder.add_extension(x509.SubjectAlternativeName(names), critical=False)
    return builder.sign(issuer[1], hashes.SHA256())


def _write(folder: Path, stem: str, cert: x509.Certificate, key: ec.EllipticCurvePrivateKey) -> None:
    (folder / f"{stem}.pem").write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    (folder / f"{stem}.key").write_bytes(
        key.private_bytes(
            serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
        )
    )


def make_files(folder: Path) -> Path:
    """A CA, the server's and the client's certificates, the token secret and the config (its path)."""
    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca = _issue("bench-ca", ca_key, (_name("bench-ca"), ca_key), ca=True)
    _write(folder, "ca", ca, ca_key)
    for stem, subject in (("server", "127.0.0.1"), ("client", SUBJECT)):
        key = ec.generate_private_key(ec.SECP256R1())
        _write(folder, stem, _issue(subject, key, (ca.subject, ca_key), ca=False), key)
    (folder / "jwt.secret").write_text(SECRET)
    config = folder / "secure.toml"
    config.write_text(
        '[tls]\ncert = "server.pem"\nkey = "server.key"\nclient_ca = "ca.pem"\nrequire_client_cert = true\n'
        '[auth]\njwt_secret_file = "jwt.secret"\n'
        f'[[rules]]\nsubject = "{SUBJECT}"\noperations = ["read", "write"]\neffect = "permit"\n'
    )
    return config


def client_side(folder: Path) -> tuple[grpc.ChannelCredentials, Metadata]:
    """The client's credentials and its token, as the SDK would send them."""
    credentials = grpc.ssl_channel_credentials(
        root_certificates=(folder / "ca.pem").read_bytes(),
        private_key=(folder / "client.key").read_bytes(),
        certificate_chain=(folder / "client.pem").read_bytes(),
    )
    token = jwt.encode({"sub": SUBJECT, "exp": int(time.time()) + 3600}, SECRET, algorithm="HS256")
    return credentials, (("authorization", f"Bearer {token}"),)


async def run_tls(
    *, calls: int, gets: int, inflight: int, batch: int, window_batches: int, rounds: int, time_limit: float
) -> dict[str, Any]:
    """Unary and Session Gets on a plaintext and an mTLS + token gateway; the best round of each."""
    best: dict[str, dict[str, Any]] = {}
    with tempfile.TemporaryDirectory(prefix="bench-tls-") as tmp:
        folder = Path(tmp)
        config = make_files(folder)
        credentials, metadata = client_side(folder)
        ways: dict[str, tuple[list[str], grpc.ChannelCredentials | None, Metadata]] = {
            "plaintext": (["bench.gateway_server", "--listen", "127.0.0.1:0"], None, ()),
            "mtls-token": (
                ["bench.gateway_server", "--listen", "127.0.0.1:0", "--config", str(config)],
                credentials,
                metadata,
            ),
        }
        for _ in range(rounds):
            for way, (argv, creds, md) in ways.items():
                server = await ServerProcess.start(f"gateway {way}", argv)
                try:
                    unary = await run_unary(
                        server,
                        calls=calls,
                        inflight=inflight,
                        warmup=max(calls // 10, 10),
                        time_limit=time_limit,
                        credentials=creds,
                        metadata=md,
                    )
                    session = await run_session(
                        server,
                        gets=gets,
                        batch=batch,
                        window_batches=window_batches,
                        warmup=max(gets // 10, batch),
                        time_limit=time_limit,
                        credentials=creds,
                        metadata=md,
                    )
                finally:
                    await server.stop()
                seen = best.setdefault(way, {})
                for part, result in (("unary", unary.as_dict()), ("session", session.as_dict())):
                    if result.get("errors"):
                        raise RuntimeError(f"{way} {part}: {result['errors']} calls failed")
                    old = seen.get(part)
                    if old is None or result["throughput_per_s"] > old["throughput_per_s"]:
                        seen[part] = result
    return best
