"""Faults injected into a real cluster, with a client at work: what each client sees, and how soon.

Each test starts etcd (``tests/support/etcd.py``) and three gateway processes (``gw-a``, ``gw-b``,
``gw-c``) with a short lease, and a real line-protocol device process named ``counter`` owned by
``gw-a``: registered by a Set on ``gw-a`` (a TCP device, which a survivor takes over), or dialled
in to ``gw-a``'s line listener (a device that moves to another gateway by itself). A client Sets
``counter.rate_hz`` to a rising value ten times a second through a survivor, and a Listen on it is
open through each survivor. Then ``gw-a`` is SIGKILLed, SIGSTOPped past its lease (and SIGCONTed),
or SIGTERMed, and each test checks what must hold:

* no acknowledged Set is lost: once the cluster has recovered, every gateway reads the last value
  acknowledged, and every Listen ends on it;
* every Listen goes on through the fault with exactly one event marked ``gap``, and none marked
  ``removed``; its values never go back;
* the service reads UNAVAILABLE while it moves, never NOT_FOUND;
* the Sets succeed again, and every Listen has its gap, within the bound of the fault.

Each test prints its row of the table in docs/performance.md ("Faults in a cluster"). The C
library's example device, dialled in, moves off a frozen gateway too, and a licence granted on one
gateway is read on every gateway. Without the ``etcd`` command the tests skip.
"""

from __future__ import annotations

import asyncio
import os
import signal
import time
from collections.abc import AsyncIterator, Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import jwt
import pytest
from line_device_support import device_process, tcp_device
from support.c_device import CProgram, build, require
from support.cluster import running_cluster
from support.etcd import EtcdServer
from support.gateway_process import GatewayProcess
from support.waiting import eventually

from clients import AsyncClient, ClientCredentials
from clients.aio import Event
from clients.errors import NotFound, PropertyServiceError

pytestmark = [pytest.mark.slow, pytest.mark.timeout(120)]

#: Seconds of each gateway's lease: short, so that a fault is over soon (etcd's floor is ~1.5 s).
LEASE = 2.0
IDS = ("gw-a", "gw-b", "gw-c")
SECRET = "a shared secret of the cluster, long enough for HS256"
SURVIVORS = ("gw-b", "gw-c")
#: Seconds between two Sets of the counter.
SET_EVERY = 0.1
#: Seconds a device that dialled in waits for an answer from a silent gateway (its keep-alive).
DEVICE_KEEPALIVE = ("--keepalive", "1", "--keepalive-timeout", "2")


@dataclass
class Cluster:
    """Three gateways on one etcd."""

    etcd: EtcdServer
    gateways: dict[str, GatewayProcess]
    lines: dict[str, str]


@pytest.fixture
def cluster(etcd_server: Callable[..., EtcdServer], tmp_path: Path) -> Iterator[Cluster]:
    etcd = etcd_server()
    with running_cluster(etcd, tmp_path, IDS, lease=LEASE, secret=SECRET) as (gateways, lines):
        yield Cluster(etcd, gateways, lines)


@pytest.fixture
async def clients(cluster: Cluster) -> AsyncIterator[dict[str, AsyncClient]]:
    opened = {gateway: AsyncClient(cluster.gateways[gateway].address, timeout=2.0) for gateway in IDS}
    yield opened
    for client in opened.values():
        await client.close()


@dataclass
class Watched:
    """A Listen on the counter through one gateway, read in the background."""

    gateway: str
    events: list[tuple[float, Event]] = field(default_factory=list)
    error: BaseException | None = None

    def gaps(self) -> list[tuple[float, Event]]:
        return [(at, event) for at, event in self.events if event.gap]

    def removals(self) -> list[Event]:
        return [event for _, event in self.events if event.removed]

    def values(self) -> list[float]:
        return [float(event.value) for _, event in self.events if not event.removed]


@dataclass
class Setter:
    """Sets the counter to a rising value every ``SET_EVERY`` seconds; remembers what was acknowledged."""

    acked: list[tuple[float, float]] = field(default_factory=list)
    failures: list[tuple[float, PropertyServiceError]] = field(default_factory=list)
    step: int = 0
    #: Set when the Setter is to stop after the Set in flight: cancelling it mid-Set would leave a
    #: value applied whose answer nobody read.
    stopping: bool = False

    def next_value(self) -> float:
        self.step += 1
        return round(0.1 + self.step / 1000, 3)  # 0.101, 0.102, ...: within rate_hz's range

    def may_hold(self) -> set[float]:
        """What the counter may read once the Setter stops: its last acknowledged value, or the last
        one it sent (refused, e.g. DEADLINE_EXCEEDED, after it was applied)."""
        last = self.acked[-1][1] if self.acked else None
        return {v for v in (last, round(0.1 + self.step / 1000, 3)) if v is not None}

    def acked_after(self, moment: float) -> float | None:
        return next((at for at, _ in self.acked if at > moment), None)


async def _set_forever(client: AsyncClient, setter: Setter) -> None:
    while not setter.stopping:
        value = setter.next_value()
        try:
            await client.set("counter", "rate_hz", str(value))
        except PropertyServiceError as exc:
            setter.failures.append((time.monotonic(), exc))
        else:
            setter.acked.append((time.monotonic(), value))
        await asyncio.sleep(SET_EVERY)


async def _read_forever(client: AsyncClient, watched: Watched) -> None:
    try:
        async for event in client.listen("counter", "rate_hz"):
            watched.events.append((time.monotonic(), event))
    except (PropertyServiceError, asyncio.CancelledError) as exc:
        watched.error = exc
        raise


@dataclass
class Trial:
    """The client at work: a Setter through one gateway, a Listen through each of ``through``."""

    setter: Setter
    watched: dict[str, Watched]
    tasks: list[asyncio.Task[None]]

    async def stop(self) -> None:
        for task in self.tasks:
            task.cancel()
        await asyncio.gather(*self.tasks, return_exceptions=True)


async def _start_trial(clients: dict[str, AsyncClient], setter_on: str, through: tuple[str, ...]) -> Trial:
    setter = Setter()
    watched = {gateway: Watched(gateway) for gateway in through}
    tasks = [asyncio.create_task(_set_forever(clients[setter_on], setter))]
    tasks += [asyncio.create_task(_read_forever(clients[g], watched[g])) for g in through]
    # Running: Sets acknowledged and every Listen hearing them.
    await eventually(lambda: _ready(setter, watched), bool, within=15.0, what="the client at work")
    return Trial(setter, watched, tasks)


async def _ready(setter: Setter, watched: dict[str, Watched]) -> bool:
    if len(setter.acked) < 3:
        return False
    first = setter.acked[0][1]
    return all(any(v > first for v in w.values()) for w in watched.values())


async def _probe_forever(client: AsyncClient, seen: list[str]) -> None:
    """Get the counter again and again through one gateway; remember each error's kind."""
    while True:
        try:
            await client.get("counter", "rate_hz")
        except PropertyServiceError as exc:
            seen.append(f"{type(exc).__name__}: {exc}")
        await asyncio.sleep(0.05)


async def _last_value(watched: Watched) -> float | None:
    values = watched.values()
    return values[-1] if values else None


async def _recovered(trial: Trial, fault_at: float) -> bool:
    return trial.setter.acked_after(fault_at) is not None and all(
        any(at > fault_at for at, _ in w.gaps()) for w in trial.watched.values()
    )


async def _settle_and_check(
    clients: dict[str, AsyncClient], trial: Trial, fault_at: float, bound: float, fault: str
) -> None:
    """Wait for the recovery, stop the client, and check what must hold (module docstring)."""
    await eventually(
        lambda: _recovered(trial, fault_at), bool, within=bound + 10.0, what=f"recovery from {fault}"
    )
    await asyncio.sleep(1.0)  # a few more Sets after the recovery
    trial.setter.stopping = True  # the Setter stops after its Set in flight; the Listens hear its last Sets
    await trial.tasks[0]
    setter = trial.setter
    last = setter.acked[-1][1]
    for gateway in SURVIVORS:
        value = await eventually(
            lambda g=gateway: clients[g].get_number("counter", "rate_hz"),
            lambda v: v >= last,
            retry_on=(PropertyServiceError,),
            what=f"{gateway} reads the last acknowledged value",
        )
        assert value in setter.may_hold(), f"{gateway} reads {value}, the last acknowledged Set was {last}"
    for w in trial.watched.values():
        await eventually(
            lambda w=w: _last_value(w),
            lambda v: v in setter.may_hold(),
            what=f"the Listen through {w.gateway} hears {last}",
        )
    await trial.stop()
    sets_back = (setter.acked_after(fault_at) or 0) - fault_at
    listens_back = {
        g: next(at for at, _ in w.gaps() if at > fault_at) - fault_at for g, w in trial.watched.items()
    }
    failed = sorted({type(exc).__name__ for at, exc in setter.failures if at > fault_at})
    seen = {
        g: f"{len(w.gaps())} gap, {len(w.removals())} removed, {len(w.events)} events"
        for g, w in trial.watched.items()
    }
    print(
        f"\n{fault}: Sets acknowledged again after {sets_back:.2f} s; Listens resumed (gap) after "
        + ", ".join(f"{g} {s:.2f} s" for g, s in listens_back.items())
        + f"; lost acknowledged Sets: 0 of {len(setter.acked)}; Sets refused meanwhile: "
        + f"{len([1 for at, _ in setter.failures if at > fault_at])} ({', '.join(failed) or 'none'}); "
        + "; ".join(f"{g}: {s}" for g, s in seen.items())
    )
    for gateway, w in trial.watched.items():
        assert w.error is None or isinstance(w.error, asyncio.CancelledError), f"{gateway}: {w.error}"
        assert not w.removals(), f"the Listen through {gateway} heard 'removed': {w.removals()}"
        gaps = w.gaps()
        assert len(gaps) == 1, f"the Listen through {gateway} heard {len(gaps)} gaps: {gaps}"
        values = w.values()
        assert values == sorted(values), f"the Listen through {gateway} went back: {values}"
        assert listens_back[gateway] < bound, (
            f"{gateway}: resumed {listens_back[gateway]:.2f} s after {fault}"
        )
    assert not [exc for _, exc in setter.failures if isinstance(exc, NotFound)], setter.failures
    assert sets_back < bound, f"Sets acknowledged again {sets_back:.2f} s after {fault}"


def _freeze(gateway: GatewayProcess) -> None:
    os.kill(gateway.proc.pid, signal.SIGSTOP)


def _thaw(gateway: GatewayProcess) -> None:
    os.kill(gateway.proc.pid, signal.SIGCONT)


async def _owned_by(clients: dict[str, AsyncClient], owner: str) -> None:
    for gateway in IDS:
        await eventually(
            lambda g=gateway: clients[g].get("registry", "services.counter.owner"),
            lambda o: o == owner,
            retry_on=(PropertyServiceError,),
            what=f"{gateway} reads counter owned by {owner}",
        )
        await eventually(
            lambda g=gateway: clients[g].get("registry", "services.counter.state"),
            lambda s: s == "up",
            retry_on=(PropertyServiceError,),
            what=f"{gateway} reads counter up",
        )


@pytest.mark.parametrize(
    "fault",
    ["SIGKILL", "SIGSTOP past the lease", "SIGTERM"],
)
async def test_a_client_loses_no_acknowledged_set_and_each_listen_one_gap_when_the_owner_fails(
    cluster: Cluster, clients: dict[str, AsyncClient], fault: str
) -> None:
    with tcp_device("--service", "sim-sensor", "--name", "counter", "--option", "rate_hz=0.1") as address:
        await clients["gw-a"].set("registry", "services.counter", f"tcp://{address[0]}:{address[1]}")
        await _owned_by(clients, "gw-a")
        trial = await _start_trial(clients, "gw-b", SURVIVORS)
        owner = cluster.gateways["gw-a"]
        fault_at = time.monotonic()
        if fault == "SIGKILL":
            owner.proc.kill()
        elif fault == "SIGTERM":
            owner.proc.terminate()
        else:
            _freeze(owner)
        try:
            await _settle_and_check(clients, trial, fault_at, LEASE + 5.0, fault)
        finally:
            await trial.stop()
        if fault.startswith("SIGSTOP"):
            # Thawed, the frozen owner finds its lease gone and the counter owned by a survivor: it
            # forwards to it from then on (no split brain), and reads the last value too.
            _thaw(owner)
            new_owner = await clients["gw-b"].get("registry", "services.counter.owner")
            assert new_owner in SURVIVORS
            await eventually(
                lambda: clients["gw-a"].get("registry", "services.counter.owner"),
                lambda o: o == new_owner,
                retry_on=(PropertyServiceError,),
                within=15.0,
                what="the thawed gateway reads the new owner",
            )
            assert await clients["gw-a"].get_number("counter", "rate_hz") in trial.setter.may_hold()


@pytest.mark.parametrize("fault", ["SIGKILL", "SIGSTOP past the lease"])
async def test_a_device_that_dialled_in_moves_off_a_failed_gateway_and_reads_unavailable_meanwhile(
    cluster: Cluster, clients: dict[str, AsyncClient], fault: str
) -> None:
    with device_process(
        "--service",
        "sim-sensor",
        "--name",
        "counter",
        "--option",
        "rate_hz=0.1",
        "--connect",
        cluster.lines["gw-a"],
        *DEVICE_KEEPALIVE,
    ):
        await _owned_by(clients, "gw-a")
        trial = await _start_trial(clients, "gw-b", SURVIVORS)
        probes = {g: [] for g in SURVIVORS}
        probing = [asyncio.create_task(_probe_forever(clients[g], probes[g])) for g in SURVIVORS]
        owner = cluster.gateways["gw-a"]
        fault_at = time.monotonic()
        if fault == "SIGKILL":
            owner.proc.kill()
        else:
            _freeze(owner)
        try:
            # The device notices (the connection ends, or its keep-alive PING goes unanswered), is
            # refused by the others while gw-a's lease runs, then dials in to one of them.
            await _settle_and_check(clients, trial, fault_at, 16.0, f"dial-in device, gateway {fault}")
        finally:
            await trial.stop()
            for task in probing:
                task.cancel()
            await asyncio.gather(*probing, return_exceptions=True)
        for gateway, seen in probes.items():
            assert not [s for s in seen if s.startswith("NotFound")], f"{gateway} answered {seen}"
            assert all(s.startswith(("Unavailable", "DeadlineExceeded")) for s in seen), seen
        refused = {g: len(s) for g, s in probes.items()}
        print(f"Gets refused while the device moved: {refused}, each UNAVAILABLE")
        new_owner = await clients["gw-b"].get("registry", "services.counter.owner")
        assert new_owner in SURVIVORS
        if fault.startswith("SIGSTOP"):
            _thaw(owner)
            await eventually(
                lambda: clients["gw-a"].get("registry", "services.counter.owner"),
                lambda o: o == new_owner,
                retry_on=(PropertyServiceError,),
                within=15.0,
                what="the thawed gateway reads the device's new owner",
            )
            # ... and does not take the device's keys away from the gateway it moved to.
            await asyncio.sleep(1.0)
            assert await clients["gw-c"].get("registry", "services.counter.owner") == new_owner


async def test_a_licence_granted_on_one_gateway_is_read_on_every_gateway(
    cluster: Cluster, clients: dict[str, AsyncClient]
) -> None:
    with tcp_device("--service", "sim-sensor", "--name", "counter") as address:
        await clients["gw-a"].set("registry", "services.counter", f"tcp://{address[0]}:{address[1]}")
        await _owned_by(clients, "gw-a")
        token = jwt.encode({"sub": "alice", "exp": int(time.time()) + 600}, SECRET, algorithm="HS256")
        async with AsyncClient(
            cluster.gateways["gw-b"].address, credentials=ClientCredentials(token=token)
        ) as alice:
            licence = str(await alice.set("registry", "acquire", "", service="counter", duration="30"))
            await _read_everywhere(clients, licence)
            await alice.set("registry", "release", "", licence=licence)
        for gateway in IDS:
            await eventually(
                lambda g=gateway: clients[g].get("registry", "services.counter.licence"),
                lambda held: held == "",
                what=f"{gateway} reads the licence gone",
            )
            assert licence not in await clients[gateway].get_names("registry", "licences")


async def _read_everywhere(clients: dict[str, AsyncClient], licence: str) -> None:
    """Every gateway reads ``licence`` on counter, lists it and reads the service active."""
    for gateway in IDS:
        client = clients[gateway]
        assert await eventually(
            lambda c=client: c.get("registry", "services.counter.licence"),
            lambda held: held == licence,
            what=f"{gateway} reads the licence on counter",
        )
        assert licence in await client.get_names("registry", "licences")
        assert "alice" in str(await client.get("registry", f"licences.{licence}"))
        assert await client.get("registry", "services.counter.availability") == "active"


async def test_the_c_example_device_moves_off_a_frozen_gateway(
    cluster: Cluster, clients: dict[str, AsyncClient], tmp_path: Path
) -> None:
    require("host")
    build("host", tmp_path / "c")
    program = tmp_path / "c" / "host" / "thermostat"
    keepalive = ("--keepalive", "1000", "--keepalive-timeout", "2000")
    with CProgram([str(program), "--connect", cluster.lines["gw-a"], *keepalive]):
        for gateway in IDS:
            await eventually(
                lambda g=gateway: clients[g].get("registry", "services.thermo1.owner"),
                lambda owner: owner == "gw-a",
                retry_on=(PropertyServiceError,),
                what=f"{gateway} reads the C device owned by gw-a",
            )
        frozen_at = time.monotonic()
        _freeze(cluster.gateways["gw-a"])
        seen: list[str] = []
        while True:
            assert time.monotonic() - frozen_at < 20.0, f"the C device did not move: {seen[-3:]}"
            try:
                await clients["gw-c"].get("thermo1", "temp")
                owner = await clients["gw-c"].get("registry", "services.thermo1.owner")
                if owner in SURVIVORS:
                    break
            except PropertyServiceError as exc:
                seen.append(f"{type(exc).__name__}: {exc}")
            await asyncio.sleep(0.1)
        moved = time.monotonic() - frozen_at
        print(f"\nC example device, gateway SIGSTOP: answering through gw-c again after {moved:.2f} s")
        assert not [s for s in seen if s.startswith("NotFound")], seen
