"""Stop all: one button that stops every robot and group, after asking, and says who answered.

Two robots drive to a far target (so that only a stop ends their motion); Stop all asks first
(the browser's confirmation box: cancelled, nothing is sent), then sends zeros to every robot
and group the list holds, and the test reads each robot's velocity through the gateway. A
robot whose device is gone is reported as not answering.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import pytest
from console_support import CSS, device_process, doc_image, eventually, velocity, wait_for, xy

from clients.sync import Client

pytestmark = [pytest.mark.browser, pytest.mark.slow, pytest.mark.timeout(120)]

ROBOTS = ("scout1", "scout2")
FAR = "<marker><location>(50 50)</location></marker>"
#: Seconds a stopped robot is watched for moving again.
STILL_FOR = 0.5


def speed(client: Client, robot: str) -> float:
    return float(np.linalg.norm(velocity(client, robot)[:3]))


def drive_away(client: Client) -> None:
    for robot in ROBOTS:
        client.set(robot, "behaviors.moveto", FAR)
    for robot in ROBOTS:
        eventually(lambda r=robot: speed(client, r), lambda v: v > 0, f"{robot} driving")


def report(driver: Any) -> dict[str, str]:
    found: dict[str, str] = driver.execute_script(
        "const s = document.querySelector('#teleop-stop-all-status');"
        "return {text: s.textContent, stopped: s.dataset.stopped ?? '', failed: s.dataset.failed ?? ''}"
    )
    return found


def confirmation(driver: Any) -> Any:
    from selenium.webdriver.support import expected_conditions

    return wait_for(driver, expected_conditions.alert_is_present(), "the confirmation box of Stop all")


def test_stop_all_asks_then_stops_every_robot(page: Any, client: Client) -> None:
    drive_away(client)
    page.find_element(CSS, "#teleop-stop-all").click()
    box = confirmation(page)
    assert all(name in box.text for name in (*ROBOTS, "swarm")), box.text
    box.dismiss()
    time.sleep(STILL_FOR)
    assert all(speed(client, robot) > 0 for robot in ROBOTS), "a cancelled Stop all stopped something"

    page.find_element(CSS, "#teleop-stop-all").click()
    confirmation(page).accept()
    wait_for(
        page, lambda d: report(d)["text"].startswith("Stop all: 3 of 3 stopped"), "the report of Stop all"
    )
    assert report(page)["stopped"].split() == ["scout1", "scout2", "swarm"], report(page)
    assert report(page)["failed"] == "", report(page)
    for robot in ROBOTS:
        assert speed(client, robot) == 0, f"{robot} still drives: velocity {velocity(client, robot)}"
        where = xy(client, robot)
        time.sleep(STILL_FOR)
        assert np.allclose(xy(client, robot), where), f"{robot} moved on after Stop all"
    doc_image(page, "stop-all")


def test_stop_all_names_a_robot_that_does_not_answer(page: Any, client: Client) -> None:
    with device_process("--service", "sim-robot", "--name", "rover9") as (device, url):
        client.set("registry", "services.rover9", url, type="mobile_robot")
        wait_for(
            page, lambda d: d.find_elements(CSS, '#services [data-service="rover9"]'), "rover9 in the list"
        )
        device.kill()  # its device is gone: nothing answers for rover9
        device.wait(5)
        drive_away(client)
        page.find_element(CSS, "#teleop-stop-all").click()
        confirmation(page).accept()
        wait_for(
            page,
            lambda d: "rover9" in report(d)["failed"].split(),
            "rover9 reported as not answering",
            within=20,
        )
        stopped = report(page)["stopped"].split()
        assert {"scout1", "scout2"} <= set(stopped), report(page)
        assert "no answer from" in report(page)["text"] and "rover9 (" in report(page)["text"], report(page)
        for robot in ROBOTS:
            assert speed(client, robot) == 0, f"{robot} still drives beside the robot that did not answer"
