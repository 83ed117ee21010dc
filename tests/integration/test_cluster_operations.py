"""Operating a cluster of real gateways on real etcd: the cluster view, a drain, a rebalance, an undrain.

Two gateway processes (``gw-a``, ``gw-b``) share etcd (``tests/support/etcd.py``), ``gw-b`` (and
``gw-c`` later) with the rebalance policy on; ``a-counter`` (a line-protocol device process) and
``DEVICES`` - 1 simulated robots (one device-farm process, ``bench.device_farm``) are registered on
``gw-a``. ``gw-a`` runs with the policy off, so that what it owns before the drain is what was
registered through it: with the policy on, ``gw-b``'s joining has ``gw-a`` hand half of its devices
over half a second later, which on a loaded machine is the very moment they are registered. The
policy is the giving gateway's: the others still hand devices over to ``gw-a`` when it is undrained.
A client Sets ``a-counter.rate_hz`` to a rising value ten times a second through ``gw-b``, and a
Listen on it is open through ``gw-a`` and through ``gw-b``. Then:

1. an admin drains ``gw-a`` by a Set of ``cluster.drain`` on ``gw-b``: every device is owned by
   ``gw-b``, ``gw-a`` keeps serving (it forwards), and its record says it is draining;
2. ``gw-c`` joins: ``gw-b`` hands devices over to it, a batch at a time, until they are within the
   spread (``a-counter`` among the first: names are handed over in order);
3. ``gw-a`` is undrained: the others hand devices over to it, within the spread again.

Throughout, no Set is refused and none acknowledged is lost, and each Listen hears at most one
``gap`` per move of the counter. The test prints the time each phase took per 100 devices moved
(docs/performance.md, "Drain and rebalance"); ``PS_MOVE_DEVICES=100`` runs it at the size measured
there (the default is smaller, for CI). Without the ``etcd`` command the test skips.
"""

from __future__ import annotations

import asyncio
import json
import os
import time
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass, field
from pathlib import Path

import pytest
from line_device_support import tcp_device
from support.cluster import cluster_config, stored
from support.etcd import EtcdServer
from support.gateway_process import GatewayProcess, start_gateway
from support.psctl import psctl
from support.waiting import eventually

from bench.register import start_farms
from bench.servers import ServerProcess
from clients import AsyncClient
from clients.aio import Event
from clients.errors import PropertyServiceError, Unavailable
from services.apps.registry.store import Kind

pytestmark = [pytest.mark.slow, pytest.mark.timeout(240)]

LEASE = 2.0
#: Devices in the cluster, the counter included (``PS_MOVE_DEVICES`` to measure at another size).
DEVICES = int(os.environ.get("PS_MOVE_DEVICES", "30"))
BATCH = 16
SPREAD = 2
COUNTER = "a-counter"
SET_EVERY = 0.1


def _config(etcd: EtcdServer, gateway: str) -> str:
    policy = "false" if gateway == "gw-a" else "true"  # see the module docstring
    return cluster_config(
        etcd,
        gateway,
        lease=LEASE,
        registry=f"rebalance = {policy}\nrebalance_spread = {SPREAD}\nrebalance_batch = {BATCH}\n"
        f"max_registrations = {4 * DEVICES}",
    )


@dataclass
class Load:
    """The client at work: Sets through one gateway, a Listen through each of two."""

    acked: list[float] = field(default_factory=list)
    failures: list[str] = field(default_factory=list)
    heard: dict[str, list[Event]] = field(default_factory=dict)
    step: int = 0
    #: Set when the client is to stop after the Set in flight (cancelling it mid-Set would leave a
    #: value applied whose acknowledgement nobody heard).
    stopping: bool = False


async def _set_forever(client: AsyncClient, load: Load) -> None:
    while not load.stopping:
        load.step += 1
        value = round(0.1 + load.step / 1000, 3)
        try:
            await client.set(COUNTER, "rate_hz", str(value))
        except PropertyServiceError as exc:
            load.failures.append(f"{type(exc).__name__}: {exc}")
        else:
            load.acked.append(value)
        await asyncio.sleep(SET_EVERY)


async def _listen_forever(client: AsyncClient, heard: list[Event]) -> None:
    async for event in client.listen(COUNTER, "rate_hz"):
        heard.append(event)


def _counts(owners: dict[str, str]) -> dict[str, int]:
    counts: dict[str, int] = {}
    for owner in owners.values():
        counts[owner] = counts.get(owner, 0) + 1
    return counts


@pytest.fixture
async def robots(tmp_path: Path) -> AsyncIterator[dict[str, int]]:
    farms: list[ServerProcess] = []
    try:
        farms, ports = await start_farms(DEVICES - 1, tmp_path)
        yield ports
    finally:
        for farm in farms:
            await farm.stop()


async def test_a_drain_a_join_and_an_undrain_move_devices_with_no_set_lost_and_one_gap_a_move(
    etcd_server: Callable[..., EtcdServer], tmp_path: Path, robots: dict[str, int]
) -> None:
    etcd = etcd_server()
    gateways: dict[str, GatewayProcess] = {}
    clients: dict[str, AsyncClient] = {}
    tasks: list[asyncio.Task[None]] = []
    load = Load()
    try:
        for gateway in ("gw-a", "gw-b"):
            gateways[gateway] = start_gateway(tmp_path, _config(etcd, gateway))
            clients[gateway] = AsyncClient(gateways[gateway].address, timeout=5.0)
        with tcp_device("--service", "sim-sensor", "--name", COUNTER, "--option", "rate_hz=0.1") as address:
            a = clients["gw-a"]
            await a.set("registry", f"services.{COUNTER}", f"tcp://{address[0]}:{address[1]}")
            places = asyncio.Semaphore(16)

            async def register(name: str) -> None:
                # A farm's device that has not greeted within the registration window (a busy
                # machine) leaves nothing registered: it is asked again.
                async with places:
                    await eventually(
                        lambda: a.set("registry", f"services.{name}", f"tcp://127.0.0.1:{robots[name]}"),
                        retry_on=(Unavailable,),
                        within=30.0,
                        what=f"{name} registered",
                    )

            await asyncio.gather(*(register(name) for name in robots))
            names = sorted([COUNTER, *robots])
            try:
                await eventually(
                    lambda: stored(etcd, Kind.OWNER),
                    lambda o: o == dict.fromkeys(names, "gw-a"),
                    within=30.0,
                    what="every device registered through gw-a owned by gw-a",
                )
            except AssertionError as exc:
                raise AssertionError(f"{exc}\n{_cluster_log(gateways)}") from None
            await eventually(
                lambda: clients["gw-b"].get("registry", f"services.{COUNTER}.state"),
                lambda s: s == "up",
                retry_on=(PropertyServiceError,),
            )

            # The cluster view, through either gateway: both members, what each owns, the policy.
            view = json.loads(await clients["gw-b"].get("registry", "cluster"))
            members = {m["id"]: m for m in view["members"]}
            assert set(members) == {"gw-a", "gw-b"}
            assert view["rebalance"] == {"policy": True, "spread": SPREAD, "batch": BATCH}
            assert members["gw-a"]["owned"] == DEVICES and members["gw-b"]["owned"] == 0
            assert members["gw-a"]["health"] == "ok" and members["gw-a"]["version"]
            assert await a.get("registry", f"services.{COUNTER}.owner") == "gw-a"

            # The client at work: Sets through gw-b, a Listen through each gateway.
            load.heard = {"gw-a": [], "gw-b": []}
            tasks.append(asyncio.create_task(_set_forever(clients["gw-b"], load)))
            for gateway, heard in load.heard.items():
                tasks.append(asyncio.create_task(_listen_forever(clients[gateway], heard)))
            await eventually(
                lambda: _heard_enough(load), bool, within=15.0, what="Sets acknowledged and heard"
            )
            rows: list[str] = []
            moves = 0

            # 1. Drain gw-a, asked through gw-b: everything goes to gw-b; gw-a goes on forwarding.
            began = time.monotonic()
            await clients["gw-b"].set("registry", "cluster.drain", "gw-a")
            await eventually(
                lambda: stored(etcd, Kind.OWNER),
                lambda o: _counts(o) == {"gw-b": DEVICES},
                within=60.0,
                every=0.1,
            )
            owned_again = time.monotonic() - began
            await _all_answer(a, sorted(robots))
            rows.append(_row("drain gw-a", DEVICES, owned_again, time.monotonic() - began))
            moves += 1
            drained = await eventually(
                lambda: a.get("registry", "cluster.members.gw-a"),
                lambda text: json.loads(text)["draining"] and json.loads(text)["owned"] == 0,
                what="gw-a's record says it is draining and owns nothing",
            )
            assert json.loads(drained)["drained_by"] == "anonymous"
            # psctl shows it as a user reads it: gw-a draining, gw-b owning every device.
            shown = await asyncio.to_thread(psctl, gateways["gw-a"].address, "cluster", "--devices")
            assert shown.returncode == 0, shown.stderr
            print("\n" + shown.stdout)
            lines = [line.split() for line in shown.stdout.splitlines()]
            table = {cells[0]: cells for cells in lines if len(cells) == 9 and cells[0].startswith("gw-")}
            assert table["gw-a"][4:6] == ["draining", "0"], shown.stdout
            assert table["gw-b"][4:6] == ["serving", str(DEVICES)], shown.stdout
            assert [cells[:2] for cells in lines if cells and cells[0] == COUNTER] == [[COUNTER, "gw-b"]]
            assert await a.get_number("a-counter", "rate_hz") > 0  # forwarded by the drained gateway

            # 2. gw-c joins: gw-b hands devices over until the loads are within the spread.
            gateways["gw-c"] = start_gateway(tmp_path, _config(etcd, "gw-c"))
            began = time.monotonic()  # from the moment gw-c serves (it has joined)
            clients["gw-c"] = AsyncClient(gateways["gw-c"].address, timeout=5.0)
            owners = await eventually(
                lambda: stored(etcd, Kind.OWNER),
                lambda o: (
                    len(o) == DEVICES and abs(_counts(o).get("gw-b", 0) - _counts(o).get("gw-c", 0)) <= SPREAD
                ),
                within=60.0,
                every=0.1,
                what="gw-b and gw-c within the spread",
            )
            owned_again = time.monotonic() - began
            await _all_answer(clients["gw-c"], sorted(robots))
            rows.append(_row("gw-c joins", _counts(owners)["gw-c"], owned_again, time.monotonic() - began))
            assert "gw-a" not in _counts(owners)  # drained: it takes nothing
            moves += owners[COUNTER] != "gw-b"

            # 3. Undrain gw-a: the others hand devices over to it, within the spread.
            before = owners
            began = time.monotonic()
            await clients["gw-c"].set("registry", "cluster.undrain", "gw-a")
            owners = await eventually(
                lambda: stored(etcd, Kind.OWNER),
                lambda o: (
                    len(o) == DEVICES
                    and len(_counts(o)) == 3
                    and max(_counts(o).values()) - min(_counts(o).values()) <= SPREAD
                ),
                within=60.0,
                every=0.1,
                what="three gateways within the spread",
            )
            owned_again = time.monotonic() - began
            await _all_answer(a, sorted(robots))
            rows.append(_row("undrain gw-a", _counts(owners)["gw-a"], owned_again, time.monotonic() - began))
            moves += owners[COUNTER] != before[COUNTER]

            await asyncio.sleep(1.0)  # a few more Sets after the last move
            load.stopping = True
            await tasks[0]
            assert not load.failures, load.failures
            last = load.acked[-1]
            for gateway, heard in load.heard.items():
                await eventually(
                    lambda h=heard: _last_value(h),
                    lambda v: v == last,
                    what=f"the Listen through {gateway} hears {last}",
                )
            assert await clients["gw-c"].get_number(COUNTER, "rate_hz") == last

            gaps = {gateway: sum(1 for e in heard if e.gap) for gateway, heard in load.heard.items()}
            print(
                "\n"
                + "; ".join(rows)
                + f"; {len(load.acked)} Sets acknowledged, {len(load.failures)} refused; the counter moved "
                f"{moves} times; gaps heard: {gaps}"
            )
            assert not load.failures, load.failures
            for gateway, heard in load.heard.items():
                assert not [e for e in heard if e.removed], f"{gateway}: removed"
                values = [float(e.value) for e in heard]
                assert values == sorted(values), f"the Listen through {gateway} went back"
                assert gaps[gateway] <= moves, f"{gateway}: {gaps[gateway]} gaps for {moves} moves"
    finally:
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        for client in clients.values():
            await client.close()
        for gw in gateways.values():
            gw.stop()


async def _heard_enough(load: Load) -> bool:
    if len(load.acked) < 3:
        return False
    first = load.acked[0]
    return all(any(float(e.value) > first for e in heard) for heard in load.heard.values())


async def _last_value(heard: list[Event]) -> float | None:
    return float(heard[-1].value) if heard else None


async def _all_answer(client: AsyncClient, names: list[str]) -> None:
    """Every robot answers a Get through ``client``'s gateway (16 at a time)."""
    places = asyncio.Semaphore(16)

    async def answers(name: str) -> None:
        async with places:
            location = await eventually(
                lambda: client.get_vector(name, "location"),
                within=30.0,
                retry_on=(PropertyServiceError,),
                what=f"{name} answers",
            )
            assert len(location) == 6

    await asyncio.gather(*(answers(name) for name in names))


def _cluster_log(gateways: dict[str, GatewayProcess]) -> str:
    """What each gateway logged about the cluster (its lease, its takeovers), to explain a failure."""
    return "\n".join(
        f"{gateway}: {line}"
        for gateway, gw in gateways.items()
        for line in gw.output.splitlines()
        if "cluster" in line or "lease" in line
    )


def _row(what: str, moved: int, owned: float, answering: float) -> str:
    per_100 = owned / moved * 100 if moved else 0.0
    return (
        f"{what}: {moved} devices owned elsewhere in {owned:.2f} s ({per_100:.2f} s per 100), "
        f"all answering {answering:.2f} s after"
    )
