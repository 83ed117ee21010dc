"""Transport security of the gateway's listeners: gRPC server credentials that reload, and the line
listener's ``ssl.SSLContext``.

The gRPC port uses grpcio's dynamic server credentials: grpc asks a fetcher for the certificate
configuration before each new handshake. :class:`ServerCredentials` answers "unchanged" until
:meth:`~ServerCredentials.reload` is called (on SIGHUP), then reads the files again and hands the new
configuration over; connections already open, and the streams on them, are not touched.
"""

from __future__ import annotations

import logging
import ssl
import threading
from collections.abc import Callable
from pathlib import Path

import grpc

from gateway.config import LineTlsSection, TlsSection

log = logging.getLogger("gateway.tls")


#: What ``client_ca`` without ``require_client_cert`` means on the gRPC port (said by check-config,
#: and logged at start): grpc's server credentials ask for a certificate only when they require one.
OPTIONAL_CLIENT_CERT = (
    "[tls] client_ca without require_client_cert: the gRPC port asks no client for a certificate, "
    "so none names a caller there (the HTTPS port checks one when given); "
    "require_client_cert = true names callers by certificate on both"
)


class ServerCredentials:
    """The gRPC port's TLS (or mutual TLS) credentials, re-read from their files on :meth:`reload`."""

    def __init__(self, settings: TlsSection) -> None:
        """Reads the files now: a missing or unreadable file fails the start, not the first handshake."""
        self.settings = settings
        self._lock = threading.Lock()
        self._pending: grpc.ServerCertificateConfiguration | None = None
        initial = self._read()
        if settings.client_ca and not settings.require_client_cert:
            log.warning("%s", OPTIONAL_CLIENT_CERT)
        self.credentials = grpc.dynamic_ssl_server_credentials(
            initial,
            # grpc documents None from the fetcher as "unchanged"; grpc-stubs does not allow it.
            self._fetch,  # type: ignore[arg-type]
            require_client_authentication=settings.require_client_cert,
        )

    def _read(self) -> grpc.ServerCertificateConfiguration:
        s = self.settings
        pair = (Path(s.key).read_bytes(), Path(s.cert).read_bytes())
        roots = Path(s.client_ca).read_bytes() if s.client_ca else None
        return grpc.ssl_server_certificate_configuration([pair], root_certificates=roots)

    def reload(self) -> bool:
        """Read the files again; new handshakes use them. False (and the old ones kept) when unreadable."""
        try:
            fresh = self._read()
        except OSError as exc:
            log.error("TLS reload failed, keeping the certificates in use: %s", exc)
            return False
        with self._lock:
            self._pending = fresh
        log.info("TLS certificates reloaded from %s", self.settings.cert)
        return True

    def _fetch(self) -> grpc.ServerCertificateConfiguration | None:
        # Called by grpc before each handshake, from its own threads: None keeps the current one.
        with self._lock:
            pending, self._pending = self._pending, None
        return pending


def line_ssl_context(settings: LineTlsSection) -> ssl.SSLContext:
    """The line listener's server context; with ``client_ca``, devices must present a certificate."""
    context = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
    context.load_cert_chain(settings.cert, settings.key)
    if settings.client_ca:
        context.load_verify_locations(settings.client_ca)
        context.verify_mode = ssl.CERT_REQUIRED
    return context


class ReloadingContext:
    """A listener's ``ssl.SSLContext`` that reads its files again on :meth:`reload` (SIGHUP) without
    closing a connection.

    The listening socket keeps one context; its server-name callback, which OpenSSL calls at
    every handshake (with or without SNI), hands the handshake the context built from the files
    as they were at the last reload: new connections get the new certificate and CA, open ones
    carry on. ``build`` makes a context from the files; ``what`` names the listener in the log.
    """

    def __init__(self, build: Callable[[], ssl.SSLContext], what: str, cert: str) -> None:
        self._build = build
        self._what = what
        self._cert = cert
        self._current = build()
        self.context = build()
        self.context.sni_callback = self._choose

    def _choose(self, connection: ssl.SSLObject, server_name: str | None, _: ssl.SSLContext) -> None:
        connection.context = self._current

    def reload(self) -> None:
        """Read the files again; a file that cannot be used is logged and the old context kept."""
        try:
            self._current = self._build()
        except (OSError, ssl.SSLError) as exc:
            log.error("%s: TLS files not reloaded, the old ones stay: %s", self._what, exc)
            return
        log.info("%s: TLS certificates reloaded from %s", self._what, self._cert)


class LineCredentials(ReloadingContext):
    """The line listener's TLS (``[tls.line]``), read again on :meth:`reload`."""

    def __init__(self, settings: LineTlsSection) -> None:
        self.settings = settings
        super().__init__(lambda: line_ssl_context(settings), "line listener", settings.cert)


def https_ssl_context(settings: TlsSection) -> ssl.SSLContext:
    """The HTTP front end's server context from the ``[tls]`` section: the gRPC port's certificate;
    with ``client_ca``, a client certificate is checked when given (required with
    ``require_client_cert``), and names the caller as on the gRPC port."""
    context = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
    context.load_cert_chain(settings.cert, settings.key)
    if settings.client_ca:
        context.load_verify_locations(settings.client_ca)
        context.verify_mode = ssl.CERT_REQUIRED if settings.require_client_cert else ssl.CERT_OPTIONAL
    return context


class HttpsCredentials(ReloadingContext):
    """The HTTP front end's TLS (``[http] tls = true``: the ``[tls]`` files), read again on :meth:`reload`."""

    def __init__(self, settings: TlsSection) -> None:
        self.settings = settings
        super().__init__(lambda: https_ssl_context(settings), "HTTP front end", settings.cert)
