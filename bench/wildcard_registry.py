"""A wildcard Listen on a big registry: ``registry`` / ``services.*.state`` at 1,000 and 10,000 services.

Run ``python -m bench.wildcard_registry`` (``--sizes 1000,10000``, ``--rounds 3``). In one process,
without gRPC: a router, the registry following it, and the listen hub, as the gateway builds
them; the services are tiny in-process resources added to the router (a registration without
a device). For each size, each round: the services join, then one Listen on
``services.*.state`` opens; the figures are the time from opening it to its ``sync`` marker and
the events that came before it (one per service, the registry's own entry included), then the
time until a service that joins after that is on the stream (its state's first value), and
until a change of state is. The best round of each size is printed. The garbage collector runs
as ``psgateway serve`` sets it (``gateway.cli.YOUNG_COLLECTION_THRESHOLD``).
"""

from __future__ import annotations

import argparse
import asyncio
import gc
import time
from collections.abc import Callable
from dataclasses import dataclass

from gateway.cli import YOUNG_COLLECTION_THRESHOLD
from gateway.config import Limits
from gateway.engine.events import Mark, events
from gateway.engine.listen import ListenHub, Selector, StreamOptions
from gateway.engine.router import Router
from services.apps.registry import Registry, RegistryService
from services.kernel.core import LocalService, Resource

PATTERN = "services.*.state"
#: Seconds any one wait may take before the round is reported as failed.
WAIT_S = 120.0


class Beacon(Resource):
    """The smallest service: one value."""

    resource_type = "beacon"
    level: int = 0


@dataclass
class Round:
    """One round's figures; ``None``: it did not happen within ``WAIT_S``."""

    services: int
    open_s: float
    events: int
    error: str
    joined_s: float | None
    changed_s: float | None


class Reader:
    """Takes what the stream has ready, as a front end's writer does, and notes when what is awaited came."""

    def __init__(self, hub: ListenHub) -> None:
        self.events: list[tuple[str, str]] = []
        self.synced = asyncio.Event()
        self.heard = asyncio.Event()
        self.awaited: tuple[str, str] | None = None
        self.stream = hub.open([Selector("registry", PATTERN)], StreamOptions(), self._ready)

    def _ready(self) -> None:
        asyncio.get_running_loop().call_soon(self._drain)

    def _drain(self) -> None:
        while (taken := self.stream.take()) is not None:
            if isinstance(taken, Mark):
                if taken is Mark.SYNC:
                    self.synced.set()
                continue
            for event in events(taken):
                self.events.append((event.path, event.value))
                if (event.path, event.value) == self.awaited:
                    self.heard.set()
        if self.stream.error is not None:
            self.synced.set()
            self.heard.set()


async def one_round(size: int) -> Round:
    router = Router()
    registry = Registry(directory=router.directory, period=0)
    service = RegistryService(registry)
    await service.start()
    router.add("registry", service)
    await registry.start()
    for i in range(size):
        router.add(f"beacon{i:05d}", LocalService(Beacon()))
    await asyncio.sleep(0)  # the registry learns each one's type in a task of its own
    hub = ListenHub(router, Limits(max_stream_properties=2 * size + 16), call_timeout=WAIT_S)
    reader = Reader(hub)
    started = time.perf_counter()
    try:
        await reader.stream.start()
        await asyncio.wait_for(reader.synced.wait(), WAIT_S)
        open_s = time.perf_counter() - started
        events = len(reader.events)
        joined_s = changed_s = None
        if reader.stream.error is None:
            joined_s = await _timed(
                reader, "services.late.state", "up", lambda: router.add("late", LocalService(Beacon()))
            )
            changed_s = await _timed(
                reader,
                "services.beacon00000.state",
                "down",
                lambda: registry.set_state("beacon00000", "down"),
            )
        error = reader.stream.error.message if reader.stream.error is not None else ""
        return Round(size, open_s, events, error, joined_s, changed_s)
    finally:
        reader.stream.close()
        await hub.aclose()
        await registry.stop()
        await service.aclose()


async def _timed(reader: Reader, path: str, value: str, act: Callable[[], None]) -> float | None:
    """Seconds from ``act()`` until ``path`` = ``value`` is on the stream; None if not within 10 s."""
    reader.awaited = (path, value)
    reader.heard.clear()
    started = time.perf_counter()
    act()
    try:
        await asyncio.wait_for(reader.heard.wait(), 10.0)
    except TimeoutError:
        return None
    return time.perf_counter() - started if reader.stream.error is None else None


def _shown(seconds: float | None) -> str:
    return "never" if seconds is None else f"{seconds * 1000:.1f} ms"


def main(argv: list[str] | None = None) -> int:
    """Command line: ``python -m bench.wildcard_registry``."""
    parser = argparse.ArgumentParser(prog="python -m bench.wildcard_registry", description=__doc__)
    parser.add_argument("--sizes", default="1000,10000", help="registry sizes, comma-separated")
    parser.add_argument("--rounds", type=int, default=3, help="rounds per size; the best is shown")
    args = parser.parse_args(argv)
    sizes = [int(s) for s in args.sizes.split(",") if s]
    _, middle, oldest = gc.get_threshold()
    gc.set_threshold(YOUNG_COLLECTION_THRESHOLD, middle, oldest)
    print(f"{'services':>8} {'open to sync':>13} {'events':>7} {'a join after':>13} {'a change':>10}  error")
    for size in sizes:
        rounds = [asyncio.run(one_round(size)) for _ in range(max(1, args.rounds))]
        best = min(rounds, key=lambda r: r.open_s)
        print(
            f"{best.services:>8} {best.open_s * 1000:>10.1f} ms {best.events:>7} "
            f"{_shown(best.joined_s):>13} {_shown(best.changed_s):>10}  {best.error[:80]}"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
