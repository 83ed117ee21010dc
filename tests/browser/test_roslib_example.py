"""The roslibjs example page in a real headless Chromium: a page written for ROS drives our robots.

The page (``gateway/console/examples/roslib/``) knows only roslibjs's API and rosbridge v2; the
gateway serves it from the console's route and answers it on ``/rosbridge``. roslibjs itself
comes from npm: ``npm ci`` in the page's folder (once per lock file) installs the ``roslib``
package whose browser bundle the page loads. Without npm, or when the install fails (no
registry), every test here skips and says why.

The robots are one of each kind the demo has: ``scout1`` in the gateway's process, ``rover1``
behind the TCP proxy and ``rover2`` behind the serial proxy (a pseudo-terminal), both in
their own processes speaking the line protocol. Their ``velocity`` and ``location``, read over
gRPC, are the checks; a stop within STOP_WITHIN is the page's doing, because each robot's
``velocity_timeout`` is raised to TELEOP_HOLD seconds first.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from console_support import (
    CSS,
    ROOT,
    STOP_WITHIN,
    ConsoleGateway,
    eventually,
    page_errors,
    save_screenshot,
    velocity,
    wait_for,
    xy,
)
from support.gateway_process import start_gateway
from support.npm import NPM_TIMEOUT, npm_ci

from clients.sync import Client

pytestmark = [pytest.mark.browser, pytest.mark.slow, pytest.mark.timeout(NPM_TIMEOUT + 120)]

PAGE_DIR = ROOT / "gateway" / "console" / "examples" / "roslib"
BUNDLE = PAGE_DIR / "node_modules" / "roslib" / "build" / "roslib.min.js"
#: Seconds a velocity command holds once the test raised the robot's velocity_timeout.
TELEOP_HOLD = 30.0
ROBOTS = ("scout1", "rover1", "rover2")
CONFIG = """
[[services]]
name = "scout1"
type = "sim-robot"
options = { start = [0.0, 0.0] }

[[devices]]
name = "rover1"
type = "sim-robot"
tcp = "127.0.0.1:0"
options = { start = [3.0, 0.0] }

[[devices]]
name = "rover2"
type = "sim-robot"
serial = "pty"
options = { start = [4.0, 0.0] }
"""


@pytest.fixture(scope="module")
def roslib_bundle() -> Path:
    """roslibjs's browser bundle, installed beside the page by `npm ci` (once per lock file)."""
    npm_ci(PAGE_DIR, "the roslibjs example page's tests", installed=BUNDLE)
    assert BUNDLE.is_file(), f"npm installed roslib without its browser bundle {BUNDLE}"
    return BUNDLE


@pytest.fixture(scope="module")
def robots_gateway(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ConsoleGateway]:
    gw = start_gateway(tmp_path_factory.mktemp("roslib"), CONFIG)
    try:
        assert gw.http_url, f"no 'HTTP front end and console on' line:\n{gw.output}"
        yield ConsoleGateway(gw, gw.address, gw.http_url)
    finally:
        gw.stop()


@pytest.fixture(scope="module")
def robots(robots_gateway: ConsoleGateway) -> Iterator[Client]:
    """The SDK's client of the gateway, once every robot (the devices too) answers."""
    with Client(robots_gateway.address, timeout=10.0) as client:
        for robot in ROBOTS:
            eventually(lambda r=robot: _answers(client, r), bool, f"{robot} answers", within=20.0)
        yield client


def _answers(client: Client, robot: str) -> bool:
    try:
        client.get(robot, "location")
    except Exception:
        return False
    return True


def open_page(browser: Any, gateway: ConsoleGateway, robot: str) -> None:
    browser.get_log("browser")  # read and so dropped: what earlier tests left
    browser.get(f"{gateway.url}console/examples/roslib/index.html?robot={robot}")
    wait_for(
        browser,
        lambda d: d.find_element(CSS, "#status").get_attribute("data-state") == "connected",
        "the page connected to /rosbridge",
    )
    wait_for(
        browser, lambda d: d.find_element(CSS, "#robot").get_attribute("value") == robot, f"{robot} chosen"
    )


@pytest.fixture
def page(
    browser: Any,
    roslib_bundle: Path,
    robots_gateway: ConsoleGateway,
    robots: Client,
    request: pytest.FixtureRequest,
) -> Iterator[Any]:
    """The browser, for the test to open the page in; a screenshot and a check for page errors after."""
    yield browser
    save_screenshot(browser, request.node.name)
    errors = page_errors(browser)
    assert not errors, f"the page threw or logged errors: {errors}"


def readout(browser: Any) -> str:
    return str(browser.find_element(CSS, "#location").text.strip())


def readout_xy(browser: Any) -> np.ndarray:
    """The x and y of the readout (``x 1.23 y -0.45 θ 0.10``); NaN when it shows none yet."""
    words = readout(browser).split()
    try:
        return np.array([float(words[words.index("x") + 1]), float(words[words.index("y") + 1])])
    except (ValueError, IndexError):
        return np.array([np.nan, np.nan])


def test_the_page_lists_the_topics_of_every_robot(page: Any, robots_gateway: ConsoleGateway) -> None:
    open_page(page, robots_gateway, "scout1")
    for robot in ROBOTS:
        wait_for(
            page,
            lambda d, r=robot: d.find_elements(CSS, f'#topics li[data-topic="/{r}/location"]'),
            f"/{robot}/location in the topic list",
        )
    options = [o.get_attribute("value") for o in page.find_elements(CSS, "#robot option")]
    assert set(ROBOTS) <= set(options), options


@pytest.mark.parametrize("robot", ROBOTS)
def test_the_joystick_drives_the_robot_and_letting_go_stops_it(
    page: Any, robots_gateway: ConsoleGateway, robots: Client, robot: str
) -> None:
    from selenium.webdriver.common.action_chains import ActionChains

    open_page(page, robots_gateway, robot)
    first = wait_for(page, lambda d: readout(d) if readout(d) != "—" else None, "a location readout")
    start = xy(robots, robot)
    robots.set(robot, "velocity_timeout", TELEOP_HOLD)
    joystick = page.find_element(CSS, "#joystick")
    try:
        # Pushed up, two thirds of the way: forward at two thirds of the page's top speed.
        ActionChains(page).move_to_element_with_offset(joystick, 0, -66).click_and_hold().perform()
        eventually(lambda: velocity(robots, robot), lambda v: bool(v.any()), f"{robot} drives")
        wait_for(page, lambda d: readout(d) != first, "the location readout changes")
        ActionChains(page).release().perform()
        eventually(
            lambda: velocity(robots, robot),
            lambda v: not v.any(),
            f"{robot} stops when the joystick is let go",
            within=STOP_WITHIN,
        )
    finally:
        ActionChains(page).release().perform()
        robots.set(robot, "velocity_timeout", 0.5)
    here = xy(robots, robot)
    assert float(np.linalg.norm(here - start)) > 0.01, f"{robot} moved"
    # Standing still, the readout shows where the robot is (to its two decimals).
    wait_for(
        page,
        lambda d: np.allclose(readout_xy(d), here, atol=0.011),
        f"the readout showing {robot} at {here}",
    )


@pytest.mark.parametrize("robot", ROBOTS)
def test_the_move_to_button_sends_the_robot_toward_the_target(
    page: Any, robots_gateway: ConsoleGateway, robots: Client, robot: str
) -> None:
    open_page(page, robots_gateway, robot)
    here = xy(robots, robot)
    target = np.round(here + np.array([1.0, 1.0]), 1)
    for field, value in (("#target-x", target[0]), ("#target-y", target[1])):
        element = page.find_element(CSS, field)
        element.clear()
        element.send_keys(f"{value:g}")
    page.find_element(CSS, "#moveto").click()
    wait_for(
        page,
        lambda d: d.find_element(CSS, "#moveto-result").get_attribute("data-state") == "ok",
        "moveto answered",
    )
    eventually(
        lambda: float(np.linalg.norm(xy(robots, robot) - target)),
        lambda distance: distance < float(np.linalg.norm(here - target)) - 0.1,
        f"{robot} nears {target}",
    )
    robots.set(robot, "behaviors.stop", "")
