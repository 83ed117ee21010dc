"""The console on a gateway of fifty robots: every view follows its values live.

The page's one event stream may name at most ``[limits] max_selectors`` (64) selectors, and a
view of the group of fifty robots shows some 700 properties, the registry's some 650. The page
covers them with a few wildcards (``js/selector_cover.js``): no view reads anything "once", and
a property deep in the group (``robots.scout37.location``) moves on the page as the robot drives.
The test prints what the cover cost: the value events the page received, and how many of them
no view wanted.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest
from console_support import CSS, doc_image, page_errors, pose_on_map, save_screenshot, select, wait_for
from support.gateway_process import GatewayProcess, start_gateway

from clients.sync import Client

pytestmark = [pytest.mark.browser, pytest.mark.slow, pytest.mark.timeout(240)]

ROBOTS = 50
#: The robots the test drives; the others stand still.
DRIVEN = ("scout37", "scout50")
#: Seconds a live value has to change in: the gateway, 50 simulated robots and Chromium share
#: two loaded cores.
LIVE_WITHIN = 30.0


def fleet_config(robots: int = ROBOTS) -> str:
    """A gateway config of ``robots`` simulated robots on a 10-wide grid 1 m apart and a group of them all."""
    parts = ["[registry]\nperiod = 0.5\ntimeout = 1.0\nmisses = 2\n"]
    for i in range(robots):
        parts.append(
            f'[[services]]\nname = "scout{i + 1}"\ntype = "sim-robot"\n'
            f"options = {{ start = [{i % 10}.0, {i // 10}.0] }}\n"
        )
    parts.append(
        '[[services]]\nname = "swarm"\ntype = "group"\noptions = { query = { type = "mobile_robot" } }\n'
    )
    return "\n".join(parts)


@pytest.fixture(scope="module")
def fleet(tmp_path_factory: pytest.TempPathFactory) -> Iterator[GatewayProcess]:
    gw = start_gateway(tmp_path_factory.mktemp("fleet"), fleet_config())
    try:
        yield gw
    finally:
        gw.stop()


def value_text(driver: Any, path: str) -> str | None:
    """The service view's value text of ``path``, read in one script (the view may be rebuilt)."""
    text: str | None = driver.execute_script(
        'const v = document.querySelector(`#service-view [data-property="${arguments[0]}"] .value`);'
        "return v ? v.textContent.trim() : null",
        path,
    )
    return text


def notices(driver: Any) -> list[str]:
    return [el.text for el in driver.find_elements(CSS, "#service-view .notice")]


def changes_live(driver: Any, path: str, what: str) -> None:
    """Wait for ``path``'s value in the view, then for two changes of it."""
    first = wait_for(driver, lambda d: value_text(d, path), f"{what}: a value", within=LIVE_WITHIN)
    second = wait_for(
        driver,
        lambda d: (v := value_text(d, path)) not in (None, first) and v,
        f"{what} changing",
        within=LIVE_WITHIN,
    )
    wait_for(
        driver,
        lambda d: value_text(d, path) not in (None, second),
        f"{what} changing again",
        within=LIVE_WITHIN,
    )


def stream_stats(driver: Any) -> dict[str, Any]:
    stats: dict[str, Any] = driver.execute_script("return window.PropertyConsole.streamStats()")
    return stats


def cost_of_view(driver: Any, name: str, before: dict[str, Any]) -> dict[str, Any]:
    """Check the stream while ``name`` is shown, print what it cost since ``before``, return the stats now."""
    now = stream_stats(driver)
    assert len(now["selectors"]) <= 64, now["selectors"]
    assert now["leftOut"] == 0, now
    received = now["received"] - before["received"]
    unwanted = now["unwanted"] - before["unwanted"]
    print(
        f"\n{name}: {now['subscriptions']} subscriptions in {len(now['selectors'])} selectors;"
        f" {received} value events received,"
        f" {unwanted} ({100 * unwanted / max(1, received):.1f} %) wanted by none"
        f"\n  {' '.join(now['selectors'])}"
    )
    return now


def test_every_view_of_fifty_robots_follows_its_values_live(browser: Any, fleet: GatewayProcess) -> None:
    with Client(fleet.address, timeout=10.0) as client:
        for robot in DRIVEN:  # far away: they drive for the whole test
            client.set(robot, "behaviors.moveto", "<marker><location>(60 60)</location></marker>")
    page_errors(browser)  # read and so dropped: what earlier tests left
    try:
        browser.get(fleet.http_url)
        wait_for(
            browser,
            lambda d: len(d.find_elements(CSS, "#services [data-service]")) >= ROBOTS + 2,
            "the fifty robots, the group and the registry in the list",
            within=LIVE_WITHIN,
        )
        stats = stream_stats(browser)

        select(browser, "swarm")
        changes_live(browser, "robots.scout37.location", "swarm: robots.scout37.location")
        changes_live(
            browser, "robots.scout50.sensors.temperature", "swarm: robots.scout50.sensors.temperature"
        )
        assert not notices(browser), f"the group's view reads something once: {notices(browser)}"
        shown = len(browser.find_elements(CSS, "#service-view [data-property]"))
        assert shown > 14 * ROBOTS, f"the group's view shows {shown} properties"
        doc_image(browser, "fifty-robots")
        stats = cost_of_view(browser, "swarm", stats)

        select(browser, "registry")
        changes_live(browser, "services.scout50.location", "registry: services.scout50.location")
        assert not notices(browser), f"the registry's view reads something once: {notices(browser)}"
        stats = cost_of_view(browser, "registry", stats)

        select(browser, "scout37")
        changes_live(browser, "location", "scout37: location")
        assert not notices(browser), f"scout37's view reads something once: {notices(browser)}"
        before = pose_on_map(browser, "scout50")
        wait_for(
            browser, lambda d: pose_on_map(d, "scout50") not in (None, before), "scout50 moving on the map"
        )
        cost_of_view(browser, "scout37", stats)

        errors = page_errors(browser)
        assert not errors, f"the page threw or logged errors: {errors}"
    finally:
        save_screenshot(browser, "fifty_robots")
