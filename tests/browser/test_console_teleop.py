"""Teleoperation from the console in a real headless Chromium: keys and joystick drive, letting go stops.

The robot's ``velocity`` (through gRPC) is the check. Where a stop must be the
page's doing, the robot's ``velocity_timeout`` is first raised to TELEOP_HOLD
seconds, so a stop within STOP_WITHIN cannot be the timeout's.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import pytest
from console_support import (
    CSS,
    STOP_WITHIN,
    ConsoleGateway,
    blur,
    doc_image,
    eventually,
    forward,
    select,
    velocity,
    wait_for,
    xy,
)

from clients.sync import Client

pytestmark = [pytest.mark.browser, pytest.mark.slow, pytest.mark.timeout(120)]

#: Seconds a velocity command holds once a test raised the robot's velocity_timeout.
TELEOP_HOLD = 30.0


def test_teleop_with_the_keyboard_moves_the_robot_and_releasing_stops_it(page: Any, client: Client) -> None:
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.keys import Keys

    select(page, "scout2")
    start = xy(client, "scout2")
    blur(page)
    try:
        ActionChains(page).key_down(Keys.ARROW_UP).perform()
        eventually(lambda: forward(client, "scout2"), lambda v: v > 0, "scout2 drives forward")
        wait_for(page, lambda d: d.find_element(CSS, "#teleop-status").text.strip(), "#teleop-status")
        doc_image(page, "teleop")
        # Held for a second, twice the robot's velocity_timeout: it still drives only if the
        # console renews the command while the key is down.
        time.sleep(1.0)
        eventually(
            lambda: forward(client, "scout2"), lambda v: v > 0, "still driving after 1 s held", within=1.0
        )
        # From now on a command holds for TELEOP_HOLD seconds: a stop within STOP_WITHIN is the console's.
        client.set("scout2", "velocity_timeout", TELEOP_HOLD)
        ActionChains(page).key_up(Keys.ARROW_UP).perform()
        eventually(
            lambda: velocity(client, "scout2"),
            lambda v: not v.any(),
            "scout2 stops when the key is released",
            within=STOP_WITHIN,
        )
    finally:
        ActionChains(page).key_up(Keys.ARROW_UP).perform()
        client.set("scout2", "velocity_timeout", 0.5)
    assert float(np.linalg.norm(xy(client, "scout2") - start)) > 0.1, "scout2 moved"


def test_keys_typed_into_an_input_do_not_drive(page: Any, client: Client) -> None:
    from selenium.webdriver.common.action_chains import ActionChains

    select(page, "scout2")
    start = client.get("scout2", "location")
    field = page.find_element(CSS, "#inspector-path")
    field.clear()
    field.click()
    ActionChains(page).key_down("w").perform()
    try:
        wait_for(page, lambda d: field.get_attribute("value") == "w", "the w typed into #inspector-path")
        time.sleep(0.3)  # time for a (wrong) command to reach the robot
        assert not velocity(client, "scout2").any(), "a key typed into an input drove the robot"
    finally:
        ActionChains(page).key_up("w").perform()
    assert client.get("scout2", "location") == start, "scout2 never moved"


def test_the_joystick_drives_and_letting_go_stops(page: Any, client: Client) -> None:
    from selenium.webdriver.common.action_chains import ActionChains

    select(page, "scout2")
    client.set("scout2", "velocity_timeout", TELEOP_HOLD)
    stick = wait_for(page, lambda d: d.find_element(CSS, "#joystick"), "#joystick")
    try:
        # Press the middle of the stick and push it up: forward.
        ActionChains(page).move_to_element(stick).click_and_hold().move_by_offset(0, -40).perform()
        eventually(lambda: forward(client, "scout2"), lambda v: v > 0, "scout2 drives forward with the stick")
        ActionChains(page).release().perform()
        eventually(
            lambda: velocity(client, "scout2"),
            lambda v: not v.any(),
            "scout2 stops when the stick is let go",
            within=STOP_WITHIN,
        )
    finally:
        ActionChains(page).release().perform()
        client.set("scout2", "velocity_timeout", 0.5)


def test_a_robot_selected_after_a_group_drives_along_its_heading(page: Any, client: Client) -> None:
    """docs/console.md: "along the heading" is a robot's default, "as on the map" a group's."""
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.keys import Keys

    select(page, "swarm")
    select(page, "scout2")
    assert page.find_element(CSS, "#teleop-mode").get_attribute("value") == "heading"
    blur(page)
    try:
        ActionChains(page).key_down(Keys.ARROW_UP).perform()
        v = eventually(lambda: velocity(client, "scout2"), lambda v: v.any(), "scout2 drives")
        yaw = float(np.asarray(client.get_vector("scout2", "location"))[5])
        heading = np.array([np.cos(yaw), np.sin(yaw)])
        assert float(v[:2] @ heading) > 0 and abs(float(heading[0] * v[1] - heading[1] * v[0])) < 0.05, (
            f"velocity {v[:2]} is not along the heading {heading}"
        )
    finally:
        ActionChains(page).key_up(Keys.ARROW_UP).perform()
    eventually(lambda: velocity(client, "scout2"), lambda v: not v.any(), "scout2 stops", within=STOP_WITHIN)


def test_a_stick_mode_the_operator_picks_stays(page: Any) -> None:
    from selenium.webdriver.support.ui import Select

    select(page, "scout2")
    Select(page.find_element(CSS, "#teleop-mode")).select_by_value("map")
    select(page, "swarm")
    select(page, "scout1")
    assert page.find_element(CSS, "#teleop-mode").get_attribute("value") == "map"


@pytest.mark.parametrize("how", ["navigate away", "close the tab"])
def test_losing_the_page_stops_a_teleoperated_robot(
    page: Any, client: Client, console_gateway: ConsoleGateway, how: str
) -> None:
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.keys import Keys

    home = page.current_window_handle
    if how == "close the tab":
        page.switch_to.new_window("tab")
        page.get(console_gateway.url)
    select(page, "scout2")
    blur(page)
    # A command now holds for TELEOP_HOLD seconds: a stop within STOP_WITHIN is the page's doing.
    client.set("scout2", "velocity_timeout", TELEOP_HOLD)
    try:
        ActionChains(page).key_down(Keys.ARROW_UP).perform()
        eventually(lambda: forward(client, "scout2"), lambda v: v > 0, "scout2 drives forward")
        if how == "close the tab":
            page.close()
            page.switch_to.window(home)
        else:
            page.get("about:blank")
        eventually(
            lambda: velocity(client, "scout2"),
            lambda v: not v.any(),
            f"scout2 stops when the page goes away ({how})",
            within=STOP_WITHIN,
        )
    finally:
        if page.current_window_handle != home:
            page.close()
            page.switch_to.window(home)
        ActionChains(page).key_up(Keys.ARROW_UP).perform()
        client.set("scout2", "velocity_timeout", 0.5)
        client.set("scout2", "velocity", "(0 0 0 0 0 0)")
