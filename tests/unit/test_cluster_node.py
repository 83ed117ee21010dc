"""The cluster's decisions, one gateway's node at a time, on a store held in memory.

Each "gateway" here is what a cluster node works with: a router, a registry whose directory is
the node's, and a node; devices are real line-protocol devices on loopback TCP ports. Calls
between gateways (forwarding) need real gateway processes and are tested with real etcd in
``tests/integration/test_cluster.py``; here the forwarding entries are checked by where they
point.
"""

from __future__ import annotations

import asyncio
import json
from collections.abc import AsyncIterator
from dataclasses import dataclass
from typing import Any

import pytest
from support.fake_backend import DictBackend
from support.memory_store import MemoryServer, MemoryStore
from support.waiting import eventually, wait_until

from gateway.cluster import ClusterNode, SwitchingBackend
from gateway.engine.router import Router
from services.apps.registry import Registry
from services.apps.registry.store import Kind
from services.device import DeviceServer
from services.kernel.errors import Code, PropertyError

LEASE = 1.0


@dataclass
class Member:
    """One gateway of the test cluster: its router, registry and node."""

    id: str
    router: Router
    registry: Registry
    node: ClusterNode

    def target(self, name: str) -> str:
        backend = self.router.lookup(name)
        assert isinstance(backend, SwitchingBackend), backend
        return backend.target_label


async def _member(server: MemoryServer, gateway_id: str, **options: Any) -> Member:
    router = Router()
    store = server.store(gateway_id)
    await store.start()
    node = ClusterNode(store, router, lease=LEASE, **options)
    registry = Registry(directory=node.directory, period=0, register_timeout=3.0, store=store, restore=False)
    await registry.start()
    await node.start(registry, address=f"127.0.0.1:{50050 + len(server.stores)}", line="127.0.0.1:7100")
    return Member(gateway_id, router, registry, node)


@pytest.fixture
async def cluster() -> AsyncIterator[tuple[MemoryServer, list[Member]]]:
    server = MemoryServer()
    members = [await _member(server, f"gw-{letter}") for letter in "abc"]
    yield server, members
    for member in members:
        await member.node.stop()
        await member.registry.stop()
        for name in member.router.names():
            await member.router.remove(name).aclose()


async def _stop(member: Member) -> None:
    await member.node.stop()
    await member.registry.stop()
    for name in member.router.names():
        await member.router.remove(name).aclose()


@pytest.fixture
async def device() -> AsyncIterator[str]:
    server = DeviceServer(DictBackend({"temperature": "21.5"}, type="sensor"), name="thermo")
    host, port = await server.serve_tcp("127.0.0.1", 0)
    yield f"tcp://{host}:{port}"
    await server.aclose()


async def test_a_registration_on_one_gateway_is_served_by_every_gateway(
    cluster: tuple[MemoryServer, list[Member]], device: str
) -> None:
    server, (a, b, c) = cluster
    assert await a.registry.register("thermo", device) == device
    assert server.value(Kind.OWNER, "thermo") == "gw-a"
    assert json.loads(server.value(Kind.SERVICE, "thermo") or "{}")["url"] == device
    assert a.target("thermo") == "owned here"
    assert await a.router.lookup("thermo").get("temperature") == "21.5"
    for other in (b, c):
        await wait_until(lambda m=other: "thermo" in m.router, what=f"{other.id} serves thermo")
        assert other.target("thermo") == "forwarded to gateway gw-a at 127.0.0.1:50051"
        assert other.registry.services.children()["thermo"].url == device  # type: ignore[attr-defined]
    # The owner's state is every gateway's: it reports it, the others mirror it.
    await wait_until(lambda: server.value(Kind.STATE, "thermo") == "up", what="the owner reports up")
    for other in (b, c):
        await wait_until(lambda m=other: m.registry.state_of("thermo") == "up", what="the state mirrored")
    await wait_until(
        lambda: json.loads(server.value(Kind.GATEWAY, "gw-a") or "{}").get("owned") == 1,
        what="gw-a counts what it owns",
    )
    assert b.node.alternates() == ["127.0.0.1:7100", "127.0.0.1:7100"]  # gw-a's and gw-c's


async def test_a_name_taken_in_the_cluster_is_refused_on_another_gateway(
    cluster: tuple[MemoryServer, list[Member]], device: str
) -> None:
    _, (a, b, _c) = cluster
    await a.registry.register("thermo", device)
    await wait_until(lambda: "thermo" in b.router, what="b serves thermo")
    with pytest.raises(PropertyError) as taken:
        await b.registry.register("thermo", "tcp://127.0.0.1:9")
    assert taken.value.code is Code.ALREADY_EXISTS


async def test_unregistering_on_any_gateway_removes_it_everywhere(
    cluster: tuple[MemoryServer, list[Member]], device: str
) -> None:
    server, (a, b, c) = cluster
    await a.registry.register("thermo", device)
    await wait_until(lambda: "thermo" in b.router and "thermo" in c.router, what="everyone serves thermo")
    await b.registry.unregister("thermo")
    for member in (a, b, c):
        await wait_until(lambda m=member: "thermo" not in m.router, what=f"{member.id} dropped thermo")
        await wait_until(
            lambda m=member: "thermo" not in m.registry.services.children(),
            what=f"{member.id}'s registry forgot thermo",
        )
    for kind in (Kind.SERVICE, Kind.OWNER, Kind.STATE):
        await wait_until(lambda k=kind: server.value(k, "thermo") is None, what=f"{kind} key deleted")


async def test_a_dead_owners_registration_is_taken_over_by_the_least_loaded(
    cluster: tuple[MemoryServer, list[Member]], device: str
) -> None:
    server, (a, b, c) = cluster
    await a.registry.register("thermo", device)
    await wait_until(lambda: "thermo" in c.router, what="c serves thermo")
    server.kill("gw-a")
    # gw-b and gw-c own nothing; the tie goes to the smaller id.
    await wait_until(lambda: server.value(Kind.OWNER, "thermo") == "gw-b", what="gw-b takes thermo over")
    await wait_until(lambda: b.target("thermo") == "owned here", what="gw-b opens the device")
    value = await eventually(lambda: b.router.lookup("thermo").get("temperature"), retry_on=(PropertyError,))
    assert value == "21.5"
    await wait_until(
        lambda: c.target("thermo").startswith("forwarded to gateway gw-b"), what="gw-c forwards to gw-b"
    )
    await wait_until(lambda: server.value(Kind.STATE, "thermo") == "up", what="gw-b reports the state")
    assert b.registry.state_of("thermo") == "up"


async def test_without_the_store_registrations_are_refused_and_what_is_served_stays(
    cluster: tuple[MemoryServer, list[Member]], device: str
) -> None:
    server, (a, b, _c) = cluster
    await a.registry.register("thermo", device)
    await wait_until(lambda: "thermo" in b.router, what="b serves thermo")
    server.stop("connection refused")
    with pytest.raises(PropertyError) as refused:
        await b.registry.register("other", device)
    assert refused.value.code is Code.UNAVAILABLE
    assert refused.value.message.startswith("registering 'other': the registry is read-only: ")
    assert "connection refused" in refused.value.message
    assert await a.router.lookup("thermo").get("temperature") == "21.5"
    assert b.target("thermo").startswith("forwarded to gateway gw-a")


async def test_a_store_restarted_empty_gets_every_key_again(
    cluster: tuple[MemoryServer, list[Member]], device: str
) -> None:
    server, (a, b, _c) = cluster
    await a.registry.register("thermo", device)
    await wait_until(lambda: server.value(Kind.STATE, "thermo") == "up", what="the state written")
    server.stop()
    server.start(empty=True)
    await wait_until(lambda: server.value(Kind.OWNER, "thermo") == "gw-a", what="the owner written again")
    await wait_until(lambda: server.value(Kind.SERVICE, "thermo") is not None, what="the registration again")
    await wait_until(lambda: server.value(Kind.STATE, "thermo") == "up", what="the state written again")
    for gateway in ("gw-a", "gw-b", "gw-c"):
        await wait_until(lambda g=gateway: server.value(Kind.GATEWAY, g) is not None, what=f"{gateway} again")
    # Nobody dropped it meanwhile, nor took it over.
    assert a.target("thermo") == "owned here"
    assert b.target("thermo").startswith("forwarded to gateway gw-a")
    assert "thermo" in b.registry.services.children()


async def test_a_reconnect_keeps_the_view_the_watch_reported_and_reads_nothing_older(
    cluster: tuple[MemoryServer, list[Member]], device: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    server, (a, b, _c) = cluster
    await a.registry.register("thermo", device)
    await wait_until(lambda: "thermo" in b.router, what="b serves thermo")
    assert b.target("thermo").startswith("forwarded to gateway gw-a")
    # A read of the folders answered late is older than the watch: here it misses gw-a's record,
    # as one sent before gw-a wrote its key again and answered after the watch reported it.
    store = b.node.store
    assert isinstance(store, MemoryStore)
    fresh = store.read

    async def stale(kind: Kind) -> dict[str, str]:
        folder = await fresh(kind)
        return {name: value for name, value in folder.items() if name != "gw-a"}

    monkeypatch.setattr(store, "read", stale)
    server.stop()
    server.start()
    await wait_until(lambda: not b.node._resyncing, what="the reconnect handled")
    await asyncio.sleep(0.2)
    assert "gw-a" in b.node.view.gateways
    assert b.target("thermo").startswith("forwarded to gateway gw-a")


async def test_a_device_that_dialled_in_is_published_and_awaited_when_its_gateway_dies(
    cluster: tuple[MemoryServer, list[Member]],
) -> None:
    server, (a, b, c) = cluster
    a.router.add("probe", DictBackend({"x": "1"}, type="sensor", url="tcp-in://127.0.0.1:5555"))
    await wait_until(lambda: server.value(Kind.OWNER, "probe") == "gw-a", what="the device published")
    assert json.loads(server.value(Kind.SERVICE, "probe") or "{}") == {
        "url": "tcp-in://127.0.0.1:5555",
        "options": {"type": "sensor"},
    }
    await wait_until(lambda: "probe" in b.router, what="b serves probe")
    assert b.target("probe").startswith("forwarded to gateway gw-a")
    server.kill("gw-a")
    # Nobody takes it over (it dials in again itself): meanwhile every gateway waits for it under its
    # name, which reads UNAVAILABLE ("reconnecting"), never NOT_FOUND.
    await wait_until(lambda: c.node.awaits("probe"), what="the device awaited")
    assert server.value(Kind.OWNER, "probe") is None
    with pytest.raises(PropertyError, match="reconnecting") as refused:
        await b.router.lookup("probe").get("x")
    assert refused.value.code is Code.UNAVAILABLE
    assert b.registry.state_of("probe") == "connecting"
    # It dials in to gw-c: gw-c publishes it, and gw-b forwards to gw-c under the same entry.
    entry = b.router.lookup("probe")
    await c.node.seat("probe", DictBackend({"x": "2"}, type="sensor", url="tcp-in://127.0.0.1:5557"))
    assert server.value(Kind.OWNER, "probe") == "gw-c"
    await wait_until(
        lambda: b.target("probe").startswith("forwarded to gateway gw-c"), what="b forwards to c"
    )
    assert b.router.lookup("probe") is entry
    assert c.target("probe") == "dialled in here"
    assert await c.router.lookup("probe").get("x") == "2"


async def test_a_device_that_dialled_in_and_does_not_come_back_leaves_after_the_grace() -> None:
    server = MemoryServer()
    a, b = [await _member(server, gateway, reconnect_grace=0.5) for gateway in ("gw-a", "gw-b")]
    try:
        a.router.add("probe", DictBackend({"x": "1"}, type="sensor", url="tcp-in://127.0.0.1:5555"))
        await wait_until(lambda: "probe" in b.router, what="b serves probe")
        server.kill("gw-a")
        await wait_until(lambda: b.node.awaits("probe"), what="the device awaited")
        await wait_until(lambda: "probe" not in b.router, what="the device gone after the grace")
        assert b.registry.entry_of("probe") is None
    finally:
        await _stop(b)


async def test_a_device_dialling_in_under_a_name_taken_in_the_cluster_is_turned_away(
    cluster: tuple[MemoryServer, list[Member]], device: str
) -> None:
    server, (a, b, _c) = cluster
    await a.registry.register("thermo", device)
    await wait_until(lambda: server.value(Kind.STATE, "thermo") is not None, what="thermo known")
    impostor = DictBackend({"x": "1"}, url="tcp-in://127.0.0.1:5556")
    b.node.served.pop("thermo", None)  # as if b had not heard of thermo yet when the device greeted
    if "thermo" in b.router:
        b.router.remove("thermo")
    b.router.add("thermo", impostor)
    await wait_until(lambda: impostor.closed, what="the impostor hung up on")
    assert server.value(Kind.OWNER, "thermo") == "gw-a"


async def test_a_gateway_started_without_its_store_joins_when_the_store_is_back(device: str) -> None:
    server = MemoryServer()
    server.stop("connection refused")
    member = await _member(server, "gw-a")
    try:
        assert not member.node.joined
        with pytest.raises(PropertyError, match="read-only") as refused:
            await member.registry.register("thermo", device)
        assert refused.value.code is Code.UNAVAILABLE
        server.start()
        await wait_until(lambda: member.node.joined, what="joined once the store is back")
        assert server.value(Kind.GATEWAY, "gw-a") is not None
        await member.registry.register("thermo", device)
        assert server.value(Kind.OWNER, "thermo") == "gw-a"
    finally:
        await member.node.stop()
        await member.registry.stop()
        for name in member.router.names():
            await member.router.remove(name).aclose()


#: Devices of the bulk tests: 60 a survivor, in one bulk write each.
MANY = 120


@pytest.fixture
async def shared_device() -> AsyncIterator[str]:
    """One device that answers under any name, on enough connections for every registration."""
    server = DeviceServer(
        DictBackend({"temperature": "21.5"}, type="sensor"), name="many", max_connections=2 * MANY
    )
    host, port = await server.serve_tcp("127.0.0.1", 0)
    yield f"tcp://{host}:{port}"
    await server.aclose()


async def test_a_dead_gateways_devices_are_claimed_in_bulk_and_opened_side_by_side(
    shared_device: str,
) -> None:
    server = MemoryServer()
    members = [await _member(server, f"gw-{letter}", max_opening=8) for letter in "abc"]
    a, b, c = members
    try:
        names = [f"dev{n:03d}" for n in range(MANY)]
        for name in names:
            await a.registry.register(name, shared_device)
        await wait_until(lambda: all(name in c.router for name in names), what="c serves every device")
        single_creates = {m.id: len([w for w in m.node.store.writes if w[0] == "create"]) for m in (b, c)}
        peak = {"b": 0, "c": 0}
        sampling = True

        async def sample() -> None:  # how many devices each survivor connects at once
            while sampling:
                peak["b"] = max(peak["b"], b.node.connecting)
                peak["c"] = max(peak["c"], c.node.connecting)
                await asyncio.sleep(0)

        sampler = asyncio.ensure_future(sample())
        server.kill("gw-a")
        await wait_until(
            lambda: all(server.value(Kind.OWNER, name) in ("gw-b", "gw-c") for name in names),
            what="every device owned again",
        )
        for member in (b, c):
            await wait_until(
                lambda m=member: all(
                    m.target(n) == "owned here" for n in names if m.node.owners()[n] == m.id
                ),
                what=f"{member.id} opened what it took over",
            )
        sampling = False
        await sampler
        owners = [server.value(Kind.OWNER, name) for name in names]
        assert owners.count("gw-b") == owners.count("gw-c") == MANY // 2  # spread evenly
        for member in (b, c):
            store = member.node.store
            assert isinstance(store, MemoryStore)
            claims = [call for call in store.bulk_calls if call[:2] == ("create_many", Kind.OWNER)]
            # One bulk claim of its own half (rank 0), maybe one of what the other left (rank 1).
            assert claims and claims[0][2] == MANY // 2, store.bulk_calls
            creates = [w for w in store.writes if w[0] == "create"]
            assert len(creates) - single_creates[member.id] == MANY // 2  # the claims, nothing more
        # Opened side by side, never more than its places at once.
        assert 1 < peak["b"] <= 8 and 1 < peak["c"] <= 8, peak
        for name in names[:6]:  # each through its new owner (forwarding needs gateway processes)
            owner = b if server.value(Kind.OWNER, name) == "gw-b" else c
            assert await owner.router.lookup(name).get("temperature") == "21.5"
    finally:
        for member in (b, c):
            await _stop(member)


async def test_after_a_reconnect_only_what_the_store_lost_is_written_again(shared_device: str) -> None:
    server = MemoryServer()
    a = await _member(server, "gw-a")
    try:
        names = [f"dev{n:03d}" for n in range(MANY)]
        for name in names:
            await a.registry.register(name, shared_device)
        await wait_until(
            lambda: all(server.value(Kind.STATE, name) == "up" for name in names), what="every state written"
        )
        store = a.node.store
        assert isinstance(store, MemoryStore)
        keys = (Kind.OWNER, Kind.SERVICE, Kind.STATE, Kind.GATEWAY)

        # The store went away and came back with its data and this gateway's lease: nothing to write.
        before, calls = len(store.writes), len(store.bulk_calls)
        server.stop()
        server.start()
        await wait_until(lambda: not a.node._resyncing, what="the reconnect handled")
        await asyncio.sleep(0.1)
        assert _keys_written_since(store, before, keys) == [] and store.bulk_calls[calls:] == []

        # The lease ended while it was away: every leased key again, in bulk; the registrations stayed.
        server.stop()
        server.end_lease("gw-a")
        before, calls = len(store.writes), len(store.bulk_calls)
        server.start()
        await wait_until(
            lambda: all(server.value(Kind.STATE, name) == "up" for name in names), what="the states again"
        )
        assert {server.value(Kind.OWNER, name) for name in names} == {"gw-a"}
        assert store.bulk_calls[calls:] == [
            ("create_many", Kind.OWNER, MANY),
            ("put_many", Kind.STATE, MANY),
        ]
        written = _keys_written_since(store, before, keys)
        assert ("put", Kind.GATEWAY, "gw-a") in written
        assert not [w for w in written if w[1] is Kind.SERVICE]

        # Restarted empty: the registrations too.
        before, calls = len(store.writes), len(store.bulk_calls)
        server.stop()
        server.start(empty=True)
        await wait_until(
            lambda: all(server.value(Kind.SERVICE, name) is not None for name in names),
            what="the registrations again",
        )
        await wait_until(
            lambda: all(server.value(Kind.STATE, name) == "up" for name in names), what="the states again"
        )
        assert store.bulk_calls[calls:] == [
            ("create_many", Kind.OWNER, MANY),
            ("create_many", Kind.SERVICE, MANY),
            ("put_many", Kind.STATE, MANY),
        ]
        assert a.target(names[0]) == "owned here"
    finally:
        await _stop(a)


def _keys_written_since(
    store: MemoryStore, start: int, kinds: tuple[Kind, ...]
) -> list[tuple[str, Kind, str]]:
    return [write for write in store.writes[start:] if write[1] in kinds]
