"""roslibpy (from PyPI, unchanged) drives a real gateway process through its rosbridge endpoint.

It lists what there is through rosapi, receives typed messages of a robot driving, sets a
property by publishing, calls actions and queries as services, is throttled as it asks, and is
refused where the access rules say no (docs/ros-and-foxglove.md). roslibpy runs Twisted's
reactor in a thread of its own: the tests wait on queues, each bounded.
"""

from __future__ import annotations

import queue
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import jwt
import pytest
from support.gateway_process import GatewayProcess

roslibpy = pytest.importorskip(
    "roslibpy",
    reason="the rosbridge tests need roslibpy: pip install -e '.[test]' (it is in the test extras)",
)

WAIT = 15.0
SECRET = "a shared secret of the lab, long enough for HS256"

ROBOTS = """
[[services]]
name = "scout1"
type = "sim-robot"

[[services]]
name = "scout2"
type = "sim-robot"
options = { start = [1.0, 0.0] }
"""

RULES = """
[auth]
jwt_secret_file = "jwt.secret"
issuer = "lab"

[[rules]]
subject = "*"
service = "scout1"
operations = ["read"]
effect = "permit"

[[rules]]
subject = "*"
service = "scout1"
path = "sensors.**"
operations = ["read"]
effect = "deny"

[[rules]]
subject = "operator"
service = "scout1"
operations = ["write", "invoke"]
effect = "permit"

[[rules]]
subject = "*"
service = "registry"
operations = ["read"]
effect = "permit"
"""


def token(subject: str) -> str:
    claims = {"sub": subject, "iss": "lab", "exp": int(time.time()) + 600}
    return jwt.encode(claims, SECRET, algorithm="HS256")


def connect(gw: GatewayProcess, headers: dict[str, str] | None = None) -> Any:
    ros = roslibpy.Ros(host=f"ws://{gw.http_address}/rosbridge", headers=headers)
    ros.run(timeout=WAIT)
    assert ros.is_connected
    return ros


@pytest.fixture
def robots(gateway_process: Callable[[str], GatewayProcess]) -> Iterator[Any]:
    gw = gateway_process(ROBOTS)
    ros = connect(gw)
    try:
        yield ros
    finally:
        ros.close()


def received(topic: Any, accept: Callable[[dict[str, Any]], bool] = lambda _: True) -> dict[str, Any]:
    """The first message of ``topic`` that ``accept`` takes (subscribed here, unsubscribed after)."""
    messages: queue.Queue[dict[str, Any]] = queue.Queue(maxsize=1000)
    topic.subscribe(lambda message: messages.put_nowait(message) if not messages.full() else None)
    deadline = time.monotonic() + WAIT
    try:
        while True:
            message = messages.get(timeout=max(0.01, deadline - time.monotonic()))
            if accept(message):
                return message
    finally:
        topic.unsubscribe()


def call(ros: Any, name: str, args: dict[str, Any] | None = None) -> dict[str, Any]:
    service = roslibpy.Service(ros, name, "")
    return dict(service.call(roslibpy.ServiceRequest(args or {}), timeout=WAIT))


def test_rosapi_lists_the_robots_topics_services_and_nodes(robots: Any) -> None:
    topics = robots.get_topics()
    assert {"/scout1/location", "/scout1/cmd_vel", "/scout1/odom", "/scout1/pose", "/scout2/speed"} <= set(
        topics
    )
    assert robots.get_topic_type("/scout1/location") == "std_msgs/Float64MultiArray"
    assert robots.get_topic_type("/scout1/sensors/battery") == "std_msgs/Float64"
    assert robots.get_topic_type("/scout1/actuators/led") == "std_msgs/Bool"
    assert robots.get_topic_type("/scout1/cmd_vel") == "geometry_msgs/Twist"
    assert "/scout1/pose" in robots.get_topics_for_type("geometry_msgs/Pose2D")
    services = robots.get_services()
    assert {"/scout1/behaviors/moveto", "/scout1/behaviors/stop", "/registry/find", "/rosapi/topics"} <= set(
        services
    )
    assert robots.get_service_type("/scout1/behaviors/stop") == "std_srvs/Trigger"
    assert {"/scout1", "/scout2", "/registry"} <= set(robots.get_nodes())
    details = robots.get_node_details("/scout1")
    assert "/scout1/location" in details["publishing"]
    assert "/scout1/cmd_vel" in details["subscribing"]
    assert "/scout1/behaviors/moveto" in details["services"]


def test_a_robot_driving_to_a_target_is_seen_as_typed_poses(robots: Any) -> None:
    pose = roslibpy.Topic(robots, "/scout1/pose", "geometry_msgs/Pose2D")
    assert received(pose) == {"x": 0.0, "y": 0.0, "theta": 0.0}
    assert call(robots, "/scout1/behaviors/moveto", {"x": 0.5, "y": 0.0}) == {"success": True, "message": ""}
    arrived = received(pose, lambda m: abs(m["x"] - 0.5) < 1e-6)
    assert arrived["y"] == 0.0
    stamped = received(roslibpy.Topic(robots, "/scout1/location", "geometry_msgs/PoseStamped"))
    assert stamped["pose"]["position"] == {"x": 0.5, "y": 0.0, "z": 0.0}
    assert stamped["header"]["frame_id"] == "world"
    odom = received(roslibpy.Topic(robots, "/scout1/odom", "nav_msgs/Odometry"))
    assert odom["pose"]["pose"]["position"]["x"] == 0.5
    vector = received(roslibpy.Topic(robots, "/scout1/location", "std_msgs/Float64MultiArray"))
    assert vector["data"] == [0.5, 0.0, 0.0, 0.0, 0.0, 0.0]


def test_publishing_a_number_sets_the_property(robots: Any) -> None:
    speed = roslibpy.Topic(robots, "/scout2/speed", "std_msgs/Float64")
    speed.advertise()
    speed.publish(roslibpy.Message({"data": 0.25}))
    heard = roslibpy.Topic(robots, "/scout2/speed", "std_msgs/Float64")
    assert received(heard, lambda m: m["data"] == 0.25) == {"data": 0.25}
    assert call(robots, "/scout2/speed") == {"value": "0.25", "data": 0.25}
    speed.unadvertise()
    led = roslibpy.Topic(robots, "/scout2/actuators/led", "std_msgs/Bool")
    led.publish(roslibpy.Message({"data": True}))
    heard = roslibpy.Topic(robots, "/scout2/actuators/led", "std_msgs/Bool")
    assert received(heard, lambda m: m["data"] is True) == {"data": True}


def test_cmd_vel_drives_the_robots_velocity_until_its_dead_man_stops_it(robots: Any) -> None:
    cmd_vel = roslibpy.Topic(robots, "/scout1/cmd_vel", "geometry_msgs/Twist")
    cmd_vel.publish(
        roslibpy.Message({"linear": {"x": 0.3, "y": 0, "z": 0}, "angular": {"x": 0, "y": 0, "z": 0}})
    )
    velocity = roslibpy.Topic(robots, "/scout1/velocity", "std_msgs/Float64MultiArray")
    assert received(velocity, lambda m: m["data"][0] == 0.3)["data"] == [0.3, 0, 0, 0, 0, 0]
    # Not renewed: the robot's velocity_timeout (its dead-man) ends the command by itself.
    assert received(velocity, lambda m: m["data"] == [0, 0, 0, 0, 0, 0])["data"] == [0, 0, 0, 0, 0, 0]


def test_a_query_and_an_unknown_service_are_answered_as_service_calls(robots: Any) -> None:
    found = call(robots, "/registry/find", {"type": "mobile_robot"})
    assert found["names"] == ["scout1", "scout2"]
    with pytest.raises(roslibpy.core.ServiceException, match=r"NOT_FOUND: scout1 has no property 'dance'"):
        call(robots, "/scout1/dance")
    with pytest.raises(roslibpy.core.ServiceException, match=r"INVALID_ARGUMENT: .*target"):
        call(robots, "/scout1/behaviors/moveto", {"frame": "world"})


def test_throttle_rate_bounds_how_often_a_moving_robot_is_heard(robots: Any) -> None:
    counts = {"throttled": 0, "every": 0}
    every = roslibpy.Topic(robots, "/scout1/location", "std_msgs/Float64MultiArray")
    # Both on one connection would be one subscription: the throttled one on a second connection.
    other = roslibpy.Ros(host=robots.factory.url)
    other.run(timeout=WAIT)
    try:
        throttled = roslibpy.Topic(other, "/scout1/location", "std_msgs/Float64MultiArray", throttle_rate=500)
        throttled.subscribe(lambda _: counts.__setitem__("throttled", counts["throttled"] + 1))
        every.subscribe(lambda _: counts.__setitem__("every", counts["every"] + 1))
        time.sleep(0.5)  # the current values arrive
        call(robots, "/scout1/behaviors/moveto", {"x": 5.0, "y": 0.0})
        started = dict(counts)
        time.sleep(2.0)
        throttled.unsubscribe()
        every.unsubscribe()
    finally:
        other.close()
    heard_throttled = counts["throttled"] - started["throttled"]
    heard_every = counts["every"] - started["every"]
    # The robot moves at 20 ticks a second: about 40 changes in 2 s; at most one per 0.5 s throttled.
    assert heard_every >= 15, counts
    assert 1 <= heard_throttled <= 6, counts


@pytest.fixture
def secured(gateway_process: Callable[[str], GatewayProcess], tmp_path: Path) -> GatewayProcess:
    (tmp_path / "jwt.secret").write_text(SECRET)
    return gateway_process(ROBOTS + RULES)


def test_the_rules_refuse_a_viewer_and_let_an_operator_through(secured: GatewayProcess) -> None:
    viewer = connect(secured, {"Authorization": f"Bearer {token('viewer')}"})
    try:
        with pytest.raises(roslibpy.core.ServiceException, match=r"PERMISSION_DENIED"):
            call(viewer, "/scout1/behaviors/stop")
        topics = viewer.get_topics()
        assert "/scout1/location" in topics
        assert "/scout1/sensors/battery" not in topics  # denied reads are not listed
        assert "/scout2/location" not in topics
        pose = roslibpy.Topic(viewer, "/scout1/pose", "geometry_msgs/Pose2D")
        assert received(pose)["x"] == 0.0
    finally:
        viewer.close()
    operator = connect(secured, {"Authorization": f"Bearer {token('operator')}"})
    try:
        assert call(operator, "/scout1/behaviors/stop") == {"success": True, "message": ""}
    finally:
        operator.close()


def test_the_auth_op_names_the_caller_and_a_bad_token_ends_the_connection(secured: GatewayProcess) -> None:
    anonymous = connect(secured)
    try:
        with pytest.raises(roslibpy.core.ServiceException, match=r"UNAUTHENTICATED|PERMISSION_DENIED"):
            call(anonymous, "/scout1/behaviors/stop")
    finally:
        anonymous.close()
    # roslibpy's authenticate(mac, ...) sends rosauth's op: the gateway reads the token from mac.
    ros = roslibpy.Ros(host=f"ws://{secured.http_address}/rosbridge")
    ros.authenticate(token("operator"), "", "", "", 0, "", 0)
    ros.run(timeout=WAIT)
    try:
        assert call(ros, "/scout1/behaviors/stop") == {"success": True, "message": ""}
    finally:
        ros.close()
