"""Names on the console's map stay readable where things stand together, in a real headless Chromium.

The demo starts its sensor thermo1 where the robot scout1 stands, (0 0), and its
group's centroid lies between its robots: no two names may be drawn over each other.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest
from console_support import ConsoleGateway, wait_for
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
"""


@pytest.fixture(scope="module")
def console_gateway(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ConsoleGateway]:
    gw = start_gateway(tmp_path_factory.mktemp("console-labels"), TOGETHER)
    try:
        assert gw.http_url, f"no 'HTTP front end and console on' line:\n{gw.output}"
        yield ConsoleGateway(gw, gw.address, gw.http_url)
    finally:
        gw.stop()


def label_boxes(driver: Any) -> dict[str, list[float]]:
    """Each thing's name on the map: its box on the page, [left, top, right, bottom]."""
    boxes: dict[str, list[float]] = driver.execute_script(
        "const out = {};"
        "for (const g of document.querySelectorAll('#map g[data-service]')) {"
        "  const r = g.querySelector(':scope > text').getBoundingClientRect();"
        "  out[g.dataset.service] = [r.left, r.top, r.right, r.bottom];"
        "}"
        "return out;"
    )
    return boxes


def overlap(a: list[float], b: list[float]) -> bool:
    return a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]


def test_names_of_things_at_one_place_are_not_drawn_over_each_other(page: Any) -> None:
    boxes = wait_for(page, lambda d: (b := label_boxes(d)) and len(b) == 6 and b, "six names on the map")
    names = sorted(boxes)
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            assert not overlap(boxes[a], boxes[b]), f"the names {a} and {b} overlap: {boxes}"
