"""What the browser tests share: the console's gateway, the browser, bounded waits, screenshots.

The browser is Debian's ``chromium`` driven through its ``chromedriver``
(``tests/run.sh`` installs both when missing) by Selenium, with the driver's
path given so that Selenium never looks for one on the network.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
from support.gateway_process import GatewayProcess, start_gateway

from clients.sync import Client

ROOT = Path(__file__).resolve().parents[2]
#: Debian's paths; PS_CHROMIUM and PS_CHROMEDRIVER name others (a Chromium and its matching driver).
CHROMIUM = Path(os.environ.get("PS_CHROMIUM", "/usr/bin/chromium"))
CHROMEDRIVER = Path(os.environ.get("PS_CHROMEDRIVER", "/usr/bin/chromedriver"))
SCREENSHOTS = ROOT / "build" / "screenshots"
DOC_IMAGES = ROOT / "docs" / "images"
#: Seconds a browser-side wait lasts: the page's own work is milliseconds, but two loaded cores
#: run the gateway, Chromium and the test at once.
WAIT = 10.0
#: The flags Chromium needs to run headless in a container, quietly and without the network:
#: no sandbox (root in a container), no GPU, no QUIC, none of the background fetches a fresh profile makes.
CHROMIUM_FLAGS = (
    "--headless=new",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--disable-dev-shm-usage",
    "--window-size=1280,800",
)

#: The page's size in CSS pixels, and so the screenshots' size.
VIEWPORT = (1280, 800)
#: The console's world: two robots, a sensor and a group of every mobile robot.
CONFIG = """
[registry]
period = 0.5
timeout = 1.0
misses = 2

[[services]]
name = "scout1"
type = "sim-robot"
options = { start = [0.0, 0.0] }

[[services]]
name = "scout2"
type = "sim-robot"
options = { start = [1.0, 0.0] }

[[services]]
name = "thermo1"
type = "sim-sensor"
options = { location = [0.5, 1.0, 0, 0, 0, 0] }

[[services]]
name = "swarm"
type = "group"
options = { query = { type = "mobile_robot" } }
"""

T = TypeVar("T")
CSS = "css selector"
#: Seconds within which the page must stop a robot (a key let go, the Stop button, the page
#: gone) whose velocity command would otherwise hold much longer: only the page can have done it.
STOP_WITHIN = 3.0


def missing_browser(chromium: Path = CHROMIUM, chromedriver: Path = CHROMEDRIVER) -> str | None:
    """Why the browser tests cannot run here, or None when they can."""
    missing = [str(p) for p in (chromium, chromedriver) if not (p.is_file() and os.access(p, os.X_OK))]
    if missing:
        return (
            f"browser tests skipped: {' and '.join(missing)} missing"
            " (Debian: apt-get install chromium chromium-driver; tests/run.sh does it as root)"
        )
    try:
        import selenium  # noqa: F401
    except ImportError:
        return "browser tests skipped: selenium is not installed (pip install -e '.[test]')"
    return None


@dataclass
class ConsoleGateway:
    """A running gateway: ``address`` for gRPC, ``url`` for the console (ends with ``/``)."""

    process: GatewayProcess
    address: str
    url: str


@contextmanager
def console_gateway_process(folder: Path) -> Iterator[ConsoleGateway]:
    """``psgateway serve`` of :data:`CONFIG` with gRPC and HTTP on free loopback ports."""
    gw = start_gateway(folder, CONFIG)
    try:
        # The front end prints its URL before the gateway's "listening on" line.
        assert gw.http_url, f"no 'HTTP front end and console on' line:\n{gw.output}"
        yield ConsoleGateway(gw, gw.address, gw.http_url)
    finally:
        gw.stop()


@contextmanager
def chromium() -> Iterator[Any]:
    """A headless Chromium under Selenium, with a fresh profile removed afterwards."""
    # The driver is named below, so Selenium Manager has nothing to find; offline all the same.
    os.environ.setdefault("SE_OFFLINE", "true")
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    profile = tempfile.mkdtemp(prefix="ps-chromium-")
    options = webdriver.ChromeOptions()
    options.binary_location = str(CHROMIUM)
    for flag in (*CHROMIUM_FLAGS, f"--user-data-dir={profile}"):
        options.add_argument(flag)
    try:
        driver = webdriver.Chrome(service=Service(str(CHROMEDRIVER)), options=options)
        try:
            # --window-size counts the window's own frame; the page itself gets VIEWPORT.
            width, height = VIEWPORT
            driver.execute_cdp_cmd(
                "Emulation.setDeviceMetricsOverride",
                {"width": width, "height": height, "deviceScaleFactor": 1, "mobile": False},
            )
            yield driver
        finally:
            driver.quit()
    finally:
        shutil.rmtree(profile, ignore_errors=True)


def page_errors(driver: Any) -> list[str]:
    """Uncaught exceptions and ``console.error`` lines the page logged since the last call.

    Failed requests (``source`` network: a refused Set is a 400, a test's stopped gateway
    refuses connections) are the page's business to show, and are left out.
    """
    return [
        entry["message"]
        for entry in driver.get_log("browser")
        if entry.get("level") == "SEVERE" and entry.get("source") != "network"
    ]


def save_screenshot(driver: Any, name: str) -> Path:
    SCREENSHOTS.mkdir(parents=True, exist_ok=True)
    path = SCREENSHOTS / f"{re.sub(r'[^A-Za-z0-9_.-]+', '_', name)}.png"
    driver.save_screenshot(str(path))
    return path


def doc_image(driver: Any, name: str) -> None:
    """A screenshot of a view ``docs/console.md`` shows (``console-NAME.png``)."""
    path = save_screenshot(driver, f"console-{name}")
    if os.environ.get("PS_DOC_IMAGES") == "1":
        DOC_IMAGES.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(path, DOC_IMAGES / path.name)


def wait_for(driver: Any, condition: Callable[[Any], T], what: str, within: float = WAIT) -> T:
    """Selenium's bounded wait, failing with an AssertionError that says what was awaited."""
    from selenium.common.exceptions import StaleElementReferenceException, TimeoutException
    from selenium.webdriver.support.ui import WebDriverWait

    try:
        result: T = WebDriverWait(
            driver, within, poll_frequency=0.05, ignored_exceptions=(StaleElementReferenceException,)
        ).until(condition)
    except TimeoutException:
        raise AssertionError(f"{what}: not seen in the page within {within} s") from None
    return result


def eventually(probe: Callable[[], T], ok: Callable[[T], bool], what: str, within: float = WAIT) -> T:
    """Call ``probe()`` (a gRPC Get, say) until ``ok(answer)``; fail after ``within`` s saying the last."""
    deadline = time.monotonic() + within
    last: object = "no answer yet"
    while True:
        answer = probe()
        if ok(answer):
            return answer
        last = answer
        if time.monotonic() >= deadline:
            raise AssertionError(f"{what}: not as expected within {within} s; last answer: {last!r}")
        time.sleep(0.05)


@contextmanager
def device_process(*args: str) -> Iterator[tuple[subprocess.Popen[str], str]]:
    """``python -m services.device ARGS --tcp 127.0.0.1:0``; yields it and its ``tcp://`` URL."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "services.device", *args, "--tcp", "127.0.0.1:0"],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout is not None
        first = proc.stdout.readline().strip()
        m = re.fullmatch(r"listening on (\S+:\d+)", first)
        assert m, f"device said {first!r}, exit {proc.poll()}"
        yield proc, "tcp://" + m.group(1)
    finally:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)


# -- the page, through the DOM hooks of the console's contract ------------------------------------


def service(driver: Any, name: str) -> Any:
    return driver.find_element(CSS, f'#services [data-service="{name}"]')


def select(driver: Any, name: str) -> None:
    """Click a service in the list and wait for its properties in the service view."""
    # The list is drawn anew when the registry changes: a click on an element just replaced
    # is stale, and the wait tries again.
    wait_for(driver, lambda d: service(d, name).click() or True, f"a click on {name} in the service list")
    wait_for(
        driver,
        lambda d: d.find_elements(CSS, "#service-view [data-property]"),
        f"the properties of {name} in #service-view",
    )


def prop(driver: Any, path: str) -> Any:
    return driver.find_element(CSS, f'#service-view [data-property="{path}"]')


def shown(driver: Any, path: str) -> str:
    """The value text the service view shows for ``path``."""
    text: str = prop(driver, path).find_element(CSS, ".value").text
    return text.strip()


def set_from_page(driver: Any, path: str, text: str) -> None:
    """Type ``text`` into the property's input and press its Set button."""
    widget = wait_for(driver, lambda d: prop(d, path), f"[data-property={path}] in #service-view")
    field = widget.find_element(CSS, "input, select, textarea")
    field.clear()
    field.send_keys(text)
    widget.find_element(CSS, '[data-action="set"]').click()


def pose_on_map(driver: Any, robot: str) -> str | None:
    """The ``transform`` of the robot's ``<g>`` on the map (read in one script: the map redraws it)."""
    found: str | None = driver.execute_script(
        'const g = document.querySelector(`#map [data-robot="${arguments[0]}"]`);'
        "return g ? g.getAttribute('transform') : null",
        robot,
    )
    return found


def target_on_map(driver: Any, robot: str) -> str | None:
    """The ``transform`` of the mark of where a map click sent the robot."""
    found: str | None = driver.execute_script(
        'const g = document.querySelector(`#map [data-target="${arguments[0]}"]`);'
        "return g ? g.getAttribute('transform') : null",
        robot,
    )
    return found


def translation(transform: str) -> np.ndarray:
    """(x, y) of an SVG ``translate(x y)``."""
    m = re.fullmatch(r"translate\(\s*(\S+?)[\s,]+(\S+?)\s*\)", transform.strip())
    assert m, transform
    return np.array([float(m.group(1)), float(m.group(2))])


def blur(driver: Any) -> None:
    """Take the focus off any input, so that keys go to the page (teleop)."""
    driver.execute_script("document.activeElement && document.activeElement.blur()")


# -- the robots, through gRPC ---------------------------------------------------------------------


def velocity(client: Client, robot: str) -> np.ndarray:
    return np.asarray(client.get_vector(robot, "velocity"))


def forward(client: Client, robot: str) -> float:
    """The robot's speed along its heading (velocity is in the world frame, yaw in its location)."""
    v = velocity(client, robot)
    yaw = float(np.asarray(client.get_vector(robot, "location"))[5])
    return float(v[0] * np.cos(yaw) + v[1] * np.sin(yaw))


def xy(client: Client, robot: str) -> np.ndarray:
    return np.asarray(client.get_vector(robot, "location"))[:2]
