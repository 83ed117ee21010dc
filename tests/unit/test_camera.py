"""The camera in-process: real simulated robots behind LocalService, a small in-memory directory."""

from __future__ import annotations

import asyncio
import io
import math
from collections.abc import AsyncIterator
from typing import Any

import numpy as np
import pytest
from PIL import Image
from support.group_support import MemoryDirectory
from support.waiting import wait_until

from services.apps.simulators import SimRobot
from services.apps.vision import Camera
from services.kernel.backend import Change
from services.kernel.core import LocalService, serve
from services.kernel.errors import Code, InvalidArgument, PropertyError
from services.kernel.values import parse_names, parse_vector
from services.kernel.values.markers import parse_markers

OBJECTS = [
    {"id": "crate", "class": "box", "location": [4, 0.5], "colour": "red", "size": 0.6},
    {"id": "ball", "class": "ball", "location": [6, -1], "colour": "blue"},
    {"id": "shelf", "location": [-3, 0], "colour": "green"},  # behind the camera
]


def robot(x: float, y: float) -> LocalService:
    return LocalService(SimRobot(start=(x, y), speed=200.0, tick_hz=200.0))


def ids(text: str) -> list[str]:
    return [m.get("id") for m in parse_markers(text)]


@pytest.fixture
async def world() -> AsyncIterator[MemoryDirectory]:
    directory = MemoryDirectory()
    await directory.add("scout1", robot(3.0, 0.0))
    await directory.add("scout2", robot(0.0, 5.0))  # to the camera's left, out of a 60 degree view
    yield directory
    await directory.aclose()


async def camera_in(directory: MemoryDirectory, **options: Any) -> tuple[Camera, Any]:
    camera = Camera(directory=directory, **options)
    service = serve(camera)
    await directory.add("cam", service)
    return camera, service


async def drive(directory: MemoryDirectory, name: str, x: float, y: float) -> None:
    backend = directory.backend(name)
    await backend.set("behaviors.moveto", f"<marker><location>({x} {y})</location></marker>")
    await wait_until(
        lambda: np.allclose(backend.obj.location[:2], [x, y]),  # type: ignore[attr-defined]
        what=f"{name} arrives at ({x} {y})",
    )


async def test_static_objects_in_view_in_world_and_camera_frames() -> None:
    camera = Camera(location=(0, 0, 1.0), objects=OBJECTS)
    service = serve(camera)
    assert ids(await service.get("markers")) == ["crate", "ball"]
    assert await service.get("data") == "2"
    world = parse_markers(await service.get("markers", {"frame": "world"}))
    local = parse_markers(await service.get("markers", {"frame": "camera"}))
    np.testing.assert_allclose(world[0].location, [4.0, 0.5, 0.0])
    np.testing.assert_allclose(local[0].location, [4.0, 0.5, -1.0])  # 1 m below a level camera
    assert world[1].get("class") == "ball" and world[1].get("color") == "(0.15 0.3 0.9)"
    assert float(world[0].get("confidence")) > float(world[1].get("confidence"))  # nearer, more central
    with pytest.raises(PropertyError) as info:
        await service.get("markers", {"frame": "robot"})
    assert info.value.code is Code.INVALID_ARGUMENT and "world or camera" in info.value.message
    await service.set("location", "(0 0 1 0 0 3.14159265)")  # turned around: the shelf only
    assert ids(await service.get("markers")) == ["shelf"]


async def test_robots_found_in_the_directory_are_seen_and_leave_the_view(world: MemoryDirectory) -> None:
    _, service = await camera_in(world, location=(0, 0, 1.0))
    changes: list[Change] = []
    sub = await service.listen("markers", changes.append)
    try:
        await wait_until(lambda: "scout1" in ids(changes[-1].value) if changes else False, what="scout1 seen")
        marker = parse_markers(await service.get("markers"))[0]
        assert marker.get("id") == "scout1" and marker.get("class") == "mobile_robot"
        np.testing.assert_allclose(marker.location, [3.0, 0.0, 0.0])
        assert "scout2" not in ids(await service.get("markers"))
        assert parse_names(await service.get("followed")) == ["scout1", "scout2"]  # robots, not cameras
        await drive(world, "scout1", 3.0, -8.0)  # far to the right: out of view
        await wait_until(lambda: ids(changes[-1].value) == [], what="scout1 leaves the view")
        assert await service.get("data") == "0"
    finally:
        await sub.close()


async def test_markers_do_not_change_while_nothing_in_view_moves(world: MemoryDirectory) -> None:
    _, service = await camera_in(world, location=(0, 0, 1.0), objects=OBJECTS[:1])
    await wait_until(lambda: "scout1" in ids(service.obj.markers), what="scout1 seen")
    changes: list[Change] = []
    sub = await service.listen("markers", changes.append)
    try:
        await drive(world, "scout2", -2.0, 8.0)  # moves, but out of view all the way
        await drive(world, "scout2", 0.0, 6.0)
        assert changes == []
        await drive(world, "scout1", 2.0, 0.0)  # moves in view: its marker moves with it
        await wait_until(
            lambda: bool(changes) and parse_markers(changes[-1].value)[0].location.tolist()[:2] == [2.0, 0.0],
            what="the marker of scout1 at (2 0)",
        )
    finally:
        await sub.close()


async def test_a_listen_in_the_camera_frame_gets_camera_frame_markers(world: MemoryDirectory) -> None:
    _, service = await camera_in(world, location=(1, 0, 1.0))
    await wait_until(lambda: "scout1" in ids(service.obj.markers), what="scout1 seen")
    changes: list[Change] = []
    sub = await service.listen("markers", changes.append, {"frame": "camera"})
    try:
        await drive(world, "scout1", 4.0, 1.0)
        await wait_until(lambda: bool(changes) and "(3 1 -1)" in changes[-1].value, what="camera-frame event")
    finally:
        await sub.close()
    with pytest.raises(PropertyError) as info:
        await service.listen("markers", changes.append, {"frame": "sky"})
    assert info.value.code is Code.INVALID_ARGUMENT


async def test_a_mounted_camera_follows_its_robot(world: MemoryDirectory) -> None:
    objects = [{"id": "east", "location": [8, 0]}, {"id": "north", "location": [3, 8]}]
    camera, service = await camera_in(world, mount="scout1", mount_offset=(0.2, 0, 0.5), objects=objects)
    await wait_until(lambda: camera.location[0] == pytest.approx(3.2), what="the camera is on scout1")
    np.testing.assert_allclose(parse_vector(await service.get("location")), [3.2, 0, 0.5, 0, 0, 0])
    assert ids(await service.get("markers")) == ["east"]  # not scout1 itself
    # A robot turns toward its target on each step that does not arrive, and a step is at most five
    # ticks of driving: at 20 m/s that is 0.5 m, so however late the loop wakes it, the 2 m below
    # take several steps and scout1 faces +y on the way (at 200 m/s one late tick arrived unturned).
    await world.backend("scout1").set("speed", "20")
    await drive(world, "scout1", 3.0, 2.0)
    await wait_until(lambda: camera.location[1] == pytest.approx(2.2), what="the camera moved with scout1")
    assert camera.location[5] == pytest.approx(math.pi / 2)
    assert ids(await service.get("markers")) == ["north"]
    with pytest.raises(PropertyError) as info:
        await service.set("location", "(0 0 1)")
    assert info.value.code is Code.FAILED_PRECONDITION and "scout1" in info.value.message


async def test_a_frame_is_a_jpeg_of_the_configured_resolution() -> None:
    camera = Camera(location=(0, 0, 1.2), objects=OBJECTS, resolution=(320, 200), quality=60)
    try:
        frame = await camera.fresh_frame()
        image = Image.open(io.BytesIO(frame))
        assert image.format == "JPEG" and image.size == (320, 200)
        assert await camera.fresh_frame() == frame  # asked again within a period: the same frame
        camera.resolution = np.array([160.0, 120.0])
        camera._frame_at = -math.inf  # the period is over
        assert Image.open(io.BytesIO(await camera.fresh_frame())).size == (160, 120)
    finally:
        await camera.stop()


async def test_options_are_checked() -> None:
    bad: list[tuple[dict[str, Any], str]] = [
        ({"fov": 180}, "fov must be"),
        ({"range": 0}, "range must be"),
        ({"resolution": (640,)}, "resolution must be"),
        ({"resolution": (8000, 480)}, "resolution must be"),
        ({"rate_hz": 61}, "rate_hz must be"),
        ({"quality": 100}, "quality must be"),
        ({"location": (1, 2, 3, 4)}, "location must be"),
        ({"mount": "a.b"}, "no dots"),
        ({"max_followed": -1}, "max_followed must be"),
    ]
    for options, message in bad:
        with pytest.raises(InvalidArgument, match=message):
            Camera(**options)


async def test_frames_are_rendered_only_while_someone_listens() -> None:
    camera = Camera(location=(0, 0, 1.2), objects=OBJECTS, resolution=(160, 120), rate_hz=60)
    service = serve(camera)
    await service.start()
    try:
        frame = await service.get("frame")  # nobody listens: a Get renders one frame
        assert isinstance(frame, bytes) and Image.open(io.BytesIO(frame)).size == (160, 120)
        rendered = camera._frames
        for _ in range(5):
            await asyncio.sleep(0.02)  # a few periods at 60 Hz: nothing renders by itself
        assert camera._frames == rendered
        frames: list[Change] = []
        others: list[Change] = []
        first = await service.listen("frame", others.append)
        second = await service.listen("frame", frames.append)
        await wait_until(lambda: len(frames) >= 6, what="frames arrive while two listen")
        assert all(isinstance(c.value, bytes) for c in frames)
        assert len({c.value for c in frames}) == len(frames)  # each frame differs (number, time)
        assert {c.value for c in others} & {c.value for c in frames}  # both hear the same frames
        await first.close()
        count = len(frames)
        await wait_until(lambda: len(frames) >= count + 2, what="frames go on while one listens")
        await second.close()
        await wait_until(lambda: camera._render_task is None, what="the render loop ends")
        rendered = camera._frames
        for _ in range(5):
            await asyncio.sleep(0.02)
        assert camera._frames == rendered
    finally:
        await service.aclose()


async def test_describe_says_frame_is_a_jpeg() -> None:
    service = serve(Camera())
    model = {p.name: p for p in (await service.describe()).properties}
    assert model["frame"].type == "bytes" and model["frame"].media_type == "image/jpeg"
    assert model["frame"].access.value == "read"
    markers = model["markers"]
    assert markers.gui == "markers" and markers.access.value == "read" and not markers.needs_parameters
    assert [(p.name, p.default) for p in markers.parameters] == [("frame", "world")]
    assert await service.get("markers.parameters") == "((frame text world))"


async def test_following_is_bounded_and_a_robot_that_leaves_is_forgotten(world: MemoryDirectory) -> None:
    await world.add("scout3", robot(6.0, 0.0))
    camera, service = await camera_in(world, location=(0, 0, 1.0), max_followed=2)
    assert parse_names(await service.get("followed")) == ["scout1", "scout2"]  # scout3 is one too many
    await wait_until(lambda: ids(camera.markers) == ["scout1"], what="scout1 seen, scout3 not followed")
    await world.unregister("scout1")  # forgotten; its place goes to scout3
    await wait_until(lambda: ids(camera.markers) == ["scout3"], what="scout1 forgotten, scout3 seen")
    assert parse_names(await service.get("followed")) == ["scout2", "scout3"]
