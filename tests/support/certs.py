"""Throw-away certificates for tests: a CA, a server certificate, client certificates, bad ones.

Everything is made at test time by :mod:`gateway.certificates` (what ``psgateway tls init`` uses)
and written as PEM files into a folder; nothing here is meant to be secure beyond the test that
made it.

``make_certificates(folder)`` writes the whole set and returns their paths; the ``certificates``
fixture does it in the test's tmp folder.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import pytest

from gateway.certificates import Authority, KeyPair, issue_certificate, make_authority

__all__ = [
    "Authority",
    "CertificateFiles",
    "KeyPair",
    "certificates",
    "issue_certificate",
    "make_authority",
    "make_certificates",
]


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
