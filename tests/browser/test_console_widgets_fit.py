"""Widgets that fit the data, in a real headless Chromium against a real gateway: a speed's slider
spans what the speed needs, a location reads rounded, group headings name the types for people, a
service's doc shows its code and guide paths, the heat map has axes, a scale and a colour legend,
and a plot takes a second and a third signal, each opened with its last minute."""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from console_support import CONFIG, CSS, ConsoleGateway, doc_image, eventually, prop, select, wait_for
from support.gateway_process import start_gateway

from clients.sync import Client
from clients.values import Marker

pytestmark = [pytest.mark.browser, pytest.mark.slow, pytest.mark.timeout(180)]

#: The console's world, a small camera (its doc names a guide) and an environment model whose
#: temperature layer the swarm fills as it drives; the numbers the plot draws are kept.
WORLD = """
[history]
selectors = ["*/location", "*/sensors.*", "scout1/speed", "scout1/max_speed"]

[[services]]
name = "camera1"
type = "camera"
options = { location = [0.0, -3.0, 1.5, 0.0, 0.0, 1.5708], resolution = [64, 48], rate_hz = 1 }

[[services]]
name = "environment"
type = "environment"
[services.options]
robots = ["swarm"]
readings = [{ selector = "swarm robots.*.sensors.temperature", layer = "temperature" }]
grid = { origin = [-4.0, -4.0], cell = 0.5, shape = [16, 16] }
"""


@pytest.fixture(scope="module")
def console_gateway(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ConsoleGateway]:
    folder: Path = tmp_path_factory.mktemp("console-widgets")
    gw = start_gateway(folder, CONFIG + WORLD)
    try:
        assert gw.http_url, f"no 'HTTP front end and console on' line:\n{gw.output}"
        yield ConsoleGateway(gw, gw.address, gw.http_url)
    finally:
        gw.stop()


def slider_state(page: Any, path: str) -> dict[str, Any]:
    state: dict[str, Any] = page.execute_script(
        """
        const p = document.querySelector(`#service-view [data-property="${arguments[0]}"]`);
        const track = p && p.querySelector('.slider');
        if (!track) return {};
        return {
          min: track.getAttribute('aria-valuemin'), max: track.getAttribute('aria-valuemax'),
          now: track.getAttribute('aria-valuenow'), knob: p.querySelector('.slider-thumb').style.left,
          scale: p.querySelector('.slider-scale').textContent,
        };
        """,
        path,
    )
    return state


def test_a_speed_slider_spans_what_the_speed_needs_and_a_location_reads_rounded(
    page: Any, client: Client
) -> None:
    client.set("scout1", "speed", "0.5")
    select(page, "scout1")
    state = wait_for(
        page, lambda d: (s := slider_state(d, "speed")).get("now") == "0.5" and s, "speed's slider at 0.5"
    )
    # The model allows 0 … 1000 m/s; the slider spans 0 … 1 m/s, the knob in the middle.
    assert (state["min"], state["max"], state["knob"]) == ("0", "1", "50%"), state
    assert "m/s" in state["scale"] and "allowed 0 … 1000" in state["scale"], state
    # An arrow key steps by the span's hundredth and sets it.
    prop(page, "speed").find_element(CSS, ".slider").send_keys("\ue014")  # ArrowRight
    eventually(lambda: client.get("scout1", "speed"), lambda v: v == "0.51", "speed 0.51 set by the slider")
    wait_for(page, lambda d: "busy" not in prop(d, "speed").get_attribute("class"), "the page's Set answered")

    # While it drives, its location has every digit a double has; the page shows centimetres.
    client.set("scout1", "speed", "0.3")
    client.set("scout1", "behaviors.moveto", Marker.at([1.3333333, 0.6666667]))
    location = prop(page, "location")

    def rounded(d: Any) -> str | None:
        text: str = location.find_element(CSS, ".value").text.strip()
        numbers = text.strip("()").split()
        moving = len(numbers) == 6 and 0.5 < float(numbers[0]) < 1.3
        return text if moving and all(len(n.partition(".")[2]) <= 2 for n in numbers) else None

    text = wait_for(page, rounded, "scout1's location rounded to centimetres while it drives")
    sent = location.find_element(CSS, ".value").get_attribute("title")
    assert len(sent) > len(text), "the tooltip keeps the digits the service sent"
    clipped = page.execute_script(
        "const v = arguments[0].querySelector('.value'); return v.scrollWidth > v.clientWidth", location
    )
    assert not clipped, f"{text} is cut"
    pose = location.find_element(CSS, ".pose-text").text
    assert re.fullmatch(r"x -?\d+\.\d\d m\s+y -?\d+\.\d\d m\s+heading -?\d+\.\d°", pose), pose
    doc_image(page, "widgets-fit")
    client.set("scout1", "behaviors.stop", "")


def test_group_headings_name_the_types_for_people(page: Any) -> None:
    expected = {
        "Camera (1)",
        "Environment model (1)",
        "Group (1)",
        "Registry (1)",
        "Robots (2)",
        "Sensor (1)",
    }

    def all_headings(d: Any) -> list[str] | None:
        shown = [h.text.strip() for h in d.find_elements(CSS, "#services h3.by-type")]
        return shown if expected <= set(shown) else None

    # The list fills (and is drawn again) as the services answer: wait for every group.
    shown = wait_for(page, all_headings, f"the headings {sorted(expected)}")
    assert expected <= set(shown), shown
    assert not any("_" in h for h in shown), shown


def test_a_service_doc_shows_its_code_and_its_guide_path(page: Any) -> None:
    select(page, "camera1")
    path = wait_for(
        page, lambda d: d.find_element(CSS, "#service-view div.doc code.doc-path"), "the doc's guide path"
    )
    assert path.text == "docs/vision.md"
    doc = page.find_element(CSS, "#service-view div.doc").text
    assert "``" not in doc and "see docs/vision.md" in doc, doc
    doc_image(page, "doc-rendered")


def test_the_heat_map_has_axes_a_scale_and_a_colour_legend(page: Any, client: Client) -> None:
    # The swarm sweeps the field at 2 m/s, reading the temperature as it goes.
    for robot in ("scout1", "scout2"):
        client.set(robot, "speed", "2")
    for x, y in ((3, 3), (-3, 1), (-3, -3)):
        client.set("swarm", "behaviors.moveto", Marker.at([x, y]), formation="line", spacing="1.5")
        eventually(
            lambda x=x, y=y: client.get("swarm", "location"),
            lambda v, x=x, y=y: (
                abs(float(v.strip("()").split()[0]) - x) + abs(float(v.strip("()").split()[1]) - y) < 0.2
            ),
            f"the swarm at ({x} {y})",
            within=20.0,
        )
    info = eventually(
        lambda: client.get("environment", "grid.temperature.info"),
        lambda v: "(min ())" not in v,
        "temperature readings in the environment's grid",
    )
    assert "(unit degC)" in info, info
    select(page, "environment")
    heat = wait_for(
        page,
        lambda d: d.find_element(
            CSS, '#service-view [data-property="grid.temperature.image"] .heat-map[data-legend=drawn]'
        ),
        "the heat map's legend drawn",
        within=20.0,
    )
    xs = [t.text for t in heat.find_elements(CSS, ".heat-axis-x .tick")]
    ys = [t.text for t in heat.find_elements(CSS, ".heat-axis-y .tick")]
    assert xs[0] == "-4" and xs[-1] == "4" and "0" in xs, xs
    assert ys[0] == "-4" and ys[-1] == "4", ys
    assert heat.find_element(CSS, ".heat-scale-label").text == "2 m"
    view = prop(page, "grid.temperature.image")
    legend = view.find_element(CSS, ".heat-legend")
    low, high = legend.find_element(CSS, ".heat-low").text, legend.find_element(CSS, ".heat-high").text
    assert low.endswith(" degC") and high.endswith(" degC"), (low, high)
    assert float(low.split()[0]) <= float(high.split()[0])
    # North is up: the y axis's largest coordinate is drawn at the top.
    tops = page.execute_script(
        "const ticks = arguments[0].querySelectorAll('.heat-axis-y .tick');"
        "return [...ticks].map(t => t.getBoundingClientRect().top)",
        heat,
    )
    assert tops == sorted(tops, reverse=True), tops
    page.execute_script("arguments[0].scrollIntoView({block: 'center'})", heat)
    doc_image(page, "heat-map-legend")
    client.set("swarm", "behaviors.stop", "")


def plotted(page: Any) -> dict[str, Any]:
    state: dict[str, Any] = page.execute_script(
        """
        const box = document.querySelector('#service-view [data-property="speed"] .plot-box');
        if (!box) return {};
        const signals = {};
        for (const line of box.querySelectorAll('polyline[data-signal]')) {
          const points = (line.getAttribute('points') || '').split(' ');
          signals[line.dataset.signal] = points.filter(Boolean).length;
        }
        return {
          signals,
          keys: [...box.querySelectorAll('.plot-signal-key:not([hidden])')].map((k) => k.dataset.signal),
          history: Object.fromEntries([...box.querySelectorAll('.plot-signal-key[data-history-points]')].map(
            (k) => [k.dataset.signal, k.dataset.historyPoints])),
          colours: [...box.querySelectorAll('polyline')].map((l) => getComputedStyle(l).stroke),
          picker: !box.querySelector('select[data-action=add-signal]').hidden,
        };
        """
    )
    return state


def add_signal(page: Any, path: str) -> None:
    from selenium.webdriver.support.ui import Select

    picker = wait_for(
        page,
        lambda d: (
            (s := prop(d, "speed").find_element(CSS, "select[data-action=add-signal]")).find_elements(
                CSS, f'option[value="{path}"]'
            )
            and s
        ),
        f"{path} offered to the plot",
    )
    Select(picker).select_by_value(path)


def test_a_plot_takes_a_second_and_a_third_signal_each_from_its_history(page: Any, client: Client) -> None:
    for value in ("0.6", "0.7"):
        client.set("scout1", "max_speed", value)
    eventually(lambda: client.history("scout1", "max_speed"), lambda h: len(h) >= 2, "max_speed kept")
    select(page, "scout1")
    wait_for(
        page, lambda d: prop(d, "speed").find_element(CSS, "[data-action=plot]"), "a plot button"
    ).click()
    add_signal(page, "max_speed")
    add_signal(page, "sensors.battery")
    state = wait_for(
        page,
        lambda d: (s := plotted(d)).get("history", {}).get("max_speed") not in (None, "0") and s,
        "max_speed drawn from its history",
    )
    assert int(state["history"]["max_speed"]) >= 2, state
    assert state["keys"] == ["speed", "max_speed", "sensors.battery"], state
    assert not state["picker"], "three signals: nothing more is offered"
    assert len(set(state["colours"])) == 3, state
    # Then the added signal follows live.
    before = state["signals"]["max_speed"]
    client.set("scout1", "max_speed", "0.9")
    wait_for(
        page, lambda d: plotted(d)["signals"]["max_speed"] > before, "max_speed's live value in the plot"
    )
    page.execute_script(
        "arguments[0].scrollIntoView({block: 'center'})", prop(page, "speed").find_element(CSS, ".plot-box")
    )
    doc_image(page, "plot-signals")
    # A signal taken off gives its place back.
    prop(page, "speed").find_element(
        CSS, '[data-signal="sensors.battery"] [data-action=remove-signal]'
    ).click()
    state = wait_for(page, lambda d: (s := plotted(d))["picker"] and s, "the picker back")
    assert state["keys"] == ["speed", "max_speed"], state
