"""The demo's camera, environment model and patrol state machine in the console, as docs/vision.md,
docs/environment.md, docs/statemachine.md and docs/console.md show them.

Each view is checked for what its image shows (a frame drawn, the heat map with its legend, the
chart with an active state), then kept as a doc image: ``PS_DOC_IMAGES=1`` refreshes
``console-demo-camera.png``, ``console-demo-environment.png`` and ``console-statechart.png``.
"""

from __future__ import annotations

from typing import Any

import pytest
from console_support import CSS, doc_image, select, wait_for

from clients.sync import Client

pytestmark = [pytest.mark.browser, pytest.mark.slow]


def test_the_demos_camera_heat_map_and_patrol_machine_show_in_the_console(
    browser: Any, demo_gateway: Any
) -> None:
    browser.get(demo_gateway.http_url)
    wait_for(
        browser, lambda d: d.find_elements(CSS, '#services [data-service="camera1"]'), "the demo's services"
    )

    select(browser, "camera1")
    wait_for(
        browser,
        lambda d: d.execute_script(
            "const i = document.querySelector('#service-view img.live-image');"
            " return !!i && i.complete && i.naturalWidth > 0;"
        ),
        "camera1's frame drawn",
    )
    browser.execute_script(
        "document.querySelector('#service-view img.live-image').scrollIntoView({block: 'center'})"
    )
    doc_image(browser, "demo-camera")

    select(browser, "environment")
    heat = wait_for(
        browser,
        lambda d: d.find_element(
            CSS, '#service-view [data-property="grid.temperature.image"] .heat-map[data-legend=drawn]'
        ),
        "the temperature heat map with its legend",
    )
    assert heat.find_elements(CSS, ".heat-axis-x .tick"), "the heat map's x axis"
    legend = browser.find_element(CSS, '#service-view [data-property="grid.temperature.image"] .heat-legend')
    assert legend.find_element(CSS, ".heat-high").text.endswith(" degC"), legend.text
    browser.execute_script("arguments[0].scrollIntoView({block: 'center'})", heat)
    doc_image(browser, "demo-environment")

    with Client(demo_gateway.address) as client:
        if client.get("missions", "patrol.status").strip() != "running":
            client.set("missions", "patrol.start", "")
    select(browser, "missions")
    wait_for(
        browser,
        lambda d: d.find_element(CSS, "#service-view .statechart-active").text.strip(),
        "the patrol machine's active state named",
    )
    wait_for(
        browser,
        lambda d: (
            d.find_element(CSS, "#service-view img.statechart-image").get_attribute("src") or ""
        ).startswith("data:image/svg+xml"),
        "the patrol chart drawn",
    )
    browser.execute_script(
        "document.querySelector('#service-view img.statechart-image').scrollIntoView({block: 'center'})"
    )
    doc_image(browser, "statechart")
