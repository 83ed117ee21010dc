"""Listen: fan-out of backend changes to Listen streams, with bounded memory.

* :mod:`~gateway.listen.requests` — a Listen request parsed: selectors, options.
* :mod:`~gateway.listen.topics` — one shared backend subscription per
  (service, path, parameters), with its latest value; and per service, one that follows
  where its property list changes.
* :mod:`~gateway.listen.stream` — one client's Listen: wildcard expansion by the service
  itself, at any size (a service that cannot be reached is skipped and tried again), the
  conflating queue, pacing (throttle, sampling, heartbeat), ``take``.
* :mod:`~gateway.listen.matched` — a wildcard's matches on one service, kept sorted.
* :mod:`~gateway.fronts.grpc_v1.listen_encoding` — events into ``ListenResponse`` messages, batched by bytes.
* :mod:`~gateway.listen.hub` — the hub that owns topics and streams.
* :mod:`~gateway.listen.drain` — how a front end writes a stream: wait, take, repeat.
* :mod:`~gateway.listen.budget` — one total for the large values readers hold, all together.
"""

from gateway.listen.hub import ListenHub
from gateway.listen.requests import Selector, StreamOptions, parse_options, parse_selectors
from gateway.listen.stream import ListenStream

__all__ = ["ListenHub", "ListenStream", "Selector", "StreamOptions", "parse_options", "parse_selectors"]
