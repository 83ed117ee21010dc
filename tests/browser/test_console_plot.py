"""The console's plot, in a real headless Chromium against a real gateway that keeps history:
it opens with the last minute the gateway kept of a property, one line per element of a vector,
then follows it live."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from console_support import CONFIG, CSS, ConsoleGateway, eventually, prop, select, wait_for
from support.gateway_process import start_gateway

from clients.sync import Client
from clients.values import Marker

pytestmark = [pytest.mark.browser, pytest.mark.slow, pytest.mark.timeout(120)]

HISTORY = """
[history]
selectors = ["thermo1/data", "*/location"]
"""


@pytest.fixture(scope="module")
def console_gateway(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ConsoleGateway]:
    """The console's world, its sensor's readings and the robots' poses kept."""
    folder: Path = tmp_path_factory.mktemp("console-plot")
    gw = start_gateway(folder, CONFIG + HISTORY)
    try:
        yield ConsoleGateway(gw, gw.address, gw.http_url)
    finally:
        gw.stop()


def plot_state(page: Any, path: str) -> dict[str, Any]:
    """What the plot of ``path`` drew: the points from the history, and each line's points."""
    state: dict[str, Any] = page.execute_script(
        """
        const chart = document.querySelector(`#service-view [data-property="${arguments[0]}"] svg.plot`);
        if (!chart) return {history: null, lines: []};
        return {
          history: chart.dataset.historyPoints ?? null,
          lines: [...chart.querySelectorAll('polyline')].map(
            (l) => (l.getAttribute('points') || '').split(' ').filter(Boolean).length),
        };
        """,
        path,
    )
    return state


def test_a_plot_opens_with_the_minute_the_gateway_kept(page: Any, client: Client) -> None:
    kept = eventually(lambda: client.history("thermo1", "data"), lambda h: len(h) >= 4, "four kept readings")
    select(page, "thermo1")
    state = wait_for(
        page,
        lambda d: (s := plot_state(d, "data"))["history"] is not None and s,
        "the plot of thermo1's data asked the history",
    )
    assert int(state["history"]) >= len(kept.events), state
    assert state["lines"][0] >= len(kept.events), "every kept reading is a point of the line"
    # Then it follows the sensor live: more points than the history brought.
    wait_for(page, lambda d: plot_state(d, "data")["lines"][0] > int(state["history"]), "a live point")


def test_a_vector_is_plotted_one_line_per_element_from_its_history(page: Any, client: Client) -> None:
    client.set("scout2", "behaviors.moveto", Marker.at([3, 2]))
    eventually(lambda: client.history("scout2", "location"), lambda h: len(h) >= 5, "scout2 moving, kept")
    select(page, "scout2")
    toggle = wait_for(
        page,
        lambda d: prop(d, "location").find_element(CSS, "[data-action=plot]"),
        "a plot button on location",
    )
    toggle.click()
    state = wait_for(
        page,
        lambda d: (s := plot_state(d, "location"))["history"] not in (None, "0") and s,
        "the plot of scout2's location drawn from its history",
    )
    assert int(state["history"]) >= 5, state
    assert len(state["lines"]) == 6, "x y z roll pitch yaw"
    assert all(n >= 5 for n in state["lines"]), state
    legend = prop(page, "location").find_element(CSS, ".plot-legend").text.split()
    assert legend == ["x", "y", "z", "roll", "pitch", "yaw"]
    toggle.click()
    wait_for(
        page,
        lambda d: not d.find_elements(CSS, '#service-view [data-property="location"] svg.plot'),
        "closed",
    )
