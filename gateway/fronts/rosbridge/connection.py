"""One rosbridge client: its operations carried out through the engine, its subscriptions written.

A :class:`Connection` is handed each text message the client sends (:meth:`Connection.received`)
and writes through one ``send`` coroutine the WebSocket handler gives it. Every call goes through
the engine as the connection's subject (the WebSocket's, or the one an ``auth`` op named): a
``subscribe`` opens a listen-hub stream (the same rules, limits and conflating queue as a gRPC
Listen or an event stream), a ``publish`` is a Set, a ``call_service`` an action's Set or a
query's Get (or a rosapi question, :mod:`gateway.fronts.rosbridge.rosapi`).

Bounds: at most :data:`MAX_SUBSCRIPTIONS` topics and :data:`MAX_CALLS_IN_FLIGHT` service calls a
connection (past the latter the connection reads no further message until one ends); each
subscription's writer holds at most one message while the client is slow, and its stream keeps
only the latest value meanwhile, so a client that reads slowly gets the latest, never a backlog.
"""

from __future__ import annotations

import asyncio
import logging
import math
from collections import OrderedDict
from collections.abc import Awaitable, Callable, Iterable, Mapping
from contextlib import aclosing, suppress
from dataclasses import dataclass, field
from typing import Any

from gateway.engine.calls import Calls
from gateway.engine.events import Event, ListenRequest, Mark, Selector
from gateway.engine.guard import Guard
from gateway.engine.listen import ListenHub, ListenStream
from gateway.engine.listen.drain import Wake, taken
from gateway.engine.listen.requests import check_listen
from gateway.engine.rules import Subject
from gateway.engine.status import to_property_error
from gateway.engine.types import DescribeCall, GetCall, SetCall
from gateway.fronts.rosbridge import protocol
from gateway.fronts.rosbridge.rosapi import ROSAPI_PREFIX, Rosapi
from services.kernel import ros_messages as messages
from services.kernel.backend import NO_PARAMS
from services.kernel.errors import (
    Code,
    InvalidArgument,
    NotFound,
    PropertyError,
    ResourceExhausted,
)
from services.kernel.model import Access, PropertyModel, ServiceModel
from services.kernel.ros_names import Target, for_service, global_name, parse_name
from services.kernel.values import Marker, Value, format_marker, format_number, parse_names, parse_vector

log = logging.getLogger(__name__)

#: Topics one connection may subscribe to at once (a dashboard shows tens; each holds a hub
#: stream and at most one message in writing).
MAX_SUBSCRIPTIONS = 256
#: Service calls one connection runs at once; the next message waits for a place.
MAX_CALLS_IN_FLIGHT = 16
#: Service models a connection keeps (each read by Describe once, for the types of its topics).
MAX_MODELS = 64
#: A Describe refused with one of these is remembered as "no model" (the caller's topics of that
#: service are plain strings, each read still checked by the rules).
REFUSED = frozenset((Code.PERMISSION_DENIED, Code.UNAUTHENTICATED))
#: The smallest fragment_size honoured: smaller ones would multiply frames for nothing.
MIN_FRAGMENT = 256

#: Writes one text frame (its UTF-8 bytes) to the client.
Send = Callable[[bytes], Awaitable[None]]
#: The copies of a large message a slow reader holds while it is written: the encoded message and
#: the transport's copy of what the socket did not take (counted against limits.max_pending_binary).
WRITE_COPIES = 2


def error_text(err: PropertyError) -> str:
    """A refusal as rosbridge clients show it: the code's name, then the gateway's message."""
    return f"{err.code.name}: {err.message}"


@dataclass
class Subscription:
    """One subscribed topic: its property, message type, options and listen-hub stream."""

    topic: str
    target: Target
    type: str
    media_type: str
    throttle_rate: int
    fragment_size: int
    stream: ListenStream
    #: The ids of the ``subscribe`` ops that asked for it (an ``unsubscribe`` names one).
    idents: set[str | None] = field(default_factory=set)
    writer: asyncio.Task[None] | None = None
    #: Messages written so far: a fragmented one's id is ``publish:TOPIC:N``, each its own.
    written: int = 0

    def same_options(self, op: protocol.Subscribe, type_name: str) -> bool:
        return (self.type, self.throttle_rate, self.fragment_size) == (
            type_name,
            op.throttle_rate,
            _fragment(op.fragment_size),
        )


def _fragment(size: int) -> int:
    return 0 if size <= 0 else max(size, MIN_FRAGMENT)


class Connection:
    """The operations of one rosbridge client; see the module docstring."""

    def __init__(
        self,
        *,
        calls: Calls,
        hub: ListenHub,
        guard: Guard,
        subject: Subject,
        send: Send,
        peer: str,
    ) -> None:
        self.calls = calls
        self.hub = hub
        self.guard = guard
        self.subject = subject
        self.peer = peer
        self._send = send
        #: Why the connection must end (a refused ``auth``); None while it may go on.
        self.refused: str | None = None
        self.subscriptions: dict[str, Subscription] = {}
        #: Types of the topics this client advertised (what its publish messages are).
        self.advertised: dict[str, str] = {}
        self.status_level = "error"
        self._models: OrderedDict[str, ServiceModel | None] = OrderedDict()
        self._calls: set[asyncio.Task[None]] = set()
        self._call_places = asyncio.Semaphore(MAX_CALLS_IN_FLIGHT)
        #: Frames go out one message at a time (a fragmented one together).
        self._sending = asyncio.Lock()
        self.rosapi = Rosapi(calls, guard)
        self.closed = False

    # -- sending -----------------------------------------------------------

    async def send(self, frames: Iterable[str]) -> None:
        """Write ``frames`` in order, none of another message between them (each encoded as it goes)."""
        async with self._sending:
            for frame in frames:
                await self._send(frame.encode())

    async def send_encoded(self, data: bytes) -> None:
        async with self._sending:
            await self._send(data)

    async def report(self, level: str, text: str, ident: str | None = None) -> None:
        """A ``status`` message, when the client's ``set_level`` lets it hear ``level``."""
        if protocol.heard(level, self.status_level):
            await self.send([protocol.status(level, text, ident)])

    # -- receiving ---------------------------------------------------------

    async def received(self, text: str | bytes) -> None:
        """Carry out one message of the client; what goes wrong is told as rosbridge does."""
        try:
            op = protocol.parse(text)
        except protocol.BadMessage as exc:
            prefix = f"{exc.op}: " if exc.op and not exc.message.startswith(exc.op) else ""
            await self.report("error", prefix + exc.message, exc.ident)
            return
        try:
            await self._carry_out(op)
        except ConnectionError:
            raise  # the client went away: the WebSocket's loop ends
        except Exception as exc:
            # A bug is logged once with its traceback and told as INTERNAL; the connection goes on.
            err = to_property_error(exc, f"rosbridge {_op_name(op)}")
            await self.report("error", f"{_op_name(op)} {_what(op)}: {error_text(err)}", _ident(op))

    async def _carry_out(self, op: protocol.Operation) -> None:
        if isinstance(op, protocol.Subscribe):
            await self.subscribe(op)
        elif isinstance(op, protocol.Unsubscribe):
            self.unsubscribe(op.topic, op.ident)
        elif isinstance(op, protocol.Publish):
            await self.publish(op)
        elif isinstance(op, protocol.CallService):
            await self._call_places.acquire()
            task = asyncio.create_task(self._call(op))
            self._calls.add(task)
            task.add_done_callback(self._call_done)
        elif isinstance(op, protocol.Advertise):
            await self.advertise(op)
        elif isinstance(op, protocol.Unadvertise):
            self.advertised.pop(op.topic, None)
        elif isinstance(op, protocol.Auth):
            self.authenticate(op.token)
        elif isinstance(op, protocol.SetLevel):
            self.status_level = op.level

    def _call_done(self, task: asyncio.Task[None]) -> None:
        self._calls.discard(task)
        self._call_places.release()

    def authenticate(self, token: str) -> None:
        """The subject of the bearer ``token`` from now on; a bad token ends the connection
        (:attr:`refused`), as rosbridge ends one whose ``auth`` fails."""
        try:
            self.subject = self.guard.identify([("authorization", f"Bearer {token}")], {})
        except PropertyError as exc:
            self.refused = f"auth refused: {error_text(exc)}"
            raise

    # -- models --------------------------------------------------------------

    async def model(self, service: str) -> ServiceModel | None:
        """The service's model, read once per connection; None when it cannot be read (refused)."""
        if service in self._models:
            self._models.move_to_end(service)
            return self._models[service]
        try:
            found: ServiceModel | None = await self.calls.describe(
                DescribeCall(service), self.calls.timeout, self.subject
            )
        except PropertyError as exc:
            if exc.code not in REFUSED:
                raise  # gone, or not answering now: said as it is, and asked again next time
            found = None  # the caller may not describe it: its topics are plain strings
        self._models[service] = found
        if len(self._models) > MAX_MODELS:
            self._models.popitem(last=False)
        return found

    async def resolve(self, name: str, what: str) -> tuple[Target, PropertyModel | None]:
        """The property a topic or service name stands for, and its model when it can be read."""
        target = parse_name(name, what)
        model = await self.model(target.service)
        if model is None:
            return target, None
        target = for_service(target, model.type)
        for prop in model.properties:
            if prop.name == target.path:
                return target, prop
        raise NotFound(f"{target.service} has no property {target.path[:300]!r}")

    # -- topics --------------------------------------------------------------

    async def subscribe(self, op: protocol.Subscribe) -> None:
        target, prop = await self.resolve(op.topic, "topic")
        if prop is not None and not prop.access.listenable:
            raise InvalidArgument(
                f"{target.service}/{target.path} is {prop.access.value}: call it as a service, not a topic"
            )
        type_name = (
            messages.check_type(op.type, prop, target.convention, op.topic)
            if prop is not None
            else messages.STRING
        )
        old = self.subscriptions.get(op.topic)
        if old is not None and old.same_options(op, type_name):
            old.idents.add(op.ident)
            return
        if old is None and len(self.subscriptions) >= MAX_SUBSCRIPTIONS:
            raise ResourceExhausted(f"a connection may subscribe to at most {MAX_SUBSCRIPTIONS} topics")
        request = ListenRequest([Selector(target.service, target.path)], min_interval=op.throttle_rate / 1000)
        selectors, options = check_listen(request, self.hub.limits)
        wake = Wake()
        stream = self.hub.open(selectors, options, wake.set, self.subject)
        if old is not None:
            self._end(old)
        sub = Subscription(
            op.topic,
            target,
            type_name,
            prop.media_type if prop is not None else "",
            op.throttle_rate,
            _fragment(op.fragment_size),
            stream,
            {op.ident},
        )
        self.subscriptions[op.topic] = sub
        sub.writer = asyncio.create_task(self._write(sub, wake))

    def unsubscribe(self, topic: str, ident: str | None) -> None:
        sub = self.subscriptions.get(topic)
        if sub is None:
            return
        if ident is not None and len(sub.idents) > 1:
            sub.idents.discard(ident)
            return
        self._end(sub)

    def _end(self, sub: Subscription) -> asyncio.Task[None] | None:
        """Close ``sub``'s stream and cancel its writer (returned, to be awaited by who wants)."""
        if self.subscriptions.get(sub.topic) is sub:
            del self.subscriptions[sub.topic]
        sub.stream.close()
        # The writer's frame holds ``sub``: without this, a cancelled writer's traceback and the
        # subscription would keep each other (and the message being written) until a full GC.
        writer, sub.writer = sub.writer, None
        if writer is None or writer is asyncio.current_task():
            return None
        writer.cancel()
        return writer

    async def _write(self, sub: Subscription, wake: Wake) -> None:
        """Write one subscription's messages as its stream has them, one at a time."""
        budget = self.hub.budget
        try:
            async with aclosing(taken(sub.stream, wake)) as ready:
                async for item in ready:
                    if isinstance(item, Mark):
                        continue  # rosbridge has no sync marker or heartbeat
                    for event in item:
                        if event.removed:
                            continue
                        text = self._message(sub, event)
                        size = len(text) * WRITE_COPIES
                        if not budget.take(size):
                            raise budget.refusal(size, f"topic {sub.topic[:200]}")
                        try:
                            if sub.fragment_size and len(text) > sub.fragment_size:
                                await self.send(
                                    protocol.fragments(text, sub.fragment_size, _fragment_id(sub))
                                )
                            else:
                                data = text.encode()
                                del text  # the encoded message is the one copy held while it waits
                                await self.send_encoded(data)
                                del data
                        finally:
                            budget.give_back(size)
        except asyncio.CancelledError:
            raise
        except ConnectionError:
            return
        except Exception as exc:
            err = to_property_error(exc, f"topic {sub.topic[:200]}")
            self._end(sub)
            with suppress(ConnectionError):
                await self.report(
                    "error", f"subscribe {sub.topic[:200]}: {error_text(err)}", _first(sub.idents)
                )

    def _message(self, sub: Subscription, event: Event) -> str:
        msg = messages.to_message(sub.type, event.value, stamp_ns=event.time_ns, media_type=sub.media_type)
        return protocol.publish(sub.topic, msg)

    async def advertise(self, op: protocol.Advertise) -> None:
        target, prop = await self.resolve(op.topic, "topic")
        if prop is not None and not prop.access.writable:
            raise InvalidArgument(
                f"{target.service}/{target.path} is {prop.access.value}: it cannot be published"
            )
        type_name = (
            messages.check_type(op.type, prop, target.convention, op.topic)
            if prop is not None
            else messages.STRING
        )
        self.advertised[op.topic] = type_name

    async def publish(self, op: protocol.Publish) -> None:
        target, prop = await self.resolve(op.topic, "topic")
        if prop is not None and prop.access in (Access.ACTION, Access.QUERY):
            raise InvalidArgument(
                f"{target.service}/{target.path} is {prop.access.value}: call it with call_service"
            )
        if prop is None:
            type_name = self.advertised.get(op.topic, messages.STRING)
        else:
            type_name = messages.check_type(self.advertised.get(op.topic), prop, target.convention, op.topic)
        value = messages.from_message(type_name, op.msg, f"publish {op.topic[:200]}")
        if target.convention == "cmd_vel" and isinstance(value, str):
            value = await self._world_velocity(target.service, value)
        await self.calls.set(
            SetCall(target.service, target.path, value, NO_PARAMS), self.calls.timeout, self.subject
        )

    async def _world_velocity(self, robot: str, twist: str) -> str:
        """A ``cmd_vel`` (the robot's frame) as the ``velocity`` of the world frame, by its heading now."""
        location = await self.calls.get(GetCall(robot, "location"), self.calls.timeout, self.subject)
        pose = [float(x) for x in parse_vector(_text(location.value))]
        yaw = pose[5] if len(pose) >= 6 else 0.0
        numbers = [float(x) for x in parse_vector(twist)]
        world = messages.robot_to_world(numbers, yaw)
        return "(" + " ".join(format_number(x) for x in world) + ")"

    # -- services ------------------------------------------------------------

    async def _call(self, op: protocol.CallService) -> None:
        try:
            values: Any = await self.call_service(op)
            result = True
        except PropertyError as exc:
            values, result = error_text(exc), False
        except Exception as exc:
            values, result = error_text(to_property_error(exc, f"call_service {op.service[:200]}")), False
        text = protocol.service_response(op.ident, op.service, values, result)
        ident = op.ident if op.ident is not None else f"call_service:{op.service[:200]}"
        with suppress(ConnectionError):
            await self.send(protocol.fragments(text, _fragment(op.fragment_size), ident))

    async def call_service(self, op: protocol.CallService) -> Any:
        """The response values of a service call: rosapi, an action (a Set), a query or a property (a Get)."""
        if global_name(op.service).startswith(ROSAPI_PREFIX):
            return await self.rosapi.answer(global_name(op.service), op.args, self.subject)
        target, prop = await self.resolve(op.service, "service")
        limit = min(op.timeout, self.calls.timeout) if op.timeout > 0 else self.calls.timeout
        args = op.args if op.args is not None else {}
        if isinstance(args, list) and not args:
            args = {}
        if not isinstance(args, Mapping):
            raise InvalidArgument(f"call_service {op.service[:200]}: args must be a JSON object")
        if prop is not None and prop.access == Access.ACTION:
            value, parameters = action_value(prop, args)
            answer = await self.calls.set(
                SetCall(target.service, target.path, value, parameters), limit, self.subject
            )
            return {"success": True, "message": _text(answer)}
        parameters = {key: _parameter(key, x) for key, x in args.items()}
        reply = await self.calls.get(
            GetCall(target.service, target.path, parameters or NO_PARAMS), limit, self.subject
        )
        return query_values(prop, reply.value)

    # -- closing -------------------------------------------------------------

    async def aclose(self) -> None:
        """End every subscription and call of the connection."""
        self.closed = True
        tasks = [
            writer for sub in list(self.subscriptions.values()) if (writer := self._end(sub)) is not None
        ]
        for task in list(self._calls):
            task.cancel()
            tasks.append(task)
        for task in tasks:
            with suppress(asyncio.CancelledError, Exception):
                await task


def _parameter(key: str, x: object) -> str:
    """An ``args`` field as a request parameter's text."""
    if isinstance(x, str):
        return x
    if isinstance(x, bool):
        return "true" if x else "false"
    if isinstance(x, int | float) and math.isfinite(x):
        return format_number(x)
    raise InvalidArgument(f"argument {key[:100]!r} must be text, a number or a boolean")


def action_value(prop: PropertyModel, args: Mapping[str, Any]) -> tuple[Value, Mapping[str, str]]:
    """The value and request parameters of an action's Set from a service call's ``args``.

    The action's value is the field named as its value (``target`` of ``moveto``) or ``value``;
    a marker may also be given as its location: ``{"x": 1, "y": 2}`` (a ``geometry_msgs/Point`` or
    ``Pose2D``), or a ``target`` object of those. Every other field is a request parameter.
    """
    rest = dict(args)
    value: Value = ""
    wanted = prop.value
    if wanted is not None:
        if wanted.name in rest:
            given = rest.pop(wanted.name)
        elif "value" in rest:
            given = rest.pop("value")
        elif wanted.type == "marker" and "x" in rest:
            given = {axis: rest.pop(axis) for axis in ("x", "y", "z") if axis in rest}
            rest.pop("theta", None)
        else:
            given = None
        if given is None:
            if wanted.required:
                raise InvalidArgument(f"{prop.name} takes {wanted.name} ({wanted.type}) in its args")
        elif wanted.type == "marker" and isinstance(given, Mapping):
            value = _marker_at(given)
        elif wanted.type == "bytes" and isinstance(given, str):
            value = messages.from_message(messages.UINT8_ARRAY, {"data": given}, prop.name)
        else:
            value = _parameter(wanted.name, given)
    return value, {key: _parameter(key, x) for key, x in rest.items()}


def _marker_at(point: Mapping[str, Any]) -> str:
    try:
        location = [float(point[axis]) for axis in ("x", "y", "z") if axis in point]
    except (TypeError, ValueError):
        raise InvalidArgument("a target's x, y and z must be numbers") from None
    if len(location) < 2 or not all(math.isfinite(x) for x in location):
        raise InvalidArgument("a target needs finite x and y")
    return format_marker(Marker.at(location))


def query_values(prop: PropertyModel | None, value: Value) -> dict[str, Any]:
    """A query's (or property's) answer as response values: ``value`` (the text; base64 ``data``
    for bytes), and typed beside it: ``names`` for names, ``data`` for a number or a vector."""
    if isinstance(value, bytes):
        return messages.to_message(messages.UINT8_ARRAY, value)
    values: dict[str, Any] = {"value": value}
    kind = prop.type if prop is not None else ""
    try:
        if kind == "names":
            values["names"] = parse_names(value)
        elif kind in ("number", "integer"):
            values["data"] = messages.to_message(messages.FLOAT64, value)["data"]
        elif kind == "vector":
            values["data"] = messages.to_message(messages.FLOAT64_ARRAY, value)["data"]
    except PropertyError:
        pass  # the text alone
    return values


def _text(value: Value) -> str:
    return value if isinstance(value, str) else value.decode(errors="replace")


def _fragment_id(sub: Subscription) -> str:
    sub.written += 1
    return f"publish:{sub.topic[:200]}:{sub.written}"


def _first(idents: set[str | None]) -> str | None:
    return next((i for i in idents if i is not None), None)


def _ident(op: protocol.Operation) -> str | None:
    return getattr(op, "ident", None)


def _op_name(op: protocol.Operation) -> str:
    names = {
        protocol.Subscribe: "subscribe",
        protocol.Unsubscribe: "unsubscribe",
        protocol.Publish: "publish",
        protocol.Advertise: "advertise",
        protocol.Unadvertise: "unadvertise",
        protocol.CallService: "call_service",
        protocol.Auth: "auth",
        protocol.SetLevel: "set_level",
    }
    return names[type(op)]


def _what(op: protocol.Operation) -> str:
    name = getattr(op, "topic", None) or getattr(op, "service", None) or ""
    return str(name)[:200]
