"""Licences: what the check every Set passes costs, and unary Set rates with licences held.

Two figures:

* ``check_set`` in-process: the time of one :meth:`Licences.check_set` for a
  service with no licence, and for one whose licence (held by the caller) is
  found, with 0, 1,000 and ``max_licences`` (1,024) licences held on other
  services (the licences are indexed by service, so the count should not
  matter).
* Sets on a Session through a real gateway in this process (``gateway.testing``,
  a unix socket): ``calls`` Sets of a plain property of an in-process service,
  one at a time, with no licence held; then with 1,000 licences held on other
  services and one on the service itself held by the caller (anonymous, so on
  its Session), on that service and on a free one, alternately. Best of
  ``rounds``; a fifth of ``calls`` goes first as a warm-up.

Run: ``python -m bench.licences`` (prints JSON).
"""

from __future__ import annotations

import asyncio
import json
import time
from typing import Annotated, Any

from gateway.testing import serve
from services.apps.registry import Licences, Registry
from services.kernel.backend import BackendInfo
from services.kernel.core import Prop, Resource


class Dial(Resource):
    """A plain writable value."""

    level: Annotated[float, Prop()] = 0.0


def _per_call_us(fn: Any, rounds: int) -> float:
    start = time.perf_counter()
    for _ in range(rounds):
        fn()
    return (time.perf_counter() - start) / rounds * 1e6


async def check_costs(rounds: int = 200_000) -> dict[str, float]:
    out: dict[str, float] = {}
    for held in (0, 1_000, 1_024):
        registry = Registry(max_licences=1_024)
        registry.add("dial", BackendInfo(type="dial", url="tcp://dial:1"))
        for i in range(held):
            registry.add(f"s{i}", BackendInfo(type="robot", url=f"tcp://s{i}:1"))
            await registry.licensing.grant(f"s{i}", f"h{i}", 600)
        licences = registry.licensing

        def check(licences: Licences = licences) -> None:
            licences.check_set("dial", "level", "me")

        out[f"free service, {held} licences held (us)"] = round(_per_call_us(check, rounds), 3)
        if held:
            await registry.licensing.release(registry.licensing.held()[0].id)
        await registry.licensing.grant("dial", "me", 600)
        out[f"own licence found, {held} licences held (us)"] = round(_per_call_us(check, rounds), 3)
        registry.licensing.close()
    return out


async def set_rates(calls: int = 3_000, rounds: int = 3) -> dict[str, float]:
    """Best of ``rounds`` alternating runs, so that both cases see the same load on the machine."""
    services: dict[str, Any] = {"dial": Dial(), "free": Dial()}
    services.update({f"s{i}": Dial() for i in range(1_000)})
    async with serve(services) as client, client.session() as session:
        assert await client.get("registry", "licences") == "()"

        async def rate(service: str) -> float:
            start = time.perf_counter()
            for i in range(calls):
                await session.set(service, "level", str(i % 100))
            return calls / (time.perf_counter() - start)

        for i in range(calls // 5):  # warm-up, not timed
            await session.set("dial", "level", str(i % 100))
        best_before = max([await rate("dial") for _ in range(rounds)])
        for i in range(1_000):
            await session.set("registry", "acquire", "", service=f"s{i}", duration="600")
        await session.set("registry", "acquire", "", service="dial", duration="600")
        free: list[float] = []
        own: list[float] = []
        for _ in range(rounds):
            free.append(await rate("free"))
            own.append(await rate("dial"))
        return {
            "Session Sets/s, no licence held at all": round(best_before),
            "Session Sets/s, 1,001 held, none on this service": round(max(free)),
            "Session Sets/s, 1,001 held, one on this service by the caller": round(max(own)),
        }


async def main() -> None:
    print(json.dumps({"check_set": await check_costs(), "sets": await set_rates()}, indent=2))


if __name__ == "__main__":
    asyncio.run(main())
