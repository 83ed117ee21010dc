"""Fixtures of the browser tests: a real gateway process with its HTTP front end, one headless Chromium.

* ``console_gateway`` (per module): ``psgateway serve`` with a small world
  (``console_support.CONFIG``: scout1, scout2, thermo1 and the group ``swarm``)
  and ``--http 127.0.0.1:0``; ``.address`` is the gRPC address, ``.url`` the console's;
  ``client`` (per module) the SDK's blocking client of it.
* ``browser`` (per session): the Selenium driver of Debian's Chromium
  (``PS_CHROMIUM`` and ``PS_CHROMEDRIVER`` name other paths). When Chromium,
  chromedriver or Selenium is missing, every test here skips, and the skip
  (printed, and in pytest's ``-ra`` summary) names what is missing.
* ``page`` (per test): the console loaded in that browser; when the test ends,
  pass or fail, a screenshot goes to ``build/screenshots/TEST.png``, and an
  uncaught exception or ``console.error`` in the page fails the test.
"""

from __future__ import annotations

import sys
from collections.abc import Iterator
from typing import Any

import pytest
from console_support import (
    ConsoleGateway,
    chromium,
    console_gateway_process,
    missing_browser,
    page_errors,
    save_screenshot,
    wait_for,
)

from clients.sync import Client


@pytest.fixture(scope="module")
def console_gateway(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ConsoleGateway]:
    with console_gateway_process(tmp_path_factory.mktemp("console")) as gw:
        yield gw


@pytest.fixture(scope="module")
def client(console_gateway: ConsoleGateway) -> Iterator[Client]:
    """The SDK's blocking client of the module's gateway: how a test checks what the page did."""
    with Client(console_gateway.address, timeout=10.0) as c:
        yield c


@pytest.fixture(scope="session")
def browser() -> Iterator[Any]:
    """One headless Chromium for every browser test (starting one costs a second or more)."""
    reason = missing_browser()
    if reason is not None:
        print(reason, file=sys.stderr)
        pytest.skip(reason)
    with chromium() as driver:
        yield driver


@pytest.fixture
def page(browser: Any, console_gateway: ConsoleGateway, request: pytest.FixtureRequest) -> Iterator[Any]:
    """The console freshly loaded, its service list filled; a screenshot of it when the test ends,
    and a failure if the page threw or logged an error meanwhile (refused requests are expected)."""
    browser.get_log("browser")  # read and so dropped: what earlier tests left
    browser.get(console_gateway.url)
    wait_for(browser, lambda d: d.find_elements("css selector", "#services [data-service]"), "a service list")
    yield browser
    save_screenshot(browser, request.node.name)
    errors = page_errors(browser)
    assert not errors, f"the page threw or logged errors: {errors}"
