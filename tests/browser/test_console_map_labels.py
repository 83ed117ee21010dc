"""Names on the console's map stay readable where things stand together, in a real headless Chromium.

The demo starts its sensor thermo1 where the robot scout1 stands, (0 0), and its
group's centroid lies between its robots: no two names may be drawn over each other.
A row of six robots 15 cm apart (a few pixels on the fitted map) keeps every name clear
of the other names and of the other robots, the far ones joined to theirs by a line.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from typing import Any

import pytest
from console_support import ConsoleGateway, doc_image, page_errors, wait_for
from support.gateway_process import start_gateway

pytestmark = [pytest.mark.browser, pytest.mark.slow, pytest.mark.timeout(120)]

TOGETHER = """
[[services]]
name = "scout1"
type = "sim-robot"
options = { start = [0.0, 0.0] }

[[services]]
name = "scout2"
type = "sim-robot"
options = { start = [3.0, 0.0] }

[[services]]
name = "scout3"
type = "sim-robot"
options = { start = [4.0, 0.0] }

[[services]]
name = "thermo1"
type = "sim-sensor"
options = { location = [0.0, 0.0, 0, 0, 0, 0] }

[[services]]
name = "swarm"
type = "group"
options = { members = ["scout1"] }

[[services]]
name = "pair"
type = "group"
options = { members = ["scout2", "scout3"] }

[[services]]
name = "row1"
type = "sim-robot"
options = { start = [8.15, 2.0] }

[[services]]
name = "row2"
type = "sim-robot"
options = { start = [8.30, 2.0] }

[[services]]
name = "row3"
type = "sim-robot"
options = { start = [8.45, 2.0] }

[[services]]
name = "row4"
type = "sim-robot"
options = { start = [8.60, 2.0] }

[[services]]
name = "row5"
type = "sim-robot"
options = { start = [8.75, 2.0] }

[[services]]
name = "row6"
type = "sim-robot"
options = { start = [8.90, 2.0] }
"""
#: Every thing on the map: the six of the first world, and the row.
THINGS = 12


@pytest.fixture(scope="module")
def console_gateway(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ConsoleGateway]:
    gw = start_gateway(tmp_path_factory.mktemp("console-labels"), TOGETHER)
    try:
        assert gw.http_url, f"no 'HTTP front end and console on' line:\n{gw.output}"
        yield ConsoleGateway(gw, gw.address, gw.http_url)
    finally:
        gw.stop()


#: Read after two animation frames: the map lays its names out at the frame after a thing
#: appears or moves (js/map.js, scheduleLabels), and a name read before that frame stands where
#: its thing does, not where it is placed (a slow frame on a loaded machine showed it).
_AFTER_THE_LAYOUT = (
    "const done = arguments[arguments.length - 1];"
    "requestAnimationFrame(() => requestAnimationFrame(() => done(read())));"
)


def label_boxes(driver: Any) -> dict[str, list[float]]:
    """Each thing's name on the map, as laid out: its box on the page, [left, top, right, bottom];
    empty while the layout is not settled.

    Settled: every thing's type is known (a thing whose type arrives is drawn anew, its name
    where it stands until the next frame's layout), and the boxes are the same two frames apart.
    """
    read: dict[str, Any] = driver.execute_async_script(
        "const boxes = () => {"
        "  const out = {};"
        "  for (const g of document.querySelectorAll('#map g[data-service]')) {"
        "    const r = g.querySelector(':scope > text').getBoundingClientRect();"
        "    out[g.dataset.service] = [r.left, r.top, r.right, r.bottom];"
        "  }"
        "  return out;"
        "};"
        "const known = () => [...document.querySelectorAll('#map g[data-service]')]"
        "  .every((g) => g.dataset.kind !== 'unknown');"
        "const first = boxes();"
        "const read = () => ({ first, then: boxes(), known: known() });" + _AFTER_THE_LAYOUT
    )
    settled = read["known"] and read["first"] == read["then"]
    return read["then"] if settled else {}


def overlap(a: list[float], b: list[float]) -> bool:
    return a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]


def test_names_of_things_at_one_place_are_not_drawn_over_each_other(page: Any) -> None:
    boxes = wait_for(
        page, lambda d: (b := label_boxes(d)) and len(b) == THINGS and b, "every name on the map"
    )
    names = sorted(boxes)
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            assert not overlap(boxes[a], boxes[b]), f"the names {a} and {b} overlap: {boxes}"


def shape_boxes(driver: Any) -> dict[str, list[float]]:
    """Each thing's shape on the map (its triangle, diamond or dot): [left, top, right, bottom]."""
    boxes: dict[str, list[float]] = driver.execute_script(
        "const out = {};"
        "for (const g of document.querySelectorAll('#map g[data-service]')) {"
        "  const r = g.querySelector(':scope > .shape').getBoundingClientRect();"
        "  out[g.dataset.service] = [r.left, r.top, r.right, r.bottom];"
        "}"
        "return out;"
    )
    return boxes


def test_names_of_robots_a_few_pixels_apart_stay_clear_of_each_other_and_of_the_robots(page: Any) -> None:
    row = [f"row{i}" for i in range(1, 7)]

    def settled(d: Any) -> dict[str, list[float]] | None:
        b = label_boxes(d)
        return b if all(name in b for name in row) and all(b[n][2] > b[n][0] for n in row) else None

    boxes = wait_for(page, settled, "the row's names on the map")
    shapes = shape_boxes(page)
    centres = [((shapes[n][0] + shapes[n][2]) / 2) for n in row]
    assert max(centres) - min(centres) < 80, f"the row is a few pixels a robot apart: {centres}"
    for i, a in enumerate(row):
        for b in row[i + 1 :]:
            assert not overlap(boxes[a], boxes[b]), f"the names {a} and {b} overlap: {boxes}"
        for other in row:
            if other != a:
                assert not overlap(boxes[a], shapes[other]), (
                    f"the name {a} covers {other}: {boxes[a]} {shapes[other]}"
                )
    leaders = page.execute_script(
        "return document.querySelectorAll('#map g[data-service] > line.leader').length"
    )
    assert leaders > 0, "names set off from their robots have a leader line"
    doc_image(page, "map-labels")


def visible_label_boxes(driver: Any) -> dict[str, list[float]]:
    """Every name the map shows (things, targets, markers): its box on the page, by a key that names it."""
    boxes: dict[str, list[float]] = driver.execute_async_script(
        "const read = () => {"
        "  const out = {};"
        "  let i = 0;"
        "  const names = '#map .robots text, #map .others text, #map .markers text';"
        "  for (const t of document.querySelectorAll(names)) {"
        "    if (t.getAttribute('display') === 'none') continue;"
        "    const r = t.getBoundingClientRect();"
        "    out[`${t.textContent} #${(i += 1)}`] = [r.left, r.top, r.right, r.bottom];"
        "  }"
        "  return out;"
        "};" + _AFTER_THE_LAYOUT
    )
    return boxes


def test_in_the_demo_no_name_is_drawn_over_another(browser: Any, demo_gateway: Any) -> None:
    """The demo's thermo1 stands on scout1, its swarm's centroid among the robots, and an environment
    model and a camera mark every robot again where it stands: each name is shown once, and clear."""
    browser.get(demo_gateway.http_url)
    wait_for(
        browser, lambda d: d.find_elements("css selector", '#map g[data-service="rover2"]'), "the demo's map"
    )
    # The camera's and the environment model's markers arrive after the robots.
    wait_for(
        browser, lambda d: len(d.find_elements("css selector", "#map .markers g")) >= 6, "the demo's markers"
    )
    time.sleep(1.0)  # a frame or two for the layout

    def clear_of_each_other(d: Any) -> dict[str, list[float]] | None:
        boxes = visible_label_boxes(d)
        keys = sorted(boxes)
        for i, a in enumerate(keys):
            for b in keys[i + 1 :]:
                if overlap(boxes[a], boxes[b]):
                    return None
        return boxes

    boxes = wait_for(browser, clear_of_each_other, "every name on the demo's map clear of the others")
    names = [key.split(" #")[0] for key in boxes]
    for thing in ("scout1", "thermo1", "swarm", "rover1"):
        assert names.count(thing) == 1, f"{thing} is named {names.count(thing)} times: {sorted(names)}"
    doc_image(browser, "demo-map-labels")
    errors = page_errors(browser)
    assert not errors, errors
