"""Markers as text, in and out: a camera's list of markers, an observation, a fused marker.

A marker seen (``services.kernel.values.markers``) names the object with ``id``, ``class``,
``location`` (x y [z]), and may carry ``variance`` (m², per axis) and ``confidence`` (0..1]:
the variance of the observation is the marker's own ``variance``, or the source's default
divided by the confidence. Its other fields (``colour``, ...) are kept on the fused marker.

A list of markers is written in parentheses, the markers separated by spaces:
``(<marker>..</marker> <marker>..</marker>)``, ``()`` when empty, as a camera's ``markers`` is. A
reader also takes them without the parentheses or inside a ``<markers>`` element.
"""

from __future__ import annotations

import math
import re
import xml.etree.ElementTree as ET

from services.apps.environment.fusion import FusedMarker, Observation
from services.kernel.errors import InvalidArgument
from services.kernel.values import Marker, ValueFormatError, format_number, parse_marker, parse_number
from services.kernel.values.markers import format_markers

__all__ = [
    "MAX_LIST_MARKERS",
    "MAX_LIST_TEXT",
    "fused_marker",
    "observation_of",
    "parse_marker_list",
    "write_marker_list",
]

#: Markers one list may hold (one camera frame's worth and more).
MAX_LIST_MARKERS = 1000
#: Characters of one list of markers: a thousand markers of about 250 characters.
MAX_LIST_TEXT = 256 * 1024
#: Fields of a marker that the model writes itself; a sighting's own are not copied over them.
OWN_FIELDS = ("id", "class", "location", "variance", "source", "seen", "count")
_MARKER = re.compile(r"<marker>.*?</marker>", re.DOTALL)
_FIELD_TEXT = 200


def parse_marker_list(text: str) -> list[Marker]:
    """The markers of ``text``: ``<marker>..</marker> <marker>..</marker>``, in parentheses or a
    ``<markers>`` element; ``""`` and ``()`` are none. InvalidArgument for anything else."""
    body = text.strip()
    if len(body) > MAX_LIST_TEXT:
        raise InvalidArgument(f"a list of markers is {len(body)} characters; the limit is {MAX_LIST_TEXT}")
    if body.startswith("(") and body.endswith(")"):
        body = body[1:-1].strip()
    elif body.startswith("<markers>") and body.endswith("</markers>"):
        body = body[len("<markers>") : -len("</markers>")].strip()
    if not body:
        return []
    found = _MARKER.findall(body)
    rest = _MARKER.sub("", body).strip()
    if rest:
        shown = rest if len(rest) <= 40 else rest[:40] + "..."
        raise InvalidArgument(f"a list of markers holds something else: {shown!r}")
    if len(found) > MAX_LIST_MARKERS:
        raise InvalidArgument(f"a list of {len(found)} markers; the limit is {MAX_LIST_MARKERS}")
    markers = []
    for item in found:
        try:
            markers.append(parse_marker(item))
        except (ValueFormatError, ET.ParseError) as e:
            raise InvalidArgument(f"a marker of the list is bad: {e}") from None
    return markers


def write_marker_list(markers: list[Marker]) -> str:
    """``(<marker>..</marker> <marker>..</marker>)``; ``()`` when there is none (a camera's form)."""
    return format_markers(markers)


def _text(marker: Marker, name: str) -> str:
    value = marker.fields.get(name, "")
    return value.strip() if isinstance(value, str) else ""


def observation_of(marker: Marker, source: str, default_variance: float, default_class: str) -> Observation:
    """The observation a marker reports; InvalidArgument saying what is missing or wrong."""
    location = marker.location
    if location is None:
        raise InvalidArgument(
            "a marker observed needs a location: <marker><location>(x y)</location></marker>"
        )
    if len(location) not in (2, 3, 6):
        raise InvalidArgument(
            f"a marker's location is x y [z] (or a 6-vector pose), got {len(location)} numbers"
        )
    kind = _text(marker, "class") or default_class
    if len(kind) > 64 or not kind.isprintable():
        raise InvalidArgument(f"a marker's class is at most 64 printable characters, got {kind[:80]!r}")
    variance = default_variance
    if _text(marker, "variance"):
        variance = parse_number(_text(marker, "variance"))
        if not (math.isfinite(variance) and variance > 0):
            raise InvalidArgument(f"a marker's variance is a positive number of m², got {variance}")
    elif _text(marker, "confidence"):
        confidence = parse_number(_text(marker, "confidence"))
        if not (math.isfinite(confidence) and 0 < confidence <= 1):
            raise InvalidArgument(f"a marker's confidence is more than 0 and at most 1, got {confidence}")
        variance = default_variance / confidence
    fields = {
        name: value[:_FIELD_TEXT]
        for name, value in marker.fields.items()
        if isinstance(value, str) and name not in OWN_FIELDS
    }
    position = location[:3] if len(location) >= 3 else location
    return Observation.at(kind, position, variance, source, id=_text(marker, "id")[:64], fields=fields)


def fused_marker(marker: FusedMarker) -> Marker:
    """The fused marker as a value: id, class, location, variance, source, seen, count, then its fields."""
    x, y, z = (round(float(v), 4) for v in marker.position)
    fields: dict[str, str | Marker] = {
        "id": marker.id,
        "class": marker.cls,
        "location": f"({format_number(x)} {format_number(y)} {format_number(z)})",
        "variance": format_number(float(f"{marker.variance:.3g}")),
        "source": marker.source,
        "seen": format_number(round(marker.last_seen, 3)),
        "count": str(marker.count),
    }
    for name, value in marker.fields.items():
        fields.setdefault(name, value)
    return Marker("marker", fields)
