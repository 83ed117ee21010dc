"""The console's map in a real headless Chromium: a click sends the selected robot or group there.

Where the robots go is checked through gRPC: toward the target the map marks,
a group in the formation and spacing chosen beside the map; the Stop button
ends a moveto.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import pytest
from console_support import (
    CSS,
    STOP_WITHIN,
    doc_image,
    eventually,
    pose_on_map,
    select,
    target_on_map,
    translation,
    velocity,
    wait_for,
    xy,
)

from clients.sync import Client
from services.apps.formations import formation_targets

pytestmark = [pytest.mark.browser, pytest.mark.slow, pytest.mark.timeout(120)]


def test_a_click_on_the_map_drives_the_selected_robot_there(page: Any, client: Client) -> None:
    from selenium.webdriver.common.action_chains import ActionChains

    select(page, "scout1")
    before = wait_for(page, lambda d: pose_on_map(d, "scout1"), "scout1 on the map")
    the_map = page.find_element(CSS, "#map")
    ActionChains(page).move_to_element_with_offset(the_map, 120, -80).click().perform()
    # The map marks where the click sends the robot, in world coordinates.
    target = translation(wait_for(page, lambda d: target_on_map(d, "scout1"), "scout1's target on the map"))
    away = float(np.linalg.norm(xy(client, "scout1") - target))
    assert away > 0.5, f"the click was {away} m from the robot"
    eventually(
        lambda: float(np.linalg.norm(xy(client, "scout1") - target)),
        lambda d: d < away - 0.1,
        f"scout1 heads for the target {target} the click set",
    )
    wait_for(
        page, lambda d: pose_on_map(d, "scout1") not in (None, before), "scout1's pose on the map follows it"
    )
    doc_image(page, "map")
    client.set("scout1", "behaviors.stop", "")


def test_a_click_on_the_map_drives_a_group_in_the_chosen_formation(page: Any, client: Client) -> None:
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.support.ui import Select

    select(page, "swarm")
    robots = ("scout1", "scout2")
    formation = wait_for(page, lambda d: d.find_element(CSS, "#formation"), "#formation for a group")
    wait_for(page, lambda d: formation.is_displayed(), "#formation shown while a group is selected")
    Select(formation).select_by_value("circle")
    spacing = page.find_element(CSS, "#spacing")
    spacing.clear()
    spacing.send_keys("1.5")
    ActionChains(page).move_to_element_with_offset(page.find_element(CSS, "#map"), -60, 60).click().perform()
    try:
        target = translation(wait_for(page, lambda d: target_on_map(d, "swarm"), "swarm's target on the map"))
        for name in robots:  # quicker, so that they arrive within the wait
            client.set(name, "speed", 50)
        places = formation_targets(robots, target, "circle", 1.5)
        for name, place in places.items():
            eventually(
                lambda n=name: xy(client, n),
                lambda p, at=place: bool(np.allclose(p, at, atol=0.01)),
                f"{name} at its place {place} of a circle of spacing 1.5 around the click {target}",
            )
    finally:
        client.set("swarm", "behaviors.stop", "")
        for name in robots:
            client.set(name, "speed", 0.5)
    for name in robots:
        eventually(lambda n=name: velocity(client, n), lambda v: not v.any(), f"{name} stopped")


@pytest.mark.parametrize("selected", ["scout1", "swarm"])
def test_the_stop_button_ends_a_moveto(page: Any, client: Client, selected: str) -> None:
    from selenium.webdriver.common.action_chains import ActionChains

    robots = ("scout1", "scout2") if selected == "swarm" else (selected,)
    select(page, selected)
    ActionChains(page).move_to_element_with_offset(page.find_element(CSS, "#map"), 150, 100).click().perform()
    try:
        for name in robots:
            eventually(lambda n=name: velocity(client, n), lambda v: v.any(), f"{name} on its way")
        page.find_element(CSS, "#teleop-stop").click()
        for name in robots:
            eventually(
                lambda n=name: velocity(client, n),
                lambda v: not v.any(),
                f"{name} stopped by the Stop button",
                within=STOP_WITHIN,
            )
        still = {name: client.get(name, "location") for name in robots}
        time.sleep(0.3)  # a robot still on its way would have moved meanwhile
        assert {name: client.get(name, "location") for name in robots} == still, "and stays stopped"
    finally:
        client.set("swarm", "behaviors.stop", "")


def test_the_map_grid_labels_do_not_overlap(page: Any) -> None:
    wait_for(page, lambda d: d.find_elements(CSS, "#map .grid-label"), "the map's grid labels")
    for _ in range(2):  # as drawn first, and after Fit zoomed to the robots
        overlaps = page.execute_script(
            """const boxes = [...document.querySelectorAll('#map .grid-label')]
                 .map(e => [e.textContent, e.getBoundingClientRect()]);
               const out = [];
               boxes.forEach(([a, p], i) => boxes.slice(i + 1).forEach(([b, q]) => {
                 const apart = p.right <= q.left || q.right <= p.left
                   || p.bottom <= q.top || q.bottom <= p.top;
                 if (!apart) out.push([a, b]);
               }));
               return out;"""
        )
        assert overlaps == [], f"grid labels drawn over each other: {overlaps}"
        page.find_element(CSS, "#map-fit").click()
