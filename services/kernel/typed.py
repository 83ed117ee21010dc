"""A property's value as the tools that draw it want it: JSON typed by the model, a pose from a location.

Foxglove's panels, the rosbridge front and the recorder's MCAP channels all show a value as
the JSON its model's type says (a number as a number, a vector as an array of numbers, a
boolean as a boolean, anything else as its text), and a robot's ``location`` as a pose.
Computed here once, for every front and application that shows them; pure functions of the
model and the value.
"""

from __future__ import annotations

from typing import Any

from services.kernel.model import PropertyModel
from services.kernel.pose import quaternion
from services.kernel.values import ValueFormatError, parse_bool, parse_int, parse_number, parse_vector

__all__ = [
    "LOCATION",
    "WORLD_FRAME",
    "is_image",
    "is_pose",
    "pose_of",
    "typed",
    "value_json_schema",
]

#: The frame every pose and scene entity is given: a location is in the world frame.
WORLD_FRAME = "world"
#: The property whose vector value is a pose (``x y z roll pitch yaw``) by the robots' convention.
LOCATION = "location"

#: The JSON type of a model's data type word; what is not here travels as its text.
_JSON_TYPES = {"number": "number", "integer": "integer", "boolean": "boolean"}


def is_image(model: PropertyModel) -> bool:
    """A binary property whose values are images (a camera's frames)."""
    return model.type == "bytes" and model.media_type.startswith("image/")


def is_pose(model: PropertyModel) -> bool:
    """A ``location`` vector: a pose by the robots' convention."""
    return model.type == "vector" and model.name.rpartition(".")[2] == LOCATION


def value_json_schema(model: PropertyModel) -> dict[str, Any]:
    """The JSON schema of a text value typed by its model (see :func:`typed`): type, range,
    length, choices and doc (with the unit)."""
    value: dict[str, Any]
    if model.type == "vector":
        item: dict[str, Any] = {"type": "number"}
        _bounds(item, model)
        value = {"type": "array", "items": item}
        if model.length is not None:
            value.update(minItems=model.length, maxItems=model.length)
    elif model.type in _JSON_TYPES:
        value = {"type": _JSON_TYPES[model.type]}
        _bounds(value, model)
    else:
        value = {"type": "string"}
        if model.choices:
            value["enum"] = list(model.choices)
    described = " ".join(part for part in (model.doc, f"({model.unit})" if model.unit else "") if part)
    if described:
        value["description"] = described
    return value


def _bounds(schema: dict[str, Any], model: PropertyModel) -> None:
    if model.minimum is not None:
        schema["minimum"] = model.minimum
    if model.maximum is not None:
        schema["maximum"] = model.maximum


def typed(data_type: str, text: str) -> Any:
    """A value's text as the JSON value of its type; its text when it does not read as that type
    (a device may answer outside its model: the message still goes out)."""
    try:
        if data_type == "number":
            return parse_number(text)
        if data_type == "integer":
            return parse_int(text)
        if data_type == "boolean":
            return parse_bool(text)
        if data_type == "vector":
            return [float(x) for x in parse_vector(text)]
    except ValueFormatError:
        return text
    return text


def pose_of(text: str) -> tuple[list[float], list[float]] | None:
    """A location's text (``x y [z [roll pitch yaw]]``) as a position and a quaternion
    (``x y z w``); None when it is not one (an empty location, a word)."""
    try:
        numbers = [float(x) for x in parse_vector(text)]
    except ValueFormatError:
        return None
    if len(numbers) < 2:
        return None
    numbers += [0.0] * (6 - len(numbers))
    x, y, z, roll, pitch, yaw = numbers[:6]
    return [x, y, z], quaternion(roll, pitch, yaw)
