"""The console's inspector in a real headless Chromium: Get, Set and Listen on any path.

The Set is checked through gRPC; a gRPC Set shows up in the Listen's event log.
"""

from __future__ import annotations

from typing import Any

import pytest
from console_support import (
    CSS,
    doc_image,
    eventually,
    wait_for,
)

from clients.sync import Client

pytestmark = [pytest.mark.browser, pytest.mark.slow, pytest.mark.timeout(120)]


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
