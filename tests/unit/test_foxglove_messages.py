"""The Foxglove front's pure parts: messages read and written, schemas and messages from models,
and what a connection is shown."""

from __future__ import annotations

import base64
import json
import math
import struct

import pytest

from gateway.fronts.foxglove import catalog as catalog_module
from gateway.fronts.foxglove import protocol, schemas
from gateway.fronts.foxglove.catalog import SCENE_TOPIC, Catalog, Kind
from gateway.fronts.foxglove.protocol import ClientMessage, ProtocolError, ServiceCallRequest
from services.kernel.errors import InvalidArgument
from services.kernel.model import Access, ParameterModel, PropertyModel, ServiceModel

SPEED = PropertyModel(
    "speed", "number", Access.READ_WRITE, unit="m/s", minimum=0, maximum=2, doc="cruise speed"
)
LOCATION = PropertyModel("location", "vector", Access.READ, length=6)
FRAME = PropertyModel("frame", "bytes", Access.READ, media_type="image/jpeg")
MOVETO = PropertyModel(
    "behaviors.moveto",
    "none",
    Access.ACTION,
    value=ParameterModel("target", "marker"),
    parameters=(ParameterModel("frame", "text", required=False, default="world"),),
)
ROBOT = ServiceModel(
    "mobile_robot",
    (
        LOCATION,
        SPEED,
        FRAME,
        MOVETO,
        PropertyModel("sensors", "namespace", Access.READ),
        PropertyModel("sensors.bumper", "boolean", Access.READ),
        PropertyModel("find", "text", Access.QUERY),
    ),
)


def test_a_message_data_frame_is_opcode_subscription_and_time_little_endian() -> None:
    assert protocol.message_head(7, 1_500_000_000_123) == struct.pack("<BIQ", 1, 7, 1_500_000_000_123)


def test_a_service_call_request_is_read_and_its_response_written_in_the_specs_layout() -> None:
    frame = struct.pack("<BIII", 2, 3, 41, 4) + b"json" + b'{"value": ""}'
    assert protocol.read_binary(frame) == ServiceCallRequest(3, 41, "json", b'{"value": ""}')
    assert (
        protocol.service_call_response(3, 41, "json", b"{}") == struct.pack("<BIII", 3, 3, 41, 4) + b"json{}"
    )


def test_a_client_message_is_read_with_its_channel() -> None:
    assert protocol.read_binary(b"\x01\x02\x00\x00\x00{}") == ClientMessage(2, b"{}")


@pytest.mark.parametrize(
    ("frame", "says"),
    [
        (b"", "no opcode"),
        (b"\x01\x02", "shorter than its head"),
        (b"\x02\x01\x00\x00\x00", "shorter than its head"),
        (struct.pack("<BIII", 2, 1, 1, 99) + b"json", "runs past its end"),
        (b"\x09", "unknown binary opcode 0x09"),
    ],
)
def test_a_broken_binary_frame_is_a_protocol_error_saying_what_is_wrong(frame: bytes, says: str) -> None:
    with pytest.raises(ProtocolError, match=says):
        protocol.read_binary(frame)


def test_subscriptions_are_checked_as_unsigned_32_bit_ids_and_bounded() -> None:
    body = {"subscriptions": [{"id": 1, "channelId": 2}]}
    assert protocol.subscriptions(body, 4) == [protocol.Subscription(1, 2)]
    with pytest.raises(ProtocolError, match="at most 0 items"):
        protocol.subscriptions(body, 0)
    with pytest.raises(ProtocolError, match="channelId must be"):
        protocol.subscriptions({"subscriptions": [{"id": 1, "channelId": 2**32}]}, 4)
    with pytest.raises(ProtocolError, match="subscription id must be"):
        protocol.subscriptions({"subscriptions": [{"id": True, "channelId": 1}]}, 4)


def test_a_numbers_schema_carries_its_type_bounds_unit_and_doc() -> None:
    schema = schemas.value_schema(SPEED, "bot")
    assert schema["properties"]["value"] == {
        "type": "number",
        "minimum": 0,
        "maximum": 2,
        "description": "cruise speed (m/s)",
    }
    assert schemas.value_schema_name(SPEED) == "propertyservice.Number"


def test_values_become_typed_json_and_published_json_becomes_the_value_grammar() -> None:
    assert schemas.value_message(SPEED, "0.5", 0) == {"value": 0.5}
    assert schemas.value_message(LOCATION, "(1 2 0 0 0 0)", 0) == {"value": [1.0, 2.0, 0.0, 0.0, 0.0, 0.0]}
    assert schemas.value_message(SPEED, "not a number", 0) == {"value": "not a number"}
    assert schemas.published_value({"value": 0.7}, binary=False) == "0.7"
    assert schemas.published_value({"value": True}, binary=False) == "true"
    assert schemas.published_value({"value": [1, 2.5]}, binary=False) == "(1 2.5)"
    assert schemas.published_value({"data": "AAE="}, binary=True) == b"\x00\x01"
    with pytest.raises(InvalidArgument, match="value"):
        schemas.published_value({"speed": 1}, binary=False)
    with pytest.raises(InvalidArgument, match="cannot send"):
        schemas.published_value({"value": {"x": 1}}, binary=False)


def test_a_location_is_a_pose_in_the_world_frame_with_its_yaw_as_a_quaternion() -> None:
    message = schemas.pose_message(f"(1 2 0 0 0 {math.pi / 2})", 3_000_000_001)
    assert message is not None
    assert message["timestamp"] == {"sec": 3, "nsec": 1}
    assert message["frame_id"] == "world"
    assert message["pose"]["position"] == {"x": 1.0, "y": 2.0, "z": 0.0}
    q = message["pose"]["orientation"]
    assert (q["x"], q["y"]) == (0.0, 0.0)
    assert q["z"] == pytest.approx(math.sqrt(0.5))
    assert q["w"] == pytest.approx(math.sqrt(0.5))
    assert schemas.pose_message("()", 0) is None


def test_the_scene_replaces_a_services_entity_and_deletes_it_when_its_location_goes() -> None:
    update = schemas.scene_message("scout1", "(1 2)", 0, removed=False)
    assert update is not None
    (entity,) = update["entities"]
    assert entity["id"] == "scout1"
    assert entity["texts"][0]["text"] == "scout1"
    assert entity["arrows"][0]["pose"]["position"] == {"x": 1.0, "y": 2.0, "z": 0.0}
    gone = schemas.scene_message("scout1", "", 0, removed=True)
    assert gone == {
        "deletions": [{"timestamp": {"sec": 0, "nsec": 0}, "type": 0, "id": "scout1"}],
        "entities": [],
    }


def test_an_image_frame_is_a_compressed_image_with_its_format() -> None:
    message = schemas.value_message(FRAME, b"\xff\xd8", 5)
    assert message == {
        "timestamp": {"sec": 0, "nsec": 5},
        "frame_id": "",
        "data": base64.b64encode(b"\xff\xd8").decode(),
        "format": "jpeg",
    }


def test_a_robots_model_becomes_channels_services_and_parameters_named_as_ros_topics() -> None:
    catalog = Catalog()
    catalog.add("bot", ROBOT)
    catalog.add_scene()
    channels = {c.topic: c for c in catalog.channels.values()}
    assert set(channels) == {
        "/bot/location",
        "/bot/pose",
        "/bot/speed",
        "/bot/frame",
        "/bot/sensors/bumper",
        SCENE_TOPIC,
    }
    assert channels["/bot/pose"].kind is Kind.POSE
    assert channels["/bot/frame"].schema_name == "foxglove.CompressedImage"
    advertised = channels["/bot/speed"].advertised()
    assert (advertised["encoding"], advertised["schemaEncoding"]) == ("json", "jsonschema")
    assert json.loads(advertised["schema"])["properties"]["value"]["type"] == "number"
    services = {s.name: s for s in catalog.services.values()}
    assert set(services) == {"/bot/behaviors/moveto", "/bot/find"}
    assert services["/bot/find"].is_query
    request = json.loads(services["/bot/behaviors/moveto"].advertised()["requestSchema"])
    assert set(request["properties"]["parameters"]["properties"]) == {"frame"}
    assert catalog.parameter_names() == ["/bot/speed"]
    assert catalog.parameter("/bot/location") is None


def test_only_what_the_subject_may_read_becomes_a_channel() -> None:
    catalog = Catalog()
    catalog.add("bot", ROBOT, may_read=["speed"])
    assert [c.topic for c in catalog.channels.values()] == ["/bot/speed"]


def test_two_connections_shown_the_same_robot_share_its_channels_and_their_ids() -> None:
    first, second = Catalog(), Catalog()
    first.add("bot", ROBOT)
    second.add("bot", ROBOT)
    assert list(first.channels) == list(second.channels)
    assert all(first.channels[i] is second.channels[i] for i in first.channels)


def test_a_service_that_leaves_is_taken_out_of_the_catalog_with_the_ids_to_unadvertise() -> None:
    catalog = Catalog()
    catalog.add("bot", ROBOT)
    catalog.add("other", ServiceModel("mobile_robot", (SPEED,)))
    catalog.add_scene()
    bot_channels = {c.id for c in catalog.channels.values() if c.service == "bot"}
    channels, services = catalog.remove("bot")
    assert set(channels) == bot_channels
    assert len(services) == 2
    assert sorted(c.topic for c in catalog.channels.values()) == ["/other/speed", SCENE_TOPIC]
    assert catalog.parameter_names() == ["/other/speed"]


def test_a_parameter_is_followed_by_a_channel_of_its_own_kind() -> None:
    catalog = Catalog()
    catalog.add("bot", ROBOT)
    channel = catalog.parameter_channel("/bot/speed")
    assert channel is not None
    assert (channel.kind, channel.service, channel.path) == (Kind.PARAMETER, "bot", "speed")
    assert channel.id not in catalog.channels  # never advertised
    assert catalog.parameter_channel("/bot/location") is None


def test_a_catalog_stops_at_its_bound_and_says_it_was_cut(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(catalog_module, "MAX_PROPERTIES", 3)
    catalog = Catalog()
    catalog.add("bot", ROBOT)
    assert catalog.clipped
    assert len(catalog.properties) == 3
