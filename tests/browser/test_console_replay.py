"""A replayed swarm in the console, in a real headless Chromium: the recorded robots on the map where
the recording had them, their view marked as replayed, and ``docs/images/console-replay.png``
(``PS_DOC_IMAGES=1`` copies the screenshot there).
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from console_support import CSS, ConsoleGateway, doc_image, pose_on_map, select, translation, wait_for
from support.gateway_process import start_gateway
from support.recordings import swarm_changes, swarm_recording

from clients.sync import Client
from services.kernel.values import parse_vector

pytestmark = [pytest.mark.browser, pytest.mark.slow, pytest.mark.timeout(120)]

#: Where the picture is taken: seconds into the recording.
AT_S = 3.0


def replay_world(recording: Path) -> str:
    """The recording replayed, standing still, and a group of every robot it serves."""
    return f"""
        [[services]]
        name = "replay"
        type = "replay"
        options = {{ recording = "{recording}", autostart = false }}

        [[services]]
        name = "swarm"
        type = "group"
        options = {{ query = {{ type = "mobile_robot" }} }}
    """


@pytest.fixture(scope="module")
def console_gateway(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ConsoleGateway]:
    """The console's gateway serving the test swarm's recording as live services."""
    folder: Path = tmp_path_factory.mktemp("console-replay")
    gw = start_gateway(folder, replay_world(swarm_recording(folder / "recordings")))
    try:
        assert gw.http_url, f"no 'HTTP front end and console on' line:\n{gw.output}"
        yield ConsoleGateway(gw, gw.address, gw.http_url)
    finally:
        gw.stop()


def recorded_xy(robot: str, at_s: float) -> np.ndarray:
    """Where the recording has ``robot`` at ``at_s``."""
    moves = [c for c in swarm_changes() if c.service == robot and c.path == "location" and c.at_s <= at_s]
    last = max(moves, key=lambda c: c.at_s)
    return np.asarray(parse_vector(str(last.value)), dtype=float)[:2]


def test_a_replayed_swarm_shows_on_the_map_where_it_was_recorded_and_says_it_is_replayed(
    page: Any, client: Client
) -> None:
    client.set("replay", "seek", AT_S)
    for robot in ("scout1", "scout2"):
        wait_for(
            page,
            lambda d, robot=robot: (
                (pose := pose_on_map(d, robot)) is not None
                and np.allclose(translation(pose), recorded_xy(robot, AT_S), atol=1e-6)
            ),
            f"{robot} on the map where the recording had it at {AT_S} s",
        )
    select(page, "scout1")
    view = page.find_element(CSS, "#service-view")
    wait_for(page, lambda d: "replayed from swarm" in view.text, "the replay's mark in scout1's view")
    assert "replay:swarm" in view.text
    services = page.find_element(CSS, "#services").text
    for name in ("replay", "swarm", "scout1", "scout2", "cam1"):
        assert name in services
    doc_image(page, "replay")
