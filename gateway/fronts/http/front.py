"""The HTTP front end: an aiohttp application in the gateway's own asyncio loop.

:class:`HttpFront` serves the JSON routes (:mod:`gateway.fronts.http.api`), Server-Sent Events
(:mod:`gateway.fronts.http.events`), the OpenAPI document and the browser console's files
(:mod:`gateway.fronts.http.console`) on ``[http] listen``. It holds no state of its own beyond its
open event streams: calls go through the gateway's :class:`~gateway.engine.calls.Calls`, streams
through its :class:`~gateway.engine.listen.ListenHub`, identity and rules through its
:class:`~gateway.engine.guard.Guard`. Every error leaves as JSON (:mod:`gateway.fronts.http.errors`),
unknown routes and wrong methods included.
"""

from __future__ import annotations

import asyncio
import json
import logging
from collections.abc import Awaitable, Callable
from time import perf_counter
from typing import NamedTuple

from aiohttp import HttpVersion11, hdrs, web
from aiohttp.http_exceptions import HttpProcessingError

from gateway.client_faults import filter_client_faults
from gateway.config import Config, is_loopback
from gateway.connections import BoundedListener, ConnectionCaps
from gateway.engine.calls import Calls
from gateway.engine.guard import Guard
from gateway.engine.history import HistoryKeeper
from gateway.engine.listen import ListenHub
from gateway.engine.rules import Subject
from gateway.fronts.http.api import Api, body_too_large
from gateway.fronts.http.binary import MediaTypes
from gateway.fronts.http.bodies import BodyTooLarge
from gateway.fronts.http.console import CONSOLE_ROOT, Console
from gateway.fronts.http.errors import PAYLOAD_TOO_LARGE, connection_refusal, error_response
from gateway.fronts.http.events import EventStreams
from gateway.fronts.http.floor_plan import DESCRIPTION_ROUTE, IMAGE_ROUTE, FloorPlan
from gateway.fronts.http.history import HistoryRoute
from gateway.fronts.http.image_stream import ImageStreams
from gateway.fronts.http.openapi import document
from gateway.fronts.http.places import StreamPlaces
from gateway.fronts.http.safety import JSON_TYPE, check_request, identify
from gateway.handshake_log import HandshakeFailureLog, TlsPortAdvice
from gateway.logs import (
    REQUEST_ID_HEADER,
    RequestContext,
    current_request,
    current_request_id,
    request_id_from,
)
from gateway.metrics.counts import HttpCounts
from gateway.ports import start_bounded
from gateway.tls import HttpsCredentials
from services.kernel.errors import Code, InvalidArgument, PropertyError, ResourceExhausted, error_for

log = logging.getLogger("gateway.fronts.http")

#: What the log says of a failed handshake on the HTTPS port (``[http] tls = true``, the ``[tls]`` files).
HTTPS_ADVICE = TlsPortAdvice(
    connect="use https:// and the CA",
    requires_cert="[http] tls follows [tls] require_client_cert",
    client_ca="[tls] client_ca",
)

Handler = Callable[[web.Request], Awaitable[web.StreamResponse]]


class WebSocketRoute(NamedTuple):
    """A WebSocket protocol served on this port by another front (Foxglove's, rosbridge's).

    The HTTP front checks the request as every other (Origin, Host), names its subject (bearer
    header, ``ps_token`` cookie, client certificate) and holds one of the stream places
    (``http.max_streams``, ``max_streams_per_client``) while ``handler`` serves it. ``path`` is its
    own route; an upgrade at ``/`` that offers one of ``subprotocols`` goes to it too (clients such
    as Foxglove's dial ``ws://host:port/``).
    """

    path: str
    subprotocols: tuple[str, ...]
    handler: Callable[[web.Request, Subject], Awaitable[web.StreamResponse]]


#: HTTP errors aiohttp raises itself, as the code each stands for (others: by their class of status).
_HTTP_CODES = {404: Code.NOT_FOUND, 413: Code.RESOURCE_EXHAUSTED}


async def _echo_request_id(request: web.BaseRequest, response: web.StreamResponse) -> None:
    """Every answer, an event stream's too, says which request it answers (headers go out first).

    Prepared in the handler's task, where the middleware set the request's context.
    """
    request_id = current_request_id()
    if request_id is not None:
        response.headers["X-Request-Id"] = request_id


#: The routes whose answer is a stream: counted, but their life is no latency.
STREAM_ROUTES = frozenset(("GET /api/v1/events", "GET /api/v1/services/{service}/properties/{path}/stream"))

#: The status counted for a request whose client went away before the answer (nginx's 499).
CLIENT_CLOSED = 499


def _route_of(request: web.Request) -> str:
    """The route's template with its method, or ``unrouted``: a bounded set, whatever the path was."""
    info = request.match_info
    resource = info.route.resource if info.http_exception is None else None
    if resource is None:
        return "unrouted"
    return f"{info.route.method} {resource.canonical}"


class HttpFront:
    """The HTTP/JSON + SSE front end of one gateway; :meth:`start` and :meth:`stop` in its loop."""

    def __init__(
        self, calls: Calls, hub: ListenHub, config: Config, guard: Guard, history: HistoryKeeper | None = None
    ) -> None:
        """``history``: what answers the history route (None: the gateway keeps no history)."""
        self.settings = config.http
        self.config = config
        self.api = Api(calls, guard, self.settings.max_body)
        self.history = HistoryRoute(history, guard, MediaTypes(calls))
        self.guard = guard
        #: WebSocket protocols of other fronts served here (set before :meth:`start`).
        self.websockets: list[WebSocketRoute] = []
        self.websocket_origins = frozenset(origin.lower() for origin in self.settings.websocket_origins)
        #: Event streams and live images share the bounds on open streams.
        self.places = StreamPlaces(self.settings)
        self.events = EventStreams(
            hub, calls, guard=guard, limits=config.limits, settings=self.settings, places=self.places
        )
        self.images = ImageStreams(
            hub, calls, guard=guard, limits=config.limits, settings=self.settings, places=self.places
        )
        self.console = Console(CONSOLE_ROOT)
        self.floor_plan = FloorPlan(config.console)
        #: Whether Host headers must be loopback names (DNS rebinding): the front end listens on loopback.
        self.loopback_only = is_loopback(self.settings.listen)
        self._runner: web.AppRunner | None = None
        #: HTTPS: the ``[tls]`` files, read again on SIGHUP (:meth:`Gateway.reload_certificates`).
        self.credentials: HttpsCredentials | None = None
        #: "host:port" it listens on (the real port when 0 was asked); "" before start.
        self.address = ""
        self.scheme = "https" if self.settings.tls else "http"
        #: Responses by route and status, and latencies; None when ``[metrics]`` is off.
        self.counts = HttpCounts() if config.metrics.enabled else None
        #: ``GET /metrics``, set by the gateway when metrics are on (before :meth:`start`).
        self.metrics: Handler | None = None
        #: Connections held at once: ``max_connections``, or the share of open files the gateway
        #: gave this port (set before :meth:`start`).
        self.max_connections = self.settings.max_connections
        #: The listening sockets and their connection caps; None before :meth:`start`.
        self.listener: BoundedListener | None = None

    @property
    def url(self) -> str:
        """``http://HOST:PORT/`` (or https)."""
        return f"{self.scheme}://{self.address}/"

    def build_app(self) -> web.Application:
        """The aiohttp application with every route (also used to check the OpenAPI document)."""
        app = web.Application(middlewares=[self._middleware], client_max_size=self.settings.max_body)
        app.on_response_prepare.append(_echo_request_id)
        api = self.api
        openapi = json.dumps(document(self.settings.console))
        add = app.router.add_route
        add("GET", "/api/v1/services", api.services)
        add("GET", "/api/v1/services/{service}/model", api.model)
        add("GET", "/api/v1/services/{service}/properties/{path}", api.get)
        add("GET", "/api/v1/services/{service}/properties/{path}/stream", self.images.stream)
        add("GET", "/api/v1/services/{service}/properties/{path}/history", self.history.history_json)
        add("PUT", "/api/v1/services/{service}/properties/{path}", api.set, expect_handler=self._expect)
        add("POST", "/api/v1/services/{service}/properties/{path}", api.set, expect_handler=self._expect)
        add("GET", "/api/v1/events", self.events.events)
        add("GET", "/api/v1/health", api.health)

        async def openapi_json(request: web.Request) -> web.Response:
            return web.Response(text=openapi, content_type="application/json")

        add("GET", "/api/v1/openapi.json", openapi_json)
        if self.metrics is not None:
            add("GET", "/metrics", self.metrics)
        for route in self.websockets:
            add("GET", route.path, self._websocket(route))
        if self.settings.console or self.websockets:
            add("GET", "/", self._root)
        if self.settings.console:
            # Before the console's files, whose route takes every other /console/ path.
            add("GET", DESCRIPTION_ROUTE, self.floor_plan.description)
            add("GET", IMAGE_ROUTE, self.floor_plan.image)
            add("GET", "/console/{file:.*}", self.console.file)
        return app

    def _websocket(self, route: WebSocketRoute) -> Handler:
        async def serve(request: web.Request) -> web.StreamResponse:
            subject = identify(request, self.guard)
            peer = request.remote or "?"
            refused = self.places.refusal(peer)
            if refused is not None:
                return refused
            with self.places.held(peer):
                return await route.handler(request, subject)

        return serve

    async def _root(self, request: web.Request) -> web.StreamResponse:
        """``/``: a WebSocket upgrade offering a served subprotocol goes to its front; anything
        else is the console (when served)."""
        if request.headers.get(hdrs.UPGRADE, "").lower() == "websocket":
            offered = {p.strip() for p in request.headers.get(hdrs.SEC_WEBSOCKET_PROTOCOL, "").split(",")}
            for route in self.websockets:
                if offered.intersection(route.subprotocols):
                    return await self._websocket(route)(request)
        if not self.settings.console:
            raise web.HTTPNotFound()
        return await self.console.file(request)

    async def _expect(self, request: web.Request) -> web.StreamResponse | None:
        """``Expect: 100-continue``: a body announced over ``max_body`` (JSON) or over the property's
        ``max_size`` (the raw bytes of a binary property) is refused before it is sent (aiohttp's
        own handler says 100 Continue first, and the client sends it all)."""
        length = request.content_length
        if length is not None and request.content_type == JSON_TYPE and length > self.settings.max_body:
            return body_too_large(length, self.settings.max_body)
        if length is not None and request.content_type != JSON_TYPE:
            limit = await self.api.raw_limit(request)
            if limit is not None and length > limit:
                return body_too_large(length, limit, "the property's max_size")
        if (
            request.version == HttpVersion11
            and request.headers.get(hdrs.EXPECT, "").lower() == "100-continue"
        ):
            await request.writer.write(b"HTTP/1.1 100 Continue\r\n\r\n")
            request.writer.output_size = 0  # the answer proper has not begun
            return None
        expect = request.headers.get(hdrs.EXPECT, "")[:100]
        return error_response(
            InvalidArgument(f"unknown Expect: {expect!r} (known: 100-continue)"), status=417
        )

    @web.middleware
    async def _middleware(self, request: web.Request, handler: Handler) -> web.StreamResponse:
        counts = self.counts
        if counts is None:
            return await self._answer(request, handler)
        started = perf_counter()
        status = 500
        try:
            response = await self._answer(request, handler)
            status = response.status
            return response
        except web.HTTPException as exc:
            status = exc.status
            raise
        except asyncio.CancelledError:
            status = CLIENT_CLOSED
            raise
        finally:
            route = _route_of(request)
            # A WebSocket (its own route, or an upgrade at /) lives as long as its client stays.
            upgraded = request.headers.get(hdrs.UPGRADE, "").lower() == "websocket"
            streamed = route in STREAM_ROUTES or upgraded
            counts.done(route, status, None if streamed else perf_counter() - started)

    async def _answer(self, request: web.Request, handler: Handler) -> web.StreamResponse:
        what = f"{request.method} {request.path[:200]}"
        # The request's id in every log line of its handler (and of the proxy calls it makes).
        request_id = request_id_from(request.headers.get(REQUEST_ID_HEADER))
        current_request.set(
            RequestContext(request_id, request.match_info.get("service"), request.match_info.get("path"))
        )
        try:
            check_request(
                request,
                self.loopback_only,
                routed=request.match_info.http_exception is None,
                websocket_origins=self.websocket_origins,
            )
            return await handler(request)
        except BodyTooLarge as exc:
            return error_response(exc, what, status=PAYLOAD_TOO_LARGE)
        except PropertyError as exc:
            return error_response(exc, what)
        except web.HTTPRequestEntityTooLarge:
            limit = self.settings.max_body
            err = ResourceExhausted(f"the request body is larger than http.max_body ({limit} bytes)")
            return error_response(err, status=PAYLOAD_TOO_LARGE)
        except web.HTTPMethodNotAllowed as exc:
            allowed = ", ".join(sorted(exc.allowed_methods))
            message = f"{request.method} is not allowed on {request.path[:200]} (allowed: {allowed})"
            response = error_response(error_for(Code.UNIMPLEMENTED, message), status=exc.status)
            response.headers["Allow"] = ",".join(sorted(exc.allowed_methods))
            return response
        except web.HTTPException as exc:
            if exc.status < 400:
                raise
            code = _HTTP_CODES.get(exc.status, Code.INVALID_ARGUMENT if exc.status < 500 else Code.INTERNAL)
            message = f"no route {request.path[:200]}" if exc.status == 404 else exc.reason
            return error_response(error_for(code, message), status=exc.status)
        except ConnectionResetError:
            # The client went away while its answer's headers were being written (a page closed
            # just as its event stream opened): nobody is left to answer, and it is no fault of
            # ours to log. aiohttp drops the answer quietly; 499 is what the access count shows.
            return web.Response(status=CLIENT_CLOSED, reason="Client Closed Request")
        except Exception as exc:
            # A bug: INTERNAL, logged with its traceback by to_property_error; still JSON.
            return error_response(exc, what)

    async def start(self) -> None:
        """Listen; raises PortInUse (one line naming the holder) when the port is taken."""
        # aiohttp logs a request it cannot parse (a malformed header, an oversized line) with a
        # traceback: a client's doing, one rate-limited line instead.
        filter_client_faults("aiohttp.server", (HttpProcessingError,))
        host, _, port_text = self.settings.listen.rpartition(":")
        host = host.strip("[]")
        port = int(port_text)
        if self.settings.tls:
            self.credentials = HttpsCredentials(self.config.tls)
        ssl_context = self.credentials.context if self.credentials is not None else None
        # handler_cancellation: a client that goes away ends its handler (an idle event stream
        # would otherwise only notice at its next heartbeat). keepalive_timeout: aiohttp closes a
        # connection with no request running after it, a fresh one that sends nothing included.
        runner = web.AppRunner(
            self.build_app(),
            handler_cancellation=True,
            access_log=None,
            shutdown_timeout=self.config.gateway.shutdown_grace,
            keepalive_timeout=self.settings.idle_timeout,
        )
        await runner.setup()
        caps = ConnectionCaps(
            self.max_connections,
            self.settings.max_connections_per_address,
            "http.max_connections",
            "http.max_connections_per_address",
        )
        server = runner.server
        assert server is not None  # set up just before
        self.listener = BoundedListener(
            server,  # aiohttp's server makes each connection's protocol
            caps,
            "http.listen",
            ssl_context=ssl_context,
            ssl_handshake_timeout=self.config.gateway.handshake_timeout,
            refusal=None if ssl_context is not None else connection_refusal,
            handshake_failures=None
            if ssl_context is None
            else HandshakeFailureLog("http.listen", HTTPS_ADVICE),
        )
        self.address = await start_bounded(self.listener, runner, host, port, "http.listen")
        self._runner = runner
        log.debug("HTTP front end and console on %s", self.url)

    async def stop(self) -> None:
        """Stop listening and end every request (event streams end with the hub's error first)."""
        listener, self.listener = self.listener, None
        if listener is not None:
            await listener.aclose()
        runner, self._runner = self._runner, None
        if runner is not None:
            await runner.cleanup()
