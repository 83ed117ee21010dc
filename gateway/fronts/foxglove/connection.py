"""One Foxglove WebSocket connection: the catalog advertised, subscriptions as Listen streams,
publishes as Sets, service calls as actions and queries, parameters as Gets and Sets.

Every call goes through the engine as the connection's subject (identified by the HTTP front
from the bearer header or the ``ps_token`` cookie), so the rules, licences, limits and audit are
those of every front. Bounds:

* each subscription is one listen-hub stream (``limits.max_streams`` in all), at most
  :data:`MAX_SUBSCRIPTIONS` a connection; the writer takes what streams have ready when the socket
  has taken the last message, so a slow reader holds one value per property (the streams'
  conflating queues), never a backlog;
* a write the client does not take within ``http.write_timeout`` drops the connection;
* a message carrying a large value counts against the hub's budget while it is written;
* a client's messages are read one at a time (a publish is a Set awaited in order); service calls
  run beside them, at most :data:`MAX_CALLS` at once (reading waits beyond);
* a message is at most ``MAX_FRAME_BYTES``.
"""

from __future__ import annotations

import asyncio
import json
import time
from collections.abc import Awaitable, Callable, Mapping
from contextlib import suppress
from dataclasses import dataclass
from typing import Any, ClassVar

from aiohttp import WSMsgType, web

from gateway.engine.calls import Calls
from gateway.engine.events import Mark, Selector, StreamOptions, events
from gateway.engine.listen import ListenHub, ListenStream
from gateway.engine.listen.drain import Wake
from gateway.engine.rules import Operation, Subject
from gateway.engine.status import to_property_error
from gateway.engine.types import DescribeCall, GetCall, SetCall
from gateway.fronts.foxglove import protocol, schemas
from gateway.fronts.foxglove.catalog import MAX_CHANNELS, MAX_PROPERTIES, Catalog, Channel, Kind, Service
from gateway.fronts.foxglove.protocol import Level, ProtocolError
from gateway.fronts.websocket import send_within
from services.kernel.errors import Code, InvalidArgument, PropertyError

#: Subscriptions one connection may hold; each is a listen-hub stream.
MAX_SUBSCRIPTIONS = 1024
#: Channels one client may advertise to publish on.
MAX_CLIENT_CHANNELS = 256
#: Items one request may list (subscriptions, ids, parameter names).
MAX_ITEMS = 1024
#: Service calls running at once for one connection.
MAX_CALLS = 16
#: Parameters one ``getParameters`` reads (each is a Get).
MAX_PARAMETERS = 256


@dataclass(eq=False, slots=True)
class Subscribed:
    """A client's subscription: its id, its channel, and the listen-hub stream behind it."""

    id: int
    channel: Channel
    stream: ListenStream
    #: False once unsubscribed: what the writer still holds of it is dropped.
    live: bool = True


@dataclass(frozen=True, slots=True)
class Publishing:
    """A client channel, and the property it writes."""

    topic: str
    service: str
    path: str
    binary: bool


def _failure(exc: BaseException, what: str) -> str:
    err = to_property_error(exc, what)
    return f"{what}: {err.code.name}: {err.message}"


class Connection:
    """A Foxglove client's session: its catalog, subscriptions and client channels."""

    def __init__(
        self,
        ws: web.WebSocketResponse,
        request: web.Request,
        *,
        calls: Calls,
        hub: ListenHub,
        subject: Subject,
        write_timeout: float,
        name: str,
    ) -> None:
        self.ws = ws
        self.request = request
        self.calls = calls
        self.hub = hub
        self.subject = subject
        self.write_timeout = write_timeout
        self.name = name
        self.catalog = Catalog()
        self.subscribed: dict[int, Subscribed] = {}
        #: Parameter name → the subscription to its updates (counted with :attr:`subscribed`).
        self.parameter_subs: dict[str, Subscribed] = {}
        self.publishing: dict[int, Publishing] = {}
        self._ready: set[Subscribed] = set()
        self._wake = Wake()
        self._send_lock = asyncio.Lock()
        self._calls = asyncio.Semaphore(MAX_CALLS)
        self._tasks: set[asyncio.Task[None]] = set()
        self._closed = False
        #: Services that joined or left since the catalog was last brought up to date (a set:
        #: bounded by the services there are, however often they come and go).
        self._changed: set[str] = set()
        self._changes = Wake()

    # --- the session -------------------------------------------------------------------------

    async def run(self) -> None:
        writer = asyncio.create_task(self._write_loop())
        # Watched from the start: a service that comes or goes while the catalog is made is shown
        # again once it is sent.
        unwatch = self.calls.router.watch(self._service_changed)
        follower: asyncio.Task[None] | None = None
        try:
            await self._send(protocol.server_info(self.name, str(time.time_ns())))
            await self._advertise()
            follower = asyncio.create_task(self._follow_services())
            async for message in self.ws:
                if message.type is WSMsgType.TEXT:
                    await self._on_text(message.data)
                elif message.type is WSMsgType.BINARY:
                    await self._on_binary(message.data)
                elif message.type is WSMsgType.ERROR:
                    break
        except ConnectionError:
            pass  # the client went away, or read nothing for write_timeout
        finally:
            self._closed = True
            unwatch()
            if follower is not None:
                follower.cancel()
            writer.cancel()
            for task in list(self._tasks):
                task.cancel()
            for sub in [*self.subscribed.values(), *self.parameter_subs.values()]:
                sub.stream.close()
            self.subscribed.clear()
            self.parameter_subs.clear()
            for task in [t for t in (writer, follower) if t is not None]:
                with suppress(asyncio.CancelledError, ConnectionError):
                    await task

    async def _send(self, frame: str | bytes) -> None:
        """One message, within ``write_timeout``; a client that takes nothing for that long is dropped."""
        data, kind = (frame.encode(), WSMsgType.TEXT) if isinstance(frame, str) else (frame, WSMsgType.BINARY)
        async with self._send_lock:
            await send_within(self.ws, self.request, data, kind, within=self.write_timeout, front="Foxglove")

    async def _status(self, level: Level, message: str) -> None:
        await self._send(protocol.status(level, message))

    def _service_changed(self, name: str, backend: object) -> None:
        self._changed.add(name)
        self._changes.set()

    async def _follow_services(self) -> None:
        """Advertise the channels and services of a service that joins, unadvertise those of one
        that leaves (its subscriptions end), one service at a time."""
        while True:
            await self._changes.wait()
            while self._changed:
                await self._show_again(self._changed.pop())

    async def _show_again(self, service: str) -> None:
        catalog = self.catalog
        channels, services = catalog.remove(service)
        for sub in [s for s in self.subscribed.values() if s.channel.id in channels]:
            del self.subscribed[sub.id]
            self._end(sub)
        for name, sub in list(self.parameter_subs.items()):
            if sub.channel.service == service:
                del self.parameter_subs[name]
                self._end(sub)
        if channels:
            await self._send(protocol.text({"op": "unadvertise", "channelIds": channels}))
        if services:
            await self._send(protocol.text({"op": "unadvertiseServices", "serviceIds": services}))
        if service not in self.calls.router:
            return
        known_channels, known_services = set(catalog.channels), set(catalog.services)
        await self._describe(service)
        catalog.add_scene()
        added = [c.advertised() for i, c in catalog.channels.items() if i not in known_channels]
        if added:
            await self._send(protocol.text({"op": "advertise", "channels": added}))
        offered = [s.advertised() for i, s in catalog.services.items() if i not in known_services]
        if offered:
            await self._send(protocol.text({"op": "advertiseServices", "services": offered}))

    async def _describe(self, service: str) -> None:
        """Add ``service`` to the catalog, as far as the subject may see it."""
        guard = self.calls.guard
        try:
            model = await self.calls.describe(DescribeCall(service), self.calls.timeout, self.subject)
        except PropertyError as exc:
            if exc.code not in (Code.PERMISSION_DENIED, Code.UNAUTHENTICATED):
                await self._status(Level.WARNING, _failure(exc, f"describe {service}"))
            return
        readable = None
        if guard.checks:
            readable = [
                p.name for p in model.properties if guard.may(self.subject, service, p.name, Operation.READ)
            ]
        self.catalog.add(service, model, readable)

    async def _advertise(self) -> None:
        """Describe every service the gateway serves and advertise what the subject may see.

        The names come from the router, not the registry's ``services``: rules may keep the
        registry to administrators, while a service's own model is for whoever may read it.
        """
        for service in self.calls.router.names():
            if self.catalog.clipped:
                break
            await self._describe(service)
        self.catalog.add_scene()
        if self.catalog.clipped:
            await self._status(
                Level.WARNING,
                f"only the first {MAX_CHANNELS} channels and {MAX_PROPERTIES} properties are shown",
            )
        channels = [c.advertised() for c in self.catalog.channels.values()]
        await self._send(protocol.text({"op": "advertise", "channels": channels}))
        services = [s.advertised() for s in self.catalog.services.values()]
        if services:
            await self._send(protocol.text({"op": "advertiseServices", "services": services}))

    # --- what the client sends -----------------------------------------------------------------

    async def _on_text(self, frame: str) -> None:
        try:
            op, body = protocol.read_json(frame)
            handler = self._ops.get(op)
            if handler is None:
                raise ProtocolError(f"unknown op {op[:100]!r}")
            await handler(self, body)
        except ProtocolError as exc:
            await self._status(Level.ERROR, str(exc))

    async def _on_binary(self, frame: bytes) -> None:
        try:
            message = protocol.read_binary(frame)
        except ProtocolError as exc:
            await self._status(Level.ERROR, str(exc))
            return
        if isinstance(message, protocol.ClientMessage):
            await self._publish(message)
            return
        await self._calls.acquire()  # reading waits while MAX_CALLS run
        task = asyncio.create_task(self._call(message))
        self._tasks.add(task)
        task.add_done_callback(self._call_done)

    def _call_done(self, task: asyncio.Task[None]) -> None:
        self._tasks.discard(task)
        self._calls.release()

    async def _subscribe(self, body: Mapping[str, Any]) -> None:
        for item in protocol.subscriptions(body, MAX_ITEMS):
            channel = self.catalog.channels.get(item.channel)
            if channel is None:
                raise ProtocolError(f"no channel {item.channel}")
            if item.id in self.subscribed:
                raise ProtocolError(f"subscription id {item.id} is in use")
            sub = await self._follow(item.id, channel)
            if sub is not None:
                self.subscribed[item.id] = sub

    async def _follow(self, sub_id: int, channel: Channel) -> Subscribed | None:
        """A started subscription to ``channel``; None (and an error status) when it cannot be."""
        if len(self.subscribed) + len(self.parameter_subs) >= MAX_SUBSCRIPTIONS:
            raise ProtocolError(f"a connection may hold at most {MAX_SUBSCRIPTIONS} subscriptions")
        box: list[Subscribed] = []
        try:
            stream = self._open(channel, box)
            await stream.start()
        except PropertyError as exc:
            await self._status(Level.ERROR, _failure(exc, f"subscribe {channel.topic}"))
            return None
        sub = Subscribed(sub_id, channel, stream)
        box.append(sub)
        self._ready.add(sub)  # the current value may be queued already
        self._wake.set()
        return sub

    def _end(self, sub: Subscribed) -> None:
        sub.live = False
        sub.stream.close()
        self._ready.discard(sub)

    def _open(self, channel: Channel, box: list[Subscribed]) -> ListenStream:
        """A listen-hub stream for ``channel``; it tells the writer of the subscription put in
        ``box`` once it is known (what it has before then, the subscription takes at once)."""
        selector = Selector(channel.service, channel.path)

        def ready() -> None:
            if box:
                self._ready.add(box[0])
                self._wake.set()

        return self.hub.open([selector], StreamOptions(), ready, self.subject)

    async def _unsubscribe(self, body: Mapping[str, Any]) -> None:
        for sub_id in protocol.ids(body, "subscriptionIds", MAX_ITEMS):
            sub = self.subscribed.pop(sub_id, None)
            if sub is not None:
                self._end(sub)

    async def _subscribe_parameters(self, body: Mapping[str, Any]) -> None:
        names = protocol.names(body, "parameterNames", MAX_ITEMS) or self.catalog.parameter_names()
        for name in names:
            if name in self.parameter_subs:
                continue  # the spec: a parameter is subscribed at most once
            channel = self.catalog.parameter_channel(name)
            if channel is None:
                await self._status(Level.WARNING, f"no parameter {name[:200]!r}")
                continue
            sub = await self._follow(0, channel)
            if sub is not None:
                self.parameter_subs[name] = sub

    async def _unsubscribe_parameters(self, body: Mapping[str, Any]) -> None:
        names = protocol.names(body, "parameterNames", MAX_ITEMS) or list(self.parameter_subs)
        for name in names:
            sub = self.parameter_subs.pop(name, None)
            if sub is not None:
                self._end(sub)

    async def _client_advertise(self, body: Mapping[str, Any]) -> None:
        for channel in protocol.client_channels(body, MAX_ITEMS):
            if channel.encoding != protocol.JSON_ENCODING:
                raise ProtocolError(
                    f"channel {channel.topic[:100]}: encoding {channel.encoding[:50]!r} (json only)"
                )
            found = self.catalog.properties.get(channel.topic)
            if found is None:
                raise ProtocolError(f"no property at topic {channel.topic[:200]!r}: publish to /SERVICE/PATH")
            service, path, model = found
            if not model.access.writable:
                raise ProtocolError(f"{channel.topic[:200]} is not writable ({model.access.value})")
            if channel.id not in self.publishing and len(self.publishing) >= MAX_CLIENT_CHANNELS:
                raise ProtocolError(f"a connection may advertise at most {MAX_CLIENT_CHANNELS} channels")
            self.publishing[channel.id] = Publishing(channel.topic, service, path, model.type == "bytes")

    async def _client_unadvertise(self, body: Mapping[str, Any]) -> None:
        for channel_id in protocol.ids(body, "channelIds", MAX_ITEMS):
            self.publishing.pop(channel_id, None)

    async def _publish(self, message: protocol.ClientMessage) -> None:
        target = self.publishing.get(message.channel)
        if target is None:
            await self._status(Level.ERROR, f"no client channel {message.channel}: advertise it first")
            return
        try:
            body = protocol.read_payload(message.payload, f"the message on {target.topic}")
            value = schemas.published_value(body, target.binary)
            await self.calls.set(
                SetCall(target.service, target.path, value), self.calls.timeout, self.subject
            )
        except ProtocolError as exc:
            await self._status(Level.ERROR, str(exc))
        except Exception as exc:
            await self._status(Level.ERROR, _failure(exc, f"publish {target.topic}"))

    async def _call(self, request: protocol.ServiceCallRequest) -> None:
        service = self.catalog.services.get(request.service)
        try:
            if service is None:
                raise ProtocolError(f"no service {request.service}")
            if request.encoding != protocol.JSON_ENCODING:
                raise ProtocolError(f"encoding {request.encoding[:50]!r}: this server takes json")
            body = (
                protocol.read_payload(request.payload, f"the request to {service.name}")
                if request.payload
                else {}
            )
            answer = await self._invoke(service, body)
        except ProtocolError as exc:
            await self._send_quietly(protocol.service_call_failure(request.service, request.call, str(exc)))
            return
        except Exception as exc:
            name = service.name if service is not None else str(request.service)
            failure = protocol.service_call_failure(request.service, request.call, _failure(exc, name))
            await self._send_quietly(failure)
            return
        payload = json.dumps({"value": answer}, ensure_ascii=False).encode()
        await self._send_quietly(
            protocol.service_call_response(request.service, request.call, protocol.JSON_ENCODING, payload)
        )

    async def _send_quietly(self, frame: str | bytes) -> None:
        with suppress(ConnectionError):
            await self._send(frame)

    async def _invoke(self, service: Service, body: Mapping[str, Any]) -> str:
        raw = body.get("parameters") or {}
        if not isinstance(raw, dict):
            raise ProtocolError('"parameters" must be an object of texts')
        parameters = {str(k): schemas.json_to_text(v) for k, v in raw.items()}
        timeout = self.calls.timeout
        if service.is_query:
            reply = await self.calls.get(
                GetCall(service.service, service.path, parameters), timeout, self.subject
            )
            answer = reply.value
        else:
            value = schemas.json_to_text(body.get("value", ""))
            answer = await self.calls.set(
                SetCall(service.service, service.path, value, parameters), timeout, self.subject
            )
        return answer if isinstance(answer, str) else f"<{len(answer)} bytes>"

    async def _get_parameters(self, body: Mapping[str, Any]) -> None:
        asked = protocol.names(body, "parameterNames", MAX_ITEMS) or self.catalog.parameter_names()
        if len(asked) > MAX_PARAMETERS:
            await self._status(
                Level.WARNING, f"only the first {MAX_PARAMETERS} of {len(asked)} parameters are read"
            )
            asked = asked[:MAX_PARAMETERS]
        await self._parameter_values(asked, body.get("id"))

    async def _parameter_values(self, names: list[str], request_id: Any) -> None:
        values = []
        for name in names:
            found = self.catalog.parameter(name)
            if found is None:
                await self._status(Level.WARNING, f"no parameter {name[:200]!r}")
                continue
            service, path, model = found
            try:
                reply = await self.calls.get(GetCall(service, path), self.calls.timeout, self.subject)
            except PropertyError as exc:
                await self._status(Level.WARNING, _failure(exc, f"get parameter {name}"))
                continue
            if isinstance(reply.value, str):
                values.append({"name": name, "value": schemas.typed(model.type, reply.value)})
        answer: dict[str, Any] = {"op": "parameterValues", "parameters": values}
        if isinstance(request_id, str):
            answer["id"] = request_id
        await self._send(protocol.text(answer))

    async def _set_parameters(self, body: Mapping[str, Any]) -> None:
        done = []
        for item in protocol.items(body, "parameters", MAX_ITEMS):
            if not isinstance(item, dict):
                raise ProtocolError("each parameter must be an object {name, value}")
            name = protocol.string(item.get("name"), "parameter name")
            found = self.catalog.parameter(name)
            if found is None:
                await self._status(Level.ERROR, f"no parameter {name[:200]!r}")
                continue
            service, path, _ = found
            try:
                value = schemas.json_to_text(item.get("value"))
                await self.calls.set(SetCall(service, path, value), self.calls.timeout, self.subject)
            except (PropertyError, InvalidArgument) as exc:
                await self._status(Level.ERROR, _failure(exc, f"set parameter {name}"))
                continue
            done.append(name)
        if isinstance(body.get("id"), str):
            await self._parameter_values(done, body["id"])

    async def _unsupported(self, body: Mapping[str, Any]) -> None:
        raise ProtocolError(
            f"op {body['op']!r} is not supported by this server (see serverInfo's capabilities)"
        )

    _ops: ClassVar[dict[str, Callable[[Connection, Mapping[str, Any]], Awaitable[None]]]] = {
        "subscribe": _subscribe,
        "unsubscribe": _unsubscribe,
        "advertise": _client_advertise,
        "unadvertise": _client_unadvertise,
        "getParameters": _get_parameters,
        "setParameters": _set_parameters,
        "subscribeParameterUpdates": _subscribe_parameters,
        "unsubscribeParameterUpdates": _unsubscribe_parameters,
        "subscribeConnectionGraph": _unsupported,
        "unsubscribeConnectionGraph": _unsupported,
        "fetchAsset": _unsupported,
    }

    # --- what the server sends -----------------------------------------------------------------

    async def _write_loop(self) -> None:
        budget = self.hub.budget
        while not self._closed:
            await self._wake.wait()
            while self._ready:
                sub = self._ready.pop()
                if not sub.live:
                    continue  # unsubscribed meanwhile
                while (item := sub.stream.take()) is not None:
                    if isinstance(item, Mark):
                        continue
                    for event in events(item):
                        frame = self._frame(sub, event.service, event.value, event.time_ns, event.removed)
                        if frame is None:
                            continue
                        size = len(frame)
                        if not budget.take(size):
                            del frame
                            await self._status(
                                Level.ERROR, budget.refusal(size, f"{sub.channel.topic}").message
                            )
                            continue
                        try:
                            await self._send(frame)
                        finally:
                            budget.give_back(size)
                        del frame
                if sub.stream.error is not None:
                    await self._status(
                        Level.ERROR, _failure(sub.stream.error, f"subscription {sub.channel.topic}")
                    )
                    if self.subscribed.get(sub.id) is sub:
                        del self.subscribed[sub.id]
                    if self.parameter_subs.get(sub.channel.topic) is sub:
                        del self.parameter_subs[sub.channel.topic]
                    self._end(sub)

    def _frame(
        self, sub: Subscribed, service: str, value: Any, time_ns: int, removed: bool
    ) -> bytes | str | None:
        channel = sub.channel
        message: dict[str, Any] | None
        if channel.kind is Kind.PARAMETER:
            if removed or not isinstance(value, str):
                return None
            assert channel.model is not None
            update = {"name": channel.topic, "value": schemas.typed(channel.model.type, value)}
            return protocol.text({"op": "parameterValues", "parameters": [update]})
        if channel.kind is Kind.SCENE:
            message = schemas.scene_message(
                service, value if isinstance(value, str) else "", time_ns, removed
            )
        elif removed:
            return None
        elif channel.kind is Kind.POSE:
            message = schemas.pose_message(value, time_ns) if isinstance(value, str) else None
        else:
            assert channel.model is not None
            message = schemas.value_message(channel.model, value, time_ns)
        if message is None:
            return None
        payload = json.dumps(message, ensure_ascii=False, separators=(",", ":")).encode()
        return protocol.message_head(sub.id, time_ns) + payload
