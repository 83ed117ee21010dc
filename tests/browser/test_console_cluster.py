"""The cluster page in a real headless Chromium, against three real gateway processes on real etcd.

The page (``/console/cluster.html``) draws a card per gateway from the registry's ``cluster`` view
and a row per device from ``services.*.owner``, live: an admin drains a gateway by its card's
button, and the page shows that gateway draining with nothing owned, and every device with its
new owner, without being loaded again. Without etcd, Chromium or Selenium the test skips.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from console_support import CSS, device_process, doc_image, page_errors, save_screenshot, wait_for
from support.etcd import EtcdServer
from support.gateway_process import GatewayProcess, start_gateway

from clients.sync import Client

pytestmark = [pytest.mark.browser, pytest.mark.slow, pytest.mark.timeout(120)]

IDS = ("gw-a", "gw-b", "gw-c")
DEVICES = ("rover1", "rover2", "thermo1", "thermo2", "thermo3", "thermo4")


def _config(etcd: EtcdServer, gateway: str) -> str:
    return f"""
        [registry]
        store = "{etcd.url}"
        store_lease = 3.0
        gateway_id = "{gateway}"
        period = 0.5
        """


@pytest.fixture
def cluster(etcd_server: Callable[..., EtcdServer], tmp_path: Path) -> Iterator[dict[str, GatewayProcess]]:
    etcd = etcd_server()
    gateways: dict[str, GatewayProcess] = {}
    try:
        for gateway in IDS:
            gateways[gateway] = start_gateway(tmp_path, _config(etcd, gateway))
        yield gateways
    finally:
        for gw in gateways.values():
            gw.stop()


def _card(driver: Any, gateway: str) -> Any:
    return driver.find_element(CSS, f'#members [data-member="{gateway}"]')


def _owned(driver: Any, gateway: str) -> str:
    return str(_card(driver, gateway).find_element(CSS, ".owned").get_attribute("data-owned"))


def test_the_cluster_page_shows_who_owns_what_and_a_drain_from_it_moves_every_device(
    browser: Any, cluster: dict[str, GatewayProcess]
) -> None:
    with (
        device_process("--service", "sim-robot", "--name", "rover1") as (_, rover1),
        device_process("--service", "sim-robot", "--name", "rover2") as (_, rover2),
        device_process("--service", "sim-sensor", "--name", "thermo1") as (_, thermo1),
        device_process("--service", "sim-sensor", "--name", "thermo2") as (_, thermo2),
        device_process("--service", "sim-sensor", "--name", "thermo3") as (_, thermo3),
        device_process("--service", "sim-sensor", "--name", "thermo4") as (_, thermo4),
    ):
        urls = dict(zip(DEVICES, (rover1, rover2, thermo1, thermo2, thermo3, thermo4), strict=True))
        placed = {"rover1": "gw-a", "thermo1": "gw-a", "thermo2": "gw-a", "rover2": "gw-b", "thermo3": "gw-b"}
        placed["thermo4"] = "gw-c"
        for name, gateway in placed.items():
            with Client(cluster[gateway].address, timeout=10.0) as client:
                client.set("registry", f"services.{name}", urls[name])

        browser.get_log("browser")
        browser.get(f"{cluster['gw-c'].http_url}console/cluster.html")
        for gateway, owned in (("gw-a", "3"), ("gw-b", "2"), ("gw-c", "1")):
            wait_for(
                browser,
                lambda d, g=gateway, o=owned: _owned(d, g) == o,
                f"{gateway}'s card with {owned} devices",
            )
        rows = wait_for(
            browser, lambda d: d.find_elements(CSS, "#devices tbody tr[data-device]"), "device rows"
        )
        wait_for(
            browser, lambda d: len(d.find_elements(CSS, "#devices tbody tr[data-device]")) == 6, "6 rows"
        )
        assert rows
        card = _card(browser, "gw-a")
        assert card.get_attribute("data-state") == "serving" and card.get_attribute("data-health") == "ok"
        assert "0.1.0" in card.text or "version" in card.text

        # An admin drains gw-a from its card: its devices go to gw-b and gw-c, and the page follows.
        # The cards are drawn anew with each view: a click on one just replaced is tried again.
        wait_for(
            browser,
            lambda d: _card(d, "gw-a").find_element(CSS, 'button[data-action="drain"]').click() or True,
            "a click on gw-a's Drain button",
        )
        wait_for(
            browser,
            lambda d: _card(d, "gw-a").get_attribute("data-state") == "draining" and _owned(d, "gw-a") == "0",
            "gw-a draining, owning nothing",
        )
        wait_for(browser, lambda d: _owned(d, "gw-b") == "3" and _owned(d, "gw-c") == "3", "3 and 3")
        wait_for(
            browser,
            lambda d: (
                not d.find_elements(CSS, '#devices tr[data-owner="gw-a"]')
                and len(d.find_elements(CSS, "#devices tr[data-device]")) == 6
            ),
            "no device owned by gw-a in the table",
        )
        assert _card(browser, "gw-a").find_element(CSS, 'button[data-action="undrain"]')
        doc_image(browser, "cluster")
        save_screenshot(browser, "cluster-drained")
        errors = page_errors(browser)
        assert not errors, f"the page threw or logged errors: {errors}"
