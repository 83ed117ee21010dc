"""TLS handshakes that fail on the gateway's own listeners, told to the operator in one line each.

A client that speaks plaintext to a TLS port, or shows no certificate where one is required, hears
the hint in its own error; without this the gateway's log said nothing (asyncio reports a failed
handshake as an ``OSError``, which it logs only in debug mode), so an operator looking at the
gateway could not tell why a client cannot connect. :class:`HandshakeFailureLog` turns each failed
handshake of a :class:`~gateway.connections.BoundedListener` (the HTTP front end, the line
listener) into a WARNING naming the peer, OpenSSL's reason and the likely cause in words.

A client must not be able to flood the log with bad handshakes, so the lines are bounded: at most
one per peer address per :data:`LOG_INTERVAL` and :data:`MOST_LINES` in all per interval; what is
held back is counted and written as one line when the interval is over (or at close).

The gRPC port's handshakes are grpc's C core's, out of reach of this module (docs/security.md).
"""

from __future__ import annotations

import asyncio
import logging
import ssl
from dataclasses import dataclass

log = logging.getLogger(__name__)

#: Seconds during which one peer address gets at most one line, and the lines in all at most
#: :data:`MOST_LINES`.
LOG_INTERVAL = 60.0
#: Lines about failed handshakes written at most per :data:`LOG_INTERVAL`, all peers together:
#: enough to name the few clients an operator is setting up, too few to bury other lines when
#: many addresses knock at once.
MOST_LINES = 10

#: OpenSSL's reasons for bytes that are not TLS at all (it knows an HTTP request by its first word).
_NOT_TLS = frozenset(
    (
        "HTTP_REQUEST",
        "HTTPS_PROXY_REQUEST",
        "WRONG_VERSION_NUMBER",
        "UNKNOWN_PROTOCOL",
        "PACKET_LENGTH_TOO_LONG",
        "RECORD_LENGTH_MISMATCH",
    )
)
#: The client refused the gateway's certificate (it does not trust the CA that signed it, or thinks
#: it expired or names another host) and said so with an alert.
_CLIENT_REFUSED_OURS = frozenset(
    (
        "TLSV1_ALERT_UNKNOWN_CA",
        "SSLV3_ALERT_BAD_CERTIFICATE",
        "SSLV3_ALERT_CERTIFICATE_UNKNOWN",
        "SSLV3_ALERT_CERTIFICATE_EXPIRED",
        "TLSV1_ALERT_ACCESS_DENIED",
        "TLSV1_ALERT_DECRYPT_ERROR",
    )
)
#: The two sides share no TLS version or cipher.
_NO_COMMON_GROUND = frozenset(
    (
        "UNSUPPORTED_PROTOCOL",
        "VERSION_TOO_LOW",
        "NO_PROTOCOLS_AVAILABLE",
        "NO_SHARED_CIPHER",
        "TLSV1_ALERT_PROTOCOL_VERSION",
        "SSLV3_ALERT_HANDSHAKE_FAILURE",
    )
)


@dataclass(frozen=True, slots=True)
class TlsPortAdvice:
    """What to tell an operator about one TLS port: how a client should connect to it, and which
    option makes it require a client certificate (``""`` when it never does)."""

    #: Said after "a plaintext client on the TLS port: ", e.g. "use https:// and the CA".
    connect: str
    #: The option that requires a client certificate, e.g. "[tls] require_client_cert".
    requires_cert: str = ""
    #: The option naming the CA that client certificates must come from, e.g. "[tls] client_ca".
    client_ca: str = ""


@dataclass(frozen=True, slots=True)
class HandshakeVerdict:
    """One failed handshake explained: what failed (OpenSSL's reason) and the likely cause."""

    failed: str
    cause: str


def explain_handshake_failure(exc: BaseException, advice: TlsPortAdvice) -> HandshakeVerdict | None:
    """The reason and likely cause of a failed server-side handshake; None when the peer just went
    away before TLS began (a port probe, a client that gave up): no mismatch to report."""
    if isinstance(exc, ssl.SSLError):
        reason = exc.reason or type(exc).__name__
        if reason in _NOT_TLS:
            return HandshakeVerdict(reason, f"a plaintext client on the TLS port: {advice.connect}")
        if reason == "PEER_DID_NOT_RETURN_A_CERTIFICATE":
            return HandshakeVerdict(
                reason, f"no client certificate: this port requires one ({advice.requires_cert})"
            )
        if reason == "CERTIFICATE_VERIFY_FAILED":
            why = getattr(exc, "verify_message", "") or "not trusted"
            return HandshakeVerdict(
                reason,
                f"the client certificate was refused ({why}): one from another CA or out of date; "
                f"this port trusts the CA of {advice.client_ca}",
            )
        if reason in _CLIENT_REFUSED_OURS:
            return HandshakeVerdict(
                reason, "the client refused the gateway's certificate: give it the CA that signed it (--ca)"
            )
        if reason in _NO_COMMON_GROUND:
            return HandshakeVerdict(reason, "the client and the gateway share no TLS version or cipher")
        if reason == "UNEXPECTED_EOF_WHILE_READING":
            return HandshakeVerdict(
                reason, "the client hung up during the handshake: it may not trust the gateway's certificate"
            )
        return HandshakeVerdict(reason, "the TLS handshake failed")
    if isinstance(exc, ConnectionAbortedError) and "handshake" in str(exc):
        # asyncio's handshake timeout: the client sent no TLS hello at all, as a plaintext client
        # of a protocol in which the server speaks first (the line protocol's HELLO) does.
        return HandshakeVerdict(
            "no handshake in time",
            f"a plaintext client waiting for the gateway to speak first? {advice.connect}",
        )
    return None


class HandshakeFailureLog:
    """Writes one WARNING per failed TLS handshake of one port, bounded (see the module's doc).

    ``what`` names the port's option in the lines (``http.listen``); ``advice`` says how clients
    should connect. Call :meth:`failed` for each failed handshake and :meth:`close` at the end.
    """

    def __init__(
        self,
        what: str,
        advice: TlsPortAdvice,
        *,
        interval: float = LOG_INTERVAL,
        most_lines: int = MOST_LINES,
    ) -> None:
        self.what = what
        self.advice = advice
        self.interval = interval
        self.most_lines = most_lines
        #: When each peer address last got a line; only addresses that got one within the last
        #: interval are kept, so never more than twice ``most_lines``.
        self._last_line_for: dict[str, float] = {}
        self._window_start: float | None = None
        self._lines_in_window = 0
        self._held_back = 0
        self._last_held_back = ""
        self._summary_timer: asyncio.TimerHandle | None = None

    def failed(self, address: str, exc: BaseException) -> None:
        """A handshake with ``address`` failed with ``exc``: a line now, or counted for later."""
        verdict = explain_handshake_failure(exc, self.advice)
        if verdict is None:
            log.debug("%s: a connection from %s ended before TLS began: %s", self.what, address, exc)
            return
        loop = asyncio.get_running_loop()
        now = loop.time()
        if self._window_start is None or now - self._window_start >= self.interval:
            self._window_start = now
            self._lines_in_window = 0
        self._last_line_for = {a: t for a, t in self._last_line_for.items() if now - t < self.interval}
        if address in self._last_line_for or self._lines_in_window >= self.most_lines:
            self._held_back += 1
            self._last_held_back = f"{address}: {verdict.failed}"
            if self._summary_timer is None:
                self._summary_timer = loop.call_at(self._window_start + self.interval, self._write_summary)
            return
        self._last_line_for[address] = now
        self._lines_in_window += 1
        log.warning(
            "%s: TLS handshake with %s failed (%s): %s", self.what, address, verdict.failed, verdict.cause
        )

    def _write_summary(self) -> None:
        self._summary_timer = None
        if not self._held_back:
            return
        count, self._held_back = self._held_back, 0
        log.warning(
            "%s: %d more failed TLS handshake(s) not logged one by one (at most one line per address "
            "and %d in all per %g s); the last from %s",
            self.what,
            count,
            self.most_lines,
            self.interval,
            self._last_held_back,
        )

    def close(self) -> None:
        """Write what is still held back; no timer is left behind."""
        if self._summary_timer is not None:
            self._summary_timer.cancel()
        self._write_summary()
