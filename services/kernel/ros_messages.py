"""ROS message types of the gateway's properties, and values into messages and back.

A property's type in its model picks its message (:func:`default_type`): a number is a
``std_msgs/Float64`` (``{"data": 0.5}``), an integer a ``std_msgs/Int64``, a boolean a
``std_msgs/Bool``, a vector a ``std_msgs/Float64MultiArray``, a binary image a
``sensor_msgs/CompressedImage`` (its ``data`` base64, as rosbridge writes every ``uint8[]``),
other bytes a ``std_msgs/UInt8MultiArray``, and everything else (text, names, lists, markers) a
``std_msgs/String`` of the value's text. A robot's ``location`` (x y z roll pitch yaw) is also a
``geometry_msgs/Pose2D`` or ``geometry_msgs/PoseStamped``, ``nav_msgs/Odometry`` on ``odom``;
its ``velocity`` is a ``geometry_msgs/Twist`` on ``cmd_vel``. Any value may be asked for as a
``std_msgs/String`` (its text). Nothing here does I/O.
"""

from __future__ import annotations

import base64
import binascii
import math
from collections.abc import Mapping, Sequence
from typing import Any

from services.kernel.errors import InvalidArgument
from services.kernel.model import PropertyModel
from services.kernel.pose import quaternion
from services.kernel.values import Value, format_number, format_vector, parse_bool, parse_number, parse_vector

FLOAT64 = "std_msgs/Float64"
INT64 = "std_msgs/Int64"
BOOL = "std_msgs/Bool"
STRING = "std_msgs/String"
FLOAT64_ARRAY = "std_msgs/Float64MultiArray"
UINT8_ARRAY = "std_msgs/UInt8MultiArray"
COMPRESSED_IMAGE = "sensor_msgs/CompressedImage"
POSE2D = "geometry_msgs/Pose2D"
POSE_STAMPED = "geometry_msgs/PoseStamped"
ODOMETRY = "nav_msgs/Odometry"
TWIST = "geometry_msgs/Twist"
#: The frame a robot's pose is given in (its ``location`` is in the world frame).
WORLD_FRAME = "world"

#: What rosbridge clients also write a type as: ROS 2's ``pkg/msg/Name`` and the bare ``pkg/Name``.
_ROS2_INFIX = "/msg/"


def canonical(type_name: str) -> str:
    """``std_msgs/msg/Float64`` (ROS 2's spelling) as ``std_msgs/Float64``."""
    return type_name.replace(_ROS2_INFIX, "/", 1) if _ROS2_INFIX in type_name else type_name


def default_type(prop: PropertyModel, convention: str = "") -> str:
    """The message type a property is published as when the subscriber names none."""
    if convention == "cmd_vel":
        return TWIST
    if convention == "odom":
        return ODOMETRY
    if convention == "pose":
        return POSE2D
    kind = prop.type
    if kind == "number":
        return FLOAT64
    if kind == "integer":
        return INT64
    if kind == "boolean":
        return BOOL
    if kind == "vector":
        return FLOAT64_ARRAY
    if kind == "bytes":
        return COMPRESSED_IMAGE if prop.media_type.startswith("image/") else UINT8_ARRAY
    return STRING


def accepted_types(prop: PropertyModel, convention: str = "") -> tuple[str, ...]:
    """Every message type ``prop`` may be subscribed or published as, its default first."""
    first = default_type(prop, convention)
    if convention:
        return (first,)
    more: list[str] = []
    if prop.type == "vector" and (prop.name == "location" or prop.name.endswith(".location")):
        more += [POSE2D, POSE_STAMPED]
    if prop.type != "bytes" and first != STRING:
        more.append(STRING)
    return (first, *more)


def check_type(asked: object, prop: PropertyModel, convention: str, what: str) -> str:
    """The message type to use: ``asked`` when it is one ``prop`` has (any spelling), its default
    when none is asked ("" or absent); InvalidArgument naming the ones it has otherwise."""
    types = accepted_types(prop, convention)
    if asked is None or asked == "":
        return types[0]
    if not isinstance(asked, str):
        raise InvalidArgument(f"{what}: type must be a string like {types[0]}")
    wanted = canonical(asked)
    if wanted not in types:
        raise InvalidArgument(f"{what} is published as {', '.join(types)}, not {asked[:100]!r}")
    return wanted


def _pose(value: str) -> list[float]:
    numbers = [float(x) for x in parse_vector(value)]
    return (numbers + [0.0] * 6)[:6]


def _orientation(roll: float, pitch: float, yaw: float) -> dict[str, float]:
    """``geometry_msgs/Quaternion`` of a location's rotation (the same quaternion every front shows)."""
    x, y, z, w = quaternion(roll, pitch, yaw)
    return {"x": x, "y": y, "z": z, "w": w}


def _header(stamp_ns: int) -> dict[str, Any]:
    seconds, nanoseconds = divmod(stamp_ns, 1_000_000_000)
    # ROS 1 names the fields secs/nsecs, ROS 2 sec/nanosec: both, so either client reads its own.
    stamp = {"secs": seconds, "nsecs": nanoseconds, "sec": seconds, "nanosec": nanoseconds}
    return {"stamp": stamp, "frame_id": WORLD_FRAME}


def to_message(type_name: str, value: Value, *, stamp_ns: int = 0, media_type: str = "") -> dict[str, Any]:
    """The message of type ``type_name`` carrying ``value`` (checked by :func:`check_type` first);
    InvalidArgument when the value does not read as that type (a device that sent a bad value)."""
    if isinstance(value, bytes):
        data = base64.b64encode(value).decode("ascii")
        if type_name == COMPRESSED_IMAGE:
            image_format = media_type.partition("/")[2] or "unknown"
            return {"header": _header(stamp_ns), "format": image_format, "data": data}
        return {"layout": {"dim": [], "data_offset": 0}, "data": data}
    if type_name == STRING:
        return {"data": value}
    if type_name == FLOAT64:
        return {"data": parse_number(value)}
    if type_name == INT64:
        return {"data": int(parse_number(value))}
    if type_name == BOOL:
        return {"data": parse_bool(value)}
    if type_name == FLOAT64_ARRAY:
        numbers = [float(x) for x in parse_vector(value)]
        layout = {"dim": [{"label": "", "size": len(numbers), "stride": len(numbers)}], "data_offset": 0}
        return {"layout": layout, "data": numbers}
    if type_name == TWIST:
        v = _pose(value)
        return {"linear": {"x": v[0], "y": v[1], "z": v[2]}, "angular": {"x": v[3], "y": v[4], "z": v[5]}}
    x, y, z, roll, pitch, yaw = _pose(value)
    if type_name == POSE2D:
        return {"x": x, "y": y, "theta": yaw}
    pose = {"position": {"x": x, "y": y, "z": z}, "orientation": _orientation(roll, pitch, yaw)}
    if type_name == POSE_STAMPED:
        return {"header": _header(stamp_ns), "pose": pose}
    if type_name == ODOMETRY:
        zeros = {"x": 0.0, "y": 0.0, "z": 0.0}
        return {
            "header": _header(stamp_ns),
            "child_frame_id": "base_link",
            "pose": {"pose": pose, "covariance": [0.0] * 36},
            "twist": {"twist": {"linear": zeros, "angular": zeros}, "covariance": [0.0] * 36},
        }
    raise InvalidArgument(f"no message type {type_name[:100]!r}")


def _field(msg: Mapping[str, Any], name: str, what: str) -> Any:
    if name not in msg:
        raise InvalidArgument(f"{what}: the message has no {name!r} field")
    return msg[name]


def _number(x: object, what: str) -> float:
    if isinstance(x, bool) or not isinstance(x, int | float) or not math.isfinite(x):
        raise InvalidArgument(f"{what}: {str(x)[:100]!r} is not a finite number")
    return float(x)


def _xyz(msg: Mapping[str, Any], name: str, what: str) -> list[float]:
    part = msg.get(name, {})
    if not isinstance(part, Mapping):
        raise InvalidArgument(f"{what}: {name} must be an object with x, y and z")
    return [_number(part.get(axis, 0.0), f"{what}: {name}.{axis}") for axis in ("x", "y", "z")]


def _numbers(data: object, what: str) -> Sequence[float]:
    if not isinstance(data, list):
        raise InvalidArgument(f"{what}: data must be a list of numbers")
    return [_number(x, what) for x in data]


def from_message(type_name: str, msg: object, what: str) -> Value:
    """The value a published message of ``type_name`` sets (InvalidArgument for a bad message).

    A ``Twist`` becomes the six numbers of a velocity (linear x y z, angular x y z), in the frame
    the message gives them; the caller turns a robot's ``cmd_vel`` into the world frame.
    """
    if not isinstance(msg, Mapping):
        raise InvalidArgument(f"{what}: msg must be a JSON object")
    if type_name in (COMPRESSED_IMAGE, UINT8_ARRAY):
        data = _field(msg, "data", what)
        if isinstance(data, list):  # some clients send uint8[] as numbers
            if not all(isinstance(b, int) and 0 <= b <= 255 for b in data):
                raise InvalidArgument(f"{what}: data must be base64 text or bytes 0 to 255")
            return bytes(data)
        if not isinstance(data, str):
            raise InvalidArgument(f"{what}: data must be base64 text")
        try:
            return base64.b64decode(data, validate=True)
        except binascii.Error:
            raise InvalidArgument(f"{what}: data is not base64") from None
    if type_name == STRING:
        data = _field(msg, "data", what)
        if not isinstance(data, str):
            raise InvalidArgument(f"{what}: a std_msgs/String's data must be a string")
        return data
    if type_name in (FLOAT64, INT64):
        number = _number(_field(msg, "data", what), what)
        return format_number(int(number) if type_name == INT64 else number)
    if type_name == BOOL:
        data = _field(msg, "data", what)
        if not isinstance(data, bool):
            raise InvalidArgument(f"{what}: a std_msgs/Bool's data must be true or false")
        return "true" if data else "false"
    if type_name == FLOAT64_ARRAY:
        return format_vector(_numbers(_field(msg, "data", what), what))
    if type_name == TWIST:
        return format_vector(_xyz(msg, "linear", what) + _xyz(msg, "angular", what))
    if type_name == POSE2D:
        x, y, theta = (_number(msg.get(key, 0.0), f"{what}: {key}") for key in ("x", "y", "theta"))
        return format_vector([x, y, 0.0, 0.0, 0.0, theta])
    raise InvalidArgument(f"{what}: a {type_name} cannot be published here (it is read only)")


def robot_to_world(twist: Sequence[float], yaw: float) -> list[float]:
    """A ``cmd_vel`` (the robot's own frame: x ahead, y to its left) in the world frame of
    ``velocity``, for a robot heading ``yaw``; angular rates about z are the same in both."""
    c, s = math.cos(yaw), math.sin(yaw)
    vx, vy = twist[0], twist[1]
    return [c * vx - s * vy, s * vx + c * vy, *twist[2:]]
