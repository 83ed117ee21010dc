"""The shared registry store on a real etcd server: keys, leases, compare-and-set, the watch,
etcd going away and coming back (even empty), TLS."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Callable
from typing import Any

import pytest
from support.certs import CertificateFiles, certificates
from support.etcd import EtcdServer
from support.waiting import wait_until

from gateway.stores import EtcdStore, EtcdTls, parse_store_url
from gateway.stores.etcd import START_WAIT
from services.apps.registry.store import Change, Kind, RegistryStore, SharedStore
from services.kernel.errors import InvalidArgument, Unavailable

__all__ = ["certificates"]

pytestmark = pytest.mark.slow

#: The lease the tests run with: etcd's shortest (it raises a shorter one to 2 s), so that a dead
#: gateway's keys go quickly.
LEASE = 2.0
#: etcd checks for expired leases every 500 ms and revokes one through its raft log: a key may
#: outlive its lease by that much, and a loaded machine adds to it.
EXPIRY_SLACK = 3.0


@pytest.fixture
async def stores() -> AsyncIterator[Callable[..., Any]]:
    """Open started stores on an etcd server (``store(etcd, "gw-a")``); all closed at the end."""
    opened: list[EtcdStore] = []

    async def open_store(etcd: EtcdServer, gateway_id: str, **options: Any) -> EtcdStore:
        store = EtcdStore(parse_store_url(etcd.url), gateway_id=gateway_id, lease=LEASE, **options)
        opened.append(store)
        await store.start()
        return store

    yield open_store
    for store in opened:
        await store.aclose()


class Seen:
    """What a store's watch reported, in order."""

    def __init__(self, store: SharedStore) -> None:
        self.changes: list[Change] = []
        store.watch(self.changes.append)

    def has(self, kind: Kind, name: str, value: str | None) -> bool:
        return Change(kind, name, value) in self.changes


async def test_keys_are_written_read_compared_and_deleted(etcd: EtcdServer, stores: Any) -> None:
    store = await stores(etcd, "gw-a")
    assert isinstance(store, SharedStore) and isinstance(store, RegistryStore)
    assert store.shared and store.read_only == "" and store.location == etcd.url

    await store.put(Kind.STATE, "bot", "up")
    assert await store.read(Kind.STATE) == {"bot": "up"}
    assert await store.create(Kind.LICENCE, "bot", '{"holder": "alice"}')
    assert not await store.create(Kind.LICENCE, "bot", '{"holder": "bob"}')
    assert await store.read(Kind.LICENCE) == {"bot": '{"holder": "alice"}'}

    assert not await store.replace(Kind.STATE, "bot", "down", "connecting")
    assert await store.replace(Kind.STATE, "bot", "up", "down")
    assert await store.read(Kind.STATE) == {"bot": "down"}
    assert not await store.replace(Kind.STATE, "nobody", "up", "down")
    assert await store.replace(Kind.STATE, "bot", "down", None)
    assert await store.read(Kind.STATE) == {}

    await store.delete(Kind.LICENCE, "bot")
    await store.delete(Kind.LICENCE, "bot")  # absent: no error
    assert await store.read(Kind.LICENCE) == {}

    # The registry's view: registrations under services, not leased.
    await store.save("cam", "tcp://127.0.0.1:7000", {"type": "camera"})
    await store.save("lamp", "tcp://127.0.0.1:7001", {})
    assert await store.load() == [
        ("cam", "tcp://127.0.0.1:7000", {"type": "camera"}),
        ("lamp", "tcp://127.0.0.1:7001", {}),
    ]
    await store.drop("cam")
    assert [name for name, _, _ in await store.load()] == ["lamp"]

    with pytest.raises(InvalidArgument, match="without '/'"):
        await store.put(Kind.STATE, "a/b", "up")
    with pytest.raises(InvalidArgument, match="at most"):
        await store.put(Kind.STATE, "big", "x" * 100_000)


async def test_folders_and_prefixes_keep_apart(etcd: EtcdServer, stores: Any) -> None:
    one = await stores(etcd, "gw-a")
    other_cluster = await stores(etcd, "gw-b", prefix="/elsewhere")
    await one.put(Kind.SERVICE, "bot", '{"url": "tcp://127.0.0.1:1"}')
    await one.put(Kind.OWNER, "bot", "gw-a")
    assert await one.read(Kind.OWNER) == {"bot": "gw-a"}
    assert await one.read(Kind.GATEWAY) == {}
    assert await other_cluster.read(Kind.OWNER) == {}


async def test_a_leased_key_goes_with_its_gateway(etcd: EtcdServer, stores: Any) -> None:
    dead = await stores(etcd, "gw-dead")
    survivor = await stores(etcd, "gw-survivor")
    seen = Seen(survivor)
    await dead.put(Kind.OWNER, "bot", "gw-dead", leased=True)
    await dead.put(Kind.SERVICE, "bot", "{}")  # not leased: it stays
    await wait_until(lambda: seen.has(Kind.OWNER, "bot", "gw-dead"), what="the owner key is seen")

    # A gateway that dies: its keep-alive stops, nothing is revoked.
    loop = asyncio.get_running_loop()
    died = loop.time()
    await dead.aclose(revoke=False)
    assert await survivor.read(Kind.OWNER) == {"bot": "gw-dead"}, "the key outlived its lease's keep-alive"
    await wait_until(
        lambda: seen.has(Kind.OWNER, "bot", None), within=LEASE + EXPIRY_SLACK, what="the owner key expires"
    )
    gone_after = loop.time() - died
    assert gone_after >= LEASE - 0.7, f"the key went after {gone_after:.2f} s, before its lease could end"
    assert await survivor.read(Kind.OWNER) == {}
    assert await survivor.read(Kind.SERVICE) == {"bot": "{}"}


async def test_a_clean_shutdown_revokes_the_lease_at_once(etcd: EtcdServer, stores: Any) -> None:
    leaving = await stores(etcd, "gw-leaving")
    staying = await stores(etcd, "gw-staying")
    seen = Seen(staying)
    await leaving.put(Kind.GATEWAY, "gw-leaving", '{"address": "127.0.0.1:1"}', leased=True)
    await wait_until(lambda: seen.has(Kind.GATEWAY, "gw-leaving", '{"address": "127.0.0.1:1"}'))
    await leaving.aclose()
    await wait_until(
        lambda: seen.has(Kind.GATEWAY, "gw-leaving", None), within=1.0, what="the key goes at once"
    )


async def test_two_gateways_racing_to_create_one_key_one_wins(etcd: EtcdServer, stores: Any) -> None:
    a = await stores(etcd, "gw-a")
    b = await stores(etcd, "gw-b")
    rounds = 100
    for n in range(rounds):
        won = await asyncio.gather(
            a.create(Kind.OWNER, f"dev{n}", "gw-a", leased=True),
            b.create(Kind.OWNER, f"dev{n}", "gw-b", leased=True),
        )
        assert sorted(won) == [False, True], f"round {n}: {won}"
    owners = await a.read(Kind.OWNER)
    assert len(owners) == rounds
    # And a compare-and-set race on one licence key: exactly one grant per round.
    for n in range(rounds):
        await a.put(Kind.LICENCE, "cam", f"free{n}")
        won = await asyncio.gather(
            a.replace(Kind.LICENCE, "cam", f"free{n}", "gw-a"),
            b.replace(Kind.LICENCE, "cam", f"free{n}", "gw-b"),
        )
        assert sorted(won) == [False, True], f"round {n}: {won}"


async def test_many_keys_are_created_at_once_and_a_key_taken_first_stays_its_writers(
    etcd: EtcdServer, stores: Any
) -> None:
    first = await stores(etcd, "gw-first")
    batcher = await stores(etcd, "gw-batcher")
    names = [f"dev{n:04d}" for n in range(300)]  # three transactions of at most 128 keys
    taken = {names[0], names[129], names[200], names[299]}
    for name in sorted(taken):
        assert await first.create(Kind.OWNER, name, "gw-first", leased=True)
    created = await batcher.create_many(Kind.OWNER, {name: "gw-batcher" for name in names}, leased=True)
    assert created == set(names) - taken
    owners = await batcher.read(Kind.OWNER)
    assert owners == {name: "gw-first" if name in taken else "gw-batcher" for name in names}
    assert await batcher.create_many(Kind.OWNER, {name: "gw-batcher" for name in names}) == set()
    # Leased: bound to the batcher's lease, they go when it ends.
    await batcher.aclose()
    assert await first.read(Kind.OWNER) == {name: "gw-first" for name in taken}


async def test_two_gateways_creating_the_same_keys_at_once_share_them_without_overlap(
    etcd: EtcdServer, stores: Any
) -> None:
    a = await stores(etcd, "gw-a")
    b = await stores(etcd, "gw-b")
    for round_ in range(5):
        names = [f"r{round_}-dev{n:03d}" for n in range(400)]
        won_a, won_b = await asyncio.gather(
            a.create_many(Kind.OWNER, dict.fromkeys(names, "gw-a"), leased=True),
            b.create_many(Kind.OWNER, dict.fromkeys(reversed(names), "gw-b"), leased=True),
        )
        assert not won_a & won_b, f"round {round_}: both created {sorted(won_a & won_b)[:5]}"
        assert won_a | won_b == set(names), f"round {round_}: nobody created some"
        owners = await a.read(Kind.OWNER)
        assert all(owners[name] == ("gw-a" if name in won_a else "gw-b") for name in names)


async def test_many_keys_are_put_at_once_within_etcds_request_size(etcd: EtcdServer, stores: Any) -> None:
    store = await stores(etcd, "gw-a")
    # 40 values of 60 KiB: 2.4 MiB, over etcd's 1.5 MiB a request, so more than one transaction.
    big = {f"blob{n:02d}": chr(ord("a") + n % 26) * 60_000 for n in range(40)}
    await store.put_many(Kind.LICENCE, big)
    assert await store.read(Kind.LICENCE) == big
    small = {f"dev{n:04d}": "up" for n in range(1_000)}
    await store.put_many(Kind.STATE, small, leased=True)
    await store.put_many(Kind.STATE, {name: "down" for name in list(small)[:10]}, leased=True)
    states = await store.read(Kind.STATE)
    assert len(states) == 1_000 and list(states.values()).count("down") == 10
    with pytest.raises(InvalidArgument, match="without '/'"):
        await store.put_many(Kind.STATE, {"a/b": "up"})
    assert "a" not in await store.read(Kind.STATE)


async def test_the_lease_lives_through_bulk_writes(etcd: EtcdServer, stores: Any) -> None:
    store = await stores(etcd, "gw-a")
    told: list[str] = []
    store.watch_read_only(lambda: told.append(store.read_only))
    loop = asyncio.get_running_loop()
    began = loop.time()
    rounds = 0
    # Bulk writes for at least two leases' time: the keep-alive, on its own connection, goes on.
    while loop.time() - began < 2 * LEASE:
        await store.put_many(Kind.STATE, {f"dev{n:05d}": f"up{rounds}" for n in range(2_000)}, leased=True)
        rounds += 1
    assert told == [] and store.connections == 1, (told, store.connections)
    states = await store.read(Kind.STATE)
    assert len(states) == 2_000 and set(states.values()) == {f"up{rounds - 1}"}


async def test_a_lease_that_lives_through_an_etcd_restart_keeps_its_keys(
    etcd: EtcdServer, stores: Any
) -> None:
    owner = await stores(etcd, "gw-owner")
    other = await stores(etcd, "gw-other")
    await owner.put(Kind.OWNER, "bot", "gw-owner", leased=True)
    seen = Seen(other)
    reconnected = asyncio.Event()
    owner.on_reconnect(reconnected.set)
    etcd.stop()
    etcd.start()  # with its data: the lease is still there
    await asyncio.wait_for(reconnected.wait(), 10)
    # The same lease, kept alive: its key never went, and outlives a lease's time.
    await asyncio.sleep(LEASE + EXPIRY_SLACK)
    assert await other.read(Kind.OWNER) == {"bot": "gw-owner"}
    assert not seen.has(Kind.OWNER, "bot", None)


async def test_the_watch_reports_changes_of_another_gateway_within_a_second(
    etcd: EtcdServer, stores: Any
) -> None:
    writer = await stores(etcd, "gw-writer")
    watcher = await stores(etcd, "gw-watcher")
    arrived: asyncio.Queue[tuple[Change, float]] = asyncio.Queue(maxsize=100)
    loop = asyncio.get_running_loop()
    unwatch = watcher.watch(lambda change: arrived.put_nowait((change, loop.time())))

    expected = [
        Change(Kind.SERVICE, "bot", '{"url": "tcp://127.0.0.1:9"}'),
        Change(Kind.STATE, "bot", "up"),
        Change(Kind.STATE, "bot", "down"),
        Change(Kind.STATE, "bot", None),
    ]
    for change in expected:
        sent = loop.time()
        if change.value is None:
            await writer.delete(change.kind, change.name)
        else:
            await writer.put(change.kind, change.name, change.value)
        got, when = await asyncio.wait_for(arrived.get(), 5)
        assert got == change
        assert when - sent < 1.0, f"{change} took {when - sent:.2f} s"

    unwatch()
    await writer.put(Kind.STATE, "bot", "up")
    await asyncio.sleep(0.3)
    assert arrived.empty(), "an unwatched listener heard a change"


async def test_etcd_stopped_makes_the_store_read_only_and_back(etcd: EtcdServer, stores: Any) -> None:
    store = await stores(etcd, "gw-a")
    told: list[str] = []
    store.watch_read_only(lambda: told.append(store.read_only))
    loop = asyncio.get_running_loop()
    etcd.stop()
    stopped = loop.time()
    await wait_until(lambda: store.read_only != "", within=LEASE, what="the store says it is read-only")
    assert loop.time() - stopped < LEASE
    assert store.read_only.startswith(f"etcd at {etcd.endpoint} cannot be reached (")
    with pytest.raises(Unavailable, match="cannot be reached"):
        await store.save("bot", "tcp://127.0.0.1:1", {})
    with pytest.raises(Unavailable, match="cannot be reached"):
        await store.create(Kind.OWNER, "bot", "gw-a", leased=True)

    reconnected = asyncio.Event()
    store.on_reconnect(reconnected.set)
    etcd.start()
    await asyncio.wait_for(reconnected.wait(), 10)
    assert store.read_only == ""
    assert told[0].startswith("etcd at ") and told[-1] == "", told
    await store.save("bot", "tcp://127.0.0.1:1", {})
    assert [name for name, _, _ in await store.load()] == ["bot"]


async def test_etcd_restarted_empty_gets_the_leased_keys_again(etcd: EtcdServer, stores: Any) -> None:
    owner = await stores(etcd, "gw-owner")
    other = await stores(etcd, "gw-other")
    seen = Seen(other)

    async def write_leased_keys() -> None:
        await owner.put(Kind.GATEWAY, "gw-owner", '{"address": "127.0.0.1:1"}', leased=True)
        await owner.put(Kind.OWNER, "bot", "gw-owner", leased=True)

    rewrites: set[asyncio.Task[None]] = set()

    def on_reconnect() -> None:
        task = asyncio.get_running_loop().create_task(write_leased_keys())
        rewrites.add(task)
        task.add_done_callback(rewrites.discard)

    owner.on_reconnect(on_reconnect)
    await write_leased_keys()
    await wait_until(lambda: seen.has(Kind.OWNER, "bot", "gw-owner"), what="the owner key is seen")
    connections_before = owner.connections

    etcd.kill()
    etcd.start(wipe=True)
    seen.changes.clear()
    await wait_until(lambda: owner.connections > connections_before, what="the owner reconnects")
    await wait_until(
        lambda: seen.has(Kind.OWNER, "bot", "gw-owner"), what="the other gateway sees the owner again"
    )
    assert await other.read(Kind.OWNER) == {"bot": "gw-owner"}
    assert await other.read(Kind.GATEWAY) == {"gw-owner": '{"address": "127.0.0.1:1"}'}
    # The keys are bound to a new lease that is kept alive: they outlive the old lease's time.
    await asyncio.sleep(LEASE + EXPIRY_SLACK)
    assert await other.read(Kind.OWNER) == {"bot": "gw-owner"}


async def test_a_watcher_hears_of_keys_that_went_while_etcd_was_away(etcd: EtcdServer, stores: Any) -> None:
    writer = await stores(etcd, "gw-writer")
    watcher = await stores(etcd, "gw-watcher")
    await writer.put(Kind.STATE, "bot", "up")
    seen = Seen(watcher)
    etcd.kill()
    etcd.start(wipe=True)  # the key is gone with etcd's data
    await wait_until(lambda: seen.has(Kind.STATE, "bot", None), what="the watcher hears the key is gone")


async def test_a_store_started_before_etcd_is_read_only_until_it_comes(etcd: EtcdServer, stores: Any) -> None:
    etcd.stop()
    loop = asyncio.get_running_loop()
    started = loop.time()
    store = await stores(etcd, "gw-early")
    assert loop.time() - started < START_WAIT + 1.0
    assert "cannot be reached" in store.read_only
    reconnected = asyncio.Event()
    store.on_reconnect(reconnected.set)
    etcd.start()
    await asyncio.wait_for(reconnected.wait(), 10)
    await store.put(Kind.GATEWAY, "gw-early", "{}", leased=True)


async def test_tls_with_client_certificates(
    etcd_server: Callable[..., EtcdServer], certificates: CertificateFiles, stores: Any
) -> None:
    etcd = etcd_server(tls=certificates)
    alice = certificates.clients["alice"]
    store = await stores(etcd, "gw-tls", tls=EtcdTls(str(certificates.ca), str(alice.cert), str(alice.key)))
    assert store.read_only == "" and store.location.startswith("etcds://")
    await store.put(Kind.STATE, "bot", "up")
    assert await store.read(Kind.STATE) == {"bot": "up"}

    # etcd asks for a client certificate: a store without one never connects.
    anonymous = await stores(etcd, "gw-anonymous", tls=EtcdTls(str(certificates.ca)))
    assert "cannot be reached" in anonymous.read_only
    # A store that does not trust etcd's CA does not connect either.
    foreign = certificates.foreign
    stranger = await stores(
        etcd, "gw-stranger", tls=EtcdTls(str(certificates.other_ca), str(foreign.cert), str(foreign.key))
    )
    assert "cannot be reached" in stranger.read_only
