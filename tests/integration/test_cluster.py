"""A cluster of three real gateway processes sharing one registry in a real etcd.

Each test starts etcd (``tests/support/etcd.py``) and three gateways (``gw-a``, ``gw-b``, ``gw-c``)
whose ``[registry] store`` names it, with short leases, and real line-protocol devices as processes
(``python -m services.device``). Users act as they would: the asyncio SDK against any
gateway. Without the ``etcd`` command the tests skip, saying so.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import AsyncIterator, Callable, Iterator
from contextlib import ExitStack
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path

import aiohttp
import jwt
import psutil
import pytest
from line_device_support import device_process, tcp_device
from prometheus_client.parser import text_string_to_metric_families
from support.cluster import running_cluster
from support.etcd import EtcdServer
from support.gateway_process import GatewayProcess
from support.waiting import eventually

from clients import AsyncClient, ClientCredentials
from clients.aio import Event
from clients.errors import FailedPrecondition, NotFound, PropertyServiceError, Unavailable

pytestmark = [pytest.mark.slow, pytest.mark.timeout(180)]

#: Seconds of each gateway's lease: short, so that failover is quick to watch (etcd's floor is ~1.5 s).
LEASE = 2.0
SECRET = "a shared secret of the cluster, long enough for HS256"
IDS = ("gw-a", "gw-b", "gw-c")


@dataclass
class Cluster:
    """Three gateways on one etcd; ``gateways[id]`` is a running process."""

    etcd: EtcdServer
    gateways: dict[str, GatewayProcess]
    lines: dict[str, str]
    folder: Path

    def client(self, gateway: str, who: str | None = None) -> AsyncClient:
        credentials = ClientCredentials(token=_token(who)) if who else None
        return AsyncClient(self.gateways[gateway].address, credentials=credentials)


def _token(subject: str) -> str:
    return jwt.encode({"sub": subject, "exp": int(time.time()) + 600}, SECRET, algorithm="HS256")


@pytest.fixture
def cluster(etcd_server: Callable[..., EtcdServer], tmp_path: Path) -> Iterator[Cluster]:
    etcd = etcd_server()
    with running_cluster(etcd, tmp_path, IDS, lease=LEASE, secret=SECRET) as (gateways, lines):
        yield Cluster(etcd, gateways, lines, tmp_path)


@pytest.fixture
async def clients(cluster: Cluster) -> AsyncIterator[dict[str, AsyncClient]]:
    opened = {gateway: cluster.client(gateway) for gateway in IDS}
    yield opened
    for client in opened.values():
        await client.close()


async def _register(client: AsyncClient, name: str, address: tuple[str, int]) -> None:
    host, port = address
    await client.set("registry", f"services.{name}", f"tcp://{host}:{port}")


async def _owner(client: AsyncClient, name: str) -> str:
    return str(await client.get("registry", f"services.{name}.owner"))


async def test_a_registration_on_one_gateway_is_served_by_every_gateway(
    cluster: Cluster, clients: dict[str, AsyncClient]
) -> None:
    with tcp_device("--service", "sim-sensor", "--name", "thermo") as address:
        await _register(clients["gw-a"], "thermo", address)
        for gateway in IDS:
            client = clients[gateway]
            names = await eventually(
                lambda c=client: c.get_names("registry", "services"),
                lambda names: "thermo" in names,
                what=f"{gateway} lists thermo",
            )
            assert "thermo" in names
            assert await _owner(client, "thermo") == "gw-a"
            state = await eventually(
                lambda c=client: c.get("registry", "services.thermo.state"), lambda s: s == "up"
            )
            assert state == "up"
            assert await client.get("registry", "services.thermo.url") == f"tcp://{address[0]}:{address[1]}"
        # Get, Set and Listen through gateways that do not own it reach the device owned by gw-a.
        assert 10.0 < await clients["gw-b"].get_number("thermo", "data") < 30.0
        assert await clients["gw-c"].set("thermo", "rate_hz", "20") == "20"
        assert await clients["gw-a"].get("thermo", "rate_hz") == "20"
        events = clients["gw-c"].listen("thermo", "data")
        try:
            seen = [await anext(events) for _ in range(3)]
        finally:
            await events.aclose()
        assert [e.service for e in seen] == ["thermo"] * 3
        assert len({e.value for e in seen}) > 1  # live readings, not one value repeated


async def test_every_gateway_hears_a_state_change_within_a_second(
    cluster: Cluster, clients: dict[str, AsyncClient]
) -> None:
    with tcp_device("--service", "sim-sensor", "--name", "thermo") as address:
        await _register(clients["gw-a"], "thermo", address)
        for gateway in IDS:
            await eventually(
                lambda g=gateway: clients[g].get("registry", "services.thermo.state"),
                lambda state: state == "up",
                retry_on=(PropertyServiceError,),
            )
        streams = {g: clients[g].listen("registry", "services.*.state", updates_only=True) for g in IDS}
        downs = [asyncio.ensure_future(_first_down(streams[g])) for g in IDS]
        await asyncio.sleep(0.5)  # the Listens are open
        # The device goes away (the context ends): its owner's liveness checks find it down.
    heard = dict(zip(IDS, await asyncio.gather(*downs), strict=True))
    for stream in streams.values():
        await stream.aclose()
    lag = max(heard[g] for g in ("gw-b", "gw-c")) - heard["gw-a"]
    print(f"a state change seen by the other gateways {lag.total_seconds() * 1000:.0f} ms after its owner")
    assert lag.total_seconds() < 1.0


async def _first_down(events: AsyncIterator[Event]) -> datetime:
    """When the gateway of ``events`` saw ``thermo`` go down."""
    async with asyncio.timeout(20):
        async for event in events:
            if event.property == "services.thermo.state" and event.value == "down":
                return event.time
    raise AssertionError("the stream ended before thermo went down")


async def test_a_name_registered_anywhere_is_taken_everywhere(
    cluster: Cluster, clients: dict[str, AsyncClient]
) -> None:
    with tcp_device("--service", "sim-sensor") as first, tcp_device("--service", "sim-sensor") as second:
        await _register(clients["gw-a"], "thermo", first)
        await eventually(lambda: clients["gw-b"].get_names("registry", "services"), lambda n: "thermo" in n)
        with pytest.raises(PropertyServiceError, match="taken"):
            await _register(clients["gw-b"], "thermo", second)
        # Unregistered on a gateway that does not own it: it leaves every gateway.
        await clients["gw-c"].set("registry", "services.thermo", "")
        for gateway in IDS:
            await eventually(
                lambda g=gateway: clients[g].get_names("registry", "services"),
                lambda names: "thermo" not in names,
                what=f"{gateway} forgot thermo",
            )
        await _register(clients["gw-b"], "thermo", second)
        await eventually(lambda: _owner(clients["gw-a"], "thermo"), lambda o: o == "gw-b")


async def test_killing_the_owner_moves_its_devices_and_a_listen_resumes_with_a_gap(
    cluster: Cluster, clients: dict[str, AsyncClient]
) -> None:
    names = ("thermo1", "thermo2", "thermo3")
    with ExitStack() as stack:
        for name in names:
            address = stack.enter_context(tcp_device("--service", "sim-sensor", "--name", name))
            await _register(clients["gw-a"], name, address)
        for name in names:
            await eventually(lambda n=name: _owner(clients["gw-b"], n), lambda o: o == "gw-a")
        events = clients["gw-b"].listen("thermo1", "data")
        first = await anext(events)
        assert not first.gap
        killed = time.monotonic()
        cluster.gateways["gw-a"].proc.kill()  # SIGKILL: no goodbye, its lease just runs out
        moved: dict[str, str] = {}
        while len(moved) < len(names):
            assert time.monotonic() - killed < LEASE + 8.0, f"owned again after the kill: {moved}"
            for name in names:
                with contextlib.suppress(PropertyServiceError):
                    owner = await _owner(clients["gw-c"], name)
                    if owner in ("gw-b", "gw-c"):
                        moved.setdefault(name, owner)
            await asyncio.sleep(0.05)
        failover = time.monotonic() - killed
        print(f"devices owned again {failover:.2f} s after SIGKILL of their owner (lease {LEASE:g} s)")
        assert failover < LEASE + 3.0
        # Spread over the survivors, least loaded first: not all on one gateway.
        assert set(moved.values()) == {"gw-b", "gw-c"}
        for gateway in ("gw-b", "gw-c"):
            listed = await clients[gateway].get_names("registry", "services")
            assert set(names) <= set(listed)  # no registration lost
        # The Listen through a survivor goes on: one event marked gap, then live readings.
        gap = await asyncio.wait_for(_next_gap(events), 15.0)
        assert gap.service == "thermo1"
        after = await asyncio.wait_for(anext(events), 5.0)
        assert not after.gap
        await events.aclose()
        for name in names:
            assert 10.0 < await clients["gw-c"].get_number(name, "data") < 30.0


async def _remote_gateway_gauges(gateway: GatewayProcess) -> tuple[float, float]:
    """The gateway's ``/metrics``: its channels to other gateways, and the proxies holding them."""
    async with aiohttp.ClientSession() as session, session.get(f"{gateway.http_url}metrics") as response:
        assert response.status == 200, await response.text()
        text = await response.text()
    samples = {s.name: s.value for family in text_string_to_metric_families(text) for s in family.samples}
    return samples["psgateway_remote_gateway_channels"], samples["psgateway_remote_gateway_proxies"]


def _connections_to(gateway: GatewayProcess, other: GatewayProcess) -> int:
    """Established TCP connections from ``gateway``'s process to ``other``'s gRPC port."""
    port = int(other.address.rsplit(":", 1)[1])
    return sum(
        1
        for connection in psutil.Process(gateway.proc.pid).net_connections(kind="tcp")
        if connection.status == psutil.CONN_ESTABLISHED and connection.raddr and connection.raddr.port == port
    )


async def test_the_services_forwarded_to_one_owner_share_one_channel(
    cluster: Cluster, clients: dict[str, AsyncClient]
) -> None:
    names = [f"thermo{k}" for k in range(1, 5)]
    with ExitStack() as stack:
        for name in names:
            address = stack.enter_context(tcp_device("--service", "sim-sensor", "--name", name))
            await _register(clients["gw-a"], name, address)
        for name in names:  # forwarded by gw-b, which learnt each one's type and state
            for what, expected in (("owner", "gw-a"), ("state", "up"), ("type", "sensor")):
                await eventually(
                    lambda n=name, w=what: clients["gw-b"].get("registry", f"services.{n}.{w}"),
                    lambda value, e=expected: value == e,
                    what=f"gw-b reads {name}'s {what} {expected}",
                )
            assert 10.0 < await clients["gw-b"].get_number(name, "data") < 30.0
        # gw-b forwards four services to gw-a over one channel, and one TCP connection.
        assert await _remote_gateway_gauges(cluster.gateways["gw-b"]) == (1, len(names))
        assert _connections_to(cluster.gateways["gw-b"], cluster.gateways["gw-a"]) == 1
        # The channel stays while one service is forwarded over it, and closes with the last.
        for name in names[:-1]:
            await clients["gw-a"].set("registry", f"services.{name}", "")
        await eventually(
            lambda: _remote_gateway_gauges(cluster.gateways["gw-b"]),
            lambda gauges: gauges == (1, 1),
            what="one forwarded service left on gw-b's channel",
        )
        assert await clients["gw-b"].get("registry", f"services.{names[-1]}.state") == "up"
        await clients["gw-a"].set("registry", f"services.{names[-1]}", "")
        await eventually(
            lambda: _remote_gateway_gauges(cluster.gateways["gw-b"]),
            lambda gauges: gauges == (0, 0),
            what="gw-b closed its channel to gw-a",
        )


async def _next_gap(events: AsyncIterator[object]) -> object:
    async for event in events:
        if getattr(event, "gap", False):
            return event
    raise AssertionError("the stream ended without a gap")


async def test_a_device_that_dialled_in_goes_to_another_gateway_when_its_own_dies(
    cluster: Cluster, clients: dict[str, AsyncClient]
) -> None:
    line_a = cluster.lines["gw-a"]
    with device_process(
        "--service", "sim-robot", "--name", "rover", "--connect", line_a, "--log-level", "INFO"
    ):
        for gateway in IDS:
            await eventually(
                lambda g=gateway: clients[g].get_names("registry", "services"),
                lambda names: "rover" in names,
                what=f"{gateway} lists the device that dialled in",
            )
        assert await _owner(clients["gw-c"], "rover") == "gw-a"
        assert (await clients["gw-b"].get("registry", "services.rover.url")).startswith("tcp-in://")
        cluster.gateways["gw-a"].proc.kill()
        # Its registration leaves with gw-a's lease; the device dials an alternate it was told of.
        owner = await eventually(
            lambda: _owner(clients["gw-b"], "rover"),
            lambda o: o in ("gw-b", "gw-c"),
            within=30.0,
            retry_on=(PropertyServiceError,),
            what="the device registered on another gateway",
        )
        assert owner in ("gw-b", "gw-c")
        assert len(await clients["gw-c"].get_vector("rover", "location")) == 6


async def test_etcd_restarted_empty_gets_the_keys_back(
    cluster: Cluster, clients: dict[str, AsyncClient]
) -> None:
    with tcp_device("--service", "sim-sensor", "--name", "thermo") as address:
        await _register(clients["gw-a"], "thermo", address)
        await eventually(lambda: _owner(clients["gw-c"], "thermo"), lambda o: o == "gw-a")
        cluster.etcd.kill()
        cluster.etcd.start(wipe=True)
        keys = await eventually(
            lambda: _etcd_keys(cluster.etcd),
            lambda keys: (
                {"services/thermo", "owners/thermo", "states/thermo"} <= keys
                and {f"gateways/{g}" for g in IDS} <= keys
            ),
            within=20.0,
            what="every gateway wrote its keys again",
        )
        assert "owners/thermo" in keys
        # Nobody took it over, nobody lost it.
        for gateway in IDS:
            await eventually(lambda g=gateway: _owner(clients[g], "thermo"), lambda o: o == "gw-a")
        # gw-b forwards again once its view has gw-a's record back (the owners key may come first:
        # until then it says the owner is not in the cluster).
        await eventually(
            lambda: clients["gw-b"].get_number("thermo", "data"),
            lambda value: 10.0 < value < 30.0,
            retry_on=(Unavailable,),
            what="gw-b forwards to gw-a again",
        )
        with tcp_device("--service", "sim-sensor") as other:
            await eventually(lambda: _register(clients["gw-b"], "after", other), retry_on=(Unavailable,))


async def _etcd_keys(etcd: EtcdServer) -> set[str]:
    """The keys under the default prefix, read with etcd's v3 API through the gateway's own store."""
    from gateway.stores.address import parse_store_url
    from gateway.stores.etcd import EtcdStore
    from services.apps.registry.store import Kind

    store = EtcdStore(parse_store_url(etcd.url), gateway_id="test-reader")
    await store.start()
    try:
        return {f"{kind.value}/{name}" for kind in Kind for name in await store.read(kind)}
    finally:
        await store.aclose()


async def test_without_etcd_the_registry_is_read_only_and_served_calls_go_on(
    cluster: Cluster, clients: dict[str, AsyncClient]
) -> None:
    with (
        tcp_device("--service", "sim-sensor", "--name", "thermo") as address,
        tcp_device("--service", "sim-sensor") as other,
    ):
        await _register(clients["gw-a"], "thermo", address)
        await eventually(lambda: _owner(clients["gw-b"], "thermo"), lambda o: o == "gw-a")
        cluster.etcd.stop()
        store = await eventually(
            lambda: clients["gw-b"].get("registry", "store"), lambda text: "read-only" in str(text)
        )
        assert str(store).startswith(f"{cluster.etcd.url} (read-only: etcd at ")
        with pytest.raises(Unavailable) as refused:
            await _register(clients["gw-b"], "other", other)
        assert "the registry is read-only: etcd at" in str(refused.value)
        assert "cannot be reached" in str(refused.value)
        # What is owned and what is forwarded is served as before.
        assert 10.0 < await clients["gw-a"].get_number("thermo", "data") < 30.0
        assert 10.0 < await clients["gw-c"].get_number("thermo", "data") < 30.0
        cluster.etcd.start()
        await eventually(
            lambda: _register(clients["gw-b"], "other", other), retry_on=(Unavailable,), within=20.0
        )
        await eventually(
            lambda: _owner(clients["gw-a"], "other"), lambda o: o == "gw-b", retry_on=(PropertyServiceError,)
        )


async def test_two_gateways_racing_for_one_licence_grant_it_once(cluster: Cluster) -> None:
    with tcp_device("--service", "sim-robot", "--name", "arm") as address:
        admin = cluster.client("gw-a")
        await _register(admin, "arm", address)
        await eventually(lambda: _owner(admin, "arm"), lambda o: o == "gw-a")
        racers = [cluster.client(gateway, who) for gateway, who in (("gw-b", "alice"), ("gw-c", "bob"))]
        for racer in racers:
            await eventually(lambda r=racer: r.get_names("registry", "services"), lambda n: "arm" in n)
        try:
            outcomes = await asyncio.gather(
                *(r.set("registry", "acquire", "", service="arm", duration="30") for r in racers),
                return_exceptions=True,
            )
            won = [o for o in outcomes if isinstance(o, str)]
            lost = [o for o in outcomes if isinstance(o, FailedPrecondition)]
            assert len(won) == 1 and len(lost) == 1, outcomes
            assert "is held by" in str(lost[0])
        finally:
            for racer in racers:
                await racer.close()
            await admin.close()


async def test_every_gateway_learns_the_type_the_device_greeted_with(
    cluster: Cluster, clients: dict[str, AsyncClient]
) -> None:
    """Registered with no type declared: the owner learns it from the device's greeting, which comes
    after the other gateways saw the registration; they learn it too, not 'unknown' for good."""
    with tcp_device("--service", "sim-sensor", "--name", "thermo") as address:
        await _register(clients["gw-b"], "thermo", address)
        for gateway in IDS:
            client = clients[gateway]
            kind = await eventually(
                lambda c=client: c.get("registry", "services.thermo.type"),
                lambda kind: kind == "sensor",
                what=f"{gateway} learns thermo's type",
            )
            assert kind == "sensor", gateway


async def test_a_licence_granted_on_one_gateway_holds_on_every_gateway(cluster: Cluster) -> None:
    """Alice's licence, granted by gw-b on arm (owned by gw-a), refuses Bob's Sets through every
    gateway, the owner's included; Alice's own Sets pass through any of them."""
    with tcp_device("--service", "sim-robot", "--name", "arm") as address:
        admin = cluster.client("gw-a")
        await _register(admin, "arm", address)
        await eventually(lambda: _owner(admin, "arm"), lambda o: o == "gw-a")
        alice = {gateway: cluster.client(gateway, "alice") for gateway in IDS}
        bob = {gateway: cluster.client(gateway, "bob") for gateway in IDS}
        admin_c = cluster.client("gw-c")
        try:
            for client in bob.values():
                await eventually(lambda c=client: c.get_names("registry", "services"), lambda n: "arm" in n)
            licence = await alice["gw-b"].set("registry", "acquire", "", service="arm", duration="30")
            for gateway in IDS:
                refusal = await eventually(
                    lambda g=gateway: _set_or_error(bob[g], "arm", "speed", "0.5"),
                    lambda outcome: isinstance(outcome, FailedPrecondition),
                    what=f"bob refused on {gateway}",
                )
                assert isinstance(refusal, FailedPrecondition), (gateway, refusal)
                assert "held by alice" in str(refusal), (gateway, refusal)
                assert await alice[gateway].set("arm", "speed", "0.25") == "0.25", gateway
            await alice["gw-b"].set("registry", "release", "", licence=licence)
            for gateway in IDS:
                done = await eventually(
                    lambda g=gateway: _set_or_error(bob[g], "arm", "speed", "0.5"),
                    lambda outcome: outcome == "0.5",
                    what=f"bob's Set on {gateway} once the licence is released",
                )
                assert done == "0.5", (gateway, done)
            # A subtree must name properties of the service: gw-c reads arm's model from its owner.
            with pytest.raises(NotFound, match="arm has no property 'wings'"):
                await alice["gw-c"].set("registry", "acquire", "", service="arm", subtree="wings")
            sub = await alice["gw-c"].set(
                "registry", "acquire", "", service="arm", subtree="behaviors", duration="30"
            )
            refusal = await eventually(
                lambda: _set_or_error(bob["gw-a"], "arm", "behaviors.stop", ""),
                lambda outcome: isinstance(outcome, FailedPrecondition),
                what="bob refused on gw-a under alice's subtree",
            )
            assert "held by alice" in str(refusal), refusal
            # Revoked where it was granted, it stops holding on every gateway.
            await admin_c.set("registry", "revoke", "", licence=sub)
            done = await eventually(
                lambda: _set_or_error(bob["gw-a"], "arm", "behaviors.stop", ""),
                lambda outcome: not isinstance(outcome, PropertyServiceError),
                what="bob's Set on gw-a once the licence is revoked",
            )
            assert not isinstance(done, PropertyServiceError), done
        finally:
            for client in [*alice.values(), *bob.values(), admin, admin_c]:
                await client.close()


async def _set_or_error(client: AsyncClient, service: str, path: str, value: str) -> object:
    try:
        return await client.set(service, path, value)
    except PropertyServiceError as exc:
        return exc
