"""Listen: fan-out of backend changes to Listen streams, with bounded memory.

The hub works in the engine's own types (:mod:`gateway.engine.events`): a Listen request in,
batches of events and markers out; each front end encodes them its own way.

* :mod:`~gateway.engine.listen.requests` — a Listen request checked against the limits.
* :mod:`~gateway.engine.listen.topics` — one shared backend subscription per
  (service, path, parameters), with its latest value; and per service, one that follows
  where its property list changes.
* :mod:`~gateway.engine.listen.stream` — one client's Listen: wildcard expansion by the service
  itself, at any size (a service that cannot be reached is skipped and tried again), the
  conflating queue, pacing (throttle, sampling, heartbeat), batches by bytes, ``take``.
* :mod:`~gateway.engine.listen.matched` — a wildcard's matches on one service, kept sorted.
* :mod:`~gateway.engine.listen.hub` — the hub that owns topics and streams.
* :mod:`~gateway.engine.listen.drain` — how a front end writes a stream: wait, take, repeat.
* :mod:`~gateway.engine.listen.budget` — one total for the large values readers hold, all together.
"""

from gateway.engine.events import Selector, StreamOptions
from gateway.engine.listen.hub import ListenHub
from gateway.engine.listen.stream import ListenStream

__all__ = ["ListenHub", "ListenStream", "Selector", "StreamOptions"]
