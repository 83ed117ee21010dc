"""Drain and rebalance: who takes devices, how many move, and moves that hold calls instead of refusing them.

The decisions are plain functions (:mod:`gateway.cluster.moves`); the moves are checked on three
gateways' nodes sharing a store held in memory, with a real line-protocol device on a loopback port
(forwarding between gateways needs gateway processes: tests/integration/test_cluster_operations.py).
"""

from __future__ import annotations

import asyncio
import json
from collections.abc import AsyncIterator
from typing import Any

import pytest
from support.fake_backend import DictBackend
from support.memory_store import MemoryServer
from support.waiting import wait_until

from gateway.cluster import ClusterNode, SwitchingBackend
from gateway.cluster.moves import rebalance_quota, taking_loads
from gateway.cluster.records import GatewayRecord, read_gateway
from gateway.engine.router import Router
from services.apps.registry import Registry
from services.apps.registry.store import Kind
from services.device import DeviceServer
from services.kernel.errors import Code, PropertyError

LEASE = 1.0
DEVICES = 12


def test_a_gateway_hands_over_what_it_owns_beyond_the_mean_at_most_a_batch() -> None:
    # A newcomer with nothing: each of the two others hands over its share, never past the mean.
    assert rebalance_quota({"a": 50, "b": 50, "c": 0}, "a", movable=50, spread=2, batch=32) == 17
    assert rebalance_quota({"a": 50, "b": 50, "c": 0}, "a", movable=50, spread=2, batch=8) == 8
    assert rebalance_quota({"a": 100, "b": 0}, "a", movable=100, spread=2, batch=1000) == 50
    # Within the spread, the lightest, or nothing movable (devices that dialled in): nothing moves.
    assert rebalance_quota({"a": 5, "b": 3}, "a", movable=5, spread=2, batch=32) == 0
    assert rebalance_quota({"a": 0, "b": 50}, "a", movable=0, spread=2, batch=32) == 0
    assert rebalance_quota({"a": 50, "b": 0}, "a", movable=0, spread=2, batch=32) == 0
    assert rebalance_quota({"a": 50}, "a", movable=50, spread=2, batch=32) == 0


def test_rounds_of_rebalancing_end_within_the_spread() -> None:
    loads = {"a": 60, "b": 30, "c": 0}
    for _ in range(10):  # every gateway decides from the same loads; the lightest takes what moves
        quotas = {g: rebalance_quota(loads, g, movable=loads[g], spread=2, batch=16) for g in loads}
        if not any(quotas.values()):
            break
        for gateway, quota in quotas.items():
            loads[gateway] -= quota
            for _ in range(quota):
                lightest = min(loads, key=lambda g: (loads[g], g))
                loads[lightest] += 1
    assert max(loads.values()) - min(loads.values()) <= 2, loads
    assert sum(loads.values()) == 90


def test_a_drained_gateway_takes_nothing_unless_every_gateway_is_drained() -> None:
    assert taking_loads({"a": 3, "b": 1, "c": 0}, {"c"}) == {"a": 3, "b": 1}
    assert taking_loads({"a": 3, "b": 1}, {"a", "b"}) == {"a": 3, "b": 1}


def test_a_gateway_record_carries_the_view_and_reads_records_without_it() -> None:
    record = GatewayRecord("h:1", owned=3, version="0.1.0", draining=True, calls_per_s=12.5, listens=4)
    assert read_gateway(record.to_json()) == record
    # A record written by a gateway that knows fewer fields: the others are their defaults.
    old = read_gateway('{"address": "h:2", "http": "", "line": "", "owned": 7, "protocols": [1, 2]}')
    assert old == GatewayRecord("h:2", owned=7)
    # A field of the wrong type is its default, never a refused record.
    odd = read_gateway(
        '{"address": "h:3", "listens": "many", "draining": 1, "calls_per_s": 2, "protocols": [2]}'
    )
    assert odd is not None and odd.listens == 0 and not odd.draining and odd.calls_per_s == 2.0
    # Fields at their default are not written: the record stays as small as before.
    assert set(json.loads(GatewayRecord("h:4").to_json())) == {
        "address",
        "http",
        "line",
        "owned",
        "protocols",
    }


async def test_a_set_during_a_planned_move_waits_for_the_new_target_instead_of_failing() -> None:
    first = DictBackend({"x": "1"})
    second = DictBackend({"x": "1"})
    switching = SwitchingBackend("bot", "tcp://127.0.0.1:7001")
    await switching.switch(first, "owned here")
    await switching.switch(None, reason="bot is moving", hold=5.0)
    pending = asyncio.ensure_future(switching.set("x", "2"))
    await asyncio.sleep(0.05)
    assert not pending.done()  # held, not refused
    await switching.switch(second, "forwarded to gw-b")
    assert await pending == "2"
    assert second.values["x"] == "2" and first.values["x"] == "1"
    # Past the hold, a call is refused saying why.
    await switching.switch(None, reason="bot is moving", hold=0.05)
    with pytest.raises(PropertyError, match="bot is moving") as refused:
        await switching.get("x")
    assert refused.value.code is Code.UNAVAILABLE


async def test_a_switch_closes_the_old_target_only_once_its_calls_have_ended() -> None:
    release = asyncio.Event()

    class SlowBackend(DictBackend):
        async def set(self, path: str, value: Any, params: Any = None) -> Any:
            await release.wait()
            return await super().set(path, value)

    old = SlowBackend({"x": "1"})
    switching = SwitchingBackend("bot", "tcp://127.0.0.1:7001")
    await switching.switch(old, "owned here")
    under_way = asyncio.ensure_future(switching.set("x", "2"))
    await asyncio.sleep(0.01)
    switched = asyncio.ensure_future(switching.switch(None, reason="moving", hold=5.0))
    await asyncio.sleep(0.05)
    assert not old.closed and not switched.done()
    release.set()
    assert await under_way == "2"
    await switched
    assert old.closed


# -- three nodes on a store in memory --------------------------------------------------------


class Member:
    """One gateway: its router, registry and cluster node."""

    def __init__(self, gateway_id: str, router: Router, registry: Registry, node: ClusterNode) -> None:
        self.id = gateway_id
        self.router = router
        self.registry = registry
        self.node = node


async def _member(server: MemoryServer, gateway_id: str, **options: Any) -> Member:
    router = Router()
    store = server.store(gateway_id)
    await store.start()
    node = ClusterNode(store, router, lease=LEASE, **options)
    registry = Registry(directory=node.directory, period=0, register_timeout=3.0, store=store, restore=False)
    await registry.start()
    await node.start(registry, address=f"127.0.0.1:{50050 + len(server.stores)}")
    return Member(gateway_id, router, registry, node)


async def _stop(member: Member) -> None:
    await member.node.stop()
    await member.registry.stop()
    for name in member.router.names():
        await member.router.remove(name).aclose()


@pytest.fixture
async def device() -> AsyncIterator[str]:
    """One device that answers under any name, on a connection per registration."""
    server = DeviceServer(
        DictBackend({"temperature": "21.5"}, type="sensor"), name="many", max_connections=64
    )
    host, port = await server.serve_tcp("127.0.0.1", 0)
    yield f"tcp://{host}:{port}"
    await server.aclose()


def _owners(server: MemoryServer, names: list[str]) -> dict[str, int]:
    counts: dict[str, int] = {}
    for name in names:
        owner = server.value(Kind.OWNER, name) or ""
        counts[owner] = counts.get(owner, 0) + 1
    return counts


async def test_a_drained_gateway_hands_every_device_over_spread_by_load_and_takes_none(device: str) -> None:
    server = MemoryServer()
    members = [await _member(server, f"gw-{letter}") for letter in "abc"]
    a, b, c = members
    try:
        names = [f"dev{n:02d}" for n in range(DEVICES)]
        for name in names:
            await a.registry.register(name, device)
        await wait_until(lambda: all(name in c.router for name in names), what="c serves every device")

        await b.node.set_drain("gw-a", True)  # asked through another gateway
        await wait_until(
            lambda: _owners(server, names) == {"gw-b": DEVICES // 2, "gw-c": DEVICES // 2},
            what="gw-a's devices owned by gw-b and gw-c, half each",
        )
        assert a.node.draining and not a.node.owned
        await wait_until(lambda: a.node.last_move is not None, what="gw-a's move recorded")
        assert a.node.last_move is not None and a.node.last_move[0] == DEVICES
        members_seen: Any = a.node.status()["members"]
        status = {m["id"]: m for m in members_seen}
        assert status["gw-a"]["draining"] and status["gw-a"]["owned"] == 0

        # A drained gateway registers a new device but hands it over; nothing new is owned there.
        await a.registry.register("late", device)
        await wait_until(
            lambda: server.value(Kind.OWNER, "late") in ("gw-b", "gw-c"), what="late handed over"
        )

        # Undrained, and an admin asks for a rebalance: gw-a gets devices back, within the spread.
        await c.node.set_drain("gw-a", False)
        await wait_until(lambda: not a.node.draining, what="gw-a undrained")
        await c.node.ask_rebalance()
        everything = [*names, "late"]
        await wait_until(
            lambda: (
                max(_owners(server, everything).values()) - _owners(server, everything).get("gw-a", 0) <= 2
                and "" not in _owners(server, everything)
            ),
            what="the loads within the spread again",
        )
        for name in everything:  # each answers through its owner
            owner = next(m for m in members if m.id == server.value(Kind.OWNER, name))
            await wait_until(lambda o=owner, n=name: n in o.node.owned, what=f"{name} opened by its owner")
            assert await owner.router.lookup(name).get("temperature") == "21.5"  # connected before served
    finally:
        for member in members:
            await _stop(member)


async def test_draining_is_refused_for_an_unknown_gateway_or_when_nobody_would_take_the_devices(
    device: str,
) -> None:
    server = MemoryServer()
    members = [await _member(server, f"gw-{letter}") for letter in "ab"]
    a = members[0]
    try:
        with pytest.raises(PropertyError, match="no gateway 'gw-z'") as unknown:
            await a.node.set_drain("gw-z", True)
        assert unknown.value.code is Code.NOT_FOUND
        await a.node.set_drain("gw-a", True)
        with pytest.raises(PropertyError, match="no other gateway takes devices") as alone:
            await a.node.set_drain("gw-b", True)
        assert alone.value.code is Code.FAILED_PRECONDITION
    finally:
        for member in members:
            await _stop(member)


async def test_with_the_policy_on_a_gateway_that_joins_gets_devices_a_batch_at_a_time(device: str) -> None:
    server = MemoryServer()
    options = {"rebalance": True, "rebalance_spread": 1, "rebalance_batch": 4}
    a = await _member(server, "gw-a", **options)
    members = [a]
    try:
        names = [f"dev{n:02d}" for n in range(DEVICES)]
        for name in names:
            await a.registry.register(name, device)
        b = await _member(server, "gw-b", **options)
        members.append(b)
        await wait_until(lambda: _owners(server, names) == {"gw-a": 6, "gw-b": 6}, what="half moved to gw-b")
        moves = [w for w in a.node.store.writes if w[0] == "replace" and w[1] is Kind.OWNER]  # type: ignore[attr-defined]
        assert len(moves) == 6
        assert a.node.last_move is not None and a.node.last_move[0] <= 4  # a batch at a time
    finally:
        for member in members:
            await _stop(member)


async def test_a_device_not_let_go_in_a_move_is_served_again_by_its_owner(device: str) -> None:
    """A move whose owners key stayed this gateway's (its let-go did not happen) leaves the device
    open here again after the wait, not closed with every call told that it is moving."""
    server = MemoryServer()
    members = [await _member(server, f"gw-{letter}") for letter in "ab"]
    a = members[0]
    try:
        names = ["kept", "moved"]
        for name in names:
            await a.registry.register(name, device)
        await wait_until(lambda: all(name in a.node.owned for name in names), what="gw-a owns both")
        let_go = a.node._let_go

        async def keep_one(kind: Kind, name: str, expected: str) -> bool:
            return False if name == "kept" else await let_go(kind, name, expected)

        a.node._let_go = keep_one  # type: ignore[method-assign]
        await a.node._hand_over_locked(names, "rebalancing")
        assert server.value(Kind.OWNER, "kept") == "gw-a" and server.value(Kind.OWNER, "moved") == "gw-b"
        switching = a.router.lookup("kept")
        assert isinstance(switching, SwitchingBackend)
        await wait_until(lambda: switching.target is not None, what="kept open on gw-a again")
        assert await switching.get("temperature") == "21.5"
    finally:
        for member in members:
            await _stop(member)


async def test_a_gateway_that_stops_closes_each_device_link_before_its_owners_key_goes(device: str) -> None:
    """A link left open once another gateway owns the device would pass on its changes beside the
    new owner's; a Listen forwarded through the leaving gateway could then go back in value."""
    server = MemoryServer()
    members = [await _member(server, f"gw-{letter}") for letter in "ab"]
    a, b = members
    try:
        await a.registry.register("dev", device)
        await wait_until(lambda: "dev" in a.node.owned, what="gw-a owns dev")
        switching = a.router.lookup("dev")
        assert isinstance(switching, SwitchingBackend) and switching.target is not None
        link = switching.target
        closed: list[bool] = []
        close_link = link.aclose

        async def aclose() -> None:
            closed.append(True)
            await close_link()

        link.aclose = aclose  # type: ignore[method-assign]
        let_go = a.node._let_go
        seen_at_let_go: list[tuple[object, bool]] = []

        async def watched(kind: Kind, name: str, expected: str) -> bool:
            if kind is Kind.OWNER and name == "dev":
                seen_at_let_go.append((switching.target, bool(closed)))
            return await let_go(kind, name, expected)

        a.node._let_go = watched  # type: ignore[method-assign]
        await a.node.stop()
        assert seen_at_let_go == [(None, True)], "the link was closed before the owners key went"
        await wait_until(lambda: server.value(Kind.OWNER, "dev") == "gw-b", what="gw-b owns dev")
        await wait_until(lambda: "dev" in b.node.owned, what="gw-b serves dev")
        assert await b.router.lookup("dev").get("temperature") == "21.5"
    finally:
        for member in members:
            await _stop(member)
