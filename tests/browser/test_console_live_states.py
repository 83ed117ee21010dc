"""What the console shows while its gateway is away, and after it is back.

A gateway on fixed loopback ports (chosen free) is stopped while the page is open and a new
one is started on the same ports. While it is away every service shows as ``unknown`` (grey),
never the ``up`` it had; once it answers again, each shows its state again. The inspector's
Listen survives the restart, and once stopped it logs nothing more.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from console_support import CONFIG, CSS, doc_image, page_errors, save_screenshot, wait_for
from support.gateway_process import GatewayProcess, start_gateway
from support.ports import free_port

from clients.sync import Client

pytestmark = [pytest.mark.browser, pytest.mark.slow, pytest.mark.timeout(180)]

#: Seconds the page has to notice a stopped gateway, or a started one (EventSource's own retry and
#: the backoff after it; two loaded cores).
NOTICE_WITHIN = 30.0
#: Seconds the inspector's log is watched for entries after its Listen was stopped.
QUIET_FOR = 2.0


def states(driver: Any) -> dict[str, tuple[str, str]]:
    """Each listed service's ``data-state`` and its state text, read in one script."""
    found: dict[str, tuple[str, str]] = driver.execute_script(
        "const out = {};"
        "for (const li of document.querySelectorAll('#services [data-service]')) {"
        "  out[li.dataset.service] = [li.dataset.state, li.querySelector('.service-state').textContent];"
        "}"
        "return out;"
    )
    return {name: (state, text) for name, (state, text) in found.items()}


def log_size(driver: Any) -> int:
    size: int = driver.execute_script("return document.querySelectorAll('#inspector-log li').length")
    return size


def location_events(driver: Any) -> int:
    count: int = driver.execute_script(
        "return [...document.querySelectorAll('#inspector-log li[data-path]')]"
        ".filter((li) => li.dataset.path === 'location').length"
    )
    return count


@pytest.fixture
def gateways(tmp_path: Path) -> Iterator[list[GatewayProcess]]:
    started: list[GatewayProcess] = []
    yield started
    for gw in started:
        if gw.proc.poll() is None:
            gw.stop()


def test_services_show_unknown_while_the_gateway_is_away_and_the_truth_once_it_is_back(
    browser: Any, tmp_path: Path, gateways: list[GatewayProcess]
) -> None:
    ports = ["--listen", f"127.0.0.1:{free_port()}", "--http", f"127.0.0.1:{free_port()}"]
    gateways.append(start_gateway(tmp_path, CONFIG, ports))
    page_errors(browser)  # read and so dropped: what earlier tests left
    try:
        browser.get(gateways[0].http_url)
        wait_for(
            browser,
            lambda d: len(s := states(d)) >= 4 and all(state == "up" for state, _ in s.values()),
            "every service up",
            within=NOTICE_WITHIN,
        )
        wait_for(
            browser,
            lambda d: d.find_element(CSS, '#services [data-service="scout1"]').click() or True,
            "scout1",
        )
        wait_for(browser, lambda d: d.find_elements(CSS, "#service-view [data-property]"), "scout1's view")

        gateways[0].stop()
        wait_for(
            browser,
            lambda d: all(s == ("unknown", "unknown") for s in states(d).values()),
            "every service unknown while the gateway is away",
            within=NOTICE_WITHIN,
        )
        badge = browser.find_element(CSS, "#service-view .view-head .badge")
        assert badge.get_attribute("data-state") == "unknown", badge.text
        doc_image(browser, "gateway-away")
        # It stays so: nothing the page retries meanwhile brings back an "up" nobody vouched for.
        time.sleep(QUIET_FOR)
        assert all(s == ("unknown", "unknown") for s in states(browser).values()), states(browser)

        gateways.append(start_gateway(tmp_path, CONFIG, ports))
        wait_for(
            browser,
            lambda d: all(state == "up" for state, _ in states(d).values()),
            "every service up again once the gateway answers",
            within=NOTICE_WITHIN,
        )
        wait_for(
            browser,
            lambda d: (
                d.find_element(CSS, "#service-view .view-head .badge").get_attribute("data-state") == "up"
            ),
            "scout1's badge up again",
        )
        errors = page_errors(browser)
        assert not errors, f"the page threw or logged errors: {errors}"
    finally:
        save_screenshot(browser, "live_states_unknown")


def test_a_listen_stopped_after_a_reconnect_logs_nothing_more(
    browser: Any, tmp_path: Path, gateways: list[GatewayProcess]
) -> None:
    ports = ["--listen", f"127.0.0.1:{free_port()}", "--http", f"127.0.0.1:{free_port()}"]
    gateways.append(start_gateway(tmp_path, CONFIG, ports))
    page_errors(browser)
    try:
        browser.get(gateways[0].http_url)
        wait_for(browser, lambda d: d.find_elements(CSS, "#services [data-service]"), "a service list")
        service = browser.find_element(CSS, "#inspector-service")
        service.clear()
        service.send_keys("*")
        path = browser.find_element(CSS, "#inspector-path")
        path.clear()
        path.send_keys("location")
        browser.find_element(CSS, "#inspector-listen").click()
        wait_for(browser, lambda d: location_events(d) > 0, "location events in the inspector's log")

        gateways[0].stop()
        wait_for(
            browser,
            lambda d: d.find_element(CSS, "#connection").get_attribute("data-state") != "open",
            "#connection no longer open",
        )
        gateways.append(start_gateway(tmp_path, CONFIG, ports))
        with Client(gateways[1].address, timeout=10.0) as client:
            client.set("scout1", "behaviors.moveto", "<marker><location>(40 40)</location></marker>")
        wait_for(
            browser,
            lambda d: d.find_element(CSS, "#connection").get_attribute("data-state") == "open",
            "#connection open again",
            within=NOTICE_WITHIN,
        )
        # The Listen went on through the restart: the moving robot is logged, and it still listens.
        logged = location_events(browser)
        wait_for(
            browser, lambda d: location_events(d) > logged + 2, "scout1 moving, logged after the restart"
        )
        listen = browser.find_element(CSS, "#inspector-listen")
        assert listen.get_attribute("aria-pressed") == "true", browser.find_element(
            CSS, "#inspector-output"
        ).text

        listen.click()
        output = browser.find_element(CSS, "#inspector-output").text
        assert output == "Stopped listening to */location", output
        stopped_at = log_size(browser)
        time.sleep(QUIET_FOR)  # scout1 keeps moving meanwhile
        assert log_size(browser) == stopped_at, "the inspector logged events after its Listen was stopped"
        errors = page_errors(browser)
        assert not errors, f"the page threw or logged errors: {errors}"
    finally:
        save_screenshot(browser, "live_states_listen")
