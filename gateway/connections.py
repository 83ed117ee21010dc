"""Bounded connections on every port: open-file shares, per-address and total caps, calm accepts.

Every open connection is a file descriptor, and descriptors are one pool for the whole process:
a flood on one port that takes them all leaves every other port unable to accept (and the
gateway unable to dial its devices). So:

* :func:`share_open_files` raises the soft ``RLIMIT_NOFILE`` to the hard limit at start and
  gives each port a share (its ``max_connections``), keeping :data:`RESERVED_FILES` for
  everything else (devices, proxies, log files, etcd). Shares that do not fit are lowered in
  proportion, with one warning naming what each port got.
* :class:`BoundedListener` serves an asyncio protocol factory (aiohttp's server, a line
  protocol session) on its own listening sockets. A connection past its port's share, or past
  ``max_per_address`` from one address, is accepted and closed at once (with a short refusal
  when the port speaks plaintext), so it never waits in the kernel's backlog or holds a
  descriptor. Refusals are counted and logged once per :data:`LOG_INTERVAL`: the first at once,
  those that follow when the interval is over (a timer), and any still counted at close.
* An accept that fails for want of descriptors or memory (EMFILE, ENFILE, ENOBUFS, ENOMEM)
  pauses that listener with a doubling back-off and is logged once per interval. asyncio's own
  accept loop logs such a failure once for each of up to ``backlog`` accepts in a row and
  schedules as many retries, each of which does the same: about 100,000 log lines in 20 s.

The gRPC port is grpc's own: its share is ``grpc.max_allowed_incoming_connections``
(:mod:`gateway.app`).
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import logging
import resource
import socket
import ssl
from collections import Counter
from collections.abc import Callable, Mapping
from dataclasses import dataclass

from gateway.handshake_log import HandshakeFailureLog

log = logging.getLogger(__name__)

#: Descriptors kept beside the ports' shares: devices and their proxies, the registry's and
#: storage's files, log files, etcd and peer gateways' channels.
RESERVED_FILES = 1024
#: Seconds between two log lines about refused connections or failed accepts of one port.
LOG_INTERVAL = 10.0
#: Accepts done at most for one readiness event of a listening socket (asyncio's own batch).
ACCEPT_BATCH = 100
#: Seconds a listener pauses after an accept failed for want of descriptors, doubling up to
#: :data:`_MOST_PAUSE` while it keeps failing.
_FIRST_PAUSE = 0.05
_MOST_PAUSE = 2.0
_OUT_OF_RESOURCES = frozenset((errno.EMFILE, errno.ENFILE, errno.ENOBUFS, errno.ENOMEM))


def share_open_files(wanted: Mapping[str, int], reserved: int = RESERVED_FILES) -> dict[str, int]:
    """Raise the soft open-files limit to the hard one; each port's share of it (``wanted``
    names each port's option and the connections it asks for).

    Shares that do not fit beside ``reserved`` are lowered in proportion (at least 1 each),
    with one warning saying what each got.
    """
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft != resource.RLIM_INFINITY and (hard == resource.RLIM_INFINITY or soft < hard):
        try:
            resource.setrlimit(resource.RLIMIT_NOFILE, (hard, hard))
            soft = hard
        except (ValueError, OSError) as exc:  # a hard limit of infinity that the kernel caps
            log.debug("open files: soft limit kept at %d: %s", soft, exc)
    total = sum(wanted.values())
    if soft == resource.RLIM_INFINITY or total + reserved <= soft:
        return dict(wanted)
    room = max(soft - reserved, len(wanted))
    shares = {name: max(1, want * room // total) for name, want in wanted.items()}
    log.warning(
        "open files are limited to %d: connections lowered to fit beside %d kept for devices and files: %s",
        soft,
        reserved,
        ", ".join(f"{name} {shares[name]} (asked {want})" for name, want in wanted.items()),
    )
    return shares


@dataclass(frozen=True, slots=True)
class ConnectionCaps:
    """How many connections one port holds at once, in all and from one address.

    ``max_total`` and ``max_per_address`` name the options they come from in refusals and logs.
    """

    max_total: int
    max_per_address: int
    #: The option names, for messages: ``http.max_connections``.
    total_option: str
    per_address_option: str


class _Counted(asyncio.Protocol):
    """A connection's own protocol, told apart so that its end frees its place."""

    __slots__ = ("_inner", "_release")

    def __init__(self, inner: asyncio.Protocol, release: Callable[[], None]) -> None:
        self._inner = inner
        self._release: Callable[[], None] | None = release

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self._inner.connection_made(transport)

    def data_received(self, data: bytes) -> None:
        self._inner.data_received(data)

    def eof_received(self) -> bool | None:
        return self._inner.eof_received()

    def pause_writing(self) -> None:
        self._inner.pause_writing()

    def resume_writing(self) -> None:
        self._inner.resume_writing()

    def connection_lost(self, exc: Exception | None) -> None:
        self.free()
        self._inner.connection_lost(exc)

    def free(self) -> None:
        """Give the connection's place back (once)."""
        release, self._release = self._release, None
        if release is not None:
            release()


class BoundedListener:
    """Listening sockets of one port whose connections are capped in all and per address.

    ``protocol_factory`` makes the protocol of each admitted connection (aiohttp's
    ``runner.server``, a line-protocol session's); ``refusal`` is written to a refused
    connection before it is closed (plaintext ports only); ``what`` names the port's option in
    logs (``http.listen``); ``handshake_failures`` tells the log of TLS handshakes that failed.
    """

    def __init__(
        self,
        protocol_factory: Callable[[], asyncio.Protocol],
        caps: ConnectionCaps,
        what: str,
        *,
        ssl_context: ssl.SSLContext | None = None,
        ssl_handshake_timeout: float | None = None,
        refusal: Callable[[str], bytes] | None = None,
        log_interval: float = LOG_INTERVAL,
        handshake_failures: HandshakeFailureLog | None = None,
    ) -> None:
        self._factory = protocol_factory
        #: Seconds between two lines about refused connections or failed accepts.
        self.log_interval = log_interval
        self.caps = caps
        self.what = what
        self._ssl = ssl_context
        self._handshake_timeout = ssl_handshake_timeout if ssl_context is not None else None
        self._refusal = refusal
        self._handshake_failures = handshake_failures
        self._sockets: list[socket.socket] = []
        #: Connections open now, by the peer's address.
        self.by_address: Counter[str] = Counter()
        self.open = 0
        self._handshakes: set[asyncio.Task[None]] = set()
        self._pause = _FIRST_PAUSE
        self._refused: Counter[str] = Counter()
        self._last_refused_from = ""
        #: Writes the refusals counted since the last line once the interval is over.
        self._refusals_timer: asyncio.TimerHandle | None = None
        self._failed_accepts = 0
        self._last_logged: float | None = None
        self._last_accept_logged: float | None = None

    @property
    def sockets(self) -> list[socket.socket]:
        """The listening sockets."""
        return list(self._sockets)

    async def start(self, host: str, port: int, backlog: int = 128) -> tuple[str, int]:
        """Listen on every address ``host`` resolves to (port 0: one free port for all); the first
        address bound. OSError (EADDRINUSE) when taken."""
        loop = asyncio.get_running_loop()
        infos = await loop.getaddrinfo(host or None, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
        seen: set[tuple[int, object]] = set()
        try:
            for family, kind, proto, _, resolved in infos:
                if (family, resolved) in seen:
                    continue
                seen.add((family, resolved))
                sock = socket.socket(family, kind, proto)
                self._sockets.append(sock)
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                if family == socket.AF_INET6:
                    sock.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_V6ONLY, 1)
                address = resolved
                if port == 0 and len(self._sockets) > 1:  # one free port for every address
                    address = (resolved[0], self._sockets[0].getsockname()[1], *resolved[2:])
                sock.bind(address)
                sock.listen(backlog)
                sock.setblocking(False)
        except OSError:
            self._close_sockets()
            raise
        for sock in self._sockets:
            loop.add_reader(sock.fileno(), self._accept, sock)
        bound = self._sockets[0].getsockname()
        return str(bound[0]), int(bound[1])

    def _accept(self, sock: socket.socket) -> None:
        for _ in range(ACCEPT_BATCH):
            try:
                conn, peer = sock.accept()
            except (BlockingIOError, InterruptedError, ConnectionAbortedError):
                return
            except OSError as exc:
                if exc.errno in _OUT_OF_RESOURCES:
                    self._back_off(sock, exc)
                else:
                    self._accept_failed(exc)
                return
            self._pause = _FIRST_PAUSE
            self._arrived(conn, str(peer[0]) if isinstance(peer, tuple) else "local")

    def _back_off(self, sock: socket.socket, exc: OSError) -> None:
        """Stop accepting on ``sock`` for a while (the kernel keeps it readable): no busy loop."""
        loop = asyncio.get_running_loop()
        loop.remove_reader(sock.fileno())
        self._accept_failed(exc, f"; accepting again in {self._pause:g} s")

        def resume() -> None:
            if sock in self._sockets:
                loop.add_reader(sock.fileno(), self._accept, sock)

        loop.call_later(self._pause, resume)
        self._pause = min(self._pause * 2, _MOST_PAUSE)

    def _accept_failed(self, exc: OSError, then: str = "") -> None:
        self._failed_accepts += 1
        now = asyncio.get_running_loop().time()
        if self._last_accept_logged is not None and now - self._last_accept_logged < self.log_interval:
            return
        self._last_accept_logged = now
        count, self._failed_accepts = self._failed_accepts, 0
        log.warning(
            "%s: accept failed (%d times since the last such line): %s%s", self.what, count, exc, then
        )

    def _arrived(self, conn: socket.socket, address: str) -> None:
        caps = self.caps
        if self.open >= caps.max_total:
            self._refuse(conn, f"{caps.max_total} connections are open ({caps.total_option})", address)
            return
        if self.by_address[address] >= caps.max_per_address:
            self._refuse(
                conn,
                f"{caps.max_per_address} connections from {address} are open ({caps.per_address_option})",
                address,
            )
            return
        conn.setblocking(False)
        self.open += 1
        self.by_address[address] += 1

        def release() -> None:
            self.open -= 1
            left = self.by_address[address] - 1
            if left > 0:
                self.by_address[address] = left
            else:
                del self.by_address[address]

        protocol = _Counted(self._factory(), release)
        task = asyncio.get_running_loop().create_task(self._connect(conn, protocol, address))
        self._handshakes.add(task)
        task.add_done_callback(self._handshakes.discard)

    async def _connect(self, conn: socket.socket, protocol: _Counted, address: str) -> None:
        loop = asyncio.get_running_loop()
        try:
            await loop.connect_accepted_socket(
                lambda: protocol, conn, ssl=self._ssl, ssl_handshake_timeout=self._handshake_timeout
            )
        except BaseException as exc:
            # A TLS handshake that failed or timed out, or the listener closing: the protocol
            # never heard of the connection, so its place is given back here.
            protocol.free()
            conn.close()
            if not isinstance(exc, Exception):
                raise
            if self._handshake_failures is not None:
                self._handshake_failures.failed(address, exc)
            else:
                log.debug("%s: a connection ended before it began: %s", self.what, exc)

    def _refuse(self, conn: socket.socket, reason: str, address: str) -> None:
        if self._refusal is not None:
            conn.setblocking(False)
            with contextlib.suppress(OSError):  # gone already, or its buffer full: closing says enough
                conn.send(self._refusal(reason))
        conn.close()
        self._refused[reason] += 1
        self._last_refused_from = address
        if self._refusals_timer is not None:
            return  # counted; the timer writes it
        loop = asyncio.get_running_loop()
        if self._last_logged is not None and loop.time() - self._last_logged < self.log_interval:
            # Written when the interval is over, not when (or if) the next refusal comes.
            self._refusals_timer = loop.call_at(self._last_logged + self.log_interval, self._log_refusals)
            return
        self._log_refusals()

    def _log_refusals(self) -> None:
        """One line with the refusals counted since the last (none: nothing)."""
        self._refusals_timer = None
        if not self._refused:
            return
        self._last_logged = asyncio.get_running_loop().time()
        counts, self._refused = self._refused, Counter()
        log.warning(
            "%s: refused %d connection(s) since the last such line: %s; the last from %s",
            self.what,
            sum(counts.values()),
            "; ".join(f"{count} as {why}" for why, count in counts.items()),
            self._last_refused_from,
        )

    def _close_sockets(self) -> None:
        loop = asyncio.get_event_loop()
        for sock in self._sockets:
            if sock.fileno() != -1:
                loop.remove_reader(sock.fileno())
                sock.close()
        self._sockets.clear()

    async def aclose(self) -> None:
        """Stop listening (open connections are their protocol's to end); idempotent. Refusals
        counted and not yet written are written now."""
        self._close_sockets()
        if self._refusals_timer is not None:
            self._refusals_timer.cancel()
        self._log_refusals()
        tasks = list(self._handshakes)
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        if self._handshake_failures is not None:
            self._handshake_failures.close()
