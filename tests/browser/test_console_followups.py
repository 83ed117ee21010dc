"""What a new user of the console found, in a real headless Chromium against a real gateway:
the registry's ``last_seen`` as a time, a state machine's ``definition`` in a text area, a
``remove`` that asks first, the joystick's knob following the keys, and a service that is
down described once, when it is up again."""

from __future__ import annotations

import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from console_support import CONFIG, CSS, ROOT, ConsoleGateway, eventually, prop, select, wait_for
from support.gateway_process import start_gateway
from support.ports import free_port

from clients.sync import Client

pytestmark = [pytest.mark.browser, pytest.mark.slow, pytest.mark.timeout(120)]

DEVICE_PORT = free_port()
MORE = f"""
[[services]]
name = "missions"
type = "statemachine"
options = {{ charts = {{ patrol = "builtin:patrol" }} }}

[[services]]
name = "far"
url = "tcp://127.0.0.1:{DEVICE_PORT}"
options = {{ timeout = 1.0, backoff_initial = 0.05, backoff_max = 0.3 }}
"""
#: Counts the page's requests for each service's model (window.modelFetches[name]).
COUNT_MODEL_FETCHES = """
if (!window.modelFetches) {
  window.modelFetches = {};
  const original = window.fetch;
  window.fetch = (url, init) => {
    const m = /\\/services\\/([^/]+)\\/model$/.exec(String(url));
    if (m) window.modelFetches[m[1]] = (window.modelFetches[m[1]] ?? 0) + 1;
    return original(url, init);
  };
}
"""


@pytest.fixture(scope="module")
def console_gateway(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ConsoleGateway]:
    folder: Path = tmp_path_factory.mktemp("console-followups")
    gw = start_gateway(folder, CONFIG + MORE)
    try:
        yield ConsoleGateway(gw, gw.address, gw.http_url)
    finally:
        gw.stop()


DEVICE = [sys.executable, "-m", "services.device", "--service", "sim-robot", "--name", "far"]


def device(port: int) -> subprocess.Popen[str]:
    proc = subprocess.Popen(
        [*DEVICE, "--tcp", f"127.0.0.1:{port}"],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        text=True,
    )
    assert proc.stdout is not None
    assert proc.stdout.readline().startswith("listening on"), proc.poll()
    return proc


def test_last_seen_shows_a_time_with_the_number_in_its_tooltip(page: Any, client: Client) -> None:
    select(page, "registry")
    seen = wait_for(page, lambda d: prop(d, "services.scout1.last_seen"), "scout1's last_seen")
    value = wait_for(page, lambda d: seen.find_element(CSS, ".value").text.strip() or None, "a last_seen")
    assert len(value) == 19 and value[4] == "-" and value[13] == ":", value
    title = seen.find_element(CSS, ".value").get_attribute("title")
    number = float(title.split()[0])
    assert abs(number - time.time()) < 60 and "Unix seconds" in title


def test_a_definition_is_a_text_area_and_remove_asks_first(page: Any, client: Client) -> None:
    select(page, "missions")
    definition = wait_for(page, lambda d: prop(d, "patrol.definition"), "patrol.definition")
    area = wait_for(page, lambda d: definition.find_element(CSS, "textarea.code"), "a text area")
    assert area.size["height"] > 100, area.size
    wait_for(page, lambda d: "<scxml" in (area.get_attribute("value") or ""), "the chart in the text area")

    remove = prop(page, "patrol.remove").find_element(CSS, 'button[data-action="invoke"]')
    remove.click()
    alert = wait_for(page, lambda d: d.switch_to.alert, "a question before patrol.remove")
    assert "patrol.remove" in alert.text
    alert.dismiss()
    time.sleep(0.5)  # what a Set would have done by now
    assert "patrol" in client.get("missions", "machines")
    remove.click()
    wait_for(page, lambda d: d.switch_to.alert, "the question again").accept()
    eventually(lambda: client.get("missions", "machines"), lambda v: "patrol" not in v, "patrol removed")


def test_keys_move_the_joystick_knob(page: Any, client: Client) -> None:
    from selenium.webdriver.common.action_chains import ActionChains

    select(page, "scout2")
    knob = page.find_element(CSS, "#joystick .knob")

    def offset(d: Any) -> tuple[float, float]:
        """The knob's offset from the centre as drawn (a transition may be on its way)."""
        value: str = knob.value_of_css_property("transform")
        if value in ("none", ""):
            return 0.0, 0.0
        dx, dy = (float(x) for x in value.strip("matrix()").split(",")[4:6])
        return dx, dy

    assert offset(page) == (0.0, 0.0)
    ActionChains(page).key_down("w").perform()
    try:
        # Up, not sideways (W drives forward).
        def moved_up(d: Any) -> tuple[float, float] | None:
            o = offset(d)
            return o if o[1] < -5 else None

        dx, dy = wait_for(page, moved_up, "the knob moved up")
        assert abs(dx) < 0.5, (dx, dy)
    finally:
        ActionChains(page).key_up("w").perform()
    wait_for(page, lambda d: offset(d) == (0.0, 0.0), "the knob back in the centre")
    client.set("scout2", "velocity", "(0 0 0 0 0 0)")


def test_a_service_that_is_down_is_described_once_when_it_is_up(page: Any, client: Client) -> None:
    page.execute_script(COUNT_MODEL_FETCHES)
    fetches = lambda: page.execute_script("return window.modelFetches.far ?? 0")  # noqa: E731
    eventually(lambda: client.get("registry", "services.far.state"), lambda s: s != "up", "far not up")
    wait_for(page, lambda d: d.find_element(CSS, '#services [data-service="far"]').click() or True, "far")
    wait_for(page, lambda d: "its properties show" in d.find_element(CSS, "#service-view").text, "a notice")
    time.sleep(1.5)  # several liveness checks of the registry
    assert fetches() == 0
    proc = device(DEVICE_PORT)
    try:
        wait_for(page, lambda d: prop(d, "location"), "far's properties once it is up", within=20)
        time.sleep(1.0)
        assert fetches() == 1
        # Down again and back: described once more.
        proc.terminate()
        proc.wait(10)
        eventually(lambda: client.get("registry", "services.far.state"), lambda s: s != "up", "far down")
        time.sleep(1.0)
        assert fetches() == 1
        proc = device(DEVICE_PORT)
        wait_for(page, lambda d: prop(d, "location"), "far's properties again", within=20)
        time.sleep(1.0)
        assert fetches() == 2
    finally:
        proc.terminate()
        proc.wait(10)
