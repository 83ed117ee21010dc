"""The rosbridge front's pure parts: its protocol messages, ROS names and message types, read
and written without a socket."""

from __future__ import annotations

import base64
import json
import math

import pytest

from gateway.fronts.foxglove.schemas import pose_of
from gateway.fronts.rosbridge import protocol
from gateway.fronts.rosbridge.connection import action_value, query_values
from services.kernel import ros_messages as messages
from services.kernel.errors import InvalidArgument
from services.kernel.model import Access, ParameterModel, PropertyModel
from services.kernel.ros_names import Target, for_service, parse_name, ros_name
from services.kernel.values import parse_marker


def prop(name: str, kind: str, access: Access = Access.READ_WRITE, **more: object) -> PropertyModel:
    return PropertyModel(name, kind, access, **more)  # type: ignore[arg-type]


def test_a_subscribe_as_roslibjs_sends_it_is_read_with_its_options() -> None:
    op = protocol.parse(
        json.dumps(
            {
                "op": "subscribe",
                "id": "subscribe:/scout1/location:1",
                "type": "geometry_msgs/Pose2D",
                "topic": "/scout1/location",
                "compression": "none",
                "throttle_rate": 100,
                "queue_length": 1,
                "fragment_size": 1000,
            }
        )
    )
    assert op == protocol.Subscribe(
        "subscribe:/scout1/location:1", "/scout1/location", "geometry_msgs/Pose2D", 100, 1, 1000
    )


@pytest.mark.parametrize(
    ("text", "words"),
    [
        ("{", "not JSON"),
        ("[]", "JSON object"),
        ('{"op": 3}', "'op' string"),
        ('{"op": "subscribe", "id": {}}', "id must be a string"),
        ('{"op": "publish", "topic": "/a/b"}', "no 'msg'"),
        ('{"op": "call_service", "service": "/a/b", "timeout": "soon"}', "seconds"),
        ('{"op": "auth"}', "bearer token"),
        ('{"op": "subscribe", "topic": "/a/b", "compression": "png"}', "'png' is not spoken"),
    ],
)
def test_a_message_that_is_no_op_we_speak_is_refused_saying_why(text: str, words: str) -> None:
    with pytest.raises(protocol.BadMessage, match=words):
        protocol.parse(text)


def test_the_auth_op_takes_the_token_from_token_or_from_rosauths_mac() -> None:
    assert protocol.parse('{"op": "auth", "token": "T"}') == protocol.Auth("T")
    assert protocol.parse('{"op": "auth", "mac": "M", "client": "", "t": 0}') == protocol.Auth("M")


def test_fragments_are_numbered_pieces_that_join_into_the_message() -> None:
    message = protocol.publish("/scout1/location", {"data": "x" * 1000})
    pieces = [json.loads(piece) for piece in protocol.fragments(message, 300, "m1")]
    assert [p["num"] for p in pieces] == [0, 1, 2, 3]
    assert {p["total"] for p in pieces} == {4} and {p["id"] for p in pieces} == {"m1"}
    assert "".join(p["data"] for p in pieces) == message
    assert list(protocol.fragments(message, 0, "m1")) == [message]
    assert list(protocol.fragments(message, len(message), "m1")) == [message]


def test_status_levels_below_the_one_asked_are_not_heard() -> None:
    assert protocol.heard("error", "error") and protocol.heard("error", "warning")
    assert not protocol.heard("warning", "error") and not protocol.heard("error", "none")


def test_topic_names_are_service_and_path_with_dots_as_slashes() -> None:
    assert parse_name("/scout1/sensors/battery") == Target("scout1", "sensors.battery")
    assert parse_name("scout1/location") == Target("scout1", "location")  # relative: made global
    assert ros_name("scout1", "sensors.battery") == "/scout1/sensors/battery"
    assert parse_name("/scout1/cmd_vel") == Target("scout1", "velocity", "cmd_vel")
    # A convention holds for a robot only: a sensor's own "pose" is its "pose".
    assert for_service(parse_name("/cam/pose"), "camera") == Target("cam", "pose")
    assert for_service(parse_name("/bot/odom"), "mobile_robot") == Target("bot", "location", "odom")
    for bad in ("", "/scout1", "//a", "/scout1/sensors.battery", 5):
        with pytest.raises(InvalidArgument):
            parse_name(bad)


def test_each_property_type_has_its_message_type() -> None:
    assert messages.default_type(prop("speed", "number")) == "std_msgs/Float64"
    assert messages.default_type(prop("count", "integer")) == "std_msgs/Int64"
    assert messages.default_type(prop("led", "boolean")) == "std_msgs/Bool"
    assert messages.default_type(prop("wheels", "vector")) == "std_msgs/Float64MultiArray"
    assert messages.default_type(prop("name", "text")) == "std_msgs/String"
    assert (
        messages.default_type(prop("frame", "bytes", media_type="image/jpeg"))
        == "sensor_msgs/CompressedImage"
    )
    assert messages.default_type(prop("blob", "bytes")) == "std_msgs/UInt8MultiArray"
    location = prop("location", "vector", Access.READ)
    assert messages.accepted_types(location) == (
        "std_msgs/Float64MultiArray",
        "geometry_msgs/Pose2D",
        "geometry_msgs/PoseStamped",
        "std_msgs/String",
    )
    assert messages.check_type("geometry_msgs/msg/Pose2D", location, "", "t") == "geometry_msgs/Pose2D"
    with pytest.raises(InvalidArgument, match="published as std_msgs/Float64MultiArray"):
        messages.check_type("sensor_msgs/Image", location, "", "t")


def test_values_become_messages_and_messages_values() -> None:
    pose = "(1 2 0 0 0 1.5)"
    assert messages.to_message("geometry_msgs/Pose2D", pose) == {"x": 1.0, "y": 2.0, "theta": 1.5}
    stamped = messages.to_message("geometry_msgs/PoseStamped", pose, stamp_ns=3_000_000_007)
    assert stamped["header"]["stamp"]["secs"] == 3 and stamped["header"]["stamp"]["nsecs"] == 7
    assert stamped["pose"]["orientation"]["z"] == pytest.approx(math.sin(0.75))
    assert messages.to_message("std_msgs/Float64", "0.5") == {"data": 0.5}
    assert messages.to_message("std_msgs/Bool", "true") == {"data": True}
    image = messages.to_message("sensor_msgs/CompressedImage", b"\xff\xd8", media_type="image/jpeg")
    assert image["format"] == "jpeg" and base64.b64decode(image["data"]) == b"\xff\xd8"
    twist = {"linear": {"x": 0.5, "y": 0, "z": 0}, "angular": {"x": 0, "y": 0, "z": 0.25}}
    assert messages.from_message("geometry_msgs/Twist", twist, "t") == "(0.5 0 0 0 0 0.25)"
    assert messages.from_message("std_msgs/Float64", {"data": 2}, "t") == "2"
    assert messages.from_message("std_msgs/Bool", {"data": False}, "t") == "false"
    assert messages.from_message("std_msgs/String", {"data": "hi"}, "t") == "hi"
    assert messages.from_message("std_msgs/UInt8MultiArray", {"data": "AAE="}, "t") == b"\x00\x01"
    for bad in ({"data": "x"}, {"data": float("inf")}, {"data": True}, {}, []):
        with pytest.raises(InvalidArgument):
            messages.from_message("std_msgs/Float64", bad, "t")
    with pytest.raises(InvalidArgument, match="read only"):
        messages.from_message("nav_msgs/Odometry", {}, "t")


def test_a_cmd_vel_turns_with_the_robot_into_the_world_frame() -> None:
    ahead = [1.0, 0.0, 0.0, 0.0, 0.0, 0.5]
    x, y, *rest = messages.robot_to_world(ahead, math.pi / 2)
    assert (x, y) == (pytest.approx(0.0), pytest.approx(1.0))
    assert rest == [0.0, 0.0, 0.0, 0.5]


def test_a_service_calls_args_become_an_actions_value_and_parameters() -> None:
    moveto = prop(
        "behaviors.moveto",
        "none",
        Access.ACTION,
        value=ParameterModel("target", "marker"),
        parameters=(ParameterModel("frame", "text", required=False),),
    )
    value, parameters = action_value(moveto, {"x": 1, "y": 2.5, "frame": "robot"})
    assert parse_marker(str(value)).location.tolist() == [1.0, 2.5]  # type: ignore[union-attr]
    assert parameters == {"frame": "robot"}
    value, _ = action_value(moveto, {"target": "<marker><location>(3 4)</location></marker>"})
    assert value == "<marker><location>(3 4)</location></marker>"
    with pytest.raises(InvalidArgument, match="takes target"):
        action_value(moveto, {})
    stop = prop("behaviors.stop", "none", Access.ACTION)
    assert action_value(stop, {}) == ("", {})


def test_a_querys_answer_is_its_text_and_its_typed_value() -> None:
    assert query_values(prop("find", "names", Access.QUERY), "(a b)") == {
        "value": "(a b)",
        "names": ["a", "b"],
    }
    assert query_values(prop("speed", "number"), "0.5") == {"value": "0.5", "data": 0.5}
    assert query_values(None, "text") == {"value": "text"}


def test_a_tilted_robots_pose_is_the_same_quaternion_in_ros_and_in_foxglove() -> None:
    location = "(1 2 0.5 0.1 -0.2 0.3)"
    ros = messages.to_message("geometry_msgs/PoseStamped", location)["pose"]["orientation"]
    shown = pose_of(location)
    assert shown is not None
    position, foxglove = shown
    assert position == [1.0, 2.0, 0.5]
    assert [ros["x"], ros["y"], ros["z"], ros["w"]] == pytest.approx(foxglove)
    assert ros["x"] != pytest.approx(0.0)  # the roll is in it, not only the yaw
    assert sum(q * q for q in foxglove) == pytest.approx(1.0)
