"""Listing a big registry: the ``services`` value at once, and ``service_names`` a page at a time.

Run ``python -m bench.registry_pages`` (``--services 2000 10000``, ``--rounds``). A gateway in
this process (gateway.testing) serves N in-process services; over its unix socket the figures
are, per size, the median of the rounds:

* **value**: one Get of the registry's ``services`` (the whole list as one value; the SDK
  refuses it past 64 KiB);
* **pages**: every name read through ``service_names``, 1,000 a page (the SDK's
  ``service_pages``);
* **sdk**: ``AsyncClient.services()``, as a user calls it: the value when it fits, the pages
  otherwise (the value read first and refused);
* **http**: ``GET /api/v1/services?limit=1000`` page after page, each with its columns.
"""

from __future__ import annotations

import argparse
import asyncio
import statistics
import time
from collections.abc import Awaitable, Callable

import aiohttp

from clients import AsyncClient
from gateway.config import Config, HttpSection
from gateway.testing import running_gateway
from services.kernel.core import Resource


class Idle(Resource):
    """A service with one property, standing in for a device."""

    resource_type = "sensor"
    a: int = 1


async def _timed(rounds: int, run: Callable[[], Awaitable[object]]) -> float:
    spent = []
    for _ in range(rounds):
        started = time.perf_counter()
        await run()
        spent.append(time.perf_counter() - started)
    return statistics.median(spent)


async def measure(size: int, rounds: int) -> dict[str, float]:
    """Seconds each way of listing ``size`` services takes (the median of ``rounds``)."""
    backends: dict[str, Resource] = {f"device{i:05d}": Idle() for i in range(size)}
    config = Config(http=HttpSection(listen="127.0.0.1:0"))
    async with running_gateway(backends, config=config) as gateway:
        assert gateway.http is not None
        url = f"{gateway.http.url}api/v1/services"
        async with AsyncClient(gateway.address, timeout=60.0) as client, aiohttp.ClientSession() as http:

            async def pages() -> None:
                async for _ in client.service_pages():
                    pass

            async def http_pages() -> None:
                after: str | None = ""
                while after is not None:
                    async with http.get(url, params={"limit": "1000", "after": after}) as reply:
                        after = (await reply.json())["next"]

            return {
                "value": await _timed(rounds, lambda: client.get("registry", "services")),
                "pages": await _timed(rounds, pages),
                "sdk": await _timed(rounds, client.services),
                "http": await _timed(rounds, http_pages),
            }


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--services", type=int, nargs="+", default=[2000, 10000])
    parser.add_argument("--rounds", type=int, default=5)
    args = parser.parse_args()
    print(f"{'services':>9} {'value':>9} {'pages':>9} {'sdk':>9} {'http':>9}   (ms, median of {args.rounds})")
    for size in args.services:
        figures = asyncio.run(measure(size, args.rounds))
        shown = " ".join(f"{figures[k] * 1000:9.1f}" for k in ("value", "pages", "sdk", "http"))
        print(f"{size:>9} {shown}")


if __name__ == "__main__":
    main()
