"""The gateway speaking the line protocol on raw TCP (off by default; ``gateway.line_listen``).

A microcontroller that knows only lines of text can reach every service
behind the gateway: the first path segment names the service::

    GET scout1.location.x     →  router.backend("scout1").get("location.x")
    SET light1.switch on
    LISTEN scout1.location.x  →  EVENT scout1.location.x 0.52 ...
    GET properties            →  the names of the services, "(light1 registry scout1)"

The sessions themselves are :class:`services.device.DeviceSession`s: the
gateway is just one more device whose backend is the whole router.

**A device that dials in.** When the first line a peer sends is a greeting
(``HELLO 1 name=scout4 type=mobile_robot push=1``) the peer is a device that
registers itself (docs/line-protocol.md §5): the connection is handed to an
:class:`InboundProxy` — the ordinary line-protocol proxy, whose stream is this
connection instead of one it opens — served under the greeting's ``name``
with the URL ``tcp-in://HOST:PORT`` (the device's end of the connection). The
registry lists it like any other service. A bad or missing name gets
``ERR 3`` (INVALID_ARGUMENT), a taken one ``ERR 6`` (ALREADY_EXISTS), and the
connection is closed.

**A greeting is a registration**, checked like a Set of ``services.NAME`` on the
registry from any other front end: its subject is the name the greeting proves
— a configured device's ``secret=``, or the CN of a client certificate on the
listener's TLS — else ``anonymous``, and the rules must let that subject
``register`` ``registry/services.NAME``. A refused greeting gets ``ERR 16``
(UNAUTHENTICATED; ``ERR 7``, PERMISSION_DENIED, when it proved a name the rules
refuse) naming the rule, and registers nothing. With no rules every greeting
passes, as on the gRPC port. When the connection drops the service stays, not
connected: the registry's liveness checks mark it ``down`` and its grace
removes it; a device that dials in again under the same name before that
takes its place back.

**Who asks.** Each connection is served through its own :class:`RouterBackend`,
whose :attr:`RouterBackend.subject` is the connection's subject: anonymous
unless the connection proved who it is (set it there once it has). Every GET,
SET and LISTEN passes the gateway's :class:`~gateway.engine.guard.Guard` as that
subject, exactly as on the gRPC port, and so does every call a service makes
for it (a group's members: :mod:`gateway.engine.behalf`); a refusal is an ``ERR 16``
(UNAUTHENTICATED) or ``ERR 7`` (PERMISSION_DENIED) line naming the rule.
"""

from __future__ import annotations

import asyncio
import dataclasses
import hmac
import logging
import ssl
from collections.abc import Collection, Mapping
from typing import TYPE_CHECKING, Any, Protocol

from gateway.config import GatewaySection, Limits
from gateway.connections import BoundedListener, ConnectionCaps
from gateway.engine.calls import Calls
from gateway.engine.guard import REGISTRY, Guard
from gateway.engine.identity import ANONYMOUS
from gateway.engine.rules import Operation, Subject
from gateway.engine.types import GetCall, SetCall
from gateway.handshake_log import HandshakeFailureLog, TlsPortAdvice
from services.device import DeviceServer
from services.device.alternates import ALTERNATES_FIELD, format_alternates
from services.kernel.backend import NO_PARAMS, Backend, BackendInfo, Change, Notify, Subscription
from services.kernel.directory import CALLER
from services.kernel.errors import (
    AlreadyExists,
    Code,
    FailedPrecondition,
    InvalidArgument,
    PermissionDenied,
    PropertyError,
    ReadOnly,
    ResourceExhausted,
    Unauthenticated,
    error_for,
)
from services.kernel.line_protocol import (
    MAX_LINE,
    PROTOCOL_REVISION,
    PROTOCOL_VERSION,
    BadLine,
    ErrorReply,
    Hello,
    LineReceiver,
    encode,
)
from services.kernel.paths import validate_service_name
from services.kernel.values import Value, format_names

if TYPE_CHECKING:
    from collections.abc import Callable

    from gateway.engine.router import Router
    from gateway.fronts.line.inbound import InboundProxy
    from gateway.proxies.line_proxy import ProxyOptions

#: The call timeout and the most paths of a Get of a listener not given the gateway's call layer.
CALL_TIMEOUT = GatewaySection().call_timeout
MAX_GET_PATHS = Limits().max_get_paths

log = logging.getLogger(__name__)

#: What the log says of a failed handshake on the line listener (``[tls.line]``).
LINE_TLS_ADVICE = TlsPortAdvice(
    connect="connect with TLS and the CA of [tls.line] cert",
    requires_cert="[tls.line] client_ca",
    client_ca="[tls.line] client_ca",
)

#: Connections the listener serves at once, clients and devices that dialled in together.
MAX_CONNECTIONS = 1024
#: Seconds a device that dialled in gets to be taken up by its proxy.
_TAKE_UP = 5.0
#: Seconds a connection may stay silent (nothing read from it) before it is closed.
LINE_IDLE_TIMEOUT = 300.0
#: Devices that dialled in from one source address and are served at once.
MAX_GREETINGS_PER_SOURCE = 64
#: Connections from one address served at once, devices and clients together.
MAX_CONNECTIONS_PER_ADDRESS = 128
#: Connections the door lets in beyond ``max_connections``: a full listener admits one more and
#: closes the connection silent longest, which frees its place a loop turn later.
_EVICTION_ROOM = 16
#: A full listener closes the connection silent longest to admit a new one, if it has been
#: silent at least this long (a busy listener is not churned by a flood of fresh connections).
_EVICT_AFTER = 1.0


class _Watch(Subscription):
    def __init__(self, unwatch: Callable[[], None]) -> None:
        self._unwatch: Callable[[], None] | None = unwatch

    async def close(self) -> None:
        unwatch, self._unwatch = self._unwatch, None
        if unwatch is not None:
            unwatch()


class RouterBackend(Backend):
    """Every service of a router as one tree: ``SERVICE.PATH``; ``properties`` lists the services.

    A service's name alone reads as a namespace does: the names of its properties (its own
    ``properties``), so that every name ``properties`` lists answers a GET (docs/device-spec.md §3.1).

    One per line connection: :attr:`subject` is who asks on it. A GET and a SET go through the
    gateway's call layer (``calls``) as the engine's own calls, exactly as a gRPC or HTTP call
    does: the same rules, licences, audit and time limit.
    """

    def __init__(self, calls: Calls, subject: Subject = ANONYMOUS) -> None:
        self.calls = calls
        self.router = calls.router
        self.guard = calls.guard
        self.info = BackendInfo(type="gateway", url="line")
        #: Who asks on this connection: anonymous until it proves who it is (then set it here).
        self.subject = subject

    def _check_read(self, service: str, path: str) -> None:
        """Refuse a read the rules deny; what a service reads for it is checked as the same subject."""
        guard = self.guard
        if guard.checks:
            guard.require(self.subject, service, path, Operation.READ)
            CALLER.set(self.subject)

    def _split(self, path: str) -> tuple[Backend, str, str]:
        """The service's backend, its name and the path inside it; a bare name is its ``properties``."""
        service, dot, rest = path.partition(".")
        backend = self.router.backend(service)
        if dot and not rest:
            raise InvalidArgument(f"{path!r} names a service; name one of its properties: {service}.PROPERTY")
        return backend, service, rest or "properties"

    async def get(self, path: str, params: Mapping[str, str] = NO_PARAMS) -> Value:
        if path == "properties":
            return format_names(self.router.names())
        _, service, rest = self._split(path)
        calls = self.calls
        return await calls.start_get(GetCall(service, rest, params), calls.timeout, self.subject)

    async def set(self, path: str, value: Value, params: Mapping[str, str] = NO_PARAMS) -> Value:
        if path == "properties":
            raise ReadOnly("properties (the list of services) is read-only")
        _, service, rest = self._split(path)
        calls = self.calls
        answer = await calls.start_set(SetCall(service, rest, value, params), calls.timeout, self.subject)
        # A service method that returns nothing answers an empty value.
        return answer if answer is not None else ""

    async def listen(self, path: str, notify: Notify, params: Mapping[str, str] = NO_PARAMS) -> Subscription:
        if path == "properties":

            def changed(name: str, backend: Backend | None) -> None:
                notify(Change("properties", format_names(self.router.names())))

            return _Watch(self.router.watch(changed))
        backend, service, rest = self._split(path)
        self._check_read(service, rest)

        def forward(change: Change) -> None:
            notify(Change(f"{service}.{change.path}", change.value, change.gap, change.removed))

        return await backend.listen(rest, forward, params)


class _Prefixed(asyncio.StreamReader):
    """A stream read from the start again: ``head`` (bytes already read from it), then the rest."""

    def __init__(self, inner: asyncio.StreamReader, head: bytes) -> None:
        super().__init__()
        self._inner = inner
        self._head = head

    async def read(self, n: int = -1) -> bytes:
        if self._head:
            head, self._head = self._head, b""
            return head
        return await self._inner.read(n)


class _FirstLine(asyncio.StreamReader):
    """What a connection's client session reads: the stream, unless its first line is a device greeting.

    The session greets and reads through this as usual. When the peer's
    first line turns out to be a ``HELLO 1 ...`` greeting, :attr:`device`
    gets that greeting and every byte read so far, and the session reads
    nothing more (end of stream once :meth:`release` is called).
    """

    def __init__(self, inner: asyncio.StreamReader) -> None:
        super().__init__()
        self._inner = inner
        self._head = b""
        self._decided = False
        self._released = asyncio.Event()
        #: The greeting (or the greeting that cannot be accepted) and every byte read so far.
        self.device: asyncio.Future[tuple[Hello | BadLine, bytes]] = (
            asyncio.get_running_loop().create_future()
        )

    def release(self) -> None:
        """Let the session see the end of the stream (the device's connection ended)."""
        self._released.set()
        if not self.device.done():
            self.device.cancel()

    async def read(self, n: int = -1) -> bytes:
        while not self._decided:
            data = await self._inner.read(n)
            if not data:
                self._decided = True
                head, self._head = self._head, b""
                return head
            self._head += data
            end = self._head.find(b"\n")
            if end < 0 and len(self._head) <= MAX_LINE:
                continue  # the first line is not complete yet
            self._decided = True
            frames = LineReceiver().receive_data(self._head[: end + 1]) if end >= 0 else []
            greeting = frames[0] if frames else None
            if isinstance(greeting, Hello | BadLine) and _is_greeting(greeting) and not self.device.done():
                self.device.set_result((greeting, self._head))
                self._head = b""
                await self._released.wait()
                return b""
            head, self._head = self._head, b""
            return head
        return await self._inner.read(n)


def _is_greeting(frame: Hello | BadLine) -> bool:
    """A first line that makes the peer a device: an untagged greeting, good or refused."""
    if isinstance(frame, Hello):
        return frame.tag is None
    return isinstance(frame, BadLine) and frame.greeting and frame.tag is None


class _Heard(asyncio.StreamReader):
    """A stream that remembers when its peer last sent anything (for the idle timeout)."""

    def __init__(self, inner: asyncio.StreamReader) -> None:
        super().__init__()
        self._inner = inner
        self.last_heard = asyncio.get_running_loop().time()

    async def read(self, n: int = -1) -> bytes:
        data = await self._inner.read(n)
        self.last_heard = asyncio.get_running_loop().time()
        return data


class ConnectionBounds:
    """How many line-listener connections are open, how long each has been silent, and who greeted.

    Silent connections are closed after ``idle_timeout``; a full listener
    makes room by closing the one silent longest, and an address with
    ``max_connections_per_address`` open by closing its own one silent
    longest; one source address may have at most ``max_greetings_per_source``
    devices served at once.
    """

    def __init__(
        self,
        *,
        max_connections: int,
        idle_timeout: float,
        max_greetings_per_source: int,
        max_connections_per_address: int = MAX_CONNECTIONS_PER_ADDRESS,
    ) -> None:
        self.max_connections = max_connections
        self.idle_timeout = idle_timeout
        self.max_greetings_per_source = max_greetings_per_source
        self.max_connections_per_address = max_connections_per_address
        self._open: dict[asyncio.StreamWriter, _Heard] = {}
        #: The source address of each open connection, taken when it opened: a TLS transport
        #: that has closed answers no ``peername`` any more (it raises instead).
        self._addresses: dict[asyncio.StreamWriter, str] = {}
        #: The open connections of each source address (for its own bound).
        self._by_address: dict[str, set[asyncio.StreamWriter]] = {}
        self._greetings: dict[str, int] = {}

    def admit(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> _Heard | None:
        """Track a new connection, making room when full; None when no room can be made."""
        address = _address_of(writer)
        own = self._by_address.get(address, set())
        if len(own) >= self.max_connections_per_address and not self._evict_quietest(own, address):
            return None
        if len(self._open) >= self.max_connections and not self._evict_quietest(self._open, None):
            return None
        heard = _Heard(reader)
        self._open[writer] = heard
        self._addresses[writer] = address
        self._by_address.setdefault(address, set()).add(writer)
        return heard

    def release(self, writer: asyncio.StreamWriter) -> None:
        """The connection ended."""
        self._open.pop(writer, None)
        address = self._addresses.pop(writer, None)
        if address is None:
            return
        own = self._by_address.get(address)
        if own is not None:
            own.discard(writer)
            if not own:
                del self._by_address[address]

    def _evict_quietest(self, among: Collection[asyncio.StreamWriter], address: str | None) -> bool:
        """Close the connection of ``among`` silent longest, if it has been silent long enough."""
        now = asyncio.get_running_loop().time()
        writer = min(among, key=lambda w: self._open[w].last_heard)
        silent = now - self._open[writer].last_heard
        if silent < _EVICT_AFTER:
            return False
        if address is None:
            log.debug("line listener full: closing a connection silent for %.0f s", silent)
        else:
            log.debug(
                "line listener: %s has as many connections as it may: closing one silent for %.0f s",
                address,
                silent,
            )
        self.release(writer)
        writer.close()
        return True

    def close_idle(self) -> None:
        """Close every connection silent for ``idle_timeout`` or longer."""
        now = asyncio.get_running_loop().time()
        for writer, heard in list(self._open.items()):
            if now - heard.last_heard >= self.idle_timeout:
                log.info("line listener: closing a connection silent for %.0f s", now - heard.last_heard)
                self._open.pop(writer)
                writer.close()

    def greet(self, source: str) -> None:
        """Count a device greeting from ``source``; ResourceExhausted beyond the bound."""
        if self._greetings.get(source, 0) >= self.max_greetings_per_source:
            raise ResourceExhausted(
                f"{self.max_greetings_per_source} devices from {source} are served already "
                "([limits] max_greetings_per_source)"
            )
        self._greetings[source] = self._greetings.get(source, 0) + 1

    def farewell(self, source: str) -> None:
        """A device from ``source`` hung up."""
        left = self._greetings.get(source, 0) - 1
        if left > 0:
            self._greetings[source] = left
        else:
            self._greetings.pop(source, None)


def _address_of(writer: asyncio.StreamWriter) -> str:
    peer = writer.get_extra_info("peername")
    return str(peer[0]) if isinstance(peer, tuple) else "local"


class _ListenerServer(DeviceServer):
    """The device server of the line listener: clients are served, devices that greet are registered."""

    #: A line per connection would let a flood of connections write the log full (a device that
    #: dials in is logged when it joins and when it hangs up).
    connection_log_level = logging.DEBUG

    def __init__(
        self, listener: LineListener, backend: RouterBackend, bounds: ConnectionBounds, **kwargs: object
    ) -> None:
        # The listener bounds its connections itself (ConnectionBounds), evicting silent ones.
        super().__init__(backend, max_connections=bounds.max_connections + _EVICTION_ROOM, **kwargs)  # type: ignore[arg-type]
        self._listener = listener
        self._router_backend = backend
        self._bounds = bounds

    async def serve_stream(
        self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, peer: str = ""
    ) -> None:
        heard = self._bounds.admit(reader, writer)
        if heard is None:
            full = (
                "too many connections, none silent long enough to make room for this one"
                " (limits.line_max_connections, limits.line_max_connections_per_address); try later"
            )
            writer.write(encode(ErrorReply(int(Code.RESOURCE_EXHAUSTED), full)))
            writer.close()
            return
        try:
            await self._serve_admitted(heard, writer, peer)
        finally:
            self._bounds.release(writer)

    async def _serve_admitted(
        self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, peer: str
    ) -> None:
        first = _FirstLine(reader)
        # Each connection asks as its own subject: its own view of the router.
        shared = self._router_backend
        view = RouterBackend(shared.calls)
        session = self.session(first, writer, peer, view, greeting=self._listener.greeting())
        run = asyncio.create_task(session.run(), name=f"line listener {peer}")
        try:
            waits: list[asyncio.Future[object]] = [run, first.device]  # type: ignore[list-item]
            await asyncio.wait(waits, return_when=asyncio.FIRST_COMPLETED)
            if first.device.done() and not first.device.cancelled():
                greeting, head = first.device.result()
                checksummed = head.lstrip(b" ").startswith(b"$")
                await self._listener.serve_device(
                    greeting, _Prefixed(reader, head), writer, peer, checksummed=checksummed
                )
        finally:
            first.release()
            await asyncio.gather(run, return_exceptions=True)


def certificate_name(peercert: Any) -> str:
    """The subject CN of a verified client certificate (``ssl``'s ``getpeercert()``), or ""."""
    for rdn in (peercert or {}).get("subject", ()):
        for key, value in rdn:
            if key == "commonName":
                return str(value)
    return ""


class DeviceSeats(Protocol):
    """Names a cluster of gateways holds for devices that dial in (``gateway.cluster``): a device
    whose gateway is gone dials another, whose entry for its name waits for it (its Listens open)."""

    def awaits(self, name: str) -> bool:
        """Whether ``name`` is held for its device, which may take it up here."""
        ...

    def inbound(self, name: str) -> Backend | None:
        """The proxy of device ``name`` seated here earlier (it dials again after a drop); else None."""
        ...

    async def seat(self, name: str, proxy: Backend) -> None:
        """Serve the device's ``proxy`` (connected) under the held name; AlreadyExists when it cannot."""
        ...


class LineListener:
    """A raw-TCP line-protocol server in front of a router; ``aclose`` stops it.

    Devices that dial in and greet are served through the router as
    :class:`InboundProxy` backends (see the module documentation).
    """

    def __init__(
        self,
        router: Router,
        *,
        name: str = "gateway",
        max_connections: int = MAX_CONNECTIONS,
        device_options: ProxyOptions | None = None,
        on_rejoin: Callable[[str, BackendInfo], None] | None = None,
        guard: Guard | None = None,
        idle_timeout: float = LINE_IDLE_TIMEOUT,
        max_greetings_per_source: int = MAX_GREETINGS_PER_SOURCE,
        device_secrets: Mapping[str, str] | None = None,
        alternates: Callable[[], list[str]] | None = None,
        max_connections_per_address: int = MAX_CONNECTIONS_PER_ADDRESS,
        seats: DeviceSeats | None = None,
        calls: Calls | None = None,
    ) -> None:
        """``calls``: the gateway's call layer, through which every GET and SET goes (default: one of
        its own on ``router`` and ``guard``, with the default call timeout and no licences);
        ``seats``: the names a cluster holds for devices that dial in (:class:`DeviceSeats`);
        ``alternates()`` names the line listeners of the other gateways of this one's cluster: the
        greeting tells them to every peer (``alternates=``), so that a device that dialled in knows
        where to go when this gateway is gone (docs/line-protocol.md §5);
        ``guard`` checks every request of every connection (default: nothing is refused);
        ``device_secrets`` (name → secret) are the configured devices that dial in: each name is
        taken only by a greeting that carries ``secret=`` with its secret;
        ``device_options`` tune the proxies of devices that dial in (default ``INBOUND_OPTIONS``);
        ``on_rejoin(name, info)`` hears of a device that dialled in again after a drop (the gateway
        tells its registry at once that the service is up again, at its new address)."""
        self.router = router
        self.device_options = device_options
        self._on_rejoin = on_rejoin
        self.bounds = ConnectionBounds(
            max_connections=max_connections,
            idle_timeout=idle_timeout,
            max_greetings_per_source=max_greetings_per_source,
            max_connections_per_address=max_connections_per_address,
        )
        self.server = _ListenerServer(
            self,
            RouterBackend(calls or Calls(router, CALL_TIMEOUT, MAX_GET_PATHS, guard)),
            self.bounds,
            name=name,
            type="gateway",
            push=True,
        )
        self.address: tuple[str, int] | None = None
        self._door: BoundedListener | None = None
        self._reaper: asyncio.Task[None] | None = None
        self._device_secrets = dict(device_secrets or {})
        self._alternates = alternates
        self._seats = seats
        self._guard = guard or Guard()

    def greeting(self) -> Hello:
        """The listener's greeting now: with the other gateways of its cluster, when it has any."""
        greeting = self.server.greeting
        others = format_alternates(self._alternates()) if self._alternates is not None else ""
        if not others:
            return greeting
        return dataclasses.replace(greeting, extra={**greeting.extra, ALTERNATES_FIELD: others})

    async def serve_device(
        self,
        greeting: Hello | BadLine,
        reader: asyncio.StreamReader,
        writer: asyncio.StreamWriter,
        peer: str,
        *,
        checksummed: bool = False,
    ) -> None:
        """Serve the device that greeted on this connection as service ``hello.name``, until it hangs up.

        A greeting that cannot be accepted (another protocol version, a bad
        field) is refused at once with an ERR line (docs/line-protocol.md §3),
        checksummed when the greeting was.
        """
        from gateway.fronts.line.inbound import INBOUND_SCHEME

        if isinstance(greeting, BadLine):
            await self._refuse(None, writer, peer, error_for(greeting.code, greeting.message), checksummed)
            return
        hello = greeting
        if hello.version != PROTOCOL_VERSION:
            refusal = FailedPrecondition(
                f"line protocol version {hello.version} is not supported; "
                f"this gateway speaks version {PROTOCOL_VERSION} ({PROTOCOL_REVISION})"
            )
            await self._refuse(hello, writer, peer, refusal, checksummed)
            return
        url = f"{INBOUND_SCHEME}://{peer}"
        source = peer.rpartition(":")[0]
        try:
            self.bounds.greet(source)
        except PropertyError as exc:
            await self._refuse(hello, writer, peer, exc, checksummed)
            return
        try:
            await self._serve_greeted(hello, reader, writer, url, peer, checksummed=checksummed)
        finally:
            self.bounds.farewell(source)

    async def _refuse(
        self,
        hello: Hello | None,
        writer: asyncio.StreamWriter,
        peer: str,
        exc: PropertyError,
        checksummed: bool = False,
    ) -> None:
        who = repr(hello.name) if hello is not None else "(bad greeting)"
        log.warning("line listener: device %s at %s refused: %s", who, peer, exc.message)
        try:
            writer.write(encode(ErrorReply.from_exception(exc), checksum=checksummed))
            await writer.drain()
        except OSError as gone:  # it hung up first: it would not have read the reason anyway
            log.debug("line listener: could not tell %s why: %s", peer, gone)
        writer.close()

    async def _serve_greeted(
        self,
        hello: Hello,
        reader: asyncio.StreamReader,
        writer: asyncio.StreamWriter,
        url: str,
        peer: str,
        *,
        checksummed: bool,
    ) -> None:
        try:
            proxy = await self._take_up(hello, reader, writer, url)
        except PropertyError as exc:
            await self._refuse(hello, writer, peer, exc, checksummed)
            return
        log.info("service %s joined by greeting from %s (%s)", hello.name, peer, proxy.info.type)
        try:
            await writer.wait_closed()
        except OSError as gone:  # a reset rather than a clean close: it hung up all the same
            log.debug("line listener: %s: %s", peer, gone)
        log.info("service %s: the device at %s hung up", hello.name, peer)

    async def _take_up(
        self, hello: Hello, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, url: str
    ) -> InboundProxy:
        name = hello.name
        if not name:
            raise InvalidArgument(
                "a device that dials in must give its name in its greeting: HELLO 1 name=NAME type=TYPE"
            )
        validate_service_name(name)
        subject = self._greeting_subject(hello, writer)
        self._check_register(subject, name)
        path = f"services.{name}"
        try:
            proxy = await self._serve_as(name, reader, writer, url)
        except Exception as exc:
            self._guard.audited(subject, REGISTRY, path, Operation.REGISTER, exc)
            raise
        self._guard.audited(subject, REGISTRY, path, Operation.REGISTER, None)
        return proxy

    async def _serve_as(
        self, name: str, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, url: str
    ) -> InboundProxy:
        """The proxy serving the device on this connection as ``name``: a new one, or the one it
        left when its connection dropped."""
        from gateway.fronts.line.inbound import INBOUND_OPTIONS, InboundProxy

        existing = self.router.lookup(name) if name in self.router else None
        seats = self._seats
        if existing is not None and not isinstance(existing, InboundProxy) and seats is not None:
            held = seats.inbound(name)
            if isinstance(held, InboundProxy):
                existing = held  # the device dialled in here before, and its cluster entry serves it
            elif seats.awaits(name):
                return await self._seat(seats, name, reader, writer, url)
        if existing is not None:
            if not isinstance(existing, InboundProxy):
                raise AlreadyExists(f"the name {name!r} is taken (by {existing.info.url})")
            existing.offer(reader, writer, url)  # the same device, back after a drop
            await existing.wait_connected(_TAKE_UP)
            if self._on_rejoin is not None:
                self._on_rejoin(name, existing.info)
            return existing
        proxy = InboundProxy(name, url, self.device_options or INBOUND_OPTIONS)
        proxy.offer(reader, writer, url)
        await proxy.start()
        try:
            await proxy.wait_connected(_TAKE_UP)
            self.router.add(name, proxy)
        except BaseException:
            await proxy.aclose()
            raise
        return proxy

    async def _seat(
        self,
        seats: DeviceSeats,
        name: str,
        reader: asyncio.StreamReader,
        writer: asyncio.StreamWriter,
        url: str,
    ) -> InboundProxy:
        """Serve a device that a cluster awaits under its name (it left a gateway that is gone)."""
        from gateway.fronts.line.inbound import INBOUND_OPTIONS, InboundProxy

        proxy = InboundProxy(name, url, self.device_options or INBOUND_OPTIONS)
        proxy.offer(reader, writer, url)
        await proxy.start()
        try:
            await proxy.wait_connected(_TAKE_UP)
            await seats.seat(name, proxy)
        except BaseException:
            await proxy.aclose()
            raise
        return proxy

    def _greeting_subject(self, hello: Hello, writer: asyncio.StreamWriter) -> Subject:
        """Who greets: the name a client certificate proves (its CN; the listener's ``client_ca``
        signed it), else a configured device's name proven by its secret, else anonymous.

        A configured device's name is taken only with its secret or a certificate for that name
        (UNAUTHENTICATED otherwise), whatever the rules say."""
        certified = certificate_name(writer.get_extra_info("peercert"))
        expected = self._device_secrets.get(hello.name)
        if expected is not None and certified != hello.name:
            given = hello.extra.get("secret", "")
            if not hmac.compare_digest(given.encode(), expected.encode()):
                what = "a wrong secret" if given else "no secret"
                raise Unauthenticated(f"{hello.name!r} is a configured device; the greeting carried {what}")
            return Subject(hello.name, authenticated=True, via="secret")
        if certified:
            return Subject(certified, authenticated=True, via="certificate")
        return ANONYMOUS

    def _check_register(self, subject: Subject, name: str) -> None:
        """Refuse, audited, unless the rules let ``subject`` register ``name`` (the gRPC port's check)."""
        guard = self._guard
        if not guard.checks:
            return
        path = f"services.{name}"
        decision = guard.rules.check(subject, REGISTRY, path, Operation.REGISTER)
        if decision.allowed:
            return
        what = f"register {REGISTRY}/{path}"
        error: PropertyError
        if subject.authenticated:
            error = PermissionDenied(f"{what}: {subject.name} may not: {decision.reason}")
        else:
            error = Unauthenticated(
                f"{what}: not allowed without proof of who greets (secret= of a configured device, "
                f"or a client certificate on the listener's TLS): {decision.reason}"
            )
        guard.audited(subject, REGISTRY, path, Operation.REGISTER, error)
        raise error

    async def start(
        self, host: str, port: int, *, ssl_context: ssl.SSLContext | None = None
    ) -> tuple[str, int]:
        """Listen on ``host:port`` (0 = any free port), over TLS with ``ssl_context``; the bound address.

        The door (:class:`~gateway.connections.BoundedListener`) closes at once what is past
        ``max_connections`` (and the room eviction needs); :class:`ConnectionBounds` does the rest.
        """
        most = self.bounds.max_connections + _EVICTION_ROOM
        caps = ConnectionCaps(most, most, "limits.line_max_connections", "limits.line_max_connections")
        self._door = BoundedListener(
            self.server.tcp_protocol,
            caps,
            "gateway.line_listen",
            ssl_context=ssl_context,
            refusal=None if ssl_context is not None else _line_refusal,
            handshake_failures=None
            if ssl_context is None
            else HandshakeFailureLog("gateway.line_listen", LINE_TLS_ADVICE),
        )
        self.address = await self._door.start(host, port)
        self._reaper = asyncio.create_task(self._close_idle_connections(), name="line listener: idle")
        return self.address

    async def _close_idle_connections(self) -> None:
        pause = min(self.bounds.idle_timeout / 4, 5.0)
        while True:
            await asyncio.sleep(pause)
            self.bounds.close_idle()

    async def aclose(self) -> None:
        if self._door is not None:
            await self._door.aclose()
        if self._reaper is not None:
            self._reaper.cancel()
            await asyncio.gather(self._reaper, return_exceptions=True)
        await self.server.aclose()


def _line_refusal(reason: str) -> bytes:
    return encode(ErrorReply(int(Code.RESOURCE_EXHAUSTED), f"too many connections: {reason}; try later"))


def parse_address(address: str) -> tuple[str, int]:
    """``"HOST:PORT"`` → (host, port); InvalidArgument when it is not one."""
    host, sep, port = address.rpartition(":")
    if not sep or not port.isdigit() or int(port) > 65535:
        raise InvalidArgument(f"bad line_listen address {address!r}; expected HOST:PORT, e.g. 127.0.0.1:7100")
    return host.strip("[]") or "127.0.0.1", int(port)


async def start_line_listener(
    address: str,
    router: Router,
    on_rejoin: Callable[[str, BackendInfo], None] | None = None,
    guard: Guard | None = None,
    *,
    ssl_context: ssl.SSLContext | None = None,
    idle_timeout: float = LINE_IDLE_TIMEOUT,
    max_greetings_per_source: int = MAX_GREETINGS_PER_SOURCE,
    device_secrets: Mapping[str, str] | None = None,
    alternates: Callable[[], list[str]] | None = None,
    max_connections: int = MAX_CONNECTIONS,
    max_connections_per_address: int = MAX_CONNECTIONS_PER_ADDRESS,
    seats: DeviceSeats | None = None,
    calls: Calls | None = None,
) -> LineListener:
    """Start a :class:`LineListener` on ``address`` ("HOST:PORT") for ``router``, checked by ``guard``;
    TLS with ``ssl_context``; ``alternates``, ``seats`` and ``calls``: see :class:`LineListener`."""
    listener = LineListener(
        router,
        on_rejoin=on_rejoin,
        guard=guard,
        idle_timeout=idle_timeout,
        max_greetings_per_source=max_greetings_per_source,
        device_secrets=device_secrets,
        alternates=alternates,
        max_connections=max_connections,
        max_connections_per_address=max_connections_per_address,
        seats=seats,
        calls=calls,
    )
    await listener.start(*parse_address(address), ssl_context=ssl_context)
    return listener
