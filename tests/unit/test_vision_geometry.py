"""What a camera sees, with known truth: in view, out of view, on the edges, world and camera frames."""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.apps.vision.geometry import confidence, in_view, mounted_pose, to_camera_frame
from services.apps.vision.scene import Thing, look, parse_objects
from services.kernel.errors import InvalidArgument
from services.kernel.values.markers import format_markers, parse_markers


def thing(ident: str, x: float, y: float, z: float = 0.0) -> Thing:
    return Thing(ident, "box", np.array([x, y, z]), (1.0, 0.0, 0.0), 0.5)


def test_the_camera_frame_is_forward_left_up_from_the_camera() -> None:
    camera = np.array([1.0, 2.0, 1.5, 0.0, 0.0, math.pi / 2])  # at (1 2), 1.5 m up, looking along +y
    points = np.array([[1.0, 5.0, 0.0], [0.0, 2.0, 0.0], [3.0, 2.0, 2.0]])
    local = to_camera_frame(camera, points)
    np.testing.assert_allclose(local[0], [3.0, 0.0, -1.5], atol=1e-12)  # 3 m straight ahead, on the floor
    np.testing.assert_allclose(local[1], [0.0, 1.0, -1.5], atol=1e-12)  # -x in the world is its left
    np.testing.assert_allclose(local[2], [0.0, -2.0, 0.5], atol=1e-12)  # +x its right, 0.5 m above it


def test_in_view_within_range_and_half_the_field_of_view_edges_included() -> None:
    fov = math.radians(90.0)
    c45, s45 = math.cos(math.pi / 4), math.sin(math.pi / 4)
    just_out = math.radians(45.01)
    local = np.array(
        [
            [5.0, 0.0, 0.0],  # straight ahead
            [10.0, 0.0, 0.0],  # exactly at the range
            [10.001, 0.0, 0.0],  # just beyond it
            [5 * c45, 5 * s45, 0.0],  # exactly on the left edge
            [5 * c45, -5 * s45, 0.0],  # exactly on the right edge
            [5 * math.cos(just_out), 5 * math.sin(just_out), 0.0],  # just outside the left edge
            [-1.0, 0.0, 0.0],  # behind
            [0.0, 0.0, 0.0],  # on the lens
        ]
    )
    seen, distance, bearing = in_view(local, 10.0, fov)
    assert seen.tolist() == [True, True, False, True, True, False, False, False]
    np.testing.assert_allclose(distance[:2], [5.0, 10.0])
    np.testing.assert_allclose(bearing[3:5], [math.pi / 4, -math.pi / 4])


def test_confidence_falls_with_distance_and_toward_the_edge() -> None:
    fov = math.radians(60.0)
    sure = confidence(np.array([0.0, 10.0, 10.0, 5.0]), np.array([0.0, 0.0, fov / 2, -fov / 4]), 10.0, fov)
    np.testing.assert_allclose(sure, [1.0, 0.5, 0.25, 0.75 * 0.75])


def test_a_mounted_camera_turns_with_its_robot() -> None:
    robot = np.array([2.0, 3.0, 0.0, 0.0, 0.0, math.pi / 2])
    offset = np.array([0.5, 0.1, 0.3, 0.0, 0.0, math.pi])  # ahead and a little left, looking back
    pose = mounted_pose(robot, offset)
    np.testing.assert_allclose(pose[:3], [2.0 - 0.1, 3.5, 0.3], atol=1e-12)
    assert pose[5] == pytest.approx(-math.pi / 2)  # pi/2 + pi, wrapped


def test_look_reports_what_is_in_view_nearest_first_in_both_frames() -> None:
    camera = np.array([0.0, 0.0, 1.0, 0.0, 0.0, math.pi])  # looking along -x
    things = [
        thing("far", -8.0, 1.0),
        thing("near", -2.0, -0.5),
        thing("behind", 3.0, 0.0),
        thing("out", -20.0, 0.0),
    ]
    seen = look(camera, 10.0, math.radians(60.0), things)
    assert [s.thing.id for s in seen] == ["near", "far"]
    near = seen[0]
    np.testing.assert_allclose(near.world, [-2.0, -0.5, 0.0])
    np.testing.assert_allclose(near.camera, [2.0, 0.5, -1.0], atol=1e-12)  # -y in the world: its left
    world, local = near.marker("world"), near.marker("camera")
    assert world.get("id") == "near" and world.get("class") == "box"
    np.testing.assert_allclose(world.location, [-2.0, -0.5, 0.0])
    np.testing.assert_allclose(local.location, [2.0, 0.5, -1.0])
    assert world.get("color") == "(1 0 0)"
    assert 0.25 <= float(world.get("confidence")) <= 1.0


def test_a_list_of_markers_reads_back() -> None:
    camera = np.array([0.0, 0.0, 1.0, 0.0, 0.0, 0.0])
    seen = look(camera, 10.0, math.radians(60.0), [thing("a", 2.0, 0.0), thing("b", 4.0, 1.0)])
    text = format_markers([s.marker("world") for s in seen])
    markers = parse_markers(text)
    assert [m.get("id") for m in markers] == ["a", "b"]
    assert parse_markers(format_markers([])) == []
    with pytest.raises(InvalidArgument, match="text between the markers"):
        parse_markers("(<marker><id>a</id></marker> stray)")


def test_objects_of_a_configuration_with_defaults_and_clear_errors() -> None:
    (crate,) = parse_objects([{"id": "crate", "location": [1, 2]}])
    assert crate.cls == "object" and crate.size == 0.5 and crate.location.tolist() == [1.0, 2.0, 0.0]
    (ball,) = parse_objects([{"id": "b", "class": "ball", "location": [1, 2, 0.5], "colour": [0, 0, 1]}])
    assert ball.colour == (0.0, 0.0, 1.0)
    bad = [
        ([{"location": [1, 2]}], "id must be"),
        ([{"id": "a", "location": [1]}], "location must be"),
        ([{"id": "a", "location": [1, 2], "colour": "mauve"}], "unknown colour 'mauve'"),
        ([{"id": "a", "location": [1, 2], "colour": [2, 0, 0]}], "each from 0 to 1"),
        ([{"id": "a", "location": [1, 2], "size": 0}], "size must be from"),
        ([{"id": "a", "location": [1, 2], "shape": "x"}], "unknown key 'shape'"),
        ([{"id": "a", "location": [1, 2]}, {"id": "a", "location": [3, 4]}], "used twice"),
        ("crate", "must be a list"),
    ]
    for objects, message in bad:
        with pytest.raises(InvalidArgument, match=message):
            parse_objects(objects)  # type: ignore[arg-type]
