"""Marker values: a small XML element tree such as ``<marker><location>(1 2)</location></marker>``.

Part of the value grammar (see :mod:`services.kernel.values.grammar`). A marker is
parsed with defusedxml: no DTDs, no entities, no external references.
Attributes and text mixed with child elements are refused rather than
silently dropped, and elements nest at most :data:`MAX_LIST_DEPTH` levels.
"""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from services.kernel.errors import NotFound
from services.kernel.values.grammar import (
    MAX_LIST_DEPTH,
    ValueFormatError,
    check_length,
    fail,
    format_plain,
    parse_vector,
    show,
)

if TYPE_CHECKING:
    import numpy.typing as npt

    from services.kernel.values.grammar import Vector

__all__ = ["Marker", "format_marker", "format_markers", "parse_marker", "parse_markers"]

_MARKER_EXAMPLE = 'a marker like "<marker><location>(1 2)</location></marker>"'
# Tag names are restricted so that a dotted path reaches every field and no
# XML namespace is involved.
_TAG = re.compile(r"[A-Za-z_][A-Za-z0-9_-]{0,63}")
# Characters XML 1.0 cannot carry at all (section 2.2); text holding them cannot be a marker field.
_NOT_XML = re.compile("[\x00-\x08\x0b\x0c\x0e-\x1f\ud800-\udfff\ufffe\uffff]")
_XML_ESCAPES = str.maketrans({"&": "&amp;", "<": "&lt;", ">": "&gt;", "\r": "&#13;"})


@dataclass
class Marker:
    """An XML element tree value such as ``<marker><location>(1 2)</location></marker>``.

    ``fields`` keeps the children in order: a leaf child holds its text, a
    child with children of its own is a nested :class:`Marker`. An empty
    nested element reads back as the empty text.
    """

    tag: str = "marker"
    fields: dict[str, str | Marker] = field(default_factory=dict)

    @classmethod
    def at(cls, location: Sequence[float] | npt.NDArray[Any], **fields: Any) -> Marker:
        """A ``<marker>`` with a ``location`` vector and further fields (non-text values are formatted)."""
        marker = cls("marker", {})
        for name, value in {"location": location, **fields}.items():
            marker = marker.with_field(name, value)
        return marker

    @property
    def location(self) -> Vector | None:
        """The ``location`` field as a vector, or None when there is none."""
        return self.vector("location") if "location" in self.fields else None

    def vector(self, name: str) -> Vector:
        """The field ``name`` parsed as a vector (KeyError when there is no such field)."""
        value = self.fields[name]
        if isinstance(value, Marker):
            raise ValueFormatError(f"expected the marker's {name} to be a vector, got {format_marker(value)}")
        return parse_vector(value)

    def get(self, path: str) -> str:
        """The text of the field at dotted ``path``; a nested element gives its XML."""
        node: str | Marker = self
        walked: list[str] = []
        for name in path.split("."):
            if not isinstance(node, Marker) or name not in node.fields:
                where = f"{'.'.join(walked)!r} of the marker" if walked else "the marker"
                raise NotFound(f"{where} has no field {name!r}")
            node = node.fields[name]
            walked.append(name)
        return node if isinstance(node, str) else format_marker(node)

    def with_field(self, name: str, value: Any) -> Marker:
        """A copy with field ``name`` set (replaced in place or appended); non-text values are formatted."""
        if _TAG.fullmatch(name) is None:
            raise ValueFormatError(f"bad marker field name {show(name)}: use letters, digits, _ and -")
        if isinstance(value, Marker):
            value = value if value.tag == name else Marker(name, value.fields)
        elif not isinstance(value, str):
            value = format_plain(value)
        return Marker(self.tag, {**self.fields, name: value})

    def to_xml(self) -> str:
        """Compact XML text, as a Set sends it (see :func:`format_marker`)."""
        return format_marker(self)


def parse_marker(text: str) -> Marker:
    """Parse a marker with defusedxml; DTDs, entities and external references are refused."""
    # defusedxml is imported by the parsers, not with this module: see _loaded_numpy in grammar.py.
    import defusedxml
    import defusedxml.ElementTree as DET

    check_length(text, _MARKER_EXAMPLE)
    try:
        root = DET.fromstring(text, forbid_dtd=True, forbid_entities=True, forbid_external=True)
    except defusedxml.DTDForbidden:
        raise fail(_MARKER_EXAMPLE, text, "document type declarations are not allowed") from None
    except defusedxml.EntitiesForbidden:
        raise fail(_MARKER_EXAMPLE, text, "entity declarations are not allowed") from None
    except defusedxml.DefusedXmlException:
        raise fail(_MARKER_EXAMPLE, text, "external references are not allowed") from None
    except ET.ParseError as e:
        raise fail(_MARKER_EXAMPLE, text, f"not well-formed XML ({e})") from None
    except (ValueError, RecursionError) as e:
        raise fail(_MARKER_EXAMPLE, text, f"not well-formed XML ({e})") from None
    node = _element(root, text, 1)
    if isinstance(node, str):
        if node.strip():
            raise fail(_MARKER_EXAMPLE, text, "the root element must hold fields, not text")
        return Marker(root.tag, {})
    return node


def _element(el: ET.Element, text: str, depth: int) -> str | Marker:
    if depth > MAX_LIST_DEPTH:
        raise fail(_MARKER_EXAMPLE, text, f"elements nest deeper than {MAX_LIST_DEPTH} levels")
    if _TAG.fullmatch(el.tag) is None:
        raise fail(_MARKER_EXAMPLE, text, f"bad element name {show(el.tag)} (use letters, digits, _ and -)")
    if el.attrib:
        raise fail(_MARKER_EXAMPLE, text, f"<{el.tag}> has attributes; put values in child elements")
    children = list(el)
    if not children:
        return el.text or ""
    if el.text and el.text.strip():
        raise fail(_MARKER_EXAMPLE, text, f"<{el.tag}> mixes text with child elements")
    fields: dict[str, str | Marker] = {}
    for child in children:
        if child.tail and child.tail.strip():
            raise fail(_MARKER_EXAMPLE, text, f"<{el.tag}> mixes text with child elements")
        value = _element(child, text, depth + 1)
        if child.tag in fields:
            raise fail(_MARKER_EXAMPLE, text, f"<{el.tag}> has more than one <{child.tag}>")
        fields[child.tag] = value
    return Marker(el.tag, fields)


def format_marker(m: Marker) -> str:
    """Compact XML, text escaped: ``<marker><location>(1 2)</location></marker>``."""
    parts: list[str] = []
    _write_marker(m, parts, 1)
    return "".join(parts)


def _write_marker(m: Marker, out: list[str], depth: int) -> None:
    if depth > MAX_LIST_DEPTH:
        raise ValueFormatError(f"cannot format a marker nested deeper than {MAX_LIST_DEPTH} levels")
    tag = _check_tag(m.tag)
    out.append(f"<{tag}>")
    for name, value in m.fields.items():
        _check_tag(name)
        if isinstance(value, Marker):
            # The field name is the element name; a nested marker's own tag is not consulted.
            _write_marker(value if value.tag == name else Marker(name, value.fields), out, depth + 1)
        else:
            if not isinstance(value, str):
                raise ValueFormatError(f"marker field {name!r} holds a {type(value).__name__}, not text")
            bad = _NOT_XML.search(value)
            if bad is not None:
                raise ValueFormatError(
                    f"marker field {name!r} holds the character {bad.group()!r}, which XML cannot carry"
                )
            out.append(f"<{name}>{value.translate(_XML_ESCAPES)}</{name}>")
    out.append(f"</{tag}>")


def _check_tag(tag: str) -> str:
    if not isinstance(tag, str) or _TAG.fullmatch(tag) is None:
        raise ValueFormatError(f"bad marker element name {tag!r}: use letters, digits, _ and - (max 64)")
    return tag


_MARKERS_EXAMPLE = 'a list of markers like "(<marker><location>(1 2)</location></marker>)"'


def format_markers(markers: Sequence[Marker]) -> str:
    """A list of markers: ``(<marker>...</marker> <marker>...</marker>)``; ``()`` when empty."""
    return "(" + " ".join(format_marker(m) for m in markers) + ")"


def parse_markers(text: str) -> list[Marker]:
    """Parse a list of markers (see :func:`format_markers`), each as :func:`parse_marker` does."""
    check_length(text, _MARKERS_EXAMPLE)
    inner = text.strip()
    if not (inner.startswith("(") and inner.endswith(")")):
        raise fail(_MARKERS_EXAMPLE, text, "a list is in parentheses")
    inner = inner[1:-1]
    if not inner.strip():
        return []
    import defusedxml
    import defusedxml.ElementTree as DET

    # One document: the markers as the children of a root that no marker can name.
    try:
        root = DET.fromstring(f"<_>{inner}</_>", forbid_dtd=True, forbid_entities=True, forbid_external=True)
    except defusedxml.DefusedXmlException:
        raise fail(
            _MARKERS_EXAMPLE, text, "declarations, entities and external references are not allowed"
        ) from None
    except (ET.ParseError, ValueError, RecursionError) as e:
        raise fail(_MARKERS_EXAMPLE, text, f"not well-formed XML ({e})") from None
    if root.text and root.text.strip():
        raise fail(_MARKERS_EXAMPLE, text, "text between the markers")
    found: list[Marker] = []
    for child in root:
        if child.tail and child.tail.strip():
            raise fail(_MARKERS_EXAMPLE, text, "text between the markers")
        node = _element(child, text, 1)
        if isinstance(node, str):
            if node.strip():
                raise fail(_MARKERS_EXAMPLE, text, f"<{child.tag}> must hold fields, not text")
            node = Marker(child.tag, {})
        found.append(node)
    return found
