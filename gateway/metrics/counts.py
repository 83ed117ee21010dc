"""Plain counters on the hot paths: calls by method and code, and their latencies.

Nothing here imports prometheus_client: a call raises an int in a list and
one bucket of a fixed histogram, and the collector (:mod:`gateway.metrics.collector`)
reads them only when Prometheus scrapes. Every key is from a fixed set (the
methods of the contract, the routes of the HTTP front end, the status codes), so
the number of series is bounded whatever callers send.
"""

from __future__ import annotations

from bisect import bisect_left

from services.kernel.errors import Code

#: Upper bounds (seconds) of the latency buckets: 100 µs (an in-process Get through the gateway
#: takes about that much) up to 10 s (the longest device timeouts); beyond is +Inf.
LATENCY_BOUNDS: tuple[float, ...] = (
    0.0001,
    0.00025,
    0.0005,
    0.001,
    0.0025,
    0.005,
    0.01,
    0.025,
    0.05,
    0.1,
    0.25,
    0.5,
    1.0,
    2.5,
    5.0,
    10.0,
)

#: One slot per gRPC status code number (0 OK ... 16 UNAUTHENTICATED).
CODE_SLOTS = max(int(code) for code in Code) + 1


class Latency:
    """A histogram with :data:`LATENCY_BOUNDS`: counts per bucket (the last is +Inf) and the sum."""

    __slots__ = ("buckets", "total")

    def __init__(self) -> None:
        self.buckets = [0] * (len(LATENCY_BOUNDS) + 1)
        self.total = 0.0

    def observe(self, seconds: float) -> None:
        # bisect_left: a value equal to a bound belongs to that bucket (Prometheus's "le").
        self.buckets[bisect_left(LATENCY_BOUNDS, seconds)] += 1
        self.total += seconds


class MethodCounts:
    """One method of one front end: how many calls ended with each code, and how long they took."""

    __slots__ = ("codes", "latency")

    def __init__(self) -> None:
        self.codes = [0] * CODE_SLOTS
        self.latency = Latency()

    def done(self, code: int, seconds: float | None) -> None:
        """A call ended with ``code``; ``seconds`` is None for a stream (its life is no latency)."""
        self.codes[code] += 1
        if seconds is not None:
            self.latency.observe(seconds)


class GrpcCounts:
    """The gRPC front end: one :class:`MethodCounts` per method of the contract, and Session requests."""

    METHODS = ("Get", "Set", "Describe", "Listen", "Session", "History")
    #: What a Session request can be (``Request.call``), and "none" for one that names no call.
    SESSION_REQUESTS = ("get", "set", "listen", "cancel", "none")

    def __init__(self) -> None:
        self.methods = {name: MethodCounts() for name in self.METHODS}
        self.session_requests = dict.fromkeys(self.SESSION_REQUESTS, 0)
        #: Listen calls open now.
        self.listens_open = 0


class HttpCounts:
    """The HTTP front end: responses by route and status, and latencies by route.

    Routes are the front end's own templates (``GET /api/v1/services/{service}/properties/{path}``),
    a fixed set; a request that matches none counts as ``unrouted``. Statuses are those the front
    end answers with, also a small set.
    """

    def __init__(self) -> None:
        self.responses: dict[tuple[str, int], int] = {}
        self.latency: dict[str, Latency] = {}

    def done(self, route: str, status: int, seconds: float | None) -> None:
        key = (route, status)
        self.responses[key] = self.responses.get(key, 0) + 1
        if seconds is not None:
            latency = self.latency.get(route)
            if latency is None:
                latency = self.latency[route] = Latency()
            latency.observe(seconds)
