"""Assembly: a configured, running gateway.

:class:`Gateway` builds the router from a :class:`~gateway.config.Config`
(plus the built-in ``registry`` service), starts the ``[[devices]]`` processes
(``gateway.devices``) and reaches them through their proxies, starts the grpc.aio server with the
PropertyService, server reflection and the health service, and shuts all of
it down gracefully. It runs in-process too, which is how tests and users
run a gateway and a client in one program::

    async with Gateway(config) as gw:
        channel = grpc.aio.insecure_channel(gw.address)
"""

from __future__ import annotations

import asyncio
import errno
import logging
import signal
import sys
from collections.abc import Callable, Mapping
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING
from urllib.parse import urlsplit

import grpc

from gateway.backends import open_backend, open_proxy
from gateway.client_faults import filter_grpc_client_faults
from gateway.cluster import ClusterNode, ClusterReport
from gateway.cluster.records import gateway_version
from gateway.config import METRICS_MAX_CONNECTIONS, REGISTRY_NAME, Config, ConfigError, ServiceEntry
from gateway.connections import share_open_files
from gateway.devices import SupervisedDevice, start_supervised
from gateway.dormant import DormantBackend
from gateway.engine.guard import Guard
from gateway.engine.history import HistoryKeeper
from gateway.engine.licensing import current_caller, may_license, may_provide
from gateway.engine.listen import ListenHub
from gateway.engine.listen.follow import HubFollow
from gateway.engine.router import Router
from gateway.fronts.grpc_v1.health import NOT_SERVING, SERVING, HealthService
from gateway.fronts.grpc_v1.servicer import (
    SERVICE_NAME,
    PropertyServicer,
    add_health_and_reflection,
    add_to_server,
)
from gateway.fronts.line.listener import LineListener, start_line_listener
from gateway.ports import PortInUse, check_port_free, port_holder
from gateway.stores import open_store
from gateway.tls import LineCredentials, ServerCredentials
from services.apps.catalog import build, needs_directory
from services.apps.recorder.reading import events_between
from services.apps.registry import DEFAULT_REGISTER_TIMEOUT, AllowList, Licence, Registry, RegistryService
from services.apps.registry.store import SharedStore
from services.apps.registry.table import GONE
from services.kernel.backend import Backend, BackendInfo
from services.kernel.errors import PropertyError

if TYPE_CHECKING:
    from gateway.fronts.http import HttpFront, WebSocketRoute
    from gateway.metrics.endpoint import MetricsEndpoint

log = logging.getLogger("gateway")

#: Share of the call timeout a registration by Set may spend waiting for the device: the rest
#: is for undoing it and answering, so the caller hears the registry's reason, not a bare deadline.
REGISTER_SHARE = 0.8

#: Seconds the gateway waits at startup for each of its own devices to connect and greet.
DEVICE_CONNECT_WAIT = 5.0

#: Calls grpc queues until the asyncio loop takes them up, at least (each holds its headers and
#: the start of its message). 20,000 Gets at once over 10 connections were all answered with it
#: (docs/errors.md); past it grpc ends a new call with CANCELLED before the gateway sees it.
PENDING_CALLS = 20_000

#: Keep-alive pings the gRPC port accepts from clients (see docs/client.md, failover): the SDK pings
#: every second while a call is open, so that a frozen gateway is found within two. grpc's own
#: policy answers a ping more often than every 5 minutes on a quiet stream with GOAWAY "too many
#: pings", which would end every idle Listen. Pings faster than every 0.5 s still count as abuse.
CLIENT_PING_POLICY: tuple[tuple[str, int], ...] = (("grpc.http2.min_ping_interval_without_data_ms", 500),)


class Gateway:
    """A gateway: router, listen hub, grpc.aio server; start with ``async with`` or :meth:`start`."""

    def __init__(
        self, config: Config | None = None, *, backends: Mapping[str, Backend] | None = None
    ) -> None:
        """``backends`` are extra, already built services served next to the configured ones."""
        from gateway.config import default_config

        self.config = config if config is not None else default_config()
        #: Identity, rules and audit: the one check of every front end (gRPC and the line listener),
        #: and of every call a system service makes on a client's behalf (the router's directory).
        self.guard = Guard.from_config(self.config)
        self.router = Router(self.guard)
        self.hub = ListenHub(self.router, self.config.limits, self.config.gateway.call_timeout, self.guard)
        #: Listens of the services that follow changes themselves (the recorder), on the hub.
        self.follow = HubFollow(self.hub)
        self._extra = dict(backends or {})
        self._server: grpc.aio.Server | None = None
        #: gRPC health: the whole gateway ("") and each service by name, following the registry.
        self.health = HealthService()
        self._line_listener: LineListener | None = None
        #: The HTTP/JSON + SSE front end; None when ``[http] listen`` is empty.
        self.http: HttpFront | None = None
        self._stopped = asyncio.Event()
        self._unwatch_registry: object | None = None
        self._unwatch_health: object | None = None
        self._unwatch_links: object | None = None
        #: Each service's watch on its backend's link to its device (health follows it).
        self._link_watches: dict[str, Callable[[], None]] = {}
        #: The resource service, served as ``registry`` (built in :meth:`start`).
        self.registry: Registry = Registry()
        self._devices: list[SupervisedDevice] = []
        #: The dormant services of the config, by name (their idle time follows their licences).
        self._dormant: dict[str, DormantBackend] = {}
        self._launch: asyncio.Future[list[SupervisedDevice | BaseException]] | None = None
        #: "host:port" the gRPC server listens on (the real port when 0 was asked), or "unix:PATH".
        self.address = ""
        #: "host:port" of the line-protocol listener (the real port when 0 was asked); "" when off.
        self.line_address = ""
        #: The kept changes of the ``[history]`` selectors; None when none are given.
        self.history: HistoryKeeper | None = None
        if self.config.history.selectors:
            older = events_between if self.config.history.recordings else None
            self.history = HistoryKeeper(self.hub, self.config.history, self.guard, older)
        self.servicer = PropertyServicer(self.router, self.hub, self.config, history=self.history)
        #: "host:port" of the HTTP front end (the real port when 0 was asked); "" when off.
        self.http_address = ""
        #: ``/metrics`` (on the HTTP front end and/or ``[metrics] listen``); None when not served.
        self.metrics: MetricsEndpoint | None = None
        #: "host:port" of ``[metrics] listen`` (the real port when 0 was asked); "" when off.
        self.metrics_address = ""
        #: The gRPC port's TLS credentials; None when it is plaintext.
        self.credentials: ServerCredentials | None = None
        #: The line listener's TLS, reloaded with the gRPC port's; None when it is plaintext.
        self._line_credentials: LineCredentials | None = None
        #: The shared registry store (``[registry] store = "etcd://..."``); None: the embedded one.
        self.store: SharedStore | None = None
        #: This gateway's part in the cluster that shares :attr:`store`; None without one.
        self.cluster: ClusterNode | None = None
        #: What registrations may reach (``[registry] allow``) and what is this gateway itself.
        self.allow = AllowList(self.config.registry.allow, own_ports=self._own_ports)
        #: Each port's share of open files: the connections it holds at most (set in :meth:`start`).
        self.shares: dict[str, int] = {}
        for entry in self.config.services:
            if entry.url.startswith("serial://"):
                self.allow.reserve(urlsplit(entry.url).path)

    async def __aenter__(self) -> Gateway:
        await self.start()
        return self

    async def __aexit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        await self.stop()

    async def start(self) -> None:
        """Start every service, then serve; returns once the server is listening.

        Raises :class:`~gateway.ports.PortInUse` when a port to listen on is taken and
        :class:`~gateway.config.ConfigError` when a configured service or device cannot be
        built, both before any device process is started.
        """
        self._check_ports()
        self._check_devices()
        self.shares = self._share_open_files()
        self.health.set("", NOT_SERVING)
        self.health.set(SERVICE_NAME, NOT_SERVING)
        try:
            self._launch_devices()
            # The gRPC port is bound first: in a cluster its address names this gateway.
            self._server = self._make_server()
            await self._join_store()
            await self._start_registry()
            # Services that reach others (groups) start last, once the services they name are there.
            plain = [e for e in self.config.services if not _needs_directory(e) and not e.dials_in]
            for entry in plain:
                backend = self._open(entry)
                await self._add(entry.name, backend, _described(entry))
            for name, backend in self._extra.items():
                await self._add(name, backend, backend.info.url)
            await self._start_devices()
            for entry in self.config.services:
                if _needs_directory(entry):
                    self._warn_missing_members(entry)
                    await self._add(entry.name, self._open(entry), _described(entry))
            await self._start_line_listener()
            if self.history is not None:
                self.history.start()
            await self._server.start()
            await self._start_http()
            await self._start_metrics()
            await self._start_cluster()
        except BaseException:
            await self.stop()
            raise
        self.health.set("", SERVING)
        self.health.set(SERVICE_NAME, SERVING)

    def _check_ports(self) -> None:
        gw = self.config.gateway
        check_port_free(gw.listen, "gateway.listen")
        if gw.line_listen:
            check_port_free(gw.line_listen, "gateway.line_listen")
        if self.config.http.listen:
            check_port_free(self.config.http.listen, "http.listen")
        if self.config.metrics.enabled and self.config.metrics.listen:
            check_port_free(self.config.metrics.listen, "metrics.listen")

    def _share_open_files(self) -> dict[str, int]:
        """Each listening port's share of open files, so that a flood on one cannot starve another."""
        config = self.config
        wanted = {"gateway.max_connections": config.gateway.max_connections}
        if config.gateway.line_listen:
            wanted["limits.line_max_connections"] = config.limits.line_max_connections
        if config.http.listen:
            wanted["http.max_connections"] = config.http.max_connections
        if config.metrics.enabled and config.metrics.listen:
            wanted["metrics.listen"] = METRICS_MAX_CONNECTIONS
        return share_open_files(wanted)

    def _check_devices(self) -> None:
        """Build each ``[[devices]]`` service here as its process would, so bad options launch nothing."""
        problems = []
        for device in self.config.devices:
            try:
                build(device.type, device.options)
            except PropertyError as exc:
                problems.append(f"{self.config.source}: devices ({device.name}): {exc.message}")
        if problems:
            raise ConfigError(*problems)

    def _open(self, entry: ServiceEntry) -> Backend:
        """The backend of a ``[[services]]`` entry; one that cannot be built is a config error.

        A dormant one is built here once (so that a bad entry fails now, and its type is known)
        but served by a :class:`DormantBackend`, which builds and starts it when a call needs it.
        """
        try:
            backend = open_backend(entry, self.router.directory, self.follow)
        except PropertyError as exc:
            raise ConfigError(f"{self.config.source}: services ({entry.name}): {exc.message}") from None
        if not entry.dormant:
            return backend
        directory = self.router.directory
        dormant = self._dormant[entry.name] = DormantBackend(
            entry.name,
            lambda: open_backend(entry, directory, self.follow),
            info=backend.info,
            idle_stop=entry.idle_stop,
            awake=self._awake,
            # The call that starts it hears why the device did not answer, not a bare deadline.
            connect_wait=min(DEVICE_CONNECT_WAIT, REGISTER_SHARE * self.config.gateway.call_timeout),
            held=lambda name: self.registry.licensing.holder_of(name) is not None,
        )
        return dormant

    def _on_licence(self, licence: Licence, event: str) -> None:
        """A licence changed: a dormant service's idle time runs from the end of its last licence."""
        dormant = self._dormant.get(licence.service)
        if dormant is not None:
            dormant.touch()

    def _awake(self, name: str, running: bool) -> None:
        """A dormant service started (a call needed it) or stopped (idle): the registry shows it."""
        self.registry.set_dormant(name, not running)

    async def _add(self, name: str, backend: Backend, what: str) -> None:
        try:
            await backend.start()
            self.router.add(name, backend)
        except BaseException:
            await backend.aclose()
            raise
        if backend.on_demand:
            self.registry.set_dormant(name, True)
        log.info("service %s started (%s)", name, what, extra={"service": name})

    def _launch_devices(self) -> None:
        """Start every ``[[devices]]`` process at once; they boot while the gateway starts the rest."""
        if self.config.devices and self._launch is None:
            self._launch = asyncio.ensure_future(
                asyncio.gather(
                    *(
                        start_supervised(e, wait_s=self.config.gateway.device_start_timeout)
                        for e in self.config.devices
                    ),
                    return_exceptions=True,
                )
            )

    async def _start_devices(self) -> None:
        """Wait for the device processes to say where they serve, then reach each through its proxy."""
        if self._launch is None:
            return
        started = await self._launch
        self._launch = None
        self._devices = [d for d in started if isinstance(d, SupervisedDevice)]
        for outcome in started:
            if isinstance(outcome, BaseException):
                raise outcome
        proxies: list[tuple[str, Backend]] = []
        for entry, device in zip(self.config.devices, self._devices, strict=True):
            if device.url.startswith("serial://"):
                # The link's path and the pseudo-terminal's (now and after each restart).
                self.allow.reserve(urlsplit(device.url).path)
                device.on_restart = lambda url: self.allow.reserve(urlsplit(url).path)
            backend = open_proxy(entry.name, device.url, entry.proxy)
            await self._add(entry.name, backend, f"device process {device.pid} at {device.url}")
            proxies.append((entry.name, backend))
        await asyncio.gather(*(self._wait_connected(name, backend) for name, backend in proxies))

    async def _stop_devices(self) -> None:
        launch, self._launch = self._launch, None
        if launch is not None:
            # Waited for, never cancelled here: a start_device cut short could leave its process behind.
            await asyncio.wait([launch])
            started = [] if launch.cancelled() else launch.result()
            self._devices = [d for d in started if isinstance(d, SupervisedDevice)]
        devices, self._devices = self._devices, []
        await asyncio.gather(*(d.aclose() for d in devices), return_exceptions=True)

    async def _wait_connected(self, name: str, backend: Backend) -> None:
        # Clients of a gateway that has just started should find its own devices answering.
        try:
            await backend.wait_connected(DEVICE_CONNECT_WAIT)
        except PropertyError as exc:
            log.warning("device %s: %s; the proxy keeps trying", name, exc.message)

    def _warn_missing_members(self, entry: ServiceEntry) -> None:
        members = entry.options.get("members")
        if not isinstance(members, list):
            return
        missing = [m for m in members if isinstance(m, str) and m not in self.router]
        if missing:
            log.warning(
                "group %s: %s not served yet; each joins the group when it is registered",
                entry.name,
                ", ".join(missing),
            )

    def _own_ports(self) -> list[int]:
        """The TCP ports this gateway listens on: a registration naming one would call itself."""
        ports = []
        addresses = (self.address, self.line_address, self.http_address, self.metrics_address)
        for address in (self.config.gateway.listen, *addresses):
            tail = address.rpartition(":")[2]
            if not address.startswith("unix:") and tail.isdigit() and int(tail):
                ports.append(int(tail))
        return ports

    async def _start_registry(self) -> None:
        settings = self.config.registry
        static = [e.name for e in self.config.services] + [d.name for d in self.config.devices]
        self.registry = Registry(
            # In a cluster, registrations go through the cluster (gateway.cluster.ClusterDirectory).
            directory=self.cluster.directory if self.cluster is not None else self.router.directory,
            store=self.store,
            restore=self.cluster is None,
            period=settings.period,
            timeout=settings.timeout,
            misses=settings.misses,
            grace=settings.grace,
            register_timeout=min(DEFAULT_REGISTER_TIMEOUT, REGISTER_SHARE * self.config.gateway.call_timeout),
            static=static,
            persist=settings.persist or None,
            allow=self.allow,
            max_registrations=settings.max_registrations,
            max_licences=settings.max_licences,
            max_licence_duration=settings.max_licence_duration,
            max_licences_per_holder=settings.max_licences_per_holder,
            features={e.name: e.features for e in self.config.services if e.features},
            tout=settings.tout,
            tr=settings.tr,
            max_queued=settings.max_queued,
        )
        # Only an admin (by the rules) may unregister or replace a configured service.
        self.registry.set_admin_check(self.guard.may_administer)
        # Licences are held by the caller's identity (or its Session); every Set is checked against them.
        self.registry.set_caller(current_caller)
        # A caller locks only what the rules let it change.
        self.registry.set_licence_check(may_license(self.guard))
        # And the scheduler licenses to the caller only the providers it may write.
        self.registry.set_provider_check(may_provide(self.guard))
        self.servicer.calls.licences = self.registry.licensing
        # And every Set a service makes for a client (a group's members): given before any such
        # service is added, so that each member it is handed checks them.
        self.router.directory.licences = self.registry.licensing
        self.registry.licensing.watch(self._on_licence)
        await self._add(REGISTRY_NAME, RegistryService(self.registry), "built in")
        self._unwatch_registry = self.registry.watch_states(self._on_state)
        self._unwatch_health = self.registry.watch_states(self._health_follows, members=True)
        for name, state in self.registry.states():
            self._health_follows(name, state)
        self._unwatch_links = self.router.watch(self._health_follows_link)
        for name, backend in self.router.items():
            self._health_follows_link(name, backend)

    async def _join_store(self) -> None:
        """Open the shared registry store a config names (``[registry] store``), and this gateway's
        cluster node on it; nothing for the embedded store. An etcd that cannot be reached now is
        no error: the gateway starts read-only and joins when etcd answers (docs/scale-out.md)."""
        if not self.config.registry.store:
            return
        store = open_store(self.config, listen=self.address)
        if not isinstance(store, SharedStore):  # pragma: no cover - a store URL names a shared store
            raise ConfigError(f"{self.config.source}: registry.store: {store.location} is not shared")
        await store.start()
        self.store = store
        settings = self.config.registry
        peer_tls = {
            option: value
            for option, value in (
                ("ca", settings.peer_ca),
                ("cert", settings.peer_cert),
                ("key", settings.peer_key),
            )
            if value
        }
        self.cluster = ClusterNode(
            store,
            self.router,
            lease=settings.store_lease,
            allow=self.allow,
            peer_tls=peer_tls,
            rebalance=settings.rebalance,
            rebalance_spread=settings.rebalance_spread,
            rebalance_batch=settings.rebalance_batch,
            version=gateway_version(),
            load=self._load,
        )

    def _load(self) -> tuple[int, int]:
        """(Gets, Sets and Describes answered so far, gRPC and HTTP; Listen streams open now): the
        load the cluster view shows (counted only with ``[metrics] enabled``, the default)."""
        calls = 0
        grpc_counts = self.servicer.counts
        if grpc_counts is not None:
            for method in ("Get", "Set", "Describe"):
                calls += sum(grpc_counts.methods[method].codes)
        http_counts = self.http.counts if self.http is not None else None
        if http_counts is not None:
            responses = http_counts.responses.items()
            calls += sum(count for (route, _), count in responses if "events" not in route)
        return calls, self.hub.stream_count

    async def _start_cluster(self) -> None:
        """Join the cluster, now that every port this gateway serves is known."""
        if self.cluster is None:
            return
        await self.cluster.start(
            self.registry,
            address=self.config.registry.advertise or self.address,
            http=self.http_address,
            line=self.line_address,
            tls=self.config.tls.enabled,
            via=self.servicer.gateway_id,
        )
        self.servicer.calls.peer_hop = self.cluster.is_peer_hop
        # A Set a peer forwarded comes as that peer, checked against the licences where the client called.
        self.router.directory.peer_forwarded = self.servicer.calls.forwarded_by_peer
        self.registry.attach("cluster", ClusterReport(self.cluster))
        log.info("cluster: joined as %s through %s", self.cluster.me, self.config.registry.store)

    def _alternates(self) -> list[str]:
        """The other gateways' line listeners, which the line listener's greeting names."""
        return self.cluster.alternates() if self.cluster is not None else []

    def _health_follows(self, name: str, state: str) -> None:
        """A service joined, changed state or left: its gRPC health status follows."""
        if name in ("", SERVICE_NAME):
            return  # the gateway's own names
        if state == GONE:
            self.health.forget(name)
        else:
            self.health.follow_state(name, state)

    def _health_follows_link(self, name: str, backend: Backend | None) -> None:
        """A backend was added (or removed): its health follows its link to its device as well."""
        unwatch = self._link_watches.pop(name, None)
        if unwatch is not None:
            unwatch()
        if backend is not None:
            self._link_watches[name] = backend.watch_link(
                lambda connected: self.health.follow_link(name, connected)
            )
        else:
            self.health.follow_link(name, True)

    def _on_state(self, name: str, state: str) -> None:
        """The registry marked ``name`` up, down or connecting: client calls follow."""
        if state != "down":
            # A service still connecting answers for itself (a proxy: UNAVAILABLE, saying why).
            self.router.set_down(name, None)
            log.info("service %s is %s", name, state, extra={"service": name})
            return
        reason = f"service {name!r} is down"
        entry = self.registry.entry_of(name)
        misses = entry.misses if entry is not None else 0
        if misses:
            reason += f": it missed {misses} liveness check{'s' if misses != 1 else ''}"
        self.router.set_down(name, reason)
        log.warning("%s", reason, extra={"service": name})

    async def _start_line_listener(self) -> None:
        address = self.config.gateway.line_listen
        if not address:
            return
        try:
            line_tls = self.config.tls.line
            self._line_credentials = LineCredentials(line_tls) if line_tls.enabled else None
            context = self._line_credentials.context if self._line_credentials else None
            self._line_listener = await start_line_listener(
                address,
                self.router,
                self._rejoined,
                self.guard,
                ssl_context=context,
                idle_timeout=self.config.limits.line_idle_timeout,
                max_greetings_per_source=self.config.limits.max_greetings_per_source,
                max_connections=self.shares.get(
                    "limits.line_max_connections", self.config.limits.line_max_connections
                ),
                max_connections_per_address=self.config.limits.line_max_connections_per_address,
                device_secrets=self._device_secrets(),
                alternates=self._alternates,
                seats=self.cluster,
                calls=self.servicer.calls,
            )
        except OSError as exc:
            if exc.errno != errno.EADDRINUSE:
                raise
            port = int(address.rpartition(":")[2])
            raise PortInUse(f"port {port} (gateway.line_listen) is in use by {port_holder(port)}") from None
        bound = self._line_listener.address
        if bound is not None:
            address = f"{bound[0]}:{bound[1]}"
        self.line_address = address
        log.info("line-protocol listener on %s", address)

    async def _start_http(self) -> None:
        """The HTTP front end, in this loop, through the same call layer, hub and guard as gRPC."""
        if not self.config.http.listen:
            return
        # Imported only when configured: aiohttp takes a quarter of a second to import.
        from gateway.fronts.http import HttpFront

        self.http = HttpFront(self.servicer.calls, self.hub, self.config, self.guard, self.history)
        self.http.max_connections = self.shares.get("http.max_connections", self.config.http.max_connections)
        if self.config.metrics.enabled:
            self.http.metrics = self._metrics_endpoint().guarded
        self.http.websockets.append(self._foxglove_route())
        self.http.websockets.append(self._rosbridge_route())
        await self.http.start()
        self.http_address = self.http.address

    def _foxglove_route(self) -> WebSocketRoute:
        """The Foxglove WebSocket protocol on the HTTP front's port (docs/ros-and-foxglove.md)."""
        from gateway.fronts.foxglove import SUBPROTOCOLS, FoxgloveEndpoint
        from gateway.fronts.http import WebSocketRoute

        http = self.config.http
        endpoint = FoxgloveEndpoint(
            self.servicer.calls, self.hub, write_timeout=http.write_timeout, heartbeat=http.heartbeat
        )
        return WebSocketRoute("/foxglove", SUBPROTOCOLS, endpoint.serve)

    def _rosbridge_route(self) -> WebSocketRoute:
        """rosbridge v2 on the HTTP front's port, at ``/rosbridge`` (docs/ros-and-foxglove.md)."""
        from gateway.fronts.http import WebSocketRoute
        from gateway.fronts.rosbridge import ROSBRIDGE_PATH, RosbridgeEndpoint

        http = self.config.http
        endpoint = RosbridgeEndpoint(
            self.servicer.calls,
            self.hub,
            self.guard,
            write_timeout=http.write_timeout,
            heartbeat=http.heartbeat,
            max_message=http.max_body,
        )
        return WebSocketRoute(ROSBRIDGE_PATH, RosbridgeEndpoint.protocols, endpoint.serve)

    def _metrics_endpoint(self) -> MetricsEndpoint:
        if self.metrics is None:
            from gateway.metrics.endpoint import MetricsEndpoint

            self.metrics = MetricsEndpoint(self)
        return self.metrics

    async def _start_metrics(self) -> None:
        """The listener of ``[metrics] listen``: ``/metrics`` alone, on a port of its own."""
        settings = self.config.metrics
        if settings.enabled and settings.listen:
            endpoint = self._metrics_endpoint()
            await endpoint.start(
                settings.listen,
                self.config.gateway.shutdown_grace,
                self.shares.get("metrics.listen", METRICS_MAX_CONNECTIONS),
            )
            self.metrics_address = endpoint.address
            log.debug("metrics on http://%s/metrics", endpoint.address)  # printed as well, below

    def _device_secrets(self) -> dict[str, str]:
        """Name → secret of each configured device that dials in (read at start, never logged)."""
        secrets = {}
        for entry in self.config.services:
            if entry.dials_in:
                try:
                    secrets[entry.name] = Path(entry.secret_file).read_text(encoding="utf-8").strip()
                except OSError as exc:
                    raise ConfigError(
                        f"{self.config.source}: services ({entry.name}).secret_file: {exc}"
                    ) from None
        return secrets

    def _rejoined(self, name: str, info: BackendInfo) -> None:
        """A device dialled in again after a drop: the registry hears at once that it is up."""
        try:
            self.registry.add(name, info)
        except PropertyError as exc:
            log.debug("registry: %s rejoined: %s", name, exc.message)

    def _make_server(self) -> grpc.aio.Server:
        gw, limits = self.config.gateway, self.config.limits
        pending = max(limits.max_calls, PENDING_CALLS)
        options = [
            ("grpc.so_reuseport", 0),
            # Bounded connections (docs/security.md): beyond its share of open files grpc closes a
            # new connection at once; one that never begins, or stays without a call, is closed.
            (
                "grpc.max_allowed_incoming_connections",
                self.shares.get("gateway.max_connections", gw.max_connections),
            ),
            ("grpc.server_handshake_timeout_ms", round(gw.handshake_timeout * 1000)),
            ("grpc.max_connection_idle_ms", round(gw.idle_timeout * 1000)),
            # Calls wait in grpc's queue until the asyncio loop takes them up. grpc's defaults
            # (1,000 soft, 3,000 hard, dropped at random between) end a burst of a few thousand
            # calls with CANCELLED although nothing cancelled them; a longer queue lets the
            # servicer take each up and answer RESOURCE_EXHAUSTED past limits.max_calls itself.
            ("grpc.server.max_pending_requests", pending),
            ("grpc.server.max_pending_requests_hard_limit", pending),
            *CLIENT_PING_POLICY,
        ]
        server = grpc.aio.server(options=options)
        filter_grpc_client_faults()  # a call cancelled while a message was sent: no traceback
        # Not the generated registration: a request that does not parse is INVALID_ARGUMENT.
        add_to_server(self.servicer, server)
        add_health_and_reflection(server, self.health)
        listen = self.config.gateway.listen
        if self.config.tls.enabled:
            self.credentials = ServerCredentials(self.config.tls)
        try:
            if self.credentials is not None:
                port = server.add_secure_port(listen, self.credentials.credentials)
            else:
                port = server.add_insecure_port(listen)
        except RuntimeError:
            # Checked free at the start; taken since. grpc's own error names no holder.
            port = 0
        if port == 0:
            asked = int(listen.rpartition(":")[2]) if not listen.startswith("unix:") else 0
            holder = f"in use by {port_holder(asked)}" if asked else "not available"
            raise PortInUse(f"cannot listen on {listen} (gateway.listen): {holder}")
        host = listen.rpartition(":")[0]
        # A unix-domain socket ("unix:PATH", how gateway.testing serves) has no port to fill in.
        self.address = listen if listen.startswith("unix:") else f"{host}:{port}"
        return server

    def reload_certificates(self) -> None:
        """Read the TLS certificate and key files again (SIGHUP); new connections get the new ones."""
        if self.credentials is not None:
            self.credentials.reload()
        else:
            log.info("reload asked; the gRPC port has no TLS certificates to read again")
        if self._line_credentials is not None:
            self._line_credentials.reload()
        if self.http is not None and self.http.credentials is not None:
            self.http.credentials.reload()

    async def stop(self, grace: float | None = None) -> None:
        """Graceful shutdown: NOT_SERVING, streams end with UNAVAILABLE, server stops, backends close.

        Idempotent.
        """
        if self._stopped.is_set():
            return
        self._stopped.set()
        grace = self.config.gateway.shutdown_grace if grace is None else grace
        self.health.shut_down()
        if self.history is not None:
            await self.history.aclose()
        self.hub.end_all()
        self.servicer.end_sessions()
        if self.http is not None:
            await self.http.stop()
        if self.metrics is not None:
            await self.metrics.stop()
        if self._server is not None:
            await self._server.stop(grace)
        if self.cluster is not None:
            cluster_report = self.registry.children().get("cluster")
            if isinstance(cluster_report, ClusterReport):
                cluster_report.close()
            await self.cluster.stop()  # its services are handed over before their proxies close
        await self.hub.aclose()
        if callable(self._unwatch_registry):
            self._unwatch_registry()
        if callable(self._unwatch_health):
            self._unwatch_health()
        if callable(self._unwatch_links):
            self._unwatch_links()
        for unwatch in self._link_watches.values():
            unwatch()
        self._link_watches.clear()
        if self._line_listener is not None:
            await self._line_listener.aclose()
        # Groups go first, so none of them asks the registry again once it is gone; then the
        # registry: services closed for the shutdown are not leaves it should record (a
        # registration kept in its persist file must still be there at the next start).
        groups = {e.name for e in self.config.services if _needs_directory(e)}
        names = reversed(self.router.names())
        for name in sorted(names, key=lambda n: 0 if n in groups else 1 if n == REGISTRY_NAME else 2):
            if name not in self.router:
                continue  # a service a closed one served (a replay's recorded services) went with it
            backend = self.router.remove(name)
            try:
                await asyncio.wait_for(backend.aclose(), grace)
            except Exception:
                log.warning("closing service %s failed", name, exc_info=True)
        await self._stop_devices()
        if self.store is not None:
            await self.store.aclose()

    async def wait_stopped(self) -> None:
        """Return once :meth:`stop` was called."""
        await self._stopped.wait()


def _described(entry: ServiceEntry) -> str:
    what = entry.url or f"type {entry.type}"
    return f"{what}, dormant: started on demand" if entry.dormant else what


def _needs_directory(entry: ServiceEntry) -> bool:
    return not entry.url and needs_directory(entry.type)


async def serve(config: Config) -> int:
    """Run a gateway until SIGTERM or SIGINT; the exit code.

    A signal during start-up stops what has started and returns as cleanly as one later.
    """
    gateway = Gateway(config)
    loop = asyncio.get_running_loop()
    stop = asyncio.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)
    loop.add_signal_handler(signal.SIGHUP, gateway.reload_certificates)
    starting = asyncio.ensure_future(gateway.start())
    stopped = asyncio.ensure_future(stop.wait())
    await asyncio.wait((starting, stopped), return_when=asyncio.FIRST_COMPLETED)
    if not starting.done():
        log.info("stopping during start-up")
        starting.cancel()
        await asyncio.gather(starting, return_exceptions=True)
        await gateway.stop()
        log.info("stopped")
        return 0
    if starting.exception() is not None:
        stopped.cancel()
    starting.result()  # a start that failed raises here
    if gateway.http is not None:
        # Printed whatever the log level, as the gRPC address is: tests and scripts read the port here.
        print(f"HTTP front end and console on {gateway.http.url}", flush=True, file=sys.stderr)
    if gateway.metrics_address:
        print(f"metrics on http://{gateway.metrics_address}/metrics", flush=True, file=sys.stderr)
    print(f"listening on {gateway.address}", flush=True, file=sys.stderr)
    await stopped
    log.info("shutting down")
    await gateway.stop()
    log.info("stopped")
    return 0
