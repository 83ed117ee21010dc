"""Registry and group through a real gateway, TCP devices and the gRPC client: find, drive, a dead device.

A gateway serves the registry and a group ``swarm`` (every mobile robot the
registry knows). Three simulated robots run as device processes on TCP and
are registered by Set; the registry finds them by type and location; the
group drives them to a target in a circle; one device is killed: it goes
down, the group names it, the other two still move.
"""

from __future__ import annotations

import re
from collections.abc import Awaitable, Callable, Iterator
from contextlib import ExitStack, contextmanager
from typing import TypeVar

import grpc
import numpy as np
import pytest
from line_device_support import device_process
from support import waiting

from clients.aio import AsyncClient
from clients.errors import PropertyServiceError
from gateway.app import Gateway
from gateway.config import parse_config
from services.apps.formations import formation_targets
from services.apps.group import Group
from services.apps.registry import RegistryService
from services.kernel.core import LocalService

T = TypeVar("T")

#: Seconds each step of the story may take: the robots drive across the map.
STEP_WAIT = 20.0

TARGET = "<marker><location>(10 10 0)</location></marker>"


@contextmanager
def robot_device(name: str, x: float, y: float) -> Iterator[tuple[int, object]]:
    """A simulated robot served on the line protocol over TCP by its own process; yields (port, process)."""
    with device_process(
        "--service", "sim-robot", "--name", name, "--tcp", "127.0.0.1:0",
        "--option", f"start=[{x}, {y}]", "--option", "speed=20", "--option", "tick_hz=50",
    ) as (proc, first):  # fmt: skip
        match = re.fullmatch(r"listening on (.+):(\d+)", first)
        assert match, first
        yield int(match.group(2)), proc


async def eventually(probe: Callable[[], Awaitable[T]], ok: Callable[[T], bool]) -> T:
    """Ask ``probe`` until ``ok`` holds, at most one story step."""
    return await waiting.eventually(probe, ok, within=STEP_WAIT)


def near(v: np.ndarray, p: np.ndarray, tol: float = 1e-3) -> bool:
    return bool(np.allclose(v[: p.size], p, atol=tol))


@pytest.mark.timeout(90)
async def test_register_find_drive_as_a_group_and_survive_a_dead_device() -> None:
    config = parse_config({"gateway": {"listen": "127.0.0.1:0"}})
    with ExitStack() as devices:
        ports, procs = {}, {}
        for name, (x, y) in {"scout1": (4, 5), "scout2": (6, 5), "scout3": (5, 6)}.items():
            ports[name], procs[name] = devices.enter_context(robot_device(name, x, y))
        far_port, _ = devices.enter_context(robot_device("far", 40, 40))

        async with Gateway(config) as gw, AsyncClient(gw.address, timeout=15) as client:
            swarm = LocalService(
                Group(directory=gw.router, query={"type": "mobile_robot"}, member_timeout=2.0)
            )
            await swarm.start()
            gw.router.add("swarm", swarm)

            # Register three devices (and a fourth far away) by Set on the registry.
            for name, port in [*ports.items(), ("far", far_port)]:
                url = f"tcp://127.0.0.1:{port}"
                assert await client.set("registry", f"services.{name}", url, type="mobile_robot") == url
            assert set(await client.get_names("registry", "services")) >= {
                "scout1",
                "scout2",
                "scout3",
                "far",
            }
            assert await client.get("registry", "services.scout1.state") == "up"
            assert await client.get("scout1", "location.x") == "4"

            # Bad registrations change nothing.
            with pytest.raises(PropertyServiceError) as info:
                await client.set("registry", "services.scout1", f"tcp://127.0.0.1:{far_port}")
            assert info.value.code is grpc.StatusCode.ALREADY_EXISTS
            with pytest.raises(PropertyServiceError) as info:
                await client.set("registry", "services.ghost", "tcp://127.0.0.1")
            assert info.value.code is grpc.StatusCode.INVALID_ARGUMENT

            # Find them by type and location.
            found = await eventually(
                lambda: client.get_names("registry", "find", type="mobile_robot", near="(5 5 0)", radius="3"),
                lambda names: len(names) == 3,
            )
            assert sorted(found) == ["scout1", "scout2", "scout3"]
            with pytest.raises(PropertyServiceError) as info:
                await client.get("registry", "find", colour="red")
            assert info.value.code is grpc.StatusCode.INVALID_ARGUMENT

            # The group follows the registry; drive the near three in a circle.
            await eventually(lambda: client.get_names("swarm", "robots"), lambda names: len(names) == 4)
            await client.set("swarm", "subgroup", "near", members=f"({' '.join(found)})")
            assert sorted(await client.get_names("swarm", "subgroups.near.robots")) == found
            accepted = await client.set(
                "swarm", "subgroups.near.behaviors.moveto", TARGET, formation="circle", spacing="2"
            )
            assert accepted == "(scout1 scout2 scout3)"
            places = formation_targets(found, [10, 10, 0], "circle", 2.0)
            for name, place in places.items():
                await eventually(
                    lambda n=name: client.get_vector(n, "location"), lambda v, p=place: near(v, p)
                )
            centre = await eventually(
                lambda: client.get_vector("swarm", "subgroups.near.location"),
                lambda v: near(v, np.array([10.0, 10.0, 0.0])),
            )
            assert near(centre, np.array([10.0, 10.0, 0.0]))

            # Kill one device: it goes down; the group reports it; the others still move.
            procs["scout3"].terminate()  # type: ignore[attr-defined]
            procs["scout3"].wait(10)  # type: ignore[attr-defined]
            registry = gw.router.backend("registry")
            assert isinstance(registry, RegistryService)
            # A device heard from a moment ago passes a check until its proxy sees the connection close.
            proxy = gw.router.lookup("scout3")

            async def connected() -> bool:
                return bool(getattr(proxy, "connected", False))

            await eventually(connected, lambda up: not up)
            for _ in range(registry.registry.misses):
                await registry.registry.check_all()
            assert await client.get("registry", "services.scout3.state") == "down"
            assert await client.get_names("registry", "find", state="down") == ["scout3"]

            with pytest.raises(PropertyServiceError) as info:
                await client.set(
                    "swarm", "subgroups.near.behaviors.moveto",
                    "<marker><location>(0 0 0)</location></marker>", formation="line",
                )  # fmt: skip
            assert info.value.code in (grpc.StatusCode.UNAVAILABLE, grpc.StatusCode.DEADLINE_EXCEEDED)
            assert "failed on 1 of 3 members (the other 2 acted): scout3:" in info.value.message
            assert "scout3" in await client.get("swarm", "subgroups.near.failed")
            line = formation_targets(found, [0, 0, 0], "line", 1.0)
            for name in ("scout1", "scout2"):
                await eventually(
                    lambda n=name: client.get_vector(n, "location"), lambda v, p=line[name]: near(v, p)
                )
