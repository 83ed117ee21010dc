"""Throw-away certificates for tests: a CA, a server certificate, client certificates, bad ones.

Everything is made at test time with the ``cryptography`` package and written as PEM files into a
folder; nothing here is meant to be secure beyond the test that made it. Keys are EC P-256, which
grpcio and OpenSSL accept and which is quick to generate.

``make_certificates(folder)`` writes the whole set and returns their paths; the ``certificates``
fixture does it in the test's tmp folder.
"""

from __future__ import annotations

import datetime
import ipaddress
from dataclasses import dataclass
from pathlib import Path

import pytest
from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

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


@dataclass(frozen=True)
class CertificateFiles:
    """The set a TLS test needs: paths of PEM files in one folder.

    ``ca`` signs ``server`` (for 127.0.0.1, ::1 and localhost) and every client in ``clients``
    (subject CN = the name); ``expired`` is a client certificate of ``ca`` whose validity ended
    yesterday; ``foreign`` is a client certificate signed by ``other_ca``, which the gateway does
    not trust.
    """

    folder: Path
    authority: Authority
    other_authority: Authority
    server: KeyPair
    clients: dict[str, KeyPair]
    expired: KeyPair
    foreign: KeyPair

    @property
    def ca(self) -> Path:
        """The trusted CA certificate file."""
        return self.authority.cert_path

    @property
    def other_ca(self) -> Path:
        """The untrusted CA's certificate file."""
        return self.other_authority.cert_path


def _new_key() -> ec.EllipticCurvePrivateKey:
    return ec.generate_private_key(ec.SECP256R1())


def _write_key(key: ec.EllipticCurvePrivateKey, path: Path) -> None:
    path.write_bytes(
        key.private_bytes(
            serialization.Encoding.PEM,
            serialization.PrivateFormat.PKCS8,
            serialization.NoEncryption(),
        )
    )


def _write_cert(cert: x509.Certificate, path: Path) -> None:
    path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))


def make_authority(folder: Path, name: str = "test-ca") -> Authority:
    """A self-signed CA, written as ``<name>.pem`` in ``folder``."""
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
        .not_valid_after(now + 30 * _ONE_DAY)
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
    expired: bool = False,
) -> KeyPair:
    """A leaf certificate signed by ``authority``, written as ``<file_stem>.pem`` / ``.key``.

    A server certificate names 127.0.0.1, ::1 and localhost in its SAN; a client certificate
    names ``common_name`` as its subject CN and as a DNS SAN (which grpc reports in the peer's
    auth context as x509_common_name and x509_subject_alternative_name).
    """
    key = _new_key()
    now = datetime.datetime.now(datetime.UTC)
    if expired:
        not_before, not_after = now - 10 * _ONE_DAY, now - _ONE_DAY
    else:
        not_before, not_after = now - _ONE_DAY, now + 30 * _ONE_DAY
    if server:
        names: list[x509.GeneralName] = [
            x509.DNSName("localhost"),
            x509.IPAddress(ipaddress.ip_address("127.0.0.1")),
            x509.IPAddress(ipaddress.ip_address("::1")),
        ]
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
    _write_key(key, pair.key)
    return pair


def make_certificates(folder: Path, clients: tuple[str, ...] = ("alice", "bob")) -> CertificateFiles:
    """Write a CA, a server certificate, one client certificate per name, an expired one and a
    foreign one into ``folder`` (created if missing)."""
    folder.mkdir(parents=True, exist_ok=True)
    authority = make_authority(folder, "ca")
    other_authority = make_authority(folder, "other-ca")
    return CertificateFiles(
        folder=folder,
        authority=authority,
        other_authority=other_authority,
        server=issue_certificate(authority, folder, "server", "localhost", server=True),
        clients={name: issue_certificate(authority, folder, name, name) for name in clients},
        expired=issue_certificate(authority, folder, "expired", "expired", expired=True),
        foreign=issue_certificate(other_authority, folder, "foreign", "mallory"),
    )


@pytest.fixture
def certificates(tmp_path: Path) -> CertificateFiles:
    """A fresh certificate set in the test's tmp folder (``tmp_path / "certs"``)."""
    return make_certificates(tmp_path / "certs")
