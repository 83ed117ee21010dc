"""What follows the selected service: the Drive panel's status, and the URL's ``#service``.

The Drive panel's status speaks of the selected robot only: the stop sent to a robot the
operator leaves is not shown beside the next one. The URL's fragment names the selected
service: typing another one selects it, and back and forward walk through the selections.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import pytest
from console_support import CSS, blur, eventually, select, velocity, wait_for

from clients.sync import Client

pytestmark = [pytest.mark.browser, pytest.mark.slow, pytest.mark.timeout(120)]

#: Seconds a late answer for the robot left behind has to (wrongly) show up in the status.
LATE_ANSWER_S = 1.0


def teleop_status(driver: Any) -> str:
    text: str = driver.execute_script("return document.querySelector('#teleop-status').textContent")
    return text


def selected(driver: Any) -> str | None:
    name: str | None = driver.execute_script("return window.PropertyConsole.selected()")
    return name


def view_title(driver: Any) -> str | None:
    title: str | None = driver.execute_script(
        "const h = document.querySelector('#service-view .view-head h2'); return h ? h.textContent : null"
    )
    return title


def test_the_drive_status_speaks_of_the_selected_robot_only(page: Any, client: Client) -> None:
    from selenium.webdriver.common.action_chains import ActionChains

    select(page, "scout1")
    blur(page)
    ActionChains(page).key_down("w").perform()
    try:
        wait_for(
            page, lambda d: teleop_status(d).startswith("driving scout1"), "driving scout1 in #teleop-status"
        )
        # Selecting another robot while driving stops scout1; what scout1 answers is not shown.
        wait_for(
            page, lambda d: d.find_element(CSS, '#services [data-service="scout2"]').click() or True, "scout2"
        )
    finally:
        ActionChains(page).key_up("w").perform()
    wait_for(page, lambda d: view_title(d) == "scout2", "scout2's view")
    eventually(lambda: float(np.linalg.norm(velocity(client, "scout1"))), lambda v: v == 0, "scout1 stopped")
    time.sleep(LATE_ANSWER_S)
    assert "scout1" not in teleop_status(page), teleop_status(page)

    page.find_element(CSS, "#teleop-stop").click()
    wait_for(
        page, lambda d: teleop_status(d).startswith("stopped scout2"), "stopped scout2 in #teleop-status"
    )
    select(page, "thermo1")
    wait_for(page, lambda d: teleop_status(d) == "", "an empty #teleop-status for a sensor")


def test_the_url_fragment_selects_a_service_and_back_and_forward_walk_the_selections(page: Any) -> None:
    page.execute_script("location.hash = '#scout2'")
    wait_for(
        page, lambda d: selected(d) == "scout2" and view_title(d) == "scout2", "scout2 selected by #scout2"
    )
    item = page.find_element(CSS, '#services [data-service="scout2"]')
    assert item.get_attribute("aria-selected") == "true"

    select(page, "thermo1")
    wait_for(page, lambda d: d.execute_script("return location.hash") == "#thermo1", "#thermo1 in the URL")
    select(page, "swarm")
    wait_for(page, lambda d: d.execute_script("return location.hash") == "#swarm", "#swarm in the URL")

    page.back()
    wait_for(
        page, lambda d: selected(d) == "thermo1" and view_title(d) == "thermo1", "thermo1 again after back"
    )
    page.back()
    wait_for(page, lambda d: selected(d) == "scout2" and view_title(d) == "scout2", "scout2 again after back")
    page.forward()
    wait_for(page, lambda d: selected(d) == "thermo1", "thermo1 again after forward")

    page.execute_script("location.hash = '#nothing-of-that-name'")
    time.sleep(0.3)
    assert selected(page) == "thermo1", "a fragment naming no service leaves the selection as it is"
