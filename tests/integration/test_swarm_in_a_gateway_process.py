"""Registry, greeting, group and a dead device, through a real gateway process.

A ``psgateway serve`` process with its line listener on, short liveness
checks and a group ``swarm`` chosen by the query ``type = mobile_robot``.
Four simulated robots run as device processes: three on TCP, registered by
a Set on the registry through gRPC; one dials the line listener and
registers by its greeting. The registry finds them by type and location, the
group drives them to a target in a circle, one device is killed by its PID:
it goes down (a Listen on ``services.*.state`` sees it), calls to it get
UNAVAILABLE, the group names it, and the other three still move.
"""

from __future__ import annotations

import asyncio
import re
import subprocess
from collections.abc import Callable
from contextlib import ExitStack
from typing import Any

import grpc
import numpy as np
import pytest
from line_device_support import device_process
from support.waiting import eventually

from clients.aio import AsyncClient
from clients.errors import PropertyServiceError
from services.apps.formations import formation_targets

WAIT = 10.0
CONFIG = """
[gateway]
line_listen = "127.0.0.1:0"

[registry]
period = 0.3
timeout = 1.0
misses = 2

[[services]]
name = "swarm"
type = "group"
options = { query = { type = "mobile_robot" }, member_timeout = 2.0 }
"""
START = {"scout1": (4, 5), "scout2": (6, 5), "scout3": (5, 6), "scout4": (5, 4)}
TARGET = "<marker><location>(10 10 0)</location></marker>"


def robot_args(name: str, *where: str) -> list[str]:
    x, y = START[name]
    return [
        "--service", "sim-robot", "--name", name, *where,
        "--option", f"start=[{x}, {y}]", "--option", "speed=20", "--option", "tick_hz=50",
    ]  # fmt: skip


def at(place: np.ndarray) -> Callable[[Any], bool]:
    return lambda v: bool(np.allclose(v[: place.size], place, atol=1e-3))


@pytest.mark.timeout(60)
async def test_the_registry_and_a_swarm_in_a_real_gateway_process(gateway_process: Any) -> None:
    gw = gateway_process(CONFIG)
    match = re.search(r"line-protocol listener on (127\.0\.0\.1:\d+)", gw.output)
    assert match, gw.output
    line_address = match.group(1)

    with ExitStack() as stack:
        procs: dict[str, subprocess.Popen[str]] = {}
        urls: dict[str, str] = {}
        for name in ("scout1", "scout2", "scout3"):
            proc, first = stack.enter_context(device_process(*robot_args(name, "--tcp", "127.0.0.1:0")))
            procs[name], urls[name] = proc, "tcp://" + first.removeprefix("listening on ")
        procs["scout4"], first = stack.enter_context(
            device_process(*robot_args("scout4", "--connect", line_address))
        )
        assert first == f"connecting to {line_address}"

        async with AsyncClient(gw.address, timeout=WAIT) as client:
            # Three register by Set through gRPC, the fourth by its greeting.
            for name, url in urls.items():
                assert await client.set("registry", f"services.{name}", url, type="mobile_robot") == url
            names = await eventually(
                lambda: client.get_names("registry", "services"), lambda n: "scout4" in n
            )
            assert set(names) == {"registry", "swarm", *START}
            assert (await client.get("registry", "services.scout4")).startswith("tcp-in://127.0.0.1:")
            assert await client.get("registry", "services.scout4.type") == "mobile_robot"

            # Find them by type and location.
            everyone = sorted(START)
            found = await eventually(
                lambda: client.get_names(
                    "registry", "find", type="mobile_robot", near="(5 5 0)", radius="1.5"
                ),
                lambda n: sorted(n) == everyone,
            )
            assert sorted(found) == everyone
            assert await client.get_names("registry", "find", near="(6 5)", radius="0.5") == ["scout2"]

            # Drive them as a group to the target, in a circle.
            await eventually(lambda: client.get_names("swarm", "robots"), lambda n: sorted(n) == everyone)
            accepted = await client.set("swarm", "behaviors.moveto", TARGET, formation="circle", spacing="2")
            assert accepted == "(scout1 scout2 scout3 scout4)"
            places = formation_targets(everyone, [10, 10, 0], "circle", 2.0)
            for name, place in places.items():
                await eventually(lambda n=name: client.get_vector(n, "location"), at(place))
            assert at(np.array([10.0, 10.0]))(
                await eventually(lambda: client.get_vector("swarm", "location"), at(np.array([10.0, 10.0])))
            )

            # Kill one device by its PID: it goes down, and a Listen on every state sees it.
            states = client.listen("registry", "services.*.state")
            first_event = await anext(states)
            procs["scout3"].terminate()
            procs["scout3"].wait(WAIT)
            async with asyncio.timeout(WAIT):
                event = first_event
                while not (event.property == "services.scout3.state" and event.value == "down"):
                    event = await anext(states)
            await states.aclose()
            with pytest.raises(PropertyServiceError) as info:
                await client.get("scout3", "location")
            assert info.value.code is grpc.StatusCode.UNAVAILABLE
            assert info.value.message == "service 'scout3' is down: it missed 2 liveness checks"
            assert await client.get_names("registry", "find", state="down") == ["scout3"]

            # The group names the dead device; the other three still move.
            with pytest.raises(PropertyServiceError) as info:
                await client.set(
                    "swarm",
                    "behaviors.moveto",
                    "<marker><location>(0 0 0)</location></marker>",
                    formation="line",
                )
            assert info.value.code is grpc.StatusCode.UNAVAILABLE
            assert "failed on 1 of 4 members (the other 3 acted): scout3: UNAVAILABLE" in info.value.message
            assert await client.get("swarm", "failed") == "((scout3 UNAVAILABLE))"
            line = formation_targets(everyone, [0, 0, 0], "line", 1.0)
            for name in ("scout1", "scout2", "scout4"):
                await eventually(lambda n=name: client.get_vector(n, "location"), at(line[name]))
