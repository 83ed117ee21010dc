"""What a client shows the gateway: a CA to trust, a client certificate and key, a bearer token.

:class:`ClientCredentials` is handed to :class:`clients.aio.AsyncClient` and :class:`clients.sync.Client`
(and built by ``psctl`` from ``--ca --cert --key --token`` or ``PSCTL_CA``, ``PSCTL_CERT``,
``PSCTL_KEY``, ``PSCTL_TOKEN``). With a CA or a certificate the channel is TLS; the token goes as
``authorization: Bearer TOKEN`` metadata on every call.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import grpc

__all__ = ["ENVIRONMENT", "ClientCredentials"]

#: The environment variables :meth:`ClientCredentials.from_environment` reads, by field.
ENVIRONMENT = {"ca": "PSCTL_CA", "cert": "PSCTL_CERT", "key": "PSCTL_KEY", "token": "PSCTL_TOKEN"}


@dataclass(frozen=True)
class ClientCredentials:
    """A CA file, a client certificate and key file, and a bearer token; each optional.

    ``ca``: PEM CA certificates that sign the gateway's certificate (empty: the system's roots).
    ``cert`` and ``key``: the client's certificate chain and private key, for mutual TLS (both or
    neither). ``token``: sent as ``authorization: Bearer TOKEN`` on every call.
    """

    ca: str = ""
    cert: str = ""
    key: str = ""
    token: str = ""

    def __post_init__(self) -> None:
        if bool(self.cert) != bool(self.key):
            raise ValueError("a client certificate needs its key: give both cert and key, or neither")

    @classmethod
    def from_environment(cls, environ: Mapping[str, str], **given: str | None) -> ClientCredentials:
        """Fields from ``given`` (flags) where set, else from ``PSCTL_CA`` and the others in ``environ``."""
        values = {
            name: given.get(name) or environ.get(variable, "") for name, variable in ENVIRONMENT.items()
        }
        return cls(**{name: value or "" for name, value in values.items()})

    @property
    def secure(self) -> bool:
        """True when the channel must be TLS (a CA or a client certificate was given)."""
        return bool(self.ca or self.cert)

    def channel_credentials(self) -> grpc.ChannelCredentials:
        """grpc's TLS channel credentials from the files (read now)."""
        return grpc.ssl_channel_credentials(
            root_certificates=Path(self.ca).read_bytes() if self.ca else None,
            private_key=Path(self.key).read_bytes() if self.key else None,
            certificate_chain=Path(self.cert).read_bytes() if self.cert else None,
        )

    def metadata(self) -> tuple[tuple[str, str], ...]:
        """The call metadata these credentials add: the bearer token, if any."""
        return (("authorization", f"Bearer {self.token}"),) if self.token else ()
