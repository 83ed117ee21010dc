"""roslibjs (npm ``roslib``, unchanged, in Node) drives the demo's robots through the gateway's
rosbridge endpoint, as a web teleop page does: it lists the topics, reads a robot's pose, sends
it somewhere with ``moveto``, drives it with ``cmd_vel``, stops it and asks the registry — for an
in-process robot, one behind the TCP proxy and one behind the serial proxy. And it joins the
fragments a large message is split into.

roslib comes pinned from npm (tests/interop/roslib/package.json and its lock file), installed by
``npm ci`` once per lock file; without node, npm or the registry the tests are skipped, saying so.
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path
from typing import Any

import pytest
from support.npm import NPM_TIMEOUT, npm_ci, tool

ROOT = Path(__file__).resolve().parents[2]
ROSLIB_DIR = ROOT / "tests" / "interop" / "roslib"
RUN_TIMEOUT = 90.0

pytestmark = pytest.mark.timeout(NPM_TIMEOUT + 2 * RUN_TIMEOUT)


@pytest.fixture(scope="session")
def node() -> str:
    """The ``node`` binary, with roslib installed by ``npm ci`` in tests/interop/roslib."""
    what = "the roslibjs tests"
    node = tool("node", what)
    npm_ci(ROSLIB_DIR, what)
    return node


def run(node: str, script: str, *args: str) -> list[dict[str, Any]]:
    done = subprocess.run(
        [node, script, *args],
        cwd=ROSLIB_DIR,
        check=False,
        capture_output=True,
        text=True,
        timeout=RUN_TIMEOUT,
    )
    lines = [json.loads(line) for line in done.stdout.splitlines() if line.startswith("{")]
    assert done.returncode == 0, f"{script} {' '.join(args)}:\n{done.stdout}\n{done.stderr}"
    return lines


@pytest.mark.parametrize("robot", ["scout1", "rover1", "rover2"])
def test_roslibjs_drives_a_demo_robot_as_a_teleop_page_would(
    node: str, demo_gateway: Any, robot: str
) -> None:
    steps = run(node, "drive.mjs", f"ws://{demo_gateway.http_address}/rosbridge", robot)
    by_step = {line["step"]: line["value"] for line in steps}
    assert by_step["topic type"] == "geometry_msgs/Pose2D"
    assert f"/{robot}/location" in by_step["topics"]["topics"]
    assert by_step[f"call /{robot}/behaviors/moveto"] == {"success": True, "message": ""}
    # cmd_vel drove the robot at the speed asked (0.2 m/s ahead), and stop stopped it.
    vx, vy, *_ = by_step["done"]
    assert abs((vx**2 + vy**2) ** 0.5 - 0.2) < 1e-6
    assert robot in by_step["call /registry/find"]["names"]


def test_roslibjs_joins_the_fragments_of_a_large_message(node: str, demo_gateway: Any) -> None:
    [line] = run(
        node,
        "fragments.mjs",
        f"ws://{demo_gateway.http_address}/rosbridge",
        "/scout2/odom",
        "nav_msgs/Odometry",
        "256",
    )
    message = line["message"]
    assert message["op"] == "publish" and message["topic"] == "/scout2/odom"
    assert len(json.dumps(message, separators=(",", ":"))) > 2 * 256  # three fragments at least
    assert message["msg"]["child_frame_id"] == "base_link"
    assert message["msg"]["pose"]["pose"]["orientation"]["w"] == pytest.approx(1.0)
