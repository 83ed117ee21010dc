"""``python -m bench.environment_picture FILE``: the heat map of docs/environment.md, made for real.

Four simulated robots (``services.apps.simulators.SimRobot``, the demo world's temperature field)
drive a lawn-mower pattern over an 8 m × 6 m grid of 0.25 m cells, each over its own strip;
an environment model follows their locations and temperature readings through a router, as
in a gateway, and ``grid.temperature.image`` is written to FILE. Prints the layer's info.
"""

from __future__ import annotations

import asyncio
import sys
from pathlib import Path

import numpy as np

from gateway.engine.router import Router
from services.apps.environment import EnvironmentModel
from services.apps.simulators import SimRobot
from services.kernel.core import LocalService
from services.kernel.core import serve as serve_backend

ORIGIN = (-1.0, -1.0)
CELL = 0.25
SHAPE = (24, 32)  # rows (y), cols (x)
ROBOTS = 4
#: Lanes of each robot's strip, one cell apart.
LANES = SHAPE[0] // ROBOTS


async def make_picture(path: Path) -> str:
    """Drive the robots, write the PNG to ``path``; returns ``grid.temperature.info``."""
    router = Router()
    robots: list[SimRobot] = []
    x0, y0 = ORIGIN
    x1 = x0 + SHAPE[1] * CELL
    for i in range(ROBOTS):
        robot = SimRobot(
            start=(x0 + CELL / 2, y0 + (i * LANES + 0.5) * CELL),
            speed=8.0,
            tick_hz=100.0,
            temperature_hz=100.0,
            seed=i,
        )
        backend = LocalService(robot)
        await backend.start()
        router.add(f"bot{i}", backend)
        robots.append(robot)
    model = EnvironmentModel(
        directory=router,
        robots=[f"bot{i}" for i in range(ROBOTS)],
        readings=[{"selector": f"bot{i} sensors.temperature"} for i in range(ROBOTS)],
        grid={"origin": list(ORIGIN), "cell": CELL, "shape": list(SHAPE)},
    )
    env = serve_backend(model)
    await env.start()
    router.add("environment", env)
    try:
        # The robots signal nothing when the model has caught up: ask, as a user of `sources` would.
        while not all(state == "following" for *_, state, _ in model.sources):  # noqa: ASYNC110
            await asyncio.sleep(0.01)
        for lane in range(LANES):
            far = x1 - CELL / 2 if lane % 2 == 0 else x0 + CELL / 2
            lane_y = [y0 + (i * LANES + lane + 0.5) * CELL for i in range(ROBOTS)]
            # Down to the lane, then along it.
            await _drive(robots, [(float(r.location[0]), y) for r, y in zip(robots, lane_y, strict=True)])
            await _drive(robots, [(far, y) for y in lane_y])
        await asyncio.sleep(0.6)  # the layer's change notice (0.5 s) has gone out
        png = await env.get("grid.temperature.image")
        assert isinstance(png, bytes)
        await asyncio.to_thread(path.write_bytes, png)
        info = await env.get("grid.temperature.info")
        return info if isinstance(info, str) else ""
    finally:
        for name in list(router.names()):
            await router.remove(name).aclose()


async def _drive(robots: list[SimRobot], targets: list[tuple[float, float]]) -> None:
    for robot, target in zip(robots, targets, strict=True):
        robot.drive_to(np.array(target), "world")
    async with asyncio.timeout(30):
        while not all(  # noqa: ASYNC110 - arrival is read from the robots, as the demo's users read it
            np.allclose(robot.location[:2], target) for robot, target in zip(robots, targets, strict=True)
        ):
            await asyncio.sleep(0.02)


def main(argv: list[str]) -> int:
    if len(argv) != 1:
        print("usage: python -m bench.environment_picture FILE.png", file=sys.stderr)
        return 2
    print(asyncio.run(make_picture(Path(argv[0]))))
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
