"""The console across a dead gateway, given the others: the page moves itself to the next console.

Two gateway processes serve the same world. The page is opened on the first with
``?gateways=`` naming the second and ``#scout1`` selected; the first is killed (SIGKILL),
and after the page's bound (``FAILOVER_AFTER_MS``, 10 s) it is the second's console, live,
with scout1 selected, and its top bar says where it came from. With both dead it stays and
names every address it tried.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from console_support import CONFIG, page_errors, save_screenshot, wait_for
from support.gateway_process import GatewayProcess, start_gateway

pytestmark = [pytest.mark.browser, pytest.mark.slow, pytest.mark.timeout(150)]

#: The page's bound (10 s) plus EventSource's own retries and a probe, on two loaded cores.
MOVE_WITHIN = 45.0


def connection(driver: Any) -> str | None:
    state: str | None = driver.execute_script(
        "const c = document.querySelector('#connection'); return c ? c.dataset.state : null"
    )
    return state


def selected_service(driver: Any) -> str | None:
    name: str | None = driver.execute_script(
        "const s = document.querySelector('#services .service.selected'); return s ? s.dataset.service : null"
    )
    return name


def failover_text(driver: Any) -> str:
    text: str = driver.execute_script(
        "const f = document.querySelector('#failover'); return f && !f.hidden ? f.textContent : ''"
    )
    return text


@pytest.fixture
def gateways(tmp_path: Path) -> Iterator[list[GatewayProcess]]:
    started = [start_gateway(tmp_path, CONFIG), start_gateway(tmp_path, CONFIG)]
    yield started
    for gw in started:
        gw.stop()


def kill(gw: GatewayProcess) -> None:
    """SIGKILL, this PID only: the gateway vanishes without closing its streams politely."""
    gw.proc.kill()
    gw.proc.wait(10)


def test_the_page_moves_to_the_next_gateway_when_its_own_dies(
    browser: Any, gateways: list[GatewayProcess]
) -> None:
    first, second = gateways
    try:
        page_errors(browser)  # read and so dropped: what earlier tests left
        browser.get(f"{first.http_url}?gateways={second.http_url}#scout1")
        wait_for(browser, lambda d: connection(d) == "open", "#connection open")
        wait_for(browser, lambda d: selected_service(d) == "scout1", "scout1 selected from #scout1")

        kill(first)
        wait_for(
            browser,
            lambda d: d.current_url.startswith(second.http_url),
            f"the page on the second gateway's console {second.http_url}",
            within=MOVE_WITHIN,
        )
        wait_for(
            browser, lambda d: connection(d) == "open", "#connection open on the second gateway", within=20.0
        )
        wait_for(browser, lambda d: selected_service(d) == "scout1", "scout1 still selected after the move")
        assert browser.execute_script("return location.hash") == "#scout1"
        assert failover_text(browser) == f"moved here from {first.http_url} (unreachable)"
        assert second.http_url.rstrip("/") in browser.execute_script(
            "return new URLSearchParams(location.search).get('gateways')"
        ), "the gateway list goes along"

        # Now the second dies too, and the first is gone: one round, then the page stays.
        kill(second)
        wait_for(
            browser,
            lambda d: failover_text(d).startswith("every gateway unreachable"),
            "the page saying every gateway is unreachable",
            within=MOVE_WITHIN,
        )
        text = failover_text(browser)
        assert first.http_url in text and second.http_url in text, text
        assert browser.current_url.startswith(second.http_url), "the page stayed where it was"
        assert not page_errors(browser), "the page threw or logged errors"
    finally:
        save_screenshot(browser, "test_the_page_moves_to_the_next_gateway_when_its_own_dies")
