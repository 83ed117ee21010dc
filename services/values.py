"""Value formats of the Property Service: every value travels as text.

Formats, all strict (a bad value raises :class:`ValueFormatError`, an
INVALID_ARGUMENT whose message shows what was expected and what arrived):

* number ``0.5``, ``-3e-2``, ``2`` (finite only; NaN and infinities are refused)
* integer ``42``, boolean ``true``/``false`` (also ``1 0 on off yes no``)
* vector ``(1 2.5 -0.03)``: numbers between parentheses, separated by whitespace
* list ``((1 2) (a b (c 1)))``: s-expression style nested lists of bare atoms
* vectors ``((1 0) (2 0.1))`` and names ``(location velocity behaviors.moveto)``
* marker ``<marker><location>(1 0.1)</location><color>(1 0 0)</color></marker>``:
  a small XML element tree, parsed with defusedxml (no DTDs, no entities, no
  external references). Attributes and text mixed with child elements are
  refused rather than silently dropped.

Surrounding whitespace of a whole value is ignored by the number, integer,
boolean, vector and list parsers. Every parser refuses text longer than
:data:`MAX_VALUE_LENGTH` characters.

:func:`parser_for` / :func:`parse_as` turn a type annotation into a parser
(used by the class wrapper); :func:`format_value` formats by runtime type.
"""

from __future__ import annotations

import functools
import inspect
import math
import re
import types
import typing
import xml.etree.ElementTree as ET
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

import defusedxml
import defusedxml.ElementTree as DET
import numpy as np
import numpy.typing as npt

from services.errors import InvalidArgument, NotFound

__all__ = [
    "MAX_LIST_DEPTH",
    "MAX_VALUE_LENGTH",
    "Marker",
    "ValueFormatError",
    "Vector",
    "format_bool",
    "format_list",
    "format_marker",
    "format_names",
    "format_number",
    "format_value",
    "format_vector",
    "format_vectors",
    "parse_as",
    "parse_bool",
    "parse_int",
    "parse_list",
    "parse_marker",
    "parse_names",
    "parse_number",
    "parse_vector",
    "parse_vectors",
    "parser_for",
    "type_name",
    "vector_index",
]

#: Largest value text any parser accepts. A value is one line of the line
#: protocol and one protobuf string field; 64 KiB holds a few thousand vector
#: elements and still keeps a hostile value cheap to refuse.
MAX_VALUE_LENGTH = 65536
#: Deepest nesting of lists and marker elements; real values nest two or three levels.
MAX_LIST_DEPTH = 32

Vector = npt.NDArray[np.float64]

_CLIP = 40


class ValueFormatError(InvalidArgument):
    """A value's text does not have the expected format."""


def _show(text: str, limit: int = _CLIP) -> str:
    """Quote (a clipped part of) ``text`` for an error message, control characters escaped."""
    if len(text) > limit:
        text = text[: limit - 1] + "…"
    return '"' + text.translate(_ESCAPES) + '"'


_ESCAPES = {i: f"\\x{i:02x}" for i in range(32)} | {
    ord("\n"): "\\n",
    ord("\r"): "\\r",
    ord("\t"): "\\t",
    ord('"'): '\\"',
    0x7F: "\\x7f",
}


def _fail(expected: str, text: str, why: str | None = None) -> ValueFormatError:
    message = f"expected {expected}, got {_show(text)}"
    if why:
        message += f": {why}"
    return ValueFormatError(message)


def _check_length(text: str, expected: str) -> None:
    if len(text) > MAX_VALUE_LENGTH:
        raise ValueFormatError(
            f"expected {expected}, got a value of {len(text)} characters: "
            f"the limit is {MAX_VALUE_LENGTH} characters"
        )


# ---------------------------------------------------------------------------
# numbers, integers, booleans

_NUMBER = re.compile(r"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")
_INTEGER = re.compile(r"[+-]?[0-9]+")
_NON_FINITE = frozenset({"nan", "+nan", "-nan", "inf", "+inf", "-inf", "infinity", "+infinity", "-infinity"})
_NUMBER_EXAMPLE = 'a number like "0.5"'


def _number_problem(token: str) -> str:
    """Why ``token`` is not a number (for messages)."""
    if token.lower() in _NON_FINITE:
        return f"{_show(token)} is not a finite number"
    if "," in token:
        return f"{_show(token)} is not a number (use a dot as the decimal point and spaces between numbers)"
    return f"{_show(token)} is not a number"


def _to_float(token: str) -> float | None:
    """The float ``token`` spells, or None when it is not a finite number in our grammar."""
    if _NUMBER.fullmatch(token) is None:
        return None
    x = float(token)
    if math.isinf(x):
        return None
    return x


def parse_number(text: str) -> float:
    """Parse a finite decimal number: ``0.5``, ``-3``, ``1e-3``."""
    _check_length(text, _NUMBER_EXAMPLE)
    token = text.strip()
    x = _to_float(token)
    if x is None:
        if _NUMBER.fullmatch(token) is not None:
            raise _fail(_NUMBER_EXAMPLE, text, "the number is too large")
        raise _fail(_NUMBER_EXAMPLE, text, _number_problem(token) if token else "the value is empty")
    return x


# Integral floats below this print without a fraction; above it repr's
# exponent form is shorter and still exact.
_INTEGRAL_LIMIT = 1e16

# Tuples rather than ``X | Y``: a union is built anew each time the expression runs,
# and these checks run for every value formatted.
_BOOLS = (bool, np.bool_)
_INTEGERS = (int, np.integer)
_NUMBERS = (int, float, np.integer, np.floating)
_SEQUENCES = (list, tuple)
_NESTED = (list, tuple, np.ndarray)


def format_number(x: float | np.integer[Any] | np.floating[Any]) -> str:
    """Shortest text that parses back to exactly ``x``: ``2``, ``0.5``, ``1e+20``."""
    if type(x) is float:  # the common case, kept free of the isinstance checks below
        return _format_float(x)
    if isinstance(x, _BOOLS):
        raise ValueFormatError(f"expected a number, got the boolean {x}")
    if isinstance(x, _INTEGERS):
        return str(int(x))
    return _format_float(float(x))


def _format_float(x: float) -> str:
    if x.is_integer():
        if abs(x) < _INTEGRAL_LIMIT:
            return str(int(x))
    elif not math.isfinite(x):
        raise ValueFormatError(f"cannot format {x!r}: only finite numbers are values")
    return repr(x)


def parse_int(text: str) -> int:
    """Parse a decimal integer: ``42``, ``-7``."""
    expected = 'an integer like "42"'
    _check_length(text, expected)
    token = text.strip()
    if _INTEGER.fullmatch(token) is None:
        if _NUMBER.fullmatch(token) is not None:
            raise _fail(expected, text, "the number has a fraction or an exponent")
        raise _fail(expected, text, f"{_show(token)} is not an integer" if token else "the value is empty")
    try:
        return int(token)
    except ValueError:  # more digits than Python converts (sys.int_info.default_max_str_digits)
        raise _fail(expected, text, "the integer has too many digits") from None


_TRUE = frozenset({"true", "1", "on", "yes"})
_FALSE = frozenset({"false", "0", "off", "no"})


def parse_bool(text: str) -> bool:
    """Parse ``true/false``, ``1/0``, ``on/off``, ``yes/no`` (any case)."""
    expected = 'a boolean ("true" or "false")'
    _check_length(text, expected)
    word = text.strip().lower()
    if word in _TRUE:
        return True
    if word in _FALSE:
        return False
    raise _fail(expected, text, "also accepted: 1/0, on/off, yes/no")


def format_bool(b: bool) -> str:
    """``true`` or ``false``."""
    return "true" if b else "false"


# ---------------------------------------------------------------------------
# vectors

_VECTOR_EXAMPLE = 'a vector like "(1 2 3)"'


def parse_vector(text: str) -> Vector:
    """Parse ``(1 2.5 -3e-2)`` into a 1-D float64 array; ``()`` is the empty vector."""
    _check_length(text, _VECTOR_EXAMPLE)
    body = text.strip()
    if not (body.startswith("(") and body.endswith(")")) or len(body) < 2:
        why = "the numbers must be enclosed in parentheses" if body else "the value is empty"
        raise _fail(_VECTOR_EXAMPLE, text, why)
    inner = body[1:-1]
    if "(" in inner or ")" in inner:
        raise _fail(_VECTOR_EXAMPLE, text, "a vector holds numbers only, not nested lists")
    tokens = inner.split()
    numbers = []
    for token in tokens:
        x = _to_float(token)
        if x is None:
            if "," in inner:
                raise _fail(_VECTOR_EXAMPLE, text, "separate the numbers with spaces, not commas")
            raise _fail(_VECTOR_EXAMPLE, text, _number_problem(token))
        numbers.append(x)
    return np.array(numbers, dtype=np.float64)


def format_vector(v: Sequence[float] | npt.NDArray[Any]) -> str:
    """``(1 2.5 -0.03)``: each element by :func:`format_number`."""
    if isinstance(v, np.ndarray):
        if v.ndim != 1:
            raise ValueFormatError(f"expected a 1-D vector, got an array of shape {v.shape}")
        v = v.tolist()
    return "(" + " ".join([format_number(x) for x in v]) + ")"


# ---------------------------------------------------------------------------
# lists (s-expressions)

_LIST_EXAMPLE = 'a list like "((1 2) (a b))"'
_TOKEN = re.compile(r"[()]|[^\s()]+")
_ATOM = re.compile(r"[^\s()]+")


def parse_list(text: str) -> list[Any]:
    """Parse ``((1 2) (a b (c 1)))`` into nested lists of atom strings.

    Atoms are bare words without whitespace or parentheses; numbers stay text
    at this level.
    """
    _check_length(text, _LIST_EXAMPLE)
    stack: list[list[Any]] = []
    result: list[Any] | None = None
    for m in _TOKEN.finditer(text):
        token = m.group()
        if result is not None:
            raise _fail(_LIST_EXAMPLE, text, f"unexpected {_show(token)} after the end of the list")
        if token == "(":
            if len(stack) >= MAX_LIST_DEPTH:
                raise _fail(_LIST_EXAMPLE, text, f"lists nest deeper than {MAX_LIST_DEPTH} levels")
            stack.append([])
        elif token == ")":
            if not stack:
                raise _fail(_LIST_EXAMPLE, text, f'unmatched ")" at position {m.start()}')
            done = stack.pop()
            if stack:
                stack[-1].append(done)
            else:
                result = done
        elif stack:
            stack[-1].append(token)
        else:
            raise _fail(_LIST_EXAMPLE, text, "a list must be enclosed in parentheses")
    if stack:
        raise _fail(_LIST_EXAMPLE, text, f'{len(stack)} unclosed "("')
    if result is None:
        raise _fail(_LIST_EXAMPLE, text, "the value is empty")
    return result


def _format_atom(item: Any) -> str:
    if isinstance(item, str):
        if _ATOM.fullmatch(item) is None:
            raise ValueFormatError(
                f"cannot put {_show(item)} in a list: list items are words without spaces or parentheses"
            )
        return item
    if isinstance(item, _BOOLS):
        return format_bool(bool(item))
    if isinstance(item, _NUMBERS):
        return format_number(item)
    raise ValueFormatError(f"cannot put a {type(item).__name__} in a list")


def _format_items(items: Any, depth: int) -> str:
    if depth > MAX_LIST_DEPTH:
        raise ValueFormatError(f"cannot format a list nested deeper than {MAX_LIST_DEPTH} levels")
    if isinstance(items, np.ndarray):
        items = items.tolist()
    parts = [
        _format_items(item, depth + 1) if isinstance(item, _NESTED) else _format_atom(item) for item in items
    ]
    return "(" + " ".join(parts) + ")"


def format_list(items: Sequence[Any] | npt.NDArray[Any]) -> str:
    """Format nested lists, tuples and arrays of numbers, booleans and words."""
    return _format_items(items, 1)


_VECTORS_EXAMPLE = 'a list of vectors like "((1 0) (2 0.1))"'


def parse_vectors(text: str) -> list[Vector]:
    """Parse ``((1.0 0.0) (2.0 0.1))`` into a list of 1-D float64 arrays."""
    _check_length(text, _VECTORS_EXAMPLE)
    try:
        items = parse_list(text)
    except ValueFormatError as e:
        raise ValueFormatError(e.message.replace(_LIST_EXAMPLE, _VECTORS_EXAMPLE, 1)) from None
    vectors = []
    for i, item in enumerate(items):
        if not isinstance(item, list):
            raise _fail(_VECTORS_EXAMPLE, text, f"item {i + 1} ({_show(item)}) is not a vector")
        numbers = []
        for token in item:
            x = _to_float(token) if isinstance(token, str) else None
            if x is None:
                why = "nested lists are not numbers" if not isinstance(token, str) else _number_problem(token)
                raise _fail(_VECTORS_EXAMPLE, text, f"in vector {i + 1}: {why}")
            numbers.append(x)
        vectors.append(np.array(numbers, dtype=np.float64))
    return vectors


def format_vectors(vs: Iterable[Sequence[float] | npt.NDArray[Any]]) -> str:
    """``((1 0) (2 0.1))``."""
    if isinstance(vs, np.ndarray) and vs.ndim != 2:
        raise ValueFormatError(f"expected a 2-D array of vectors, got an array of shape {vs.shape}")
    return "(" + " ".join([format_vector(v) for v in vs]) + ")"


_NAMES_EXAMPLE = 'a list of names like "(location velocity)"'


def parse_names(text: str) -> list[str]:
    """Parse a flat list of names: ``(location velocity behaviors.moveto)``.

    Names are list atoms; their grammar as paths is checked where they are used.
    """
    _check_length(text, _NAMES_EXAMPLE)
    try:
        items = parse_list(text)
    except ValueFormatError as e:
        raise ValueFormatError(e.message.replace(_LIST_EXAMPLE, _NAMES_EXAMPLE, 1)) from None
    for i, item in enumerate(items):
        if not isinstance(item, str):
            raise _fail(_NAMES_EXAMPLE, text, f"item {i + 1} is a nested list, not a name")
    return items


def format_names(names: Iterable[str]) -> str:
    """``(location velocity)``."""
    return "(" + " ".join([_format_name(n) for n in names]) + ")"


def _format_name(name: str) -> str:
    if not isinstance(name, str):
        raise ValueFormatError(f"expected a name, got a {type(name).__name__}")
    return _format_atom(name)


# ---------------------------------------------------------------------------
# markers

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

    @property
    def location(self) -> Vector | None:
        """The ``location`` field as a vector, or None when there is none."""
        value = self.fields.get("location")
        if value is None:
            return None
        if isinstance(value, Marker):
            raise ValueFormatError(
                f"expected the marker's location to be a vector, got {format_marker(value)}"
            )
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
            raise ValueFormatError(f"bad marker field name {_show(name)}: use letters, digits, _ and -")
        if isinstance(value, Marker):
            value = value if value.tag == name else Marker(name, value.fields)
        elif not isinstance(value, str):
            value = format_value(value)
        return Marker(self.tag, {**self.fields, name: value})


def parse_marker(text: str) -> Marker:
    """Parse a marker with defusedxml; DTDs, entities and external references are refused."""
    _check_length(text, _MARKER_EXAMPLE)
    try:
        root = DET.fromstring(text, forbid_dtd=True, forbid_entities=True, forbid_external=True)
    except defusedxml.DTDForbidden:
        raise _fail(_MARKER_EXAMPLE, text, "document type declarations are not allowed") from None
    except defusedxml.EntitiesForbidden:
        raise _fail(_MARKER_EXAMPLE, text, "entity declarations are not allowed") from None
    except defusedxml.DefusedXmlException:
        raise _fail(_MARKER_EXAMPLE, text, "external references are not allowed") from None
    except ET.ParseError as e:
        raise _fail(_MARKER_EXAMPLE, text, f"not well-formed XML ({e})") from None
    except (ValueError, RecursionError) as e:
        raise _fail(_MARKER_EXAMPLE, text, f"not well-formed XML ({e})") from None
    node = _element(root, text, 1)
    if isinstance(node, str):
        if node.strip():
            raise _fail(_MARKER_EXAMPLE, text, "the root element must hold fields, not text")
        return Marker(root.tag, {})
    return node


def _element(el: ET.Element, text: str, depth: int) -> str | Marker:
    if depth > MAX_LIST_DEPTH:
        raise _fail(_MARKER_EXAMPLE, text, f"elements nest deeper than {MAX_LIST_DEPTH} levels")
    if _TAG.fullmatch(el.tag) is None:
        raise _fail(_MARKER_EXAMPLE, text, f"bad element name {_show(el.tag)} (use letters, digits, _ and -)")
    if el.attrib:
        raise _fail(_MARKER_EXAMPLE, text, f"<{el.tag}> has attributes; put values in child elements")
    children = list(el)
    if not children:
        return el.text or ""
    if el.text and el.text.strip():
        raise _fail(_MARKER_EXAMPLE, text, f"<{el.tag}> mixes text with child elements")
    fields: dict[str, str | Marker] = {}
    for child in children:
        if child.tail and child.tail.strip():
            raise _fail(_MARKER_EXAMPLE, text, f"<{el.tag}> mixes text with child elements")
        value = _element(child, text, depth + 1)
        if child.tag in fields:
            raise _fail(_MARKER_EXAMPLE, text, f"<{el.tag}> has more than one <{child.tag}>")
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


# ---------------------------------------------------------------------------
# type-driven conversion


def _identity(text: str) -> str:
    return text


def _parse_floats(text: str) -> list[float]:
    return [float(x) for x in parse_vector(text)]


def _is_vector_type(tp: Any) -> bool:
    return tp is np.ndarray or typing.get_origin(tp) is np.ndarray


def _optional_inner(tp: Any) -> Any | None:
    """X for ``Optional[X]`` / ``X | None``; None when ``tp`` is not such a union."""
    origin = typing.get_origin(tp)
    if origin is typing.Union or origin is types.UnionType:
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if len(args) == 1 and len(typing.get_args(tp)) == 2:
            return args[0]
        raise TypeError(f"unsupported union type {tp!r}: only Optional[X] is a value type")
    return None


def _list_parser(item_tp: Any) -> Callable[[str], Any]:
    if item_tp is str:
        return parse_names
    if _is_vector_type(item_tp):
        return parse_vectors
    if item_tp is float:
        return _parse_floats
    if item_tp is Any:
        return parse_list
    item_parser = _build_parser(item_tp)

    def parse_items(text: str) -> list[Any]:
        items = parse_names(text)
        return [item_parser(item) for item in items]

    if item_tp in (int, bool):
        return parse_items
    raise TypeError(f"unsupported list item type {item_tp!r} for a value")


def _build_parser(tp: Any) -> Callable[[str], Any]:
    if tp is float:
        return parse_number
    if tp is int:
        return parse_int
    if tp is bool:
        return parse_bool
    if tp is str or tp is Any or tp is inspect.Parameter.empty:
        return _identity
    if _is_vector_type(tp):
        return parse_vector
    if tp is Marker:
        return parse_marker
    origin = typing.get_origin(tp)
    if origin is typing.Annotated:
        return parser_for(typing.get_args(tp)[0])
    inner = _optional_inner(tp)
    if inner is not None:
        inner_parser = parser_for(inner)
        text_inner = inner is str

        def parse_optional(text: str) -> Any:
            if text == "" or (not text_inner and not text.strip()):
                return None
            return inner_parser(text)

        return parse_optional
    if tp is list:
        return parse_list
    if origin is list:
        (item_tp,) = typing.get_args(tp)
        return _list_parser(item_tp)
    raise TypeError(f"unsupported value type {tp!r}")


@functools.lru_cache(maxsize=512)
def _cached_parser(tp: Any) -> Callable[[str], Any]:
    return _build_parser(tp)


def parser_for(tp: Any) -> Callable[[str], Any]:
    """The parser for annotation ``tp`` (cached); TypeError for a type that is not a value type."""
    try:
        return _cached_parser(tp)
    except TypeError as e:
        if "unhashable" not in str(e):
            raise
    return _build_parser(tp)  # Annotated metadata that cannot be hashed


def parse_as(tp: Any, text: str) -> Any:
    """Parse ``text`` as annotation ``tp`` says (see :func:`parser_for`)."""
    return parser_for(tp)(text)


def type_name(tp: Any) -> str:
    """A short word for ``tp`` in docs and ``NAME.parameters``."""
    if tp is bool:
        return "boolean"
    if tp is int:
        return "integer"
    if tp is float:
        return "number"
    if tp is str or tp is Any or tp is inspect.Parameter.empty:
        return "text"
    if _is_vector_type(tp):
        return "vector"
    if tp is Marker:
        return "marker"
    origin = typing.get_origin(tp)
    if origin is typing.Annotated:
        return type_name(typing.get_args(tp)[0])
    inner = _optional_inner(tp)
    if inner is not None:
        return type_name(inner)
    if tp is list:
        return "list"
    if origin is list:
        (item_tp,) = typing.get_args(tp)
        if item_tp is str:
            return "names"
        if _is_vector_type(item_tp):
            return "vectors"
        return "list"
    raise TypeError(f"unsupported value type {tp!r}")


def format_value(obj: Any) -> str:
    """Format ``obj`` by its runtime type; TypeError for a type that has no value format."""
    if type(obj) is float:  # the commonest value, kept free of the checks below
        return _format_float(obj)
    if obj is None:
        return ""
    if isinstance(obj, str):
        return obj
    if isinstance(obj, _BOOLS):
        return format_bool(bool(obj))
    if isinstance(obj, _NUMBERS):
        return format_number(obj)
    if isinstance(obj, np.ndarray):
        if obj.ndim == 0:
            return format_value(obj.item())
        if obj.ndim == 1:
            return format_vector(obj)
        return format_list(obj)
    if isinstance(obj, Marker):
        return format_marker(obj)
    if isinstance(obj, _SEQUENCES):
        if obj and all(isinstance(v, np.ndarray) for v in obj):
            return format_vectors(obj)
        return format_list(obj)
    raise TypeError(f"no value format for a {type(obj).__name__}")


# ---------------------------------------------------------------------------
# vector sub-properties

_AXES = {"x": 0, "y": 1, "z": 2, "roll": 3, "pitch": 4, "yaw": 5}
_INDEX = re.compile(r"0|[1-9][0-9]{0,8}")


def vector_index(name: str, length: int) -> int:
    """Index of sub-property ``name`` (``x y z roll pitch yaw`` or a decimal) in a vector of ``length``."""
    index = _AXES.get(name)
    if index is None:
        if _INDEX.fullmatch(name) is None:
            raise NotFound(
                f"a vector has no element {name!r}: use x, y, z, roll, pitch, yaw or an index from 0"
            )
        index = int(name)
    if index >= length:
        raise NotFound(f"a vector of {length} elements has no element {name!r} (index {index})")
    return index
