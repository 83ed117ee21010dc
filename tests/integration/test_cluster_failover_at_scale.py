"""A gateway owning a few hundred devices dies: the survivors claim them in bulk and every one answers again.

Real etcd (``tests/support/etcd.py``), three real gateway processes sharing it, and 300 line-protocol
devices, each on its own TCP port, served by one device-farm process (``bench.device_farm``). Every
device is registered on ``gw-a``; ``gw-a`` is SIGKILLed; the owners keys in etcd must all name a
survivor again, spread over both, and every device must answer a Get through a survivor.
"""

from __future__ import annotations

import asyncio
import re
import time
from collections.abc import AsyncIterator, Awaitable, Callable
from pathlib import Path

import pytest
from support.cluster import cluster_config, stored
from support.etcd import EtcdServer
from support.gateway_process import GatewayProcess, start_gateway
from support.waiting import eventually

from bench.register import start_farms
from bench.servers import ServerProcess
from clients import AsyncClient
from clients.errors import PropertyServiceError
from services.apps.registry.store import Kind

pytestmark = pytest.mark.timeout(240)

#: Seconds of each gateway's lease (etcd's floor is about 1.5 s).
LEASE = 2.0
DEVICES = 300
IDS = ("gw-a", "gw-b", "gw-c")
#: Calls in flight while registering and while asking the devices again.
IN_FLIGHT = 32


@pytest.fixture
async def devices(tmp_path: Path) -> AsyncIterator[dict[str, int]]:
    """Name → TCP port of DEVICES simulated robots, in one device-farm process."""
    farms: list[ServerProcess] = []
    try:
        farms, ports = await start_farms(DEVICES, tmp_path)
        yield ports
    finally:
        for farm in farms:
            await farm.stop()


async def _each(names: list[str], call: Callable[[str], Awaitable[None]]) -> None:
    """``await call(name)`` for every name, IN_FLIGHT at once."""
    places = asyncio.Semaphore(IN_FLIGHT)

    async def one(name: str) -> None:
        async with places:
            await call(name)

    await asyncio.gather(*(one(name) for name in names))


async def test_a_dead_gateways_few_hundred_devices_are_owned_again_and_answer_through_a_survivor(
    etcd_server: Callable[..., EtcdServer], tmp_path: Path, devices: dict[str, int]
) -> None:
    etcd = etcd_server()
    gateways: dict[str, GatewayProcess] = {}
    clients: dict[str, AsyncClient] = {}
    try:
        for gateway in IDS:
            gateways[gateway] = start_gateway(
                tmp_path,
                cluster_config(
                    etcd,
                    gateway,
                    lease=LEASE,
                    quick_checks=False,
                    registry=f"max_registrations = {2 * DEVICES}",
                ),
            )
            clients[gateway] = AsyncClient(gateways[gateway].address)
        names = sorted(devices)

        async def register(name: str) -> None:
            await clients["gw-a"].set("registry", f"services.{name}", f"tcp://127.0.0.1:{devices[name]}")

        await _each(names, register)
        await eventually(
            lambda: stored(etcd, Kind.OWNER),
            lambda owners: owners == dict.fromkeys(names, "gw-a"),
            within=30.0,
        )
        for gateway in ("gw-b", "gw-c"):
            await eventually(
                lambda g=gateway: clients[g].get_names("registry", "services"),
                lambda listed: set(names) <= set(listed),
                within=30.0,
                what=f"{gateway} lists every device",
            )

        killed = time.monotonic()
        gateways["gw-a"].proc.kill()  # SIGKILL: its lease just runs out
        owners = await eventually(
            lambda: stored(etcd, Kind.OWNER),
            lambda owners: set(owners) == set(names) and set(owners.values()) <= {"gw-b", "gw-c"},
            within=LEASE + 30.0,
            every=0.1,
            what="every device owned by a survivor",
        )
        owned_again = time.monotonic() - killed
        # Spread over the survivors, half each (the plan deals them out one at a time).
        counts = [list(owners.values()).count(gateway) for gateway in ("gw-b", "gw-c")]
        assert counts == [DEVICES // 2, DEVICES // 2], counts

        async def answers(name: str) -> None:
            location = await eventually(
                lambda: clients["gw-b"].get_vector(name, "location"),
                within=60.0,
                retry_on=(PropertyServiceError,),
                what=f"{name} answers through gw-b",
            )
            assert len(location) == 6

        await _each(names, answers)
        answered = time.monotonic() - killed
        print(
            f"{DEVICES} devices of a SIGKILLed gateway owned again {owned_again:.2f} s after, all "
            f"answering through a survivor {answered:.2f} s after (lease {LEASE:g} s)"
        )
        # Each survivor claimed what the plan gave it in bulk: few claims, each of many devices.
        claims = [
            int(n)
            for g in ("gw-b", "gw-c")
            for n in re.findall(r"taking (\d+) of \d+ orphans over", gateways[g].output)
        ]
        assert sum(claims) >= DEVICES and max(claims) >= DEVICES // 4, claims
    finally:
        for client in clients.values():
            await client.close()
        for gw in gateways.values():
            gw.stop()
