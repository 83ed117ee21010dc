"""A client given several gateways moves to a survivor when the one it uses dies or freezes.

Two independent gateway processes serving the same simulated sensor stand in for any two gateways
that offer the same services; the last tests run a cluster of two gateways on a real etcd with a
real line-protocol device, as docs/scale-out.md sets one up. The gateway in use is SIGKILLed or
SIGSTOPped (SIGCONT before it is stopped) and the user sees what a user would: a Listen with
``resume=True`` that carries on through the survivor with exactly one ``gap``, a Get answered by
the survivor, and, when every gateway is gone, an error that names each address it tried.
"""

from __future__ import annotations

import asyncio
import os
import signal
import socket
import time
from collections.abc import AsyncIterator, Callable, Iterator
from pathlib import Path

import pytest
from line_device_support import tcp_device
from support.cluster import cluster_config, running_gateways
from support.etcd import EtcdServer
from support.gateway_process import GatewayProcess, StartGateway
from support.ports import free_port
from support.psctl import psctl
from support.waiting import eventually

from clients import AsyncClient, Client
from clients.aio import DEFAULT_KEEPALIVE, Event
from clients.errors import GatewayUnreachable, PropertyServiceError, Unavailable

pytestmark = pytest.mark.timeout(120)

SENSOR = """
    [[services]]
    name = "thermo"
    type = "sim-sensor"
"""
#: Seconds of the cluster's lease in etcd; a Listen must be back within it plus 2 s (etcd's floor is ~1.5 s).
LEASE = 2.0
#: What a resumed Listen may take after its gateway died or froze: the lease plus 2 s, doubled for
#: a machine busy with other work (the measured figures are in docs/performance.md).
RECOVERY_BOUND = 2 * (LEASE + 2.0)
#: Events read after the resume, to see that no second gap follows the first.
AFTER = 6


@pytest.fixture
def pair(gateway_process: StartGateway) -> Iterator[tuple[GatewayProcess, GatewayProcess]]:
    """Two gateways serving the same sensor; a stopped one is let go on again before teardown."""
    first, second = gateway_process(SENSOR), gateway_process(SENSOR)
    yield first, second
    for gw in (first, second):
        if gw.proc.poll() is None:
            os.kill(gw.proc.pid, signal.SIGCONT)


async def _resumed_listen(client: AsyncClient, fault: Callable[[], None]) -> tuple[float, list[Event]]:
    """Listen to thermo's readings with ``resume=True``, apply ``fault`` once events flow, then read
    until AFTER events followed the first gap; the seconds from the fault to that gap, and every
    event after the fault."""
    events = client.listen("thermo", "data", resume=True)
    try:
        async with asyncio.timeout(60):
            first = await anext(events)
            assert not first.gap
            fault()
            faulted = time.monotonic()
            seen: list[Event] = []
            recovered = 0.0
            async for event in events:
                seen.append(event)
                if event.gap and not recovered:
                    recovered = time.monotonic() - faulted
                if recovered and _after_gap(seen) >= AFTER:
                    return recovered, seen
    finally:
        await events.aclose()
    raise AssertionError("the Listen ended")


def _after_gap(seen: list[Event]) -> int:
    gaps = [i for i, e in enumerate(seen) if e.gap]
    return len(seen) - gaps[0] - 1 if gaps else 0


def _exactly_one_gap(seen: list[Event]) -> None:
    assert [e.gap for e in seen].count(True) == 1, [(e.sequence, e.gap) for e in seen]


async def test_a_resumed_listen_moves_to_the_second_gateway_when_the_first_is_killed(
    pair: tuple[GatewayProcess, GatewayProcess],
) -> None:
    first, second = pair
    async with AsyncClient([first.address, second.address]) as client:
        took, seen = await _resumed_listen(client, first.proc.kill)
        assert client.target == second.address
    _exactly_one_gap(seen)
    print(f"a resumed Listen was back through the second gateway {took:.2f} s after SIGKILL")
    assert took < RECOVERY_BOUND


async def test_a_resumed_listen_leaves_a_frozen_gateway_when_its_keepalive_goes_unanswered(
    pair: tuple[GatewayProcess, GatewayProcess],
) -> None:
    first, second = pair
    async with AsyncClient([first.address, second.address]) as client:
        took, seen = await _resumed_listen(client, lambda: os.kill(first.proc.pid, signal.SIGSTOP))
        assert client.target == second.address
    _exactly_one_gap(seen)
    print(f"a resumed Listen was back through the second gateway {took:.2f} s after SIGSTOP")
    assert took < RECOVERY_BOUND


async def test_one_grpc_name_for_both_gateways_fails_over_as_well(
    pair: tuple[GatewayProcess, GatewayProcess],
) -> None:
    # One target that gRPC itself resolves to two addresses, as dns:///gateways:50051 would.
    first, second = pair
    async with AsyncClient(f"ipv4:{first.address},{second.address}") as client:
        took, seen = await _resumed_listen(client, first.proc.kill)
        assert await client.get("thermo", "rate_hz")
    _exactly_one_gap(seen)
    assert took < RECOVERY_BOUND


def test_the_blocking_client_fails_over_too(pair: tuple[GatewayProcess, GatewayProcess]) -> None:
    first, second = pair
    with Client(f"{first.address},{second.address}") as client:
        events = client.listen("thermo", "data", resume=True)
        try:
            assert not next(events).gap
            first.proc.kill()
            killed = time.monotonic()
            seen = [next(events) for _ in range(AFTER)]
        finally:
            events.close()
        assert client.target == second.address
    _exactly_one_gap(seen)
    assert time.monotonic() - killed < RECOVERY_BOUND + 5.0


async def test_a_get_is_answered_by_the_second_gateway_when_the_first_is_dead(
    pair: tuple[GatewayProcess, GatewayProcess],
) -> None:
    first, second = pair
    async with AsyncClient([first.address, second.address], timeout=10) as client:
        assert await client.get("thermo", "rate_hz")
        assert client.target == first.address
        first.proc.kill()
        first.proc.wait(5)
        started = time.monotonic()
        assert await client.get("thermo", "rate_hz")
        assert client.target == second.address
        assert time.monotonic() - started < 5.0
        # A Set goes to the survivor too, from now on.
        assert await client.set("thermo", "rate_hz", "12") == "12"
        assert await client.get("thermo", "rate_hz") == "12"


async def test_a_get_leaves_a_frozen_gateway_for_the_next(
    pair: tuple[GatewayProcess, GatewayProcess],
) -> None:
    first, second = pair
    async with AsyncClient([first.address, second.address], timeout=10) as client:
        assert await client.get("thermo", "rate_hz")
        os.kill(first.proc.pid, signal.SIGSTOP)
        started = time.monotonic()
        assert await client.get("thermo", "rate_hz")
        took = time.monotonic() - started
        assert client.target == second.address
    print(f"a Get through a frozen gateway answered by the next {took:.2f} s after")
    assert took < 8.0


async def test_a_quiet_listen_outlives_the_keepalive_pings_that_watch_its_gateway(
    gateway_process: StartGateway,
) -> None:
    # grpc's default server policy sends a client that pings a quiet stream every second away
    # ("too many pings") after three pings; the gateway accepts them.
    gw = gateway_process(SENSOR)
    async with AsyncClient(gw.address, keepalive=0.5) as client:
        events = client.listen("thermo", "rate_hz", updates_only=True, resume=True)
        try:
            waiting = asyncio.ensure_future(anext(events))
            await asyncio.sleep(5.0)
            assert not waiting.done()
            await client.set("thermo", "rate_hz", "7")
            async with asyncio.timeout(10):
                event = await waiting
        finally:
            await events.aclose()
    assert (event.value, event.gap, event.sequence) == ("7", False, 1)
    assert "too many pings" not in gw.output.lower()


async def test_a_device_away_behind_the_gateway_is_its_answer_and_moves_nothing(
    gateway_process: StartGateway,
) -> None:
    gw = gateway_process(f"""
        [[services]]
        name = "away"
        url = "tcp://127.0.0.1:{free_port()}"
        """)
    other = f"127.0.0.1:{free_port()}"
    async with AsyncClient([gw.address, other]) as client:
        with pytest.raises(Unavailable) as raised:
            await client.get("away", "location")
        assert not isinstance(raised.value, GatewayUnreachable)
        assert "away" in str(raised.value)
        assert client.target == gw.address


async def test_a_session_opened_after_its_gateway_died_goes_to_the_next(
    pair: tuple[GatewayProcess, GatewayProcess],
) -> None:
    first, second = pair
    async with AsyncClient([first.address, second.address]) as client:
        async with client.session() as session:
            assert await session.get("thermo", "rate_hz")
            first.proc.kill()
            with pytest.raises(Unavailable):
                async with asyncio.timeout(10):
                    while True:
                        await session.get("thermo", "rate_hz")
        assert client.target == second.address
        async with client.session() as again:
            assert await again.get("thermo", "rate_hz")


async def test_a_gateway_that_accepts_connections_but_never_answers_is_left_within_the_connect_limit(
    pair: tuple[GatewayProcess, GatewayProcess],
) -> None:
    # What a frozen gateway's kernel does for a new connection: the TCP handshake completes (the
    # listening socket's backlog), the HTTP/2 one never does.
    _, second = pair
    with socket.socket() as mute:
        mute.bind(("127.0.0.1", 0))
        mute.listen(8)
        silent = f"127.0.0.1:{mute.getsockname()[1]}"
        async with AsyncClient([silent, second.address], timeout=10) as client:
            started = time.monotonic()
            assert await client.get("thermo", "rate_hz")
            took = time.monotonic() - started
            assert client.target == second.address
    assert took < 2 * 2 * DEFAULT_KEEPALIVE + 2.0, took


async def test_a_listen_raises_naming_every_gateway_once_none_answers_within_the_limit(
    pair: tuple[GatewayProcess, GatewayProcess],
) -> None:
    first, second = pair
    limit = 3.0
    async with AsyncClient([first.address, second.address], failover_limit=limit) as client:
        events = client.listen("thermo", "data", resume=True)
        try:
            await anext(events)
            first.proc.kill()
            second.proc.kill()
            killed = time.monotonic()
            with pytest.raises(GatewayUnreachable) as raised:
                async with asyncio.timeout(limit + 20):
                    async for _ in events:
                        pass
            took = time.monotonic() - killed
        finally:
            await events.aclose()
    assert first.address in str(raised.value) and second.address in str(raised.value)
    assert raised.value.tried == (first.address, second.address)
    assert limit <= took < limit + 10.0


async def test_a_get_raises_naming_every_gateway_when_none_answers() -> None:
    dead = [f"127.0.0.1:{free_port()}", f"127.0.0.1:{free_port()}"]
    async with AsyncClient(dead, timeout=5) as client:
        with pytest.raises(GatewayUnreachable) as raised:
            await client.get("thermo", "rate_hz")
    assert raised.value.tried == tuple(dead)
    assert all(address in str(raised.value) for address in dead)


def test_psctl_takes_several_gateways_and_uses_the_one_that_answers(
    pair: tuple[GatewayProcess, GatewayProcess],
) -> None:
    _, second = pair
    dead = f"127.0.0.1:{free_port()}"
    done = psctl(f"{dead},{second.address}", "get", "thermo", "rate_hz")
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip()
    listened = psctl(f"{dead},{second.address}", "listen", "thermo", "data", "--count", "2", "--resume")
    assert listened.returncode == 0, listened.stderr
    assert len(listened.stdout.splitlines()) == 2
    other = f"127.0.0.1:{free_port()}"
    failed = psctl(f"{dead},{other}", "get", "thermo", "rate_hz")
    assert failed.returncode == 3, failed
    assert dead in failed.stderr and other in failed.stderr


def test_psctl_says_each_move_in_one_line_and_none_when_it_gives_up(
    pair: tuple[GatewayProcess, GatewayProcess],
) -> None:
    _, second = pair
    dead = f"127.0.0.1:{free_port()}"
    listen = ("listen", "thermo", "data", "--count", "1", "--resume")
    listened = psctl(f"{dead},{second.address}", *listen, "--keepalive", "2", "--failover-limit", "10")
    assert listened.returncode == 0, listened.stderr
    (move,) = listened.stderr.splitlines()  # one line for the one move
    assert f" at {dead}; resuming at {second.address} in 0.0 s" in move, move

    other = f"127.0.0.1:{free_port()}"
    got = psctl(f"{dead},{other}", "get", "thermo", "rate_hz")
    assert got.returncode == 3, got
    move, error = got.stderr.splitlines()  # dead to other; none back to dead when it gives up
    assert move.startswith(f"gateway {dead} failed") and move.endswith(f"moving to {other}"), move
    assert error.startswith("error: UNAVAILABLE: no gateway answered") and error.endswith(" [thermo rate_hz]")

    gave_up = psctl(f"{dead},{other}", "listen", "thermo", "data", "--resume", "--failover-limit", "0.5")
    assert gave_up.returncode == 3, gave_up
    *moves, error = gave_up.stderr.splitlines()
    assert error.startswith("error: UNAVAILABLE: no gateway answered within 0.5 s"), error
    assert moves and all(" resuming at " in line for line in moves), moves
    assert not any("moving to" in line for line in gave_up.stderr.splitlines())


# --- a cluster on etcd -------------------------------------------------------------------------


@pytest.fixture
async def cluster_with_a_device(
    etcd_server: Callable[..., EtcdServer], tmp_path: Path
) -> AsyncIterator[tuple[GatewayProcess, GatewayProcess]]:
    """Gateways ``gw-a`` and ``gw-b`` on one etcd; a sensor device ``thermo`` owned by ``gw-b``."""
    etcd = etcd_server()
    configs = {name: cluster_config(etcd, name, lease=LEASE) for name in ("gw-a", "gw-b")}
    with running_gateways(tmp_path, configs) as named:
        gateways = list(named.values())
        with tcp_device("--service", "sim-sensor", "--name", "thermo") as (host, port):
            async with AsyncClient(gateways[1].address) as owner:
                await owner.set("registry", "services.thermo", f"tcp://{host}:{port}")
            async with AsyncClient(gateways[0].address) as other:
                await eventually(
                    lambda: other.get("thermo", "rate_hz"),
                    within=20.0,
                    retry_on=(PropertyServiceError,),
                    what="gw-a reaches thermo",
                )
            yield gateways[0], gateways[1]


@pytest.mark.parametrize("fault", [signal.SIGKILL, signal.SIGSTOP], ids=["killed", "frozen"])
async def test_a_listen_through_a_cluster_gateway_resumes_on_a_survivor_within_the_lease_plus_2_s(
    cluster_with_a_device: tuple[GatewayProcess, GatewayProcess], fault: signal.Signals
) -> None:
    used, survivor = cluster_with_a_device
    async with AsyncClient([used.address, survivor.address]) as client:
        took, seen = await _resumed_listen(client, lambda: os.kill(used.proc.pid, fault))
        assert client.target == survivor.address
    _exactly_one_gap(seen)
    print(f"a resumed Listen through a cluster was back {took:.2f} s after {fault.name} (lease {LEASE:g} s)")
    assert took < RECOVERY_BOUND
