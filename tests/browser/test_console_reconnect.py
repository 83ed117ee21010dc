"""The console across a gateway restart: the page says it lost the stream, and picks it up again.

A gateway on fixed loopback ports (chosen free) is stopped while the page is
open, and a new one started on the same ports: ``#connection`` leaves ``open``,
comes back to ``open``, and a Set through gRPC on the new gateway shows in the
service view the page had open, with no reload.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from console_support import CONFIG, page_errors, save_screenshot, wait_for
from support.gateway_process import GatewayProcess, start_gateway
from support.ports import free_port

from clients.sync import Client

pytestmark = [pytest.mark.browser, pytest.mark.slow, pytest.mark.timeout(120)]

CSS = "css selector"


def connection(driver: Any) -> str | None:
    state: str | None = driver.execute_script(
        "const c = document.querySelector('#connection'); return c ? c.dataset.state : null"
    )
    return state


def shown(driver: Any, path: str) -> str | None:
    text: str | None = driver.execute_script(
        'const v = document.querySelector(`#service-view [data-property="${arguments[0]}"] .value`);'
        "return v ? v.textContent.trim() : null",
        path,
    )
    return text


@pytest.fixture
def gateways(tmp_path: Path) -> Iterator[list[GatewayProcess]]:
    started: list[GatewayProcess] = []
    yield started
    for gw in started:
        gw.stop()


def test_the_page_reconnects_to_a_restarted_gateway(
    browser: Any, tmp_path: Path, gateways: list[GatewayProcess]
) -> None:
    ports = ["--listen", f"127.0.0.1:{free_port()}", "--http", f"127.0.0.1:{free_port()}"]
    gateways.append(start_gateway(tmp_path, CONFIG, ports))
    url = gateways[0].http_url
    try:
        page_errors(browser)  # read and so dropped: what earlier tests left
        browser.get(url)
        wait_for(browser, lambda d: connection(d) == "open", "#connection open")
        wait_for(
            browser,
            lambda d: d.find_element(CSS, '#services [data-service="scout1"]').click() or True,
            "a click on scout1",
        )
        wait_for(browser, lambda d: shown(d, "max_speed") == "1", "scout1's max_speed 1 in the view")

        gateways[0].stop()
        wait_for(browser, lambda d: connection(d) != "open", "#connection no longer open after the stop")

        gateways.append(start_gateway(tmp_path, CONFIG, ports))
        assert gateways[1].http_url == url, "the new gateway serves the same address"
        wait_for(browser, lambda d: connection(d) == "open", "#connection open again", within=30.0)
        with Client(gateways[1].address, timeout=10.0) as client:
            client.set("scout1", "max_speed", 0.8)
        wait_for(
            browser,
            lambda d: shown(d, "max_speed") == "0.8",
            "a Set on the new gateway in the view opened before the restart",
        )
        assert not page_errors(browser), "the page threw or logged errors"
    finally:
        save_screenshot(browser, "test_the_page_reconnects_to_a_restarted_gateway")
