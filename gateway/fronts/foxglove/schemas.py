"""What a property looks like on a Foxglove channel: its JSON schema and its messages.

Every channel is ``json``-encoded with a ``jsonschema`` schema. A property's own channel carries
``{"value": ...}`` typed by its model (a number as a JSON number, a vector as an array of numbers,
a boolean as a boolean, anything else as its text), so Foxglove's Plot and Raw Messages panels read
``.value``. Three kinds carry Foxglove's well-known schemas, in their JSON-schema form, so its
panels draw them with no set-up:

* a robot's ``location`` (``x y z roll pitch yaw``) also on ``/<service>/pose`` as
  ``foxglove.PoseInFrame`` (the 3D panel's pose);
* every ``location`` together on ``/scene`` as ``foxglove.SceneUpdate``: one entity per service,
  an arrow where it stands and heads and its name above it, so the swarm moves live;
* a binary property of an ``image/*`` media type as ``foxglove.CompressedImage`` (the Image panel).

Pure functions of the model and the value: no I/O, so the unit tests feed them values directly.
The value typing and the pose (shared with the recorder's MCAP channels) are the kernel's,
:mod:`services.kernel.typed`; re-exported here for the front's own use.
"""

from __future__ import annotations

import base64
import json
from collections.abc import Mapping
from typing import Any

from services.kernel.errors import InvalidArgument
from services.kernel.model import PropertyModel
from services.kernel.typed import (
    LOCATION,
    WORLD_FRAME,
    is_image,
    is_pose,
    pose_of,
    typed,
    value_json_schema,
)
from services.kernel.values import format_value
from services.kernel.values.binary import Value

__all__ = [
    "IMAGE_SCHEMA",
    "LOCATION",
    "POSE_SCHEMA",
    "SCENE_SCHEMA",
    "WORLD_FRAME",
    "is_image",
    "is_pose",
    "json_to_text",
    "pose_message",
    "pose_of",
    "published_value",
    "scene_message",
    "stamp",
    "typed",
    "value_message",
    "value_schema",
    "value_schema_name",
]

POSE_SCHEMA_NAME = "foxglove.PoseInFrame"
SCENE_SCHEMA_NAME = "foxglove.SceneUpdate"
IMAGE_SCHEMA_NAME = "foxglove.CompressedImage"

_TIME = {
    "type": "object",
    "title": "time",
    "properties": {"sec": {"type": "integer", "minimum": 0}, "nsec": {"type": "integer", "minimum": 0}},
}
_VECTOR3 = {
    "type": "object",
    "properties": {"x": {"type": "number"}, "y": {"type": "number"}, "z": {"type": "number"}},
}
_QUATERNION = {
    "type": "object",
    "properties": {
        "x": {"type": "number"},
        "y": {"type": "number"},
        "z": {"type": "number"},
        "w": {"type": "number"},
    },
}
_POSE = {"type": "object", "properties": {"position": _VECTOR3, "orientation": _QUATERNION}}
_COLOR = {
    "type": "object",
    "properties": {k: {"type": "number", "minimum": 0, "maximum": 1} for k in ("r", "g", "b", "a")},
}
_DURATION = {
    "type": "object",
    "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer", "minimum": 0}},
}

#: ``foxglove.PoseInFrame`` as Foxglove's JSON schemas write it (the fields this front fills).
POSE_SCHEMA: dict[str, Any] = {
    "title": POSE_SCHEMA_NAME,
    "description": "A timestamped pose for an object or reference frame in 3D space",
    "type": "object",
    "properties": {"timestamp": _TIME, "frame_id": {"type": "string"}, "pose": _POSE},
}

_ARROW = {
    "type": "object",
    "properties": {
        "pose": _POSE,
        "shaft_length": {"type": "number"},
        "shaft_diameter": {"type": "number"},
        "head_length": {"type": "number"},
        "head_diameter": {"type": "number"},
        "color": _COLOR,
    },
}
_TEXT = {
    "type": "object",
    "properties": {
        "pose": _POSE,
        "billboard": {"type": "boolean"},
        "font_size": {"type": "number"},
        "scale_invariant": {"type": "boolean"},
        "color": _COLOR,
        "text": {"type": "string"},
    },
}
_ENTITY = {
    "type": "object",
    "properties": {
        "timestamp": _TIME,
        "frame_id": {"type": "string"},
        "id": {"type": "string"},
        "lifetime": _DURATION,
        "frame_locked": {"type": "boolean"},
        "metadata": {"type": "array", "items": {"type": "object"}},
        "arrows": {"type": "array", "items": _ARROW},
        "texts": {"type": "array", "items": _TEXT},
    },
}
#: ``foxglove.SceneUpdate``: entities added or replaced (by id), and deletions.
SCENE_SCHEMA: dict[str, Any] = {
    "title": SCENE_SCHEMA_NAME,
    "description": "An update to the entities displayed in a 3D scene",
    "type": "object",
    "properties": {
        "deletions": {
            "type": "array",
            "items": {
                "type": "object",
                "properties": {"timestamp": _TIME, "type": {"type": "integer"}, "id": {"type": "string"}},
            },
        },
        "entities": {"type": "array", "items": _ENTITY},
    },
}
#: ``foxglove.CompressedImage``: in JSON, ``data`` is base64.
IMAGE_SCHEMA: dict[str, Any] = {
    "title": IMAGE_SCHEMA_NAME,
    "description": "A compressed image",
    "type": "object",
    "properties": {
        "timestamp": _TIME,
        "frame_id": {"type": "string"},
        "data": {"type": "string", "contentEncoding": "base64"},
        "format": {"type": "string"},
    },
}


def value_schema_name(model: PropertyModel) -> str:
    """The schema name of a property's own channel: ``propertyservice.<type word>``."""
    if is_image(model):
        return IMAGE_SCHEMA_NAME
    return f"propertyservice.{model.type.capitalize()}"


def value_schema(model: PropertyModel, service: str) -> dict[str, Any]:
    """The JSON schema of a property's own channel, from its model (type, range, unit, doc)."""
    if is_image(model):
        return IMAGE_SCHEMA
    if model.type == "bytes":
        return {
            "title": value_schema_name(model),
            "type": "object",
            "properties": {
                "data": {"type": "string", "contentEncoding": "base64"},
                "media_type": {"type": "string"},
            },
        }
    return {
        "title": f"{service}/{model.name}",
        "type": "object",
        "properties": {"value": value_json_schema(model)},
        "required": ["value"],
    }


def stamp(time_ns: int) -> dict[str, int]:
    """A Foxglove ``time`` from nanoseconds since the epoch."""
    sec, nsec = divmod(time_ns, 1_000_000_000)
    return {"sec": sec, "nsec": nsec}


def value_message(model: PropertyModel, value: Value, time_ns: int) -> dict[str, Any]:
    """One value as the message of its own channel (see :func:`value_schema`)."""
    if isinstance(value, bytes):
        data = base64.b64encode(value).decode("ascii")
        if is_image(model):
            return {
                "timestamp": stamp(time_ns),
                "frame_id": "",
                "data": data,
                "format": model.media_type.partition("/")[2],
            }
        return {"data": data, "media_type": model.media_type or "application/octet-stream"}
    return {"value": typed(model.type, value)}


def _pose_json(position: list[float], orientation: list[float]) -> dict[str, Any]:
    x, y, z = position
    qx, qy, qz, qw = orientation
    return {"position": {"x": x, "y": y, "z": z}, "orientation": {"x": qx, "y": qy, "z": qz, "w": qw}}


def pose_message(text: str, time_ns: int) -> dict[str, Any] | None:
    """A location as ``foxglove.PoseInFrame``; None when the value is no pose."""
    pose = pose_of(text)
    if pose is None:
        return None
    return {"timestamp": stamp(time_ns), "frame_id": WORLD_FRAME, "pose": _pose_json(*pose)}


def scene_message(service: str, text: str, time_ns: int, removed: bool) -> dict[str, Any] | None:
    """One service's location as a ``foxglove.SceneUpdate``: its entity (an arrow along its
    heading, its name above it) replaced, or deleted when the property went; None when the value
    is no pose."""
    if removed:
        return {"deletions": [{"timestamp": stamp(time_ns), "type": 0, "id": service}], "entities": []}
    pose = pose_of(text)
    if pose is None:
        return None
    position, orientation = pose
    above = [position[0], position[1], position[2] + 0.4]
    entity = {
        "timestamp": stamp(time_ns),
        "frame_id": WORLD_FRAME,
        "id": service,
        "lifetime": {"sec": 0, "nsec": 0},
        "frame_locked": False,
        "metadata": [],
        "arrows": [
            {
                "pose": _pose_json(position, orientation),
                "shaft_length": 0.3,
                "shaft_diameter": 0.08,
                "head_length": 0.15,
                "head_diameter": 0.18,
                "color": {"r": 0.2, "g": 0.6, "b": 1.0, "a": 1.0},
            }
        ],
        "texts": [
            {
                "pose": _pose_json(above, [0.0, 0.0, 0.0, 1.0]),
                "billboard": True,
                "font_size": 14,
                "scale_invariant": True,
                "color": {"r": 1.0, "g": 1.0, "b": 1.0, "a": 1.0},
                "text": service,
            }
        ],
    }
    return {"deletions": [], "entities": [entity]}


def published_value(message: Mapping[str, Any], binary: bool) -> Value:
    """What a client publishes (``{"value": ...}``, or ``{"data": BASE64}`` for a binary
    property) as the value a Set sends: JSON numbers, booleans and arrays in the value grammar."""
    if binary:
        data = message.get("data")
        if not isinstance(data, str):
            raise InvalidArgument('a binary property takes {"data": BASE64}')
        try:
            return base64.b64decode(data, validate=True)
        except ValueError:
            raise InvalidArgument('"data" is not base64') from None
    if "value" not in message:
        raise InvalidArgument('a message to a property is {"value": ...}')
    return json_to_text(message["value"])


def json_to_text(value: Any) -> str:
    """A JSON value in the value grammar: ``2.5``, ``true``, ``(1 2 3)``; a string as it is."""
    if isinstance(value, str):
        return value
    if value is None:
        return ""
    if isinstance(value, bool | int | float):
        return format_value(value)
    if isinstance(value, list) and all(isinstance(x, int | float) and not isinstance(x, bool) for x in value):
        return format_value([float(x) for x in value])
    raise InvalidArgument(f"cannot send {json.dumps(value)[:100]} as a value: give a number, text or numbers")
