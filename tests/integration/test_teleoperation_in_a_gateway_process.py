"""Teleoperation through a real demo gateway process, with ``psctl`` and the SDK as a user would.

The demo serves ``scout1`` and ``scout2`` in-process, ``rover1`` and ``rover2``
as device processes behind the TCP and serial proxies, and ``swarm``, a group
of every mobile robot. Robots have the defaults: ``max_speed`` 1 m/s,
``max_turn_rate`` 2 rad/s, ``velocity_timeout`` 0.5 s. Every test leaves the
robots standing.
"""

from __future__ import annotations

import asyncio
import sys
from collections.abc import AsyncIterator
from typing import Any

import numpy as np
import pytest
from support.waiting import eventually

from clients.aio import AsyncClient, Mark

PSCTL = [sys.executable, "-m", "clients.cli"]
ZERO = "(0 0 0 0 0 0)"
MEMBERS = ["rover1", "rover2", "scout1", "scout2"]

pytestmark = pytest.mark.timeout(90)


async def psctl(target: str, *args: str) -> tuple[int, str, str]:
    proc = await asyncio.create_subprocess_exec(
        *PSCTL, "-t", target, *args, stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE
    )
    out, err = await asyncio.wait_for(proc.communicate(), timeout=60)
    assert proc.returncode is not None
    return proc.returncode, out.decode(), err.decode()


async def ok(target: str, *args: str) -> str:
    code, out, err = await psctl(target, *args)
    assert code == 0, f"psctl {' '.join(args)} exited {code}: {err}"
    return out.strip()


@pytest.fixture
async def client(demo_gateway: Any) -> AsyncIterator[AsyncClient]:
    async with AsyncClient(demo_gateway.address) as c:
        yield c


async def standing(client: AsyncClient, service: str) -> None:
    await eventually(lambda: client.get(service, "velocity"), lambda v: v == ZERO, what=f"{service} stands")


async def test_a_velocity_set_is_clipped_and_the_robot_stops_when_not_renewed(
    demo_gateway: Any, client: AsyncClient
) -> None:
    heard: list[str] = []
    synced, stopped = asyncio.Event(), asyncio.Event()

    async def listen() -> None:
        async for item in client.listen("scout1", "velocity", updates_only=True, marks=True):
            if isinstance(item, Mark):
                synced.set()  # the Listen is in place: every change from now on is heard
                continue
            heard.append(item.value)
            if item.value == ZERO:
                stopped.set()

    start = await client.get_vector("scout1", "location")
    listening = asyncio.create_task(listen())
    try:
        await asyncio.wait_for(synced.wait(), timeout=10)
        # 5 m/s and 3 rad/s are beyond the limits: the answer is what the robot was given.
        assert await ok(demo_gateway.address, "set", "scout1", "velocity", "(5 0 0 0 0 3)") == "(1 0 0 0 0 2)"
        await asyncio.wait_for(stopped.wait(), timeout=10)  # no renewal: it stops by itself
    finally:
        listening.cancel()
        await asyncio.gather(listening, return_exceptions=True)
    assert heard[0] == "(1 0 0 0 0 2)"
    assert heard[-1] == ZERO
    moved = await client.get_vector("scout1", "location")
    assert 0.0 < moved[0] - start[0] <= 0.5 + 1e-6  # 1 m/s for at most the 0.5 s timeout
    assert await client.get("scout1", "velocity") == ZERO


async def test_repeated_sets_teleoperate_a_robot(client: AsyncClient) -> None:
    start = await client.get_vector("scout1", "location")
    for _ in range(10):  # a joystick sending the same command ten times a second
        assert await client.set("scout1", "velocity", np.array([0.0, 0.5])) == "(0 0.5 0 0 0 0)"
        await asyncio.sleep(0.1)
    moved = await client.get_vector("scout1", "location")
    assert moved[1] > start[1]
    assert moved[0] == pytest.approx(start[0])
    await standing(client, "scout1")


async def test_moveto_and_velocity_cancel_each_other(demo_gateway: Any, client: AsyncClient) -> None:
    address = demo_gateway.address
    await ok(address, "set", "scout2", "velocity_timeout", "30")  # the command would hold long
    try:
        await ok(address, "set", "scout2", "velocity", "(0 0.5)")
        here = await client.get_vector("scout2", "location")
        target = here[:2] + np.array([0.3, 0.0])
        marker = f"<marker><location>({target[0]} {target[1]})</location></marker>"
        await ok(address, "set", "scout2", "behaviors.moveto", marker)
        # moveto took over: the robot arrives exactly and stays (the command did not come back).
        arrived = await eventually(
            lambda: client.get_vector("scout2", "location"),
            lambda v: bool(np.allclose(v[:2], target, atol=1e-9)),
            what="scout2 arrives",
        )
        await standing(client, "scout2")
        assert np.allclose((await client.get_vector("scout2", "location"))[:2], arrived[:2])

        await ok(address, "set", "scout2", "behaviors.moveto", "<marker><location>(1 40)</location></marker>")
        assert await ok(address, "set", "scout2", "velocity", "(0 0 0 0 0 0.5)") == "(0 0 0 0 0 0.5)"
        still = (await client.get_vector("scout2", "location"))[:3]
        await asyncio.sleep(0.3)
        # Turning in place: the moveto was dropped.
        assert np.allclose((await client.get_vector("scout2", "location"))[:3], still)
        assert await ok(address, "set", "scout2", "behaviors.stop", "") == ""
        assert await client.get("scout2", "velocity") == ZERO
    finally:
        await ok(address, "set", "scout2", "velocity_timeout", "0.5")
        await ok(address, "set", "scout2", "behaviors.stop", "")


async def test_psctl_set_swarm_velocity_moves_every_member(demo_gateway: Any, client: AsyncClient) -> None:
    address = demo_gateway.address
    await eventually(lambda: client.get_names("swarm", "robots"), lambda names: sorted(names) == MEMBERS)
    before = {name: await client.get_vector(name, "location") for name in MEMBERS}
    out = await ok(address, "set", "swarm", "velocity", "(0.2 0 0 0 0 0)")
    assert sorted(out.strip("()").split()) == MEMBERS
    for name in MEMBERS:  # the in-process robots and the ones behind the TCP and serial proxies
        await eventually(
            lambda name=name: client.get_vector(name, "location"),
            lambda v, name=name: v[0] > before[name][0],
            what=f"{name} moves along x",
        )
    # Beyond the limits: each member clips the command to its own, and still moves.
    for name in MEMBERS:
        await standing(client, name)
    before = {name: await client.get_vector(name, "location") for name in MEMBERS}
    out = await ok(address, "set", "swarm", "velocity", "(5 5)")
    assert sorted(out.strip("()").split()) == MEMBERS
    for name in MEMBERS:
        await standing(client, name)
        step = (await client.get_vector(name, "location"))[:2] - before[name][:2]
        assert step[0] > 0 and step[0] == pytest.approx(step[1])  # along the diagonal
        assert float(np.linalg.norm(step)) <= 0.5 + 1e-6  # at most 1 m/s for the 0.5 s timeout


async def test_behaviors_stop_on_a_robot_and_on_the_group(demo_gateway: Any, client: AsyncClient) -> None:
    address = demo_gateway.address
    await eventually(lambda: client.get_names("swarm", "robots"), lambda names: sorted(names) == MEMBERS)
    await ok(address, "set", "swarm", "behaviors.moveto", "<marker><location>(0 30)</location></marker>")
    out = await ok(address, "set", "swarm", "behaviors.stop", "")
    assert sorted(out.strip("()").split()) == MEMBERS
    for name in MEMBERS:
        assert await client.get(name, "velocity") == ZERO
    code, _, err = await psctl(address, "set", "swarm", "behaviors.halt", "")
    assert code == 1 and "behaviors.halt" in err  # one name for stopping: behaviors.stop

    await ok(address, "set", "rover1", "velocity", "(0 -1)")
    assert await ok(address, "set", "rover1", "behaviors.stop", "") == ""
    assert await client.get("rover1", "velocity") == ZERO
