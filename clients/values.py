"""Typed decoding and encoding of property values on the client side.

Values travel as text. These small, strict parsers turn the text forms into
Python objects and back:

* number ``0.5`` → ``float`` (finite only)
* vector ``(1 2 3)`` → 1-D ``numpy`` float64 array
* list of vectors ``((1 2) (3 4))`` → ``list`` of arrays
* names ``(a b c)`` → ``list[str]``
* marker ``<marker><location>(1 2)</location></marker>`` → :class:`Marker`,
  parsed with defusedxml (no DTDs, entities or external references)

A text that does not fit raises :class:`ValueFormatError` (a ``ValueError``).
"""

from __future__ import annotations

import math
import re
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import defusedxml
import defusedxml.ElementTree as DET
import numpy as np
import numpy.typing as npt

__all__ = [
    "Marker",
    "ValueFormatError",
    "Vector",
    "format_value",
    "parse_marker",
    "parse_names",
    "parse_number",
    "parse_vector",
    "parse_vectors",
]

Vector = npt.NDArray[np.float64]

_NUMBER = re.compile(r"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")
_ATOM = re.compile(r"[^\s()]+")
_TOKEN = re.compile(r"[()]|[^\s()]+")
_TAG = re.compile(r"[A-Za-z_][A-Za-z0-9_-]{0,63}")
_XML_ESCAPES = str.maketrans({"&": "&amp;", "<": "&lt;", ">": "&gt;", "\r": "&#13;"})
# Markers nest two or three levels in practice; deeper input is refused.
_MAX_DEPTH = 32


class ValueFormatError(ValueError):
    """A value's text does not have the expected format."""


def _clip(text: str, limit: int = 40) -> str:
    return repr(text if len(text) <= limit else text[: limit - 1] + "…")


def _float(token: str, text: str, expected: str) -> float:
    if _NUMBER.fullmatch(token) is None:
        raise ValueFormatError(f"expected {expected}, got {_clip(text)}: {_clip(token)} is not a number")
    x = float(token)
    if math.isinf(x):
        raise ValueFormatError(f"expected {expected}, got {_clip(text)}: the number is too large")
    return x


def parse_number(text: str) -> float:
    """``"0.5"`` → ``0.5``; surrounding whitespace is ignored."""
    return _float(text.strip(), text, 'a number like "0.5"')


def _parse_list(text: str, expected: str) -> list[Any]:
    """S-expression list of bare atoms, nested at most two levels (enough for every client helper)."""
    stack: list[list[Any]] = []
    result: list[Any] | None = None
    for m in _TOKEN.finditer(text):
        token = m.group()
        if result is not None:
            raise ValueFormatError(f"expected {expected}, got {_clip(text)}: text after the closing ')'")
        if token == "(":
            if len(stack) >= 2:
                raise ValueFormatError(f"expected {expected}, got {_clip(text)}: nested too deeply")
            stack.append([])
        elif token == ")":
            if not stack:
                raise ValueFormatError(f"expected {expected}, got {_clip(text)}: unmatched ')'")
            done = stack.pop()
            if stack:
                stack[-1].append(done)
            else:
                result = done
        elif stack:
            stack[-1].append(token)
        else:
            raise ValueFormatError(f"expected {expected}, got {_clip(text)}: missing parentheses")
    if stack or result is None:
        raise ValueFormatError(f"expected {expected}, got {_clip(text)}: unclosed or empty")
    return result


def parse_vector(text: str) -> Vector:
    """``"(1 2 3)"`` → ``array([1., 2., 3.])``; ``"()"`` is the empty vector."""
    expected = 'a vector like "(1 2 3)"'
    items = _parse_list(text, expected)
    numbers = []
    for item in items:
        if isinstance(item, list):
            raise ValueFormatError(f"expected {expected}, got {_clip(text)}: a vector holds numbers only")
        numbers.append(_float(item, text, expected))
    return np.array(numbers, dtype=np.float64)


def parse_vectors(text: str) -> list[Vector]:
    """``"((1 2) (3 4))"`` → a list of 1-D arrays (rows may differ in length)."""
    expected = 'a list of vectors like "((1 2) (3 4))"'
    rows = []
    for item in _parse_list(text, expected):
        if not isinstance(item, list):
            raise ValueFormatError(f"expected {expected}, got {_clip(text)}: {_clip(item)} is not a vector")
        rows.append(np.array([_float(t, text, expected) for t in item], dtype=np.float64))
    return rows


def parse_names(text: str) -> list[str]:
    """``"(a b c)"`` → ``["a", "b", "c"]``."""
    expected = 'a list of names like "(a b c)"'
    names = _parse_list(text, expected)
    for item in names:
        if isinstance(item, list):
            raise ValueFormatError(f"expected {expected}, got {_clip(text)}: a nested list is not a name")
    return names


@dataclass
class Marker:
    """A marker value: ``<marker><location>(1 2)</location><color>(1 0 0)</color></marker>``.

    ``fields`` holds the child elements in order: a leaf child as its text, a
    child with children of its own as a nested :class:`Marker`.
    """

    tag: str = "marker"
    fields: dict[str, str | Marker] = field(default_factory=dict)

    @classmethod
    def at(cls, location: Sequence[float] | npt.NDArray[Any], **fields: Any) -> Marker:
        """A marker with a ``location`` vector and further fields (formatted by :func:`format_value`)."""
        values: dict[str, str | Marker] = {"location": format_value(location)}
        for name, value in fields.items():
            values[name] = value if isinstance(value, Marker) else format_value(value)
        return cls("marker", values)

    @property
    def location(self) -> Vector | None:
        """The ``location`` field as a vector, or None when there is none."""
        return self.vector("location") if "location" in self.fields else None

    def vector(self, name: str) -> Vector:
        """The field ``name`` parsed as a vector (KeyError when absent)."""
        value = self.fields[name]
        if isinstance(value, Marker):
            raise ValueFormatError(f"marker field {name!r} holds elements, not a vector")
        return parse_vector(value)

    def to_xml(self) -> str:
        """Compact XML text, as a Set sends it."""
        return _marker_xml(self, 1)


def _marker_xml(m: Marker, depth: int) -> str:
    if depth > _MAX_DEPTH:
        raise ValueFormatError(f"a marker may nest at most {_MAX_DEPTH} levels")
    parts = [f"<{_check_tag(m.tag)}>"]
    for name, value in m.fields.items():
        if isinstance(value, Marker):
            parts.append(_marker_xml(Marker(name, value.fields), depth + 1))
        else:
            parts.append(f"<{_check_tag(name)}>{value.translate(_XML_ESCAPES)}</{name}>")
    parts.append(f"</{m.tag}>")
    return "".join(parts)


def _check_tag(tag: str) -> str:
    if _TAG.fullmatch(tag) is None:
        raise ValueFormatError(f"bad marker element name {tag!r}: use letters, digits, _ and -")
    return tag


def parse_marker(text: str) -> Marker:
    """Parse marker XML with defusedxml; attributes and text mixed with elements are refused."""
    expected = 'a marker like "<marker><location>(1 2)</location></marker>"'
    try:
        root = DET.fromstring(text, forbid_dtd=True, forbid_entities=True, forbid_external=True)
    except defusedxml.DefusedXmlException as e:
        raise ValueFormatError(f"expected {expected}, got {_clip(text)}: {e}") from None
    except (ET.ParseError, ValueError, RecursionError) as e:
        raise ValueFormatError(f"expected {expected}, got {_clip(text)}: not well-formed XML ({e})") from None
    node = _element(root, text, expected, 1)
    return node if isinstance(node, Marker) else Marker(root.tag, {})


def _element(el: ET.Element, text: str, expected: str, depth: int) -> str | Marker:
    def bad(why: str) -> ValueFormatError:
        return ValueFormatError(f"expected {expected}, got {_clip(text)}: {why}")

    if depth > _MAX_DEPTH:
        raise bad(f"elements nest deeper than {_MAX_DEPTH} levels")
    if _TAG.fullmatch(el.tag) is None:
        raise bad(f"bad element name {el.tag!r}")
    if el.attrib:
        raise bad(f"<{el.tag}> has attributes")
    children = list(el)
    if not children:
        if depth == 1 and el.text and el.text.strip():
            raise bad("the root element must hold fields, not text")
        return el.text or ""
    if (el.text and el.text.strip()) or any(c.tail and c.tail.strip() for c in children):
        raise bad(f"<{el.tag}> mixes text with child elements")
    fields: dict[str, str | Marker] = {}
    for child in children:
        if child.tag in fields:
            raise bad(f"<{el.tag}> has more than one <{child.tag}>")
        fields[child.tag] = _element(child, text, expected, depth + 1)
    return Marker(el.tag, fields)


def _format_number(x: Any) -> str:
    if isinstance(x, bool | np.bool_):
        raise ValueFormatError(f"expected a number, got the boolean {x}")
    if isinstance(x, int | np.integer):
        return str(int(x))
    f = float(x)
    if not math.isfinite(f):
        raise ValueFormatError(f"cannot send {f!r}: only finite numbers are values")
    # Integral floats print without a fraction ("2", not "2.0"); repr is the shortest exact text otherwise.
    return str(int(f)) if f.is_integer() and abs(f) < 1e16 else repr(f)


def _format_item(item: Any) -> str:
    if isinstance(item, str):
        if _ATOM.fullmatch(item) is None:
            raise ValueFormatError(f"cannot put {_clip(item)} in a list: use words without spaces or ()")
        return item
    if isinstance(item, Sequence | np.ndarray):
        return format_value(item)
    if isinstance(item, bool | np.bool_):
        return "true" if item else "false"
    return _format_number(item)


def format_value(value: Any) -> str:
    """The text form of ``value``.

    ``str`` as is; ``bool`` as ``true``/``false``; numbers shortest exact;
    a 1-D array or flat sequence of numbers as a vector ``(1 2 3)``; a 2-D
    array or a sequence of sequences as ``((1 2) (3 4))``; a :class:`Marker`
    as XML. Anything else raises ``TypeError``.
    """
    if isinstance(value, str):
        return value
    if isinstance(value, bool | np.bool_):
        return "true" if value else "false"
    if isinstance(value, int | float | np.integer | np.floating):
        return _format_number(value)
    if isinstance(value, Marker):
        return value.to_xml()
    if isinstance(value, np.ndarray):
        if value.ndim == 0:
            return format_value(value.item())
        if value.ndim > 2:
            raise ValueFormatError(f"cannot send an array of shape {value.shape}: use 1-D or 2-D")
        value = value.tolist()
    if isinstance(value, Sequence):
        return "(" + " ".join([_format_item(v) for v in value]) + ")"
    raise TypeError(f"no value format for a {type(value).__name__}")
