"""The console for a fleet operator, in a real headless Chromium against a real gateway process.

* A gamepad drives: a synthetic pad is put into the page (``navigator.getGamepads`` and a
  ``gamepadconnected`` event); the robot's velocity, read through gRPC, follows the stick while
  the dead-man button is held, and is zero again when the stick is centred, the button let go,
  the pad gone or the page blurred. The robot's ``velocity_timeout`` is first raised to
  TELEOP_HOLD seconds, so a stop within STOP_WITHIN is the page's doing.
* The map draws each robot's trail, and its target with a line from the robot: where a click
  sent it, or where its own ``goal`` property says (``tests.support.courier``).
* Under the robots: the floor plan the config names (``[console] map_image``), placed at its
  ``map_extent``, or an environment model's occupancy grid placed by its ``.info``.
"""

from __future__ import annotations

import re
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from console_support import (
    CSS,
    STOP_WITHIN,
    ConsoleGateway,
    doc_image,
    eventually,
    forward,
    pose_on_map,
    select,
    target_on_map,
    translation,
    velocity,
    wait_for,
    xy,
)
from support.courier import COURIER_TYPE
from support.gateway_process import start_gateway

from clients.sync import Client

pytestmark = [pytest.mark.browser, pytest.mark.slow, pytest.mark.timeout(180)]

#: Seconds a velocity command holds once a test raised the robot's velocity_timeout.
TELEOP_HOLD = 30.0
#: Where the floor plan lies, metres: [x0, y0, x1, y1].
EXTENT = [-3.0, -2.0, 7.0, 5.5]

FLEET = f"""
[registry]
period = 0.5
timeout = 1.0
misses = 2

[console]
map_image = "floor.png"
map_extent = {EXTENT}

[[services]]
name = "scout1"
type = "sim-robot"
options = {{ start = [0.0, 0.0] }}

[[services]]
name = "scout2"
type = "sim-robot"
options = {{ start = [1.0, 0.0] }}

[[services]]
name = "courier1"
type = "{COURIER_TYPE}"
options = {{ start = [-1.0, 3.0], speed = 0.1 }}

[[services]]
name = "post1"
type = "sim-sensor"
options = {{ location = [0.0, 2.0, 0, 0, 0, 0] }}

[[services]]
name = "environment"
type = "environment"
options = {{ grid = {{ origin = [-2.0, -1.0], cell = 0.5, shape = [10, 16] }} }}
"""


def draw_floor_plan(path: Path) -> None:
    """A floor plan of 10 m × 7.5 m at 50 px a metre: outer walls, two rooms with doors, shelves."""
    from PIL import Image, ImageDraw

    px = 50
    image = Image.new("RGB", (10 * px, int(7.5 * px)), "#f6f1e7")
    draw = ImageDraw.Draw(image)
    draw.rectangle((0, 0, image.width - 1, image.height - 1), outline="#5b5346", width=6)
    # A wall at x = 3 m (3 m from the left edge, x0 = -3) with a door, and one across the top room.
    wall_x = 3 * px
    draw.line((wall_x, 0, wall_x, 2.5 * px), fill="#5b5346", width=5)
    draw.line((wall_x, 3.7 * px, wall_x, image.height), fill="#5b5346", width=5)
    draw.line((wall_x, 2.5 * px, 10 * px - 3 * px, 2.5 * px), fill="#5b5346", width=5)
    for i in range(4):  # shelves along the bottom right
        left = int((5 + 1.1 * i) * px)
        draw.rectangle(
            (left, int(6.2 * px), left + int(0.7 * px), int(7.2 * px)), fill="#c9b79c", outline="#8a7a60"
        )
    image.save(path)


@pytest.fixture(scope="module")
def console_gateway(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ConsoleGateway]:
    folder = tmp_path_factory.mktemp("console-fleet")
    draw_floor_plan(folder / "floor.png")
    gw = start_gateway(folder, FLEET)
    try:
        assert gw.http_url, f"no 'HTTP front end and console on' line:\n{gw.output}"
        yield ConsoleGateway(gw, gw.address, gw.http_url)
    finally:
        gw.stop()


# -- the gamepad ------------------------------------------------------------------------------------

INSTALL_PAD = """
const pad = {
  id: 'synthetic pad (STANDARD GAMEPAD)', index: 0, connected: true, mapping: 'standard', timestamp: 0,
  axes: [0, 0, 0, 0],
  buttons: Array.from({length: 17}, () => ({pressed: false, touched: false, value: 0})),
};
window.testPad = pad;
window.testPads = [pad];
Object.defineProperty(navigator, 'getGamepads', {value: () => window.testPads, configurable: true});
const e = new Event('gamepadconnected');
Object.defineProperty(e, 'gamepad', {value: pad});
window.dispatchEvent(e);
"""

#: The pad's state: the dead-man button (left shoulder, standard button 4) and the left stick.
HOLD = """
const pad = window.testPad;
pad.buttons[4] = {pressed: arguments[0], touched: arguments[0], value: arguments[0] ? 1 : 0};
pad.axes[0] = arguments[1];
pad.axes[1] = arguments[2];
pad.timestamp += 1;
"""

LET_GO = {
    "the stick returns to the centre": "window.testPad.axes[0] = 0.04; window.testPad.axes[1] = -0.06;",
    "the dead-man button is let go": "window.testPad.buttons[4] = {pressed: false, value: 0};",
    "the pad disconnects": (
        "const gone = window.testPad; gone.connected = false; window.testPads = [null];"
        "const e = new Event('gamepaddisconnected'); Object.defineProperty(e, 'gamepad', {value: gone});"
        "window.dispatchEvent(e);"
    ),
    "the page loses the focus": "window.dispatchEvent(new Event('blur'));",
}


@pytest.mark.parametrize("how", list(LET_GO))
def test_a_gamepad_drives_the_robot_and_stops_it_when(page: Any, client: Client, how: str) -> None:
    select(page, "scout2")
    client.set("scout2", "velocity_timeout", TELEOP_HOLD)
    try:
        page.execute_script(INSTALL_PAD)
        wait_for(
            page, lambda d: "synthetic pad" in d.find_element(CSS, "#teleop-gamepad").text, "#teleop-gamepad"
        )
        page.execute_script(HOLD, True, 0.0, -1.0)  # full forward
        eventually(lambda: forward(client, "scout2"), lambda v: v > 0.3, "scout2 drives forward with the pad")

        def across_the_heading() -> float:
            v = velocity(client, "scout2")
            yaw = float(np.asarray(client.get_vector("scout2", "location"))[5])
            return abs(float(np.cos(yaw) * v[1] - np.sin(yaw) * v[0]))

        # Along the heading the page knows: a tick sent before the robot's pose reached a fresh page
        # goes along x, and the next ticks (every SEND_PERIOD_MS) along the heading.
        eventually(across_the_heading, lambda c: c < 0.05, "scout2 drives along its heading")
        page.execute_script(HOLD, True, 1.0, 0.0)  # full right: turns clockwise on the spot
        eventually(lambda: velocity(client, "scout2")[5], lambda wz: wz < -0.5, "scout2 turns right")
        if how == "the stick returns to the centre":
            doc_image(page, "fleet-gamepad")
        page.execute_script(HOLD, True, 0.0, -1.0)
        eventually(lambda: forward(client, "scout2"), lambda v: v > 0.3, "scout2 drives forward again")
        page.execute_script(LET_GO[how])
        eventually(
            lambda: velocity(client, "scout2"),
            lambda v: not v.any(),
            f"scout2 stops when {how}",
            within=STOP_WITHIN,
        )
        if how == "the page loses the focus":
            # Back on the page with the pad still held: nothing drives until the dead-man is pressed anew.
            page.execute_script("window.dispatchEvent(new Event('focus'));")
            time.sleep(0.5)
            assert not velocity(client, "scout2").any(), (
                "the pad drove again without its dead-man pressed anew"
            )
            page.execute_script(HOLD, False, 0.0, -1.0)
            time.sleep(0.2)
            page.execute_script(HOLD, True, 0.0, -1.0)
            eventually(lambda: forward(client, "scout2"), lambda v: v > 0.3, "pressed anew, the pad drives")
            page.execute_script(HOLD, False, 0.0, 0.0)
            eventually(
                lambda: velocity(client, "scout2"), lambda v: not v.any(), "stopped", within=STOP_WITHIN
            )
    finally:
        page.execute_script("window.testPads = [];")
        client.set("scout2", "velocity_timeout", 0.5)
        client.set("scout2", "velocity", "(0 0 0 0 0 0)")


# -- trails and targets --------------------------------------------------------------------------------


def trail_points(driver: Any, robot: str) -> list[list[float]]:
    """The points of the robot's trail on the map, oldest first (world metres)."""
    points: list[list[float]] = driver.execute_script(
        'const g = document.querySelector(`#map [data-trail="${arguments[0]}"]`);'
        "if (!g) return [];"
        "const out = [];"
        "for (const line of g.querySelectorAll('polyline'))"
        "  for (const p of line.getAttribute('points').trim().split(/\\s+/))"
        "    out.push(p.split(',').map(Number));"
        "return out;",
        robot,
    )
    return points


def target_line(driver: Any, robot: str) -> list[float] | None:
    """The line from the robot to its target mark: its start, relative to the target (metres)."""
    found: list[float] | None = driver.execute_script(
        'const line = document.querySelector(`#map [data-target="${arguments[0]}"] .target-line`);'
        "return line && line.getAttribute('display') !== 'none'"
        "  ? [Number(line.getAttribute('x1')), Number(line.getAttribute('y1'))] : null;",
        robot,
    )
    return found


def test_a_robot_leaves_a_trail_and_its_target_is_marked_with_a_line_from_it(
    page: Any, client: Client
) -> None:
    from selenium.webdriver.common.action_chains import ActionChains

    start = xy(client, "scout1")
    assert np.allclose(start, [0, 0]), f"scout1 starts at (0 0), not {start}"
    # The page shows scout1 where it stands before it drives: its trail begins there.
    wait_for(page, lambda d: pose_on_map(d, "scout1"), "scout1 on the map")
    client.set("scout1", "speed", 2.0)
    client.set("scout1", "behaviors.moveto", "<marker><location>(2 1)</location></marker>")
    eventually(
        lambda: xy(client, "scout1"), lambda p: bool(np.allclose(p, [2, 1], atol=0.01)), "scout1 at (2 1)"
    )
    points = wait_for(
        page, lambda d: (p := trail_points(d, "scout1")) and len(p) >= 10 and p, "scout1's trail"
    )
    assert np.allclose(points[0], [0, 0], atol=0.1), f"the trail starts where scout1 started: {points[0]}"
    assert np.allclose(points[-1], [2, 1], atol=0.1), f"and ends where it is: {points[-1]}"
    # Every point of the trail lies on the way it drove, from (0 0) to (2 1).
    for x, y in points:
        assert abs(x * 1 - y * 2) / np.hypot(1, 2) < 0.1, f"({x} {y}) is off scout1's way"

    # A click sends scout2: its target is marked, with a line from scout2 to it.
    select(page, "scout2")
    ActionChains(page).move_to_element_with_offset(page.find_element(CSS, "#map"), 150, 60).click().perform()
    target = translation(wait_for(page, lambda d: target_on_map(d, "scout2"), "scout2's target on the map"))
    start = wait_for(page, lambda d: target_line(d, "scout2"), "a line from scout2 to its target")
    at = xy(client, "scout2")
    assert np.allclose(np.add(target, start), at, atol=0.3), (
        f"the line starts at scout2 {at}: {start} from {target}"
    )
    client.set("scout2", "behaviors.stop", "")

    # courier1 is sent by its own goal property: the map marks it as a goal, with its line.
    client.set("courier1", "goal", "<marker><location>(4 4)</location></marker>")
    goal = translation(wait_for(page, lambda d: target_on_map(d, "courier1"), "courier1's goal on the map"))
    assert np.allclose(goal, [4, 4]), goal
    assert page.execute_script(
        "return document.querySelector('#map [data-target=\"courier1\"]').classList.contains('goal')"
    )
    line = wait_for(page, lambda d: target_line(d, "courier1"), "a line from courier1 to its goal")
    assert np.allclose(np.add(goal, line), xy(client, "courier1"), atol=0.2), line
    doc_image(page, "fleet-trails")
    client.set("courier1", "speed", 50.0)
    wait_for(
        page, lambda d: target_on_map(d, "courier1") is None, "courier1's goal mark gone once it is there"
    )


# -- what lies under the robots -------------------------------------------------------------------------


def page_box(driver: Any, selector: str) -> list[float] | None:
    box: list[float] | None = driver.execute_script(
        "const el = document.querySelector(arguments[0]);"
        "if (!el) return null;"
        "const r = el.getBoundingClientRect();"
        "return [r.left, r.top, r.right, r.bottom];",
        selector,
    )
    return box


def assert_placed(driver: Any, image: str, extent: list[float]) -> None:
    """The picture's box on the page is the extent's, measured from post1 at (0 2) and the picture's scale."""
    box = wait_for(driver, lambda d: (b := page_box(d, image)) and b[2] > b[0] and b, image)
    post = page_box(driver, '#map [data-service="post1"] > .shape')
    assert post is not None
    px, py = (post[0] + post[2]) / 2, (post[1] + post[3]) / 2
    scale = (box[2] - box[0]) / (extent[2] - extent[0])
    x0, y0, x1, y1 = extent
    expected = [px + x0 * scale, py - (y1 - 2) * scale, px + x1 * scale, py - (y0 - 2) * scale]
    assert np.allclose(box, expected, atol=2.0), f"{image} at {box}, expected {expected}"


def test_the_floor_plan_the_config_names_lies_under_the_robots_at_its_extent(page: Any) -> None:
    wait_for(
        page,
        lambda d: d.find_element(CSS, "#map-background").get_attribute("value") == "floor-plan",
        "the floor plan chosen",
    )
    href = wait_for(
        page,
        lambda d: d.execute_script(
            "const i = document.querySelector('#map .background image.floor-plan');"
            "return i && i.getAttribute('href');"
        ),
        "the floor plan on the map",
    )
    assert href == "/console/floor-plan"
    wait_for(
        page,
        lambda d: d.execute_script(
            "const i = document.querySelector('#map .background image');"
            "return i && i.getBoundingClientRect().width > 100;"
        ),
        "the floor plan drawn",
    )
    page.find_element(CSS, "#map-fit").click()
    assert_placed(page, "#map .background image.floor-plan", EXTENT)
    doc_image(page, "fleet-floor-plan")


def test_an_environment_models_occupancy_grid_lies_under_the_robots(page: Any, client: Client) -> None:
    from selenium.webdriver.support.ui import Select

    for x, y in [(0.5, 1.5), (0.5, 1.5), (1.5, 0.5), (3.0, 2.5), (3.0, 2.5), (3.0, 2.5), (4.5, 0.0)]:
        client.set(
            "environment", "observe", f"<marker><class>crate</class><location>({x} {y})</location></marker>"
        )
    choice = "environment/grid.occupancy"
    wait_for(
        page,
        lambda d: (
            choice in [o.get_attribute("value") for o in d.find_elements(CSS, "#map-background option")]
        ),
        "the occupancy grid offered",
    )
    Select(page.find_element(CSS, "#map-background")).select_by_value(choice)
    href = wait_for(
        page,
        lambda d: d.execute_script(
            "const i = document.querySelector('#map .background image.grid-layer');"
            "return i && i.getAttribute('href');"
        ),
        "the occupancy grid on the map",
    )
    assert re.match(r"blob:", href), href
    # origin (-2 -1), cell 0.5, 10 rows × 16 columns: x from -2 to 6, y from -1 to 4.
    assert_placed(page, "#map .background image.grid-layer", [-2.0, -1.0, 6.0, 4.0])
    assert page.find_element(CSS, "#map .background").get_attribute("data-background") == choice
    doc_image(page, "fleet-occupancy")
