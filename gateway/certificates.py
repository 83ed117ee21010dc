"""Certificates for a gateway and its clients: a CA, server certificates, client certificates.

``psgateway tls init`` (:mod:`gateway.tls_cli`) makes a set for a first set-up or a test bench
with these, and the tests make theirs with the same functions (``tests/support/certs.py``). Keys
are EC P-256, which grpcio, OpenSSL and browsers accept and which is quick to generate. Private
keys are written readable by their owner only (0600); a file already there is replaced, so a
caller that must not overwrite checks first.
"""

from __future__ import annotations

import datetime
import ipaddress
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

__all__ = [
    "DEFAULT_SERVER_NAMES",
    "Authority",
    "KeyPair",
    "issue_certificate",
    "make_authority",
    "write_private_key",
]

#: The names every server certificate is valid for: a gateway reached on this machine.
DEFAULT_SERVER_NAMES = ("localhost", "127.0.0.1", "::1")

_ONE_DAY = datetime.timedelta(days=1)


@dataclass(frozen=True)
class KeyPair:
    """A certificate and its private key, as PEM files."""

    cert: Path
    key: Path


@dataclass(frozen=True)
class Authority:
    """A certificate authority that can sign more certificates (its key is kept in memory)."""

    name: str
    cert_path: Path
    certificate: x509.Certificate
    private_key: ec.EllipticCurvePrivateKey


def _new_key() -> ec.EllipticCurvePrivateKey:
    return ec.generate_private_key(ec.SECP256R1())


def write_private_key(key: ec.EllipticCurvePrivateKey, path: Path) -> None:
    """``key`` as unencrypted PKCS#8 PEM in ``path``, mode 0600 (also when the file was there)."""
    pem = key.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
    )
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "wb") as file:
        os.fchmod(file.fileno(), 0o600)  # a file that was there keeps its mode through O_TRUNC
        file.write(pem)


def _write_cert(cert: x509.Certificate, path: Path) -> None:
    path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))


def _general_name(name: str) -> x509.GeneralName:
    try:
        return x509.IPAddress(ipaddress.ip_address(name))
    except ValueError:
        return x509.DNSName(name)


def make_authority(folder: Path, name: str = "ca", *, days: int = 30) -> Authority:
    """A self-signed CA valid for ``days`` (from a day ago), written as ``<name>.pem`` in ``folder``."""
    key = _new_key()
    subject = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, name)])
    now = datetime.datetime.now(datetime.UTC)
    cert = (
        x509.CertificateBuilder()
        .subject_name(subject)
        .issuer_name(subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - _ONE_DAY)
        .not_valid_after(now + days * _ONE_DAY)
        .add_extension(x509.BasicConstraints(ca=True, path_length=None), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=True,
                content_commitment=False,
                key_encipherment=False,
                data_encipherment=False,
                key_agreement=False,
                key_cert_sign=True,
                crl_sign=True,
                encipher_only=False,
                decipher_only=False,
            ),
            critical=True,
        )
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .sign(key, hashes.SHA256())
    )
    cert_path = folder / f"{name}.pem"
    _write_cert(cert, cert_path)
    return Authority(name=name, cert_path=cert_path, certificate=cert, private_key=key)


def issue_certificate(
    authority: Authority,
    folder: Path,
    file_stem: str,
    common_name: str,
    *,
    server: bool = False,
    hosts: Sequence[str] = DEFAULT_SERVER_NAMES,
    days: int = 30,
    expired: bool = False,
) -> KeyPair:
    """A leaf certificate signed by ``authority``, written as ``<file_stem>.pem`` / ``.key``.

    A server certificate names ``hosts`` (DNS names and IP addresses) in its SAN; a client
    certificate names ``common_name`` as its subject CN and as a DNS SAN (which grpc reports in the
    peer's auth context as x509_common_name and x509_subject_alternative_name, where the gateway
    takes the caller's identity from). ``expired``: its validity ended yesterday (for tests of
    refusal).
    """
    key = _new_key()
    now = datetime.datetime.now(datetime.UTC)
    if expired:
        not_before, not_after = now - 10 * _ONE_DAY, now - _ONE_DAY
    else:
        not_before, not_after = now - _ONE_DAY, now + days * _ONE_DAY
    if server:
        names = [_general_name(host) for host in dict.fromkeys(hosts)]
        usage = ExtendedKeyUsageOID.SERVER_AUTH
    else:
        names = [x509.DNSName(common_name)]
        usage = ExtendedKeyUsageOID.CLIENT_AUTH
    cert = (
        x509.CertificateBuilder()
        .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, common_name)]))
        .issuer_name(authority.certificate.subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(not_before)
        .not_valid_after(not_after)
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(x509.SubjectAlternativeName(names), critical=False)
        .add_extension(x509.ExtendedKeyUsage([usage]), critical=False)
        .add_extension(
            x509.AuthorityKeyIdentifier.from_issuer_public_key(authority.private_key.public_key()),
            critical=False,
        )
        .sign(authority.private_key, hashes.SHA256())
    )
    pair = KeyPair(cert=folder / f"{file_stem}.pem", key=folder / f"{file_stem}.key")
    _write_cert(cert, pair.cert)
    write_private_key(key, pair.key)
    return pair
