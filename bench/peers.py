"""Part (s): the peers, OPC UA (asyncua) and Zenoh (eclipse-zenoh), measured with the gRPC parts' patterns.

Each peer's server runs in a process of its own on 127.0.0.1
(``python -m bench.peer_opcua_server``, ``python -m bench.peer_zenoh_server``),
started afresh for each of ``--rounds`` rounds and ended by its PID, like the
gRPC servers; this process drives it with the peer's own Python client:

* Get one at a time (p50, p99) and with 8 in flight (Gets/s), as parts (q)
  and (a);
* fan-out of one value to ``--subscribers`` subscribers, Sets as fast as
  they are answered (events/s), as part (c) one-by-one;
* Set to delivery at ``--paced-rate`` Sets a second (p50), as part (r).

Each pattern keeps its best round (highest rate, lowest paced p50). The
clients are benchmark-only dependencies (the ``bench`` extra); a peer whose
client cannot be imported is skipped with the reason printed, and the run
goes on.
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import Any

from bench.peer_measure import PeerRound, PeerSizes
from bench.peer_opcua import run_opcua
from bench.peer_zenoh import run_zenoh
from bench.servers import ServerProcess


@dataclass(frozen=True)
class Peer:
    """A system measured beside the gateway: what it needs, its server, its load."""

    name: str
    title: str
    #: The module its client and server import, and the distribution that provides it.
    module: str
    distribution: str
    #: The server's module (run with ``python -m``) and the load (they import the client only when run).
    server: str
    run: Callable[[ServerProcess, PeerSizes], Awaitable[PeerRound]]


PEERS = (
    Peer("opcua", "OPC UA (asyncua)", "asyncua", "asyncua", "bench.peer_opcua_server", run_opcua),
    Peer("zenoh", "Zenoh (Python binding)", "zenoh", "eclipse-zenoh", "bench.peer_zenoh_server", run_zenoh),
)
BY_NAME = {peer.name: peer for peer in PEERS}

#: How a pattern's best round is picked: its figure, and whether the highest or the lowest wins.
BEST: dict[str, tuple[Callable[[dict[str, Any]], float], bool]] = {
    "sequential": (lambda d: float(d["throughput_per_s"]), True),
    "unary": (lambda d: float(d["throughput_per_s"]), True),
    "listen": (lambda d: float(d["events_per_s"]), True),
    "paced": (lambda d: float(d["latency"]["p50_us"]), False),
}


def missing(peer: Peer) -> str | None:
    """Why ``peer`` cannot be measured here, or None when its client is installed."""
    try:
        importlib.import_module(peer.module)
    except ImportError as exc:
        return (
            f"{peer.distribution} cannot be imported ({exc}); it is a benchmark-only dependency: "
            "pip install -e '.[bench]'"
        )
    return None


def best_of(rounds: list[dict[str, Any]]) -> dict[str, Any]:
    """Each pattern's best round, every round's figure beside it (``rounds``)."""
    best: dict[str, Any] = {key: rounds[0][key] for key in ("system", "client")}
    best["rounds"] = {}
    for pattern, (figure, highest) in BEST.items():
        runs = [data[pattern] for data in rounds]
        best[pattern] = (max if highest else min)(runs, key=figure)
        best["rounds"][pattern] = [round(figure(run), 1) for run in runs]
    best["complete"] = all(best[pattern]["complete"] for pattern in BEST)
    return best


async def run_peer(peer: Peer, rounds: int, sizes: PeerSizes) -> dict[str, Any]:
    """``rounds`` rounds on fresh servers of ``peer``; ``{"skipped": why}`` without its client."""
    reason = missing(peer)
    if reason is not None:
        print(f" skipped: {reason}", end="", file=sys.stderr, flush=True)
        return {"skipped": reason}
    seen: list[dict[str, Any]] = []
    for _ in range(rounds):
        server = await ServerProcess.start(peer.name, [peer.server, "--listen", "127.0.0.1:0"])
        try:
            seen.append((await peer.run(server, sizes)).as_dict())
        except Exception as exc:
            raise RuntimeError(f"{exc}\n{server.log_tail}") from exc
        finally:
            await server.stop()
    return best_of(seen)
