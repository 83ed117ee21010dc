"""The typed model of a service on the wire: the ``Describe`` RPC's messages and the line protocol's text.

Both sides of each wire use this one module: the gateway (serving
``Describe``, proxying another gateway or a line device), the device side
(``services.device`` answering ``GET properties.model``) and the SDK
(``clients``), which may import it: it imports only the contract
(``protos``), :mod:`services.kernel.model` and the value grammar.

The line form (docs/device-spec.md §9, docs/line-protocol.md §12) is
one list value, an entry per property::

    ((name type access (unit words) minimum maximum (doc words)) ...)

``minimum`` and ``maximum`` are numbers or ``-`` for none; unit and doc are
lists of words (the grammar has no quoting: a word holds no space or
parenthesis, and the parentheses of a text are dropped). Every field after
``access`` may be left out.

After the doc, an entry may carry tagged lists, in any order::

    (gui WORD) (length N) (choices WORD ...) (media_type WORD) (max_size N) (resolution X)
    (value NAME TYPE required|optional (DEFAULT) (doc words))
    (param NAME TYPE required|optional (DEFAULT) (doc words))   one per parameter

``DEFAULT`` is the default's value text inside a list (``()`` for none; a vector
default ``(0 0)`` is ``((0 0))``). A reader skips a tag it does not know, and an
older reader reads only the first seven fields, so a model with tags still parses
there and one without them (the C library's) still parses here.
"""

from __future__ import annotations

import math
from typing import Any

from protos.propertyservice.v1 import property_service_pb2 as pb
from services.kernel.errors import InvalidArgument
from services.kernel.model import DATA_TYPES, Access, ParameterModel, PropertyModel, ServiceModel
from services.kernel.values.grammar import format_list, parse_list, parse_number

__all__ = [
    "MODEL_PATH",
    "model_from_proto",
    "model_from_text",
    "model_to_proto",
    "model_to_text",
]

#: The path a device that describes itself answers with its model. ``properties``
#: is reserved, so no property of any service can be named this.
MODEL_PATH = "properties.model"

_ACCESS_TO_PROTO = {
    Access.UNKNOWN: pb.ACCESS_UNKNOWN,
    Access.READ: pb.ACCESS_READ,
    Access.WRITE: pb.ACCESS_WRITE,
    Access.READ_WRITE: pb.ACCESS_READ_WRITE,
    Access.ACTION: pb.ACCESS_ACTION,
    Access.QUERY: pb.ACCESS_QUERY,
}
_ACCESS_FROM_PROTO = {number: access for access, number in _ACCESS_TO_PROTO.items()}


def _parameter_to_proto(param: ParameterModel) -> pb.ParameterInfo:
    return pb.ParameterInfo(
        name=param.name, type=param.type, required=param.required, default=param.default, doc=param.doc
    )


def _parameter_from_proto(info: pb.ParameterInfo) -> ParameterModel:
    return ParameterModel(
        name=info.name, type=info.type, required=info.required, default=info.default, doc=info.doc
    )


def _property_to_proto(prop: PropertyModel) -> pb.PropertyInfo:
    info = pb.PropertyInfo(
        name=prop.name,
        type=prop.type,
        access=_ACCESS_TO_PROTO[prop.access],
        length=prop.length or 0,
        unit=prop.unit,
        choices=prop.choices,
        doc=prop.doc,
        gui=prop.gui,
        parameters=[_parameter_to_proto(p) for p in prop.parameters],
        media_type=prop.media_type,
        max_size=prop.max_size,
    )
    if prop.minimum is not None:
        info.minimum = prop.minimum
    if prop.maximum is not None:
        info.maximum = prop.maximum
    if prop.resolution is not None:
        info.resolution = prop.resolution
    if prop.value is not None:
        info.value.CopyFrom(_parameter_to_proto(prop.value))
    return info


def _property_from_proto(info: pb.PropertyInfo) -> PropertyModel:
    return PropertyModel(
        name=info.name,
        type=info.type or "unknown",
        # A number a newer peer added reads as unknown: try it.
        access=_ACCESS_FROM_PROTO.get(info.access, Access.UNKNOWN),
        length=info.length or None,
        unit=info.unit,
        minimum=info.minimum if info.HasField("minimum") else None,
        maximum=info.maximum if info.HasField("maximum") else None,
        choices=tuple(info.choices),
        doc=info.doc,
        gui=info.gui,
        value=_parameter_from_proto(info.value) if info.HasField("value") else None,
        parameters=tuple(_parameter_from_proto(p) for p in info.parameters),
        media_type=info.media_type,
        max_size=info.max_size,
        resolution=info.resolution if info.HasField("resolution") and info.resolution > 0 else None,
    )


def model_to_proto(model: ServiceModel) -> pb.DescribeResponse:
    """The ``Describe`` answer for ``model``."""
    return pb.DescribeResponse(
        type=model.type, properties=[_property_to_proto(p) for p in model.properties], doc=model.doc
    )


def model_from_proto(response: pb.DescribeResponse) -> ServiceModel:
    """The model a ``Describe`` answer carries."""
    return ServiceModel(
        type=response.type,
        properties=tuple(_property_from_proto(p) for p in response.properties),
        doc=response.doc,
    )


def _words(text: str) -> list[str]:
    return text.replace("(", " ").replace(")", " ").split()


def _bound(x: float | None) -> Any:
    return "-" if x is None or not math.isfinite(x) else x


def _is_word(text: str) -> bool:
    return bool(text) and not any(c.isspace() or c in "()" for c in text)


def _default_items(text: str) -> list[Any]:
    """A default's value text as the items of a list (``()`` for none); words when it does not parse."""
    if not text:
        return []
    try:
        return parse_list(f"({text})")
    except ValueError:
        return _words(text)


def _parameter_tail(param: ParameterModel, docs: bool) -> list[Any]:
    return [
        param.type,
        "required" if param.required else "optional",
        _default_items(param.default),
        _words(param.doc) if docs else [],
    ]


def _tags(p: PropertyModel, docs: bool) -> list[Any]:
    tags: list[Any] = []
    if _is_word(p.gui):
        tags.append(["gui", p.gui])
    if p.length:
        tags.append(["length", p.length])
    if p.choices and all(_is_word(c) for c in p.choices):
        tags.append(["choices", *p.choices])
    if _is_word(p.media_type):
        tags.append(["media_type", p.media_type])
    if p.max_size:
        tags.append(["max_size", p.max_size])
    if p.resolution is not None:
        tags.append(["resolution", p.resolution])
    if p.value is not None:
        tags.append(["value", p.value.name, *_parameter_tail(p.value, docs)])
    tags.extend(["param", q.name, *_parameter_tail(q, docs)] for q in p.parameters if _is_word(q.name))
    return tags


def model_to_text(model: ServiceModel, *, docs: bool = True, tags: bool = True) -> str:
    """The line form of ``model`` (see the module docstring); ``docs=False`` leaves the docs out,
    ``tags=False`` the tagged lists (gui, length, choices, value, parameters)."""
    entries = []
    for p in model.properties:
        entry: list[Any] = [
            p.name,
            p.type,
            p.access.value,
            _words(p.unit),
            _bound(p.minimum),
            _bound(p.maximum),
        ]
        extra = _tags(p, docs) if tags else []
        if docs or extra:
            entry.append(_words(p.doc) if docs else [])
        entries.append(entry + extra)
    return format_list(entries)


def _text_of(item: Any) -> str:
    if isinstance(item, list):
        return " ".join(w for w in item if isinstance(w, str))
    return "" if item == "-" else str(item)


def _number_or_none(item: Any, where: str) -> float | None:
    if item in ("-", []):
        return None
    if not isinstance(item, str):
        raise InvalidArgument(f"{where}: a bound must be a number or -")
    return parse_number(item)


def _step_or_none(text: str) -> float | None:
    """A ``(resolution X)`` tag's step; a step that is not a positive number is skipped, as an
    unknown tag is (a model stays readable)."""
    try:
        step = parse_number(text)
    except InvalidArgument:
        return None
    return step if step > 0 else None


def model_from_text(text: str, service_type: str) -> ServiceModel:
    """Read the line form of a model; INVALID_ARGUMENT for an entry that is not one."""
    properties: list[PropertyModel] = []
    for i, entry in enumerate(parse_list(text)):
        where = f"model entry {i + 1}"
        if not isinstance(entry, list) or len(entry) < 3 or not all(isinstance(x, str) for x in entry[:3]):
            raise InvalidArgument(f"{where}: expected (name type access ...)")
        name, type_word, access_word = entry[0], entry[1], entry[2]
        try:
            access = Access(access_word)
        except ValueError:
            access = Access.UNKNOWN
        rest = entry[3:7] + [[]] * (4 - len(entry[3:7]))
        tagged = _read_tags(entry[7:])
        properties.append(
            PropertyModel(
                name=name,
                type=type_word if type_word in DATA_TYPES else "unknown",
                access=access,
                unit=_text_of(rest[0]),
                minimum=_number_or_none(rest[1], where),
                maximum=_number_or_none(rest[2], where),
                doc=_text_of(rest[3]),
                **tagged,
            )
        )
    return ServiceModel(type=service_type, properties=tuple(properties))


def _type_word(item: Any) -> str:
    return item if isinstance(item, str) and item in DATA_TYPES else "unknown"


def _parameter_from_items(name: str, items: list[Any]) -> ParameterModel:
    items = items + [[]] * (4 - len(items))
    default = items[2]
    if isinstance(default, list):
        default_text = format_list(default)[1:-1]
    else:
        default_text = "" if default == "-" else str(default)
    return ParameterModel(
        name=name,
        type=_type_word(items[0]),
        required=items[1] != "optional",
        default=default_text,
        doc=_text_of(items[3]),
    )


def _read_tags(items: list[Any]) -> dict[str, Any]:
    """The tagged lists after an entry's doc (see the module docstring); unknown tags are skipped."""
    found: dict[str, Any] = {}
    parameters: list[ParameterModel] = []
    for item in items:
        if not isinstance(item, list) or not item or not isinstance(item[0], str):
            continue
        tag, args = item[0], item[1:]
        if tag == "gui" and args and isinstance(args[0], str):
            found["gui"] = args[0]
        elif tag == "length" and args and isinstance(args[0], str) and args[0].isdigit():
            found["length"] = int(args[0]) or None
        elif tag == "media_type" and args and isinstance(args[0], str):
            found["media_type"] = args[0]
        elif tag == "max_size" and args and isinstance(args[0], str) and args[0].isdigit():
            found["max_size"] = int(args[0])
        elif tag == "resolution" and args and isinstance(args[0], str):
            found["resolution"] = _step_or_none(args[0])
        elif tag == "choices":
            found["choices"] = tuple(a for a in args if isinstance(a, str))
        elif tag == "value" and args and isinstance(args[0], str):
            found["value"] = _parameter_from_items(args[0], args[1:])
        elif tag == "param" and args and isinstance(args[0], str):
            parameters.append(_parameter_from_items(args[0], args[1:]))
    if parameters:
        found["parameters"] = tuple(parameters)
    return found
