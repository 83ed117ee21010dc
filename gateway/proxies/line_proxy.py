"""A Backend for a device that speaks the line protocol: reconnects, shared listens, polling.

:class:`LineProxy` is the part common to the TCP and the serial proxy; a
subclass only says how to open the stream. The proxy

* keeps one connection, re-established with exponential backoff (bounded,
  with jitter) whenever it is lost; while it is down every call fails at once
  with UNAVAILABLE;
* times out every call (DEADLINE_EXCEEDED) and pipelines calls by tag;
* holds one device LISTEN per (property, parameters), shared by all its
  listeners (reference counted, :mod:`services.kernel.sharing`); after a reconnect
  it listens again, reads the current value and hands it to every listener
  as a ``Change(gap=True)``;
* polls a device whose greeting says ``push=0`` and forwards only changes;
* tells the listeners ``Change(removed=True)`` once when the device says a
  property is gone (GONE, or NOT_FOUND on a poll or a LISTEN after a
  reconnect), then asks for it every ``poll_interval`` while they stay, and
  hands them its value when it is back;
* pings the device every ``keepalive`` seconds and reconnects when a PONG
  does not come within ``keepalive_timeout``;
* when the device greets again unasked (it restarted and forgot its
  subscriptions) listens again and hands every listener the current value as
  a ``Change(gap=True)``;
* refuses a greeting it cannot accept with an ERR line to the device, and
  tells whoever waits for the device (a registration) why
  (docs/line-protocol.md §3).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import random
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from typing import Any, cast

from gateway.logs import outside_requests
from gateway.options import Wording, option, read_options, url_options
from gateway.proxies.connection import LineConnection
from services.kernel.backend import (
    NO_PARAMS,
    UNKNOWN_TYPE,
    Answer,
    Backend,
    BackendInfo,
    Change,
    LinkCounts,
    Notify,
    Subscription,
)
from services.kernel.errors import (
    Code,
    InvalidArgument,
    NotFound,
    PropertyError,
    ResourceExhausted,
    Unavailable,
    error_for,
)
from services.kernel.line_protocol import (
    MAX_LINE,
    MIN_MAX_LINE,
    Event,
    Frame,
    Get,
    Gone,
    Hello,
    Listen,
    Ok,
    Ping,
    Set,
    Unlisten,
)
from services.kernel.model import ServiceModel
from services.kernel.model_codec import MODEL_PATH, model_from_text
from services.kernel.sharing import SharedListen, SharedListens
from services.kernel.values import Value, as_text

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class ProxyOptions:
    """Tuning of a line-protocol proxy, set in the config's ``options`` or in the URL's query.

    A registration names them in its URL, so each number has bounds: without them
    ``keepalive=0.001`` would be a PING flood and ``timeout=1e300`` a call that never ends. Out
    of its bounds is INVALID_ARGUMENT, never silently clamped.
    """

    #: Seconds a call may take before DEADLINE_EXCEEDED.
    timeout: float = option(5.0, low=0.01, high=600.0, unit="seconds")
    #: Seconds to open the stream and receive the device's greeting.
    connect_timeout: float = option(5.0, low=0.01, high=3600.0, unit="seconds")
    #: First and longest wait between reconnection attempts; doubled per failure, with jitter.
    backoff_initial: float = option(0.2, low=0.01, high=600.0, unit="seconds")
    backoff_max: float = option(10.0, low=0.01, high=3600.0, unit="seconds")
    #: Seconds between polls of a device that cannot push events.
    poll_interval: float = option(0.5, low=0.01, high=3600.0, unit="seconds")
    #: Seconds of a healthy connection between PINGs (0 = never).
    keepalive: float = option(15.0, low=0.5, high=3600.0, off=0, unit="seconds")
    #: Seconds the device has to answer a keep-alive PING before the connection is dropped.
    keepalive_timeout: float = option(5.0, low=0.01, high=600.0, unit="seconds")
    #: Send a CRC-8 checksum on every line.
    checksum: bool = False
    #: Calls that may be in flight on the connection at once.
    max_in_flight: int = option(256, low=1, high=4096)
    #: The longest line accepted from the device, LF included (docs/device-spec.md §1.2,
    #: docs/line-protocol.md §11): raised for a device that sends large binary values. At most
    #: 8 MiB: a line with the base64 of the largest value one gRPC message carries (4 MiB) fits.
    maxline: int = option(MAX_LINE, low=MIN_MAX_LINE, high=8 * 1024 * 1024)

    @classmethod
    def parse(cls, url: str, options: Mapping[str, Any], skip: frozenset[str] = frozenset()) -> ProxyOptions:
        """Options from the URL's query, overridden by ``options``; InvalidArgument for a bad one.

        ``skip``: options that are the transport's own (a serial line's ``baudrate``)."""
        values, problems = read_options(
            cls, url_options(url, options), _WORDING, text=True, skip=sorted(skip)
        )
        if problems:
            raise InvalidArgument("; ".join(problems))
        return cls(**values)


_WORDING = Wording(
    unknown="unknown proxy option {key!r} (known: {known})", bad="bad proxy option {key}={raw}: {why}"
)

#: Seconds of refused connections (nothing listens at the device's address) after which a caller
#: waiting for the device hears so at once, rather than at the end of its wait.
REFUSED_GIVE_UP = 1.0


class _DeviceListen(SharedListen):
    """One device LISTEN (or one poller) shared by every listener of (path, parameters)."""

    def __init__(self, path: str, params: Mapping[str, str]) -> None:
        super().__init__(path, params)
        self.last: Value | None = None
        #: The device said the property is gone (NOT_FOUND, GONE); the listeners were told once.
        self.removed = False
        #: Polls a device that cannot push; for one that can, asks again for a property that went,
        #: or polls a property the device had no room to subscribe to.
        self.poller: asyncio.Task[None] | None = None
        #: The device pushes, but refused the LISTEN for lack of room (ERR 8): the property is
        #: polled instead, until an UNLISTEN makes room (docs/line-protocol.md §6).
        self.polled = False
        #: Listens again with backoff after a LISTEN that failed to start after a reconnect.
        self.relisten: asyncio.Task[None] | None = None


class LineProxy(Backend):
    """Base of the TCP and serial proxies (see the module docstring)."""

    #: Ask for the greeting after opening (a serial device greeted at its reset, long ago).
    ask_hello_first = False
    #: The stream is a serial line: a device that states no flow control gets ``inflight=1``.
    serial_line = False
    #: The proxy opens the stream itself; False for a device that dials in (the proxy waits for it).
    dials = True
    #: Seconds since the device last sent anything within which :meth:`check` counts it alive
    #: without asking (the registry's default period); after that a PING has to come back.
    heard_within = 5.0
    #: How the device is reached, as the metrics name it (a fixed, small set).
    transport = "tcp"

    def __init__(self, name: str, url: str, options: ProxyOptions) -> None:
        self.name = name
        self.url = url
        self.options = options
        self.info = BackendInfo(type=UNKNOWN_TYPE, url=url)  # until reached
        self.hello: Hello | None = None
        self._conn: LineConnection | None = None
        self._connected = asyncio.Event()
        self._runner: asyncio.Task[None] | None = None
        #: The device listens, one per (path, parameters), shared by the proxy's listeners.
        self.shared_listens: SharedListens[_DeviceListen] = SharedListens(
            _DeviceListen, self._subscribe, self._close_listen
        )
        self._tasks: set[asyncio.Task[None]] = set()
        self._last_error = "not connected yet"
        #: Why the device's last greeting was refused (another version, a bad field); None once it is served.
        self.refusal: PropertyError | None = None
        self._refused = asyncio.Event()
        #: When the device's host began refusing the connection (nothing listens there), None
        #: while it does not; set after every failed attempt for the waiters of wait_connected.
        self._refused_since: float | None = None
        self._attempt_failed = asyncio.Event()
        self._closing = False
        #: Connections made and lost and keep-alives missed, read by the metrics at scrape time.
        self.counts = LinkCounts(self.transport)
        #: Told at once when the device is connected (True) and lost (False): health follows it.
        self._link_watchers: list[Callable[[bool], None]] = []

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.name!r}, {self.url!r})"

    # -- subclass hook -----------------------------------------------------

    async def open_stream(self) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
        """Open the byte stream to the device (raise OSError when it cannot be opened)."""
        raise NotImplementedError

    async def attach(self, connection: LineConnection) -> None:
        """Open the stream to the device and serve ``connection`` on it (OSError when it cannot be opened).

        By default over the stream of :meth:`open_stream`, read by a task of the
        connection; a proxy that can open a transport for the connection's own
        protocol (TCP) overrides this and saves that task and a copy per read.
        """
        reader, writer = await self.open_stream()
        connection.read_from(reader, writer)

    # -- lifecycle ---------------------------------------------------------

    async def start(self) -> None:
        if self._runner is None:
            self._runner = asyncio.create_task(
                self._run(), name=f"proxy {self.name}", context=outside_requests(self.name)
            )

    async def aclose(self) -> None:
        self._closing = True
        self._last_error = "proxy closed"
        if self._runner is not None:
            self._runner.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._runner
        pollers = [
            task
            for entry in self.shared_listens
            for task in (entry.poller, entry.relisten)
            if task is not None
        ]
        for poller in pollers:
            poller.cancel()
        tasks = [*self._tasks, *pollers]
        for task in self._tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        if self._conn is not None:
            await self._conn.aclose("proxy closed")

    async def wait_connected(self, wait_s: float) -> None:
        """Wait until the device is connected and has greeted (tests, startup).

        Raises the refusal (FAILED_PRECONDITION for another protocol version,
        INVALID_ARGUMENT for a bad greeting) as soon as the device's greeting
        was refused, and Unavailable, saying why, on timeout, or as soon as the
        device's host has refused the connection for ``REFUSED_GIVE_UP``
        seconds (nothing listens there: waiting longer only eats the caller's
        deadline).
        """
        if not self._connected.is_set():
            try:
                async with asyncio.timeout(wait_s):
                    while not (self._connected.is_set() or self._refused.is_set()):
                        if self._refused_for() >= REFUSED_GIVE_UP:
                            raise Unavailable(
                                f"{self._label()}: connection refused for "
                                f"{self._refused_for():.1f} s ({self._last_error})"
                            )
                        self._attempt_failed.clear()
                        waits = [
                            asyncio.ensure_future(event.wait())
                            for event in (self._connected, self._refused, self._attempt_failed)
                        ]
                        try:
                            await asyncio.wait(waits, return_when=asyncio.FIRST_COMPLETED)
                        finally:
                            for waiting in waits:
                                waiting.cancel()
            except TimeoutError:
                raise Unavailable(
                    f"{self._label()}: not connected after {wait_s:g} s ({self._last_error})"
                ) from None
        if not self._connected.is_set() and self.refusal is not None:
            raise error_for(self.refusal.code, self.refusal.message)

    def _refused_for(self) -> float:
        """Seconds the device's host has refused every connection attempt (0 when it has not)."""
        return 0.0 if self._refused_since is None else time.monotonic() - self._refused_since

    @property
    def connected(self) -> bool:
        return self._connected.is_set()

    def link_counts(self) -> LinkCounts:
        self.counts.connected = self._connected.is_set()
        return self.counts

    def _label(self) -> str:
        return f"device {self.name} at {self.url}"

    def watch_link(self, listener: Callable[[bool], None]) -> Callable[[], None]:
        self._link_watchers.append(listener)

        def unwatch() -> None:
            if listener in self._link_watchers:
                self._link_watchers.remove(listener)

        return unwatch

    def _tell_link(self, connected: bool) -> None:
        for listener in list(self._link_watchers):
            try:
                listener(connected)
            except Exception:
                log.exception("%s: a watcher of the link failed", self._label())

    async def _run(self) -> None:
        failures = 0
        while not self._closing:
            conn = await self._connect()
            if conn is None:
                failures += 1
                delay = min(
                    self.options.backoff_max, self.options.backoff_initial * 2 ** min(failures - 1, 30)
                )
                await asyncio.sleep(delay * random.uniform(0.5, 1.0))
                continue
            failures = 0
            self._conn = conn
            self.refusal = None
            self._refused.clear()
            self._connected.set()
            self.counts.connects += 1
            self._tell_link(True)
            self._spawn(self._resubscribe(conn))
            try:
                await self._supervise(conn)
            finally:
                self._tell_link(False)
            self._connected.clear()
            if not self._closing:
                self.counts.disconnects += 1
            self._last_error = conn.close_reason
            if self.dials:
                log.warning("%s: disconnected (%s); reconnecting", self._label(), conn.close_reason)
            else:
                log.warning(
                    "%s: disconnected (%s); it cannot be dialled: waiting for it to dial in again",
                    self._label(),
                    conn.close_reason,
                )
            # Pollers and listeners stay; the next connection picks them up.
            await asyncio.sleep(self.options.backoff_initial * random.uniform(0.5, 1.0))

    async def _connect(self) -> LineConnection | None:
        conn = LineConnection(
            label=f"device {self.name}",
            on_event=self._on_event,
            checksum=self.options.checksum,
            max_in_flight=self.options.max_in_flight,
            serial=self.serial_line,
            on_restart=self._restarted,
            receive_limit=self.options.maxline,
        )
        try:
            async with asyncio.timeout(self.options.connect_timeout):
                await self.attach(conn)
        except (OSError, TimeoutError) as exc:
            self._last_error = f"cannot connect: {exc or 'timed out'}"
            if isinstance(exc, ConnectionRefusedError):
                if self._refused_since is None:
                    self._refused_since = time.monotonic()
            else:
                self._refused_since = None
            self._attempt_failed.set()
            log.info("%s: %s", self._label(), self._last_error)
            conn.hello.cancel()  # nobody will wait for a greeting on a stream that never opened
            await conn.aclose(self._last_error)
            return None
        self._refused_since = None
        try:
            async with asyncio.timeout(self.options.connect_timeout):
                if self.ask_hello_first:
                    # A board that resets when its port opens (DTR) runs its bootloader first, which
                    # eats the HELLO, and may send a fragment of a line before its boot greeting:
                    # while the line stays silent, the HELLO went unheard; ask again (every answer
                    # counts as one, §4.4). A device that is answering is never asked twice.
                    conn.ask_hello()
                    every = self.options.connect_timeout / 2  # as a TCP device is asked (below)
                    while not (await asyncio.wait([conn.hello], timeout=every))[0]:
                        if time.monotonic() - conn.last_heard >= every:
                            conn.ask_hello()
                    hello = await conn.hello
                else:
                    done, _ = await asyncio.wait([conn.hello], timeout=self.options.connect_timeout / 2)
                    if not done:  # a device that greeted before we listened; ask again
                        conn.ask_hello()
                    hello = await conn.hello
        except PropertyError as exc:
            if exc.code == Code.UNAVAILABLE:
                self._last_error = f"no greeting from the device: {exc.message}"
                log.warning("%s: %s", self._label(), self._last_error)
            else:  # refused: the connection told the device with an ERR line (docs/line-protocol.md §3)
                self._last_error = exc.message
                self.refusal = exc
                self._refused.set()
            await conn.aclose(self._last_error)
            return None
        except TimeoutError:
            self._last_error = "no greeting from the device: timed out"
            log.warning("%s: %s", self._label(), self._last_error)
            await conn.aclose(self._last_error)
            return None
        self._take_greeting(hello)
        log.info("%s: connected (%s, push=%d)", self._label(), hello.name or "unnamed", hello.push)
        return conn

    def _take_greeting(self, hello: Hello) -> None:
        self.hello = hello
        self.info.type = hello.type or "resource"
        self.info.extra.update({"device_name": hello.name, "push": "1" if hello.push else "0"})

    def _restarted(self, hello: Hello) -> None:
        """The device greeted again unasked: it forgot its subscriptions; listen again, marked as a gap."""
        conn = self._conn
        self._take_greeting(hello)
        if conn is not None and not conn.closed:
            self._spawn(self._resubscribe(conn))

    async def _supervise(self, conn: LineConnection) -> None:
        keepalive = self.options.keepalive
        while not conn.closed:
            if keepalive <= 0:
                await conn.wait_closed()
                return
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(keepalive):
                    await conn.wait_closed()
                return
            try:
                await conn.request(Ping(), self.options.keepalive_timeout)
            except PropertyError as exc:
                if exc.code == Code.UNAVAILABLE:
                    return
                self.counts.keepalive_failures += 1
                await conn.aclose(f"no answer to keep-alive: {exc.message}")
                return

    def _spawn(self, coro: Any) -> None:
        task = asyncio.create_task(coro)
        self._tasks.add(task)
        task.add_done_callback(self._task_ended)

    def _task_ended(self, task: asyncio.Task[Any]) -> None:
        """A background task ended: forget it, and log (never leave unretrieved) what it raised."""
        self._tasks.discard(task)
        if not task.cancelled() and (exc := task.exception()) is not None:
            log.error("%s: %s failed", self._label(), task.get_name(), exc_info=exc)

    def _background(self, coro: Any, name: str) -> asyncio.Task[None]:
        """A poller or a retry of one shared listen: outside any request, its failure logged."""
        task: asyncio.Task[None] = asyncio.create_task(coro, name=name, context=outside_requests(self.name))
        task.add_done_callback(self._task_ended)
        return task

    # -- calls -------------------------------------------------------------

    def _live(self) -> LineConnection:
        conn = self._conn
        if conn is None or conn.closed or not self._connected.is_set():
            raise Unavailable(f"{self._label()} is not connected ({self._last_error})")
        return conn

    async def _call(self, frame: Get | Set | Listen | Unlisten) -> Value:
        # A binary value comes as bytes (the codec reads ``\=`` and base64) and goes on as bytes.
        reply = await self._live().request(frame, self.options.timeout)
        assert isinstance(reply, Ok)
        return reply.value

    async def get(self, path: str, params: Mapping[str, str] = NO_PARAMS) -> Value:
        return await self._call(Get(path, dict(params)))

    async def check(self) -> None:
        """Alive when connected and heard from lately, or when a PING comes back within the timeout.

        Costs the device nothing while it talks anyway, and at most a PING
        (never a property listing); UNAVAILABLE when not connected.
        """
        conn = self._live()
        if time.monotonic() - conn.last_heard <= self.heard_within:
            return
        await conn.request(Ping(), self.options.timeout)

    def flush(self) -> None:
        """Send the lines held for the end of this loop turn now (:meth:`LineConnection.flush`)."""
        conn = self._conn
        if conn is not None:
            conn.flush()

    def start_get(
        self,
        path: str,
        params: Mapping[str, str],
        time_limit: float,
        then: Callable[[Answer], None] | None = None,
    ) -> asyncio.Future[Answer] | None:
        """Send a GET of ``path`` now; return the future of its reply, an :class:`Ok` frame.

        For callers that would otherwise wrap :meth:`get` in a task and a
        timeout of their own: the reply resolves the future straight from
        the connection's reader, and the one timer is the connection's. The
        future fails with the call's PropertyError (DEADLINE_EXCEEDED after
        ``time_limit`` or the proxy's own timeout, whichever is shorter).
        ``then`` has the Ok frame in the reader, before the future is resolved
        (:meth:`Backend.start_get`). Raises Unavailable when the device is not connected; returns None,
        sending nothing, when every request slot is taken (await :meth:`get`).
        """
        frame = Get(path, dict(params) if params else {})
        # The future resolves to an Ok frame (errors fail it), which carries the value.
        return cast(
            "asyncio.Future[Answer] | None",
            self._live().start_request(
                frame, min(time_limit, self.options.timeout), cast("Callable[[Frame], None] | None", then)
            ),
        )

    async def set(self, path: str, value: Value, params: Mapping[str, str] = NO_PARAMS) -> Value:
        try:
            return await self._call(Set(path, value, dict(params)))
        except InvalidArgument as exc:
            # A device that knows no ``\=`` (line protocol 1.1), or whose property takes text,
            # refuses a binary value as a bad escape (docs/line-protocol.md §11): say so plainly.
            if isinstance(value, str) or "escape" not in exc.message:
                raise
            raise InvalidArgument(
                f"{self._label()} does not take binary values for {path!r} (it answered: "
                f"{exc.message}); a device takes bytes from line protocol 1.2 on, for a property "
                "of type bytes"
            ) from None

    async def describe(self) -> ServiceModel:
        """The device's own model when it describes itself (``GET properties.model``), else names only.

        A device that does not describe itself answers NOT_FOUND (or anything
        that is not a model, or a line too long): its properties are then of
        type and access ``unknown`` (docs/line-protocol.md).
        """
        try:
            text = as_text(await self.get(MODEL_PATH), MODEL_PATH)
            return self._fit_the_line(model_from_text(text, self.info.type))
        except PropertyError as e:
            if e.code not in (Code.NOT_FOUND, Code.INVALID_ARGUMENT, Code.RESOURCE_EXHAUSTED, Code.DATA_LOSS):
                raise
            log.debug("%s does not describe itself (%s)", self._label(), e.message)
        return await super().describe()

    def _fit_the_line(self, model: ServiceModel) -> ServiceModel:
        """A binary property's ``max_size``: at most what one line carries as base64 (line-protocol §11)."""
        conn = self._conn
        if conn is None:
            return model
        fitted = []
        for prop in model.properties:
            if prop.type == "bytes":
                most = conn.largest_binary(prop.name)
                fitted.append(replace(prop, max_size=min(prop.max_size, most) if prop.max_size else most))
            else:
                fitted.append(prop)
        return replace(model, properties=tuple(fitted))

    # -- listening ---------------------------------------------------------

    def _pushes(self) -> bool:
        return self.hello is not None and self.hello.push

    async def listen(self, path: str, notify: Notify, params: Mapping[str, str] = NO_PARAMS) -> Subscription:
        return await self.shared_listens.listen(path, notify, params)

    async def listen_current(
        self, path: str, notify: Notify, params: Mapping[str, str] = NO_PARAMS
    ) -> tuple[Subscription, Value]:
        """Listen, and take the current value from the LISTEN's OK: no GET after it (device-spec §3)."""
        share = await self.shared_listens.listen(path, notify, params)
        last = share.entry.last
        if last is None:  # the property went meanwhile: what is there now (NOT_FOUND if nothing)
            try:
                last = await self.get(path, params)
            except BaseException:
                await share.close()
                raise
        return share, last

    async def _subscribe(self, entry: _DeviceListen) -> None:
        self._live()
        entry.last = await self._open_on_device(entry)

    async def _open_on_device(self, entry: _DeviceListen) -> Value:
        """LISTEN to the entry's property and return its value; a device that cannot push it
        (``push=0``, or no room left in its subscription table) has it polled instead."""
        if self._pushes():
            try:
                value = await self._call(Listen(entry.path, dict(entry.params)))
            except ResourceExhausted as exc:
                # The device's subscription table is full: this path is polled, the others of the
                # same Listen keep their LISTENs, and an UNLISTEN that makes room upgrades it.
                log.info(
                    "%s: no room to LISTEN to %s (%s): polling it every %g s",
                    self._label(),
                    entry.path,
                    exc.message,
                    self.options.poll_interval,
                )
                entry.polled = True
            else:
                entry.polled = False
                return value
        value = await self._call(Get(entry.path, dict(entry.params)))
        if entry.poller is None or entry.poller.done():
            entry.poller = self._background(self._poll(entry), f"poll {self.name}.{entry.path}")
        return value

    async def _close_listen(self, entry: _DeviceListen) -> None:
        """The last listener left: stop polling, or UNLISTEN when no listen of the path is left."""
        for task in (entry.poller, entry.relisten):
            if task is not None:
                task.cancel()
        # The device keeps one subscription per path (docs/device-spec.md §3.3), whatever the parameters.
        if (
            entry.removed
            or entry.polled
            or not (self.connected and self._pushes())
            or any(not other.polled for other in self.shared_listens.on_path(entry.path))
        ):
            return
        try:
            await self._call(Unlisten(entry.path))
        except PropertyError as exc:
            # While the proxy closes, its connection goes away under the UNLISTEN: expected, not news.
            level = logging.DEBUG if self._closing else logging.INFO
            log.log(level, "%s: UNLISTEN %s failed: %s", self._label(), entry.path, exc.message)
            return
        self._upgrade_a_polled_listen()

    def _upgrade_a_polled_listen(self) -> None:
        """An UNLISTEN made room in the device's table: the oldest polled property gets it."""
        for entry in self.shared_listens:
            if entry.polled and not entry.removed:
                self._spawn(self._upgrade(entry))
                return

    async def _upgrade(self, entry: _DeviceListen) -> None:
        try:
            value = await self._call(Listen(entry.path, dict(entry.params)))
        except PropertyError as exc:
            log.info("%s: %s stays polled: %s", self._label(), entry.path, exc.message)
            return
        if not self.shared_listens.holds(entry):
            # Its last listener left meanwhile: give the room back.
            if not self.shared_listens.on_path(entry.path):
                with contextlib.suppress(PropertyError):
                    await self._call(Unlisten(entry.path))
            return
        entry.polled = False
        if entry.poller is not None:
            entry.poller.cancel()
        if value != entry.last:
            entry.last = value
            entry.deliver(Change(entry.path, value))

    def _on_event(self, frame: Event | Gone) -> None:
        # EVENT and GONE name only the path: every listen of it hears them, whatever its parameters.
        entries = self.shared_listens.on_path(frame.path)
        if not entries:
            log.debug("%s: event for %s, which nobody listens to", self._label(), frame.path)
            return
        for entry in entries:
            if isinstance(frame, Gone):
                self._went(entry)
            else:
                entry.removed = False
                entry.last = frame.value
                entry.deliver(Change(frame.path, frame.value))

    def _went(self, entry: _DeviceListen) -> None:
        """The property is gone: tell the listeners once, then ask for it until it is back."""
        if entry.removed:
            return
        entry.removed = True
        entry.last = None
        entry.deliver(Change(entry.path, "", removed=True))
        if entry.poller is None or entry.poller.done():
            entry.poller = self._background(self._poll(entry), f"await {self.name}.{entry.path}")

    async def _resubscribe(self, conn: LineConnection) -> None:
        """After a (re)connection: listen again and hand every listener the current value, marked as a gap."""
        for entry in self.shared_listens:
            if entry.ready is not None and not entry.ready.done():
                continue  # its first LISTEN is under way on this connection
            if not self.shared_listens.holds(entry) or conn.closed:
                continue
            try:
                value = await self._open_on_device(entry)
            except NotFound:
                self._went(entry)
                continue
            except PropertyError as exc:
                # Not a dead stream: it listens again with backoff, and the listeners get a gap.
                log.warning(
                    "%s: cannot listen to %s again (%s): trying again with backoff",
                    self._label(),
                    entry.path,
                    exc.message,
                )
                if entry.relisten is None or entry.relisten.done():
                    entry.relisten = self._background(
                        self._relisten(entry, conn), f"listen again {self.name}.{entry.path}"
                    )
                continue
            self._reopened(entry, value)

    def _reopened(self, entry: _DeviceListen, value: Value) -> None:
        entry.removed = False
        entry.last = value
        entry.deliver(Change(entry.path, value, gap=True))

    async def _relisten(self, entry: _DeviceListen, conn: LineConnection) -> None:
        """LISTEN again with backoff until it starts, the connection ends or the listeners leave.

        A new connection listens to everything again itself; a property that went is asked for by
        its poller.
        """
        options = self.options
        delay = options.backoff_initial
        while self.shared_listens.holds(entry) and not conn.closed:
            await asyncio.sleep(delay * random.uniform(0.5, 1.0))
            delay = min(options.backoff_max, delay * 2)
            if conn.closed or not self.shared_listens.holds(entry):
                return
            try:
                value = await self._open_on_device(entry)
            except NotFound:
                self._went(entry)
                return
            except PropertyError as exc:
                log.info("%s: listening to %s again failed: %s", self._label(), entry.path, exc.message)
                continue
            self._reopened(entry, value)
            return

    async def _poll(self, entry: _DeviceListen) -> None:
        """Poll a device that cannot push; for one that can, LISTEN until a property that went is back."""
        interval = self.options.poll_interval
        while self.shared_listens.holds(entry):
            await asyncio.sleep(interval)
            if not self.connected:
                continue
            pushes = self._pushes() and not entry.polled
            if pushes and not entry.removed:
                return  # the device pushes the property's changes again
            try:
                if pushes:
                    value = await self._call(Listen(entry.path, dict(entry.params)))
                else:
                    value = await self._call(Get(entry.path, dict(entry.params)))
            except NotFound:
                self._went(entry)
                continue
            except PropertyError as exc:
                log.info("%s: poll of %s failed: %s", self._label(), entry.path, exc.message)
                continue
            if self.shared_listens.holds(entry) and (entry.removed or value != entry.last):
                entry.removed = False
                entry.last = value
                entry.deliver(Change(entry.path, value))
