"""The gateway's metrics as Prometheus families, read from its plain counters at scrape time.

Nothing is counted here: :class:`GatewayCollector` walks the counters of the gRPC
servicer, the HTTP front end, the listen hub, the proxies and the registry each
time Prometheus scrapes, so the calls themselves never touch prometheus_client.
Every label takes its values from a fixed set (see docs/metrics.md for each
metric, its labels and their bound): no service, property or client name
becomes a label.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import TYPE_CHECKING, Protocol

from prometheus_client.core import (
    CounterMetricFamily,
    GaugeMetricFamily,
    HistogramMetricFamily,
    Metric,
)
from prometheus_client.registry import Collector

from gateway.metrics.counts import LATENCY_BOUNDS, Latency
from gateway.proxies.grpc_channels import channel_pool
from services.kernel.backend import LinkCounts
from services.kernel.errors import Code

if TYPE_CHECKING:
    from gateway.engine.guard import Guard
    from gateway.engine.listen import ListenHub
    from gateway.engine.router import Router
    from gateway.fronts.grpc_v1.servicer import PropertyServicer
    from gateway.fronts.http.front import HttpFront
    from services.apps.registry import Registry


class Measured(Protocol):
    """What the metrics read of a gateway (``gateway.app.Gateway``), named here so that the
    metrics never import the gateway that serves them."""

    @property
    def servicer(self) -> PropertyServicer: ...
    @property
    def http(self) -> HttpFront | None: ...
    @property
    def hub(self) -> ListenHub: ...
    @property
    def router(self) -> Router: ...
    @property
    def registry(self) -> Registry: ...
    @property
    def guard(self) -> Guard: ...


#: The exported metrics' common prefix.
PREFIX = "psgateway"

#: gRPC status code names by number ("OK", "NOT_FOUND", ...).
CODE_NAMES = {int(code): code.name for code in Code}

#: The upper bounds as Prometheus writes them, +Inf last.
_BOUNDS = [*(repr(b) for b in LATENCY_BOUNDS), "+Inf"]


def _buckets(latency: Latency) -> tuple[list[tuple[str, float]], float]:
    """Cumulative buckets and the sum, as HistogramMetricFamily takes them."""
    running = 0
    cumulative = []
    for bound, count in zip(_BOUNDS, latency.buckets, strict=True):
        running += count
        cumulative.append((bound, float(running)))
    return cumulative, latency.total


class LinkTotals:
    """Connections made and lost and keep-alives missed, summed over every proxy there has been.

    A proxy that goes away (a registration removed, a dormant service gone back to sleep) keeps
    its final counts here, so the counters never go down.
    """

    def __init__(self) -> None:
        self._live: dict[int, LinkCounts] = {}
        self._retired: dict[str, list[int]] = {}

    def read(self, current: list[LinkCounts]) -> tuple[dict[str, list[int]], dict[str, list[int]]]:
        """Per transport: [connects, reconnects, disconnects, keepalive_failures] so far;
        [connected, devices] now."""
        seen = {id(c): c for c in current}
        for key, counts in list(self._live.items()):
            if key not in seen:
                _add(self._retired.setdefault(counts.transport, [0, 0, 0, 0]), counts)
                del self._live[key]
        self._live.update(seen)
        sums = {transport: list(totals) for transport, totals in self._retired.items()}
        now: dict[str, list[int]] = {}
        for counts in current:
            _add(sums.setdefault(counts.transport, [0, 0, 0, 0]), counts)
            state = now.setdefault(counts.transport, [0, 0])
            state[0] += counts.connected
            state[1] += 1
        return sums, now


def _add(totals: list[int], counts: LinkCounts) -> None:
    totals[0] += counts.connects
    totals[1] += max(counts.connects - 1, 0)  # every connection after the first is a reconnect
    totals[2] += counts.disconnects
    totals[3] += counts.keepalive_failures


class GatewayCollector(Collector):
    """Every metric of one gateway, read when collected; see the module docstring."""

    def __init__(self, gateway: Measured) -> None:
        self.gateway = gateway
        self.links = LinkTotals()

    def collect(self) -> Iterator[Metric]:
        yield from self._grpc()
        yield from self._http()
        yield from self._streams()
        yield from self._devices()
        yield from self._remote_gateways()
        yield from self._registry()

    def _grpc(self) -> Iterator[Metric]:
        counts = self.gateway.servicer.counts
        if counts is None:
            return
        calls = CounterMetricFamily(
            f"{PREFIX}_grpc_calls",
            "gRPC calls of the PropertyService ended, by method and status code",
            labels=("method", "code"),
        )
        latency = HistogramMetricFamily(
            f"{PREFIX}_grpc_call_duration_seconds",
            "Time from a unary call's arrival to its answer (Get, Set, Describe, History)",
            labels=("method",),
        )
        for method, method_counts in counts.methods.items():
            for number, n in enumerate(method_counts.codes):
                if n or number == 0:
                    calls.add_metric((method, CODE_NAMES[number]), n)
            if method in ("Get", "Set", "Describe", "History"):
                buckets, total = _buckets(method_counts.latency)
                latency.add_metric((method,), buckets, total)
        yield calls
        yield latency
        requests = CounterMetricFamily(
            f"{PREFIX}_session_requests",
            "Requests read from Session streams, by call (get, set, listen, cancel; none: no call named)",
            labels=("call",),
        )
        for call, n in counts.session_requests.items():
            requests.add_metric((call,), n)
        yield requests

    def _http(self) -> Iterator[Metric]:
        http = self.gateway.http
        if http is None or http.counts is None:
            return
        responses = CounterMetricFamily(
            f"{PREFIX}_http_requests",
            "HTTP front end requests answered, by route template and status",
            labels=("route", "status"),
        )
        for (route, status), n in sorted(http.counts.responses.items()):
            responses.add_metric((route, str(status)), n)
        yield responses
        latency = HistogramMetricFamily(
            f"{PREFIX}_http_request_duration_seconds",
            "Time from an HTTP request's arrival to its answer, by route template (streams left out)",
            labels=("route",),
        )
        for route, route_latency in sorted(http.counts.latency.items()):
            buckets, total = _buckets(route_latency)
            latency.add_metric((route,), buckets, total)
        yield latency

    def _streams(self) -> Iterator[Metric]:
        gateway = self.gateway
        servicer = gateway.servicer
        http = gateway.http
        sessions = list(servicer.sessions)
        listens = servicer.counts.listens_open if servicer.counts is not None else 0
        session_listens = sum(s.listen_count for s in sessions)
        sse = len(http.events.open) if http is not None else 0
        images = len(http.images.open) if http is not None else 0
        open_streams = GaugeMetricFamily(
            f"{PREFIX}_open_streams",
            "Streams open now: gRPC Listen and Session calls, Listens inside Sessions, "
            "Server-Sent-Events and live image streams",
            labels=("kind",),
        )
        for kind, n in (
            ("listen", listens),
            ("session", len(sessions)),
            ("session_listen", session_listens),
            ("sse", sse),
            ("image", images),
        ):
            open_streams.add_metric((kind,), n)
        yield open_streams
        sent, conflated, queued = gateway.hub.counts()
        yield CounterMetricFamily(
            f"{PREFIX}_listen_events_sent",
            "Events handed to Listen, Session-Listen, SSE and image stream writers",
            value=sent,
        )
        yield CounterMetricFamily(
            f"{PREFIX}_listen_events_conflated",
            "Values replaced by a newer one of the same property before a slow reader took them",
            value=conflated,
        )
        yield GaugeMetricFamily(
            f"{PREFIX}_listen_queued_events",
            "Events waiting in the conflating queues of every open stream (at most one per property)",
            value=sum(queued),
        )
        yield GaugeMetricFamily(
            f"{PREFIX}_listen_queue_max_depth",
            "Events waiting in the fullest conflating queue of an open stream",
            value=max(queued, default=0),
        )
        yield GaugeMetricFamily(
            f"{PREFIX}_session_queued_replies",
            "Session replies waiting to be written, all Sessions together",
            value=sum(s.queued_replies for s in sessions),
        )
        yield GaugeMetricFamily(
            f"{PREFIX}_listen_topics",
            "Backend subscriptions shared by the streams",
            value=gateway.hub.topic_count,
        )

    def _devices(self) -> Iterator[Metric]:
        current = []
        for _, backend in self.gateway.router.items():
            counts = backend.link_counts()
            if counts is not None:
                current.append(counts)
        sums, now = self.links.read(current)
        connects = CounterMetricFamily(
            f"{PREFIX}_device_connects",
            "Connections to line-protocol devices made (greeted), the first ones included",
            labels=("transport",),
        )
        reconnects = CounterMetricFamily(
            f"{PREFIX}_device_reconnects",
            "Connections to line-protocol devices made again after one was lost",
            labels=("transport",),
        )
        disconnects = CounterMetricFamily(
            f"{PREFIX}_device_disconnects",
            "Connections to line-protocol devices lost; each is followed by a reconnect (or a wait "
            "for a device that dials in)",
            labels=("transport",),
        )
        keepalive = CounterMetricFamily(
            f"{PREFIX}_device_keepalive_failures",
            "Keep-alive PINGs a device did not answer in time (each drops its connection)",
            labels=("transport",),
        )
        for transport, (made, again, lost, missed) in sorted(sums.items()):
            connects.add_metric((transport,), made)
            reconnects.add_metric((transport,), again)
            disconnects.add_metric((transport,), lost)
            keepalive.add_metric((transport,), missed)
        yield connects
        yield reconnects
        yield disconnects
        yield keepalive
        connected = GaugeMetricFamily(
            f"{PREFIX}_devices_connected",
            "Line-protocol devices connected now",
            labels=("transport",),
        )
        devices = GaugeMetricFamily(
            f"{PREFIX}_devices", "Line-protocol devices served (connected or not)", labels=("transport",)
        )
        for transport, (up, total) in sorted(now.items()):
            connected.add_metric((transport,), up)
            devices.add_metric((transport,), total)
        yield connected
        yield devices

    def _remote_gateways(self) -> Iterator[Metric]:
        # The gRPC proxies' shared channels belong to the event loop the gateway runs in, where
        # ``/metrics`` is answered.
        pool = channel_pool()
        yield GaugeMetricFamily(
            f"{PREFIX}_remote_gateway_channels",
            "gRPC channels to other gateways open now: one per address and settings, shared by "
            "the grpc:// services and the cluster's forwarded services that reach it",
            value=len(pool),
        )
        yield GaugeMetricFamily(
            f"{PREFIX}_remote_gateway_proxies",
            "gRPC proxies (grpc:// services, forwarded services of a cluster) holding those channels",
            value=pool.users,
        )

    def _registry(self) -> Iterator[Metric]:
        entries = GaugeMetricFamily(
            f"{PREFIX}_registry_entries",
            "Services the registry knows, by state (up, down, connecting) and availability "
            "(death, dormant, ready, active)",
            labels=("state", "availability"),
        )
        for (state, availability), n in sorted(self.gateway.registry.entry_states().items()):
            entries.add_metric((state, availability), n)
        yield entries
