"""The text grammar of values, shared by every service and the client SDK.

Every value travels as text; these formats are part of the contract, so the
services and the SDK parse and format them with this one module. All are
strict (a bad value raises :class:`ValueFormatError`, an INVALID_ARGUMENT and
a ``ValueError`` whose message shows what was expected and what arrived):

* number ``0.5``, ``-3e-2``, ``2`` (finite only; NaN and infinities are refused)
* integer ``42``, boolean ``true``/``false`` (also ``1 0 on off yes no``)
* vector ``(1 2.5 -0.03)``: numbers between parentheses, separated by whitespace
* list ``((1 2) (a b (c 1)))``: s-expression style nested lists of bare atoms
* vectors ``((1 0) (2 0.1))`` and names ``(location velocity behaviors.moveto)``

Markers (XML values) are in :mod:`services.kernel.values.markers`. Surrounding
whitespace of a whole value is ignored by every parser here. Every parser
refuses text longer than :data:`MAX_VALUE_LENGTH` characters.
"""

from __future__ import annotations

import math
import re
import sys
from collections.abc import Iterable, Sequence
from types import ModuleType
from typing import TYPE_CHECKING, Any, TypeGuard

from services.kernel.errors import InvalidArgument

if TYPE_CHECKING:
    from typing import TypeAlias

    import numpy as np
    import numpy.typing as npt

    #: A parsed vector: a 1-D float64 array.
    Vector: TypeAlias = npt.NDArray[np.float64]

__all__ = [
    "MAX_LIST_DEPTH",
    "MAX_VALUE_LENGTH",
    "ValueFormatError",
    "Vector",
    "check_length",
    "fail",
    "format_bool",
    "format_float",
    "format_list",
    "format_names",
    "format_number",
    "format_plain",
    "format_vector",
    "format_vectors",
    "parse_bool",
    "parse_int",
    "parse_list",
    "parse_names",
    "parse_number",
    "parse_vector",
    "parse_vectors",
    "show",
]

#: Largest value text any parser accepts. A value is one line of the line
#: protocol and one protobuf string field; 64 KiB holds a few thousand vector
#: elements and still keeps a hostile value cheap to refuse.
MAX_VALUE_LENGTH = 65536
#: Deepest nesting of lists and marker elements; real values nest two or three levels.
MAX_LIST_DEPTH = 32

_CLIP = 40


# numpy is not imported with this module: the client SDK reads and writes values without it until a
# vector is parsed, so `import clients` stays light. The parsers that make arrays import it; the
# formatters never do: a numpy value cannot exist before numpy is loaded, so they look for numpy's
# types only in a numpy that is already in sys.modules, found once (`_np or _find_numpy()`).
_np: ModuleType | None = None


def _find_numpy() -> ModuleType | None:
    """numpy when something has imported it (kept in ``_np``), else None."""
    global _np
    _np = sys.modules.get("numpy")
    return _np


def __getattr__(name: str) -> Any:
    # Vector names numpy's array type, so it is made (and numpy imported) on first use.
    if name == "Vector":
        import numpy as np
        import numpy.typing as npt

        vector = npt.NDArray[np.float64]
        globals()["Vector"] = vector
        return vector
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


class ValueFormatError(InvalidArgument, ValueError):
    """A value's text does not have the expected format.

    An INVALID_ARGUMENT for the services, and a ``ValueError`` as the client
    SDK documents it.
    """


def show(text: str, limit: int = _CLIP) -> str:
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


def fail(expected: str, text: str, why: str | None = None) -> ValueFormatError:
    """The error for ``text`` that is not ``expected``, with the reason ``why``."""
    message = f"expected {expected}, got {show(text)}"
    if why:
        message += f": {why}"
    return ValueFormatError(message)


def check_length(text: str, expected: str) -> None:
    """Refuse ``text`` longer than :data:`MAX_VALUE_LENGTH` before parsing it."""
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
        return f"{show(token)} is not a finite number"
    if "," in token:
        return f"{show(token)} is not a number (use a dot as the decimal point and spaces between numbers)"
    return f"{show(token)} is not a number"


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
    check_length(text, _NUMBER_EXAMPLE)
    token = text.strip()
    x = _to_float(token)
    if x is None:
        if _NUMBER.fullmatch(token) is not None:
            raise fail(_NUMBER_EXAMPLE, text, "the number is too large")
        raise fail(_NUMBER_EXAMPLE, text, _number_problem(token) if token else "the value is empty")
    return x


# Integral floats below this print without a fraction; above it repr's
# exponent form is shorter and still exact.
_INTEGRAL_LIMIT = 1e16

# Tuples rather than ``X | Y``: a union is built anew each time the expression runs,
# and these checks run for every value formatted. numpy's scalars and arrays are checked after them.
_NUMBERS = (int, float)
_SEQUENCES = (list, tuple)


def _numpy_scalar(x: Any) -> bool | int | float | None:
    """The Python scalar a numpy boolean, integer or float holds; None for anything else."""
    np = _np or _find_numpy()
    if np is not None and isinstance(x, (np.bool_, np.integer, np.floating)):
        return x.item()  # type: ignore[no-any-return]
    return None


def _is_array(x: object) -> TypeGuard[npt.NDArray[Any]]:
    np = _np or _find_numpy()
    return np is not None and isinstance(x, np.ndarray)


def format_number(x: float | np.integer[Any] | np.floating[Any]) -> str:
    """Shortest text that parses back to exactly ``x``: ``2``, ``0.5``, ``1e+20``."""
    if type(x) is float:  # the common case, kept free of the isinstance checks below
        return format_float(x)
    if isinstance(x, bool):
        raise ValueFormatError(f"expected a number, got the boolean {x}")
    if isinstance(x, int):
        return str(int(x))
    scalar = _numpy_scalar(x)
    if scalar is not None:
        return format_number(scalar)
    return format_float(float(x))


def format_float(x: float) -> str:
    if x.is_integer():
        if abs(x) < _INTEGRAL_LIMIT:
            return str(int(x))
    elif not math.isfinite(x):
        raise ValueFormatError(f"cannot format {x!r}: only finite numbers are values")
    return repr(x)


def parse_int(text: str) -> int:
    """Parse a decimal integer: ``42``, ``-7``."""
    expected = 'an integer like "42"'
    check_length(text, expected)
    token = text.strip()
    if _INTEGER.fullmatch(token) is None:
        if _NUMBER.fullmatch(token) is not None:
            raise fail(expected, text, "the number has a fraction or an exponent")
        raise fail(expected, text, f"{show(token)} is not an integer" if token else "the value is empty")
    try:
        return int(token)
    except ValueError:  # more digits than Python converts (sys.int_info.default_max_str_digits)
        raise fail(expected, text, "the integer has too many digits") from None


_TRUE = frozenset({"true", "1", "on", "yes"})
_FALSE = frozenset({"false", "0", "off", "no"})


def parse_bool(text: str) -> bool:
    """Parse ``true/false``, ``1/0``, ``on/off``, ``yes/no`` (any case)."""
    expected = 'a boolean ("true" or "false")'
    check_length(text, expected)
    word = text.strip().lower()
    if word in _TRUE:
        return True
    if word in _FALSE:
        return False
    raise fail(expected, text, "also accepted: 1/0, on/off, yes/no")


def format_bool(b: bool) -> str:
    """``true`` or ``false``."""
    return "true" if b else "false"


# ---------------------------------------------------------------------------
# vectors

_VECTOR_EXAMPLE = 'a vector like "(1 2 3)"'
_EMPTY_VECTOR = 'the value is empty (unclosed or empty text; the empty vector is "()")'


def parse_vector(text: str) -> Vector:
    """Parse ``(1 2.5 -3e-2)`` into a 1-D float64 array; ``()`` is the empty vector."""
    import numpy as np

    check_length(text, _VECTOR_EXAMPLE)
    body = text.strip()
    if not body:
        raise fail(
            _VECTOR_EXAMPLE, text, 'the value is empty (unclosed or empty text; the empty vector is "()")'
        )
    if not body.startswith("("):
        raise fail(_VECTOR_EXAMPLE, text, "missing parentheses: the numbers must be enclosed in parentheses")
    close = body.find(")")
    if close < 0:
        raise fail(_VECTOR_EXAMPLE, text, 'unclosed "(": the numbers must be enclosed in parentheses')
    inner = body[1:close]
    if "(" in inner or (close + 1 < len(body) and body.find("(", close) >= 0):
        raise fail(_VECTOR_EXAMPLE, text, "a vector holds numbers only, not nested lists")
    if close + 1 < len(body):
        raise fail(_VECTOR_EXAMPLE, text, 'text after the closing ")"')
    numbers = []
    for token in inner.split():
        x = _to_float(token)
        if x is None:
            if "," in inner:
                why = f"{show(token)} is not a number: separate the numbers with spaces, not commas"
            else:
                why = _number_problem(token)
            raise fail(_VECTOR_EXAMPLE, text, why)
        numbers.append(x)
    return np.array(numbers, dtype=np.float64)


def format_vector(v: Sequence[float] | npt.NDArray[Any]) -> str:
    """``(1 2.5 -0.03)``: each element by :func:`format_number`."""
    if _is_array(v):
        if v.ndim != 1:
            raise ValueFormatError(f"expected a 1-D vector, got an array of shape {v.shape}")
        v = v.tolist()
    return _format_numbers(v)


def _format_numbers(numbers: Iterable[Any]) -> str:
    return "(" + " ".join([format_number(x) for x in numbers]) + ")"


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
    check_length(text, _LIST_EXAMPLE)
    stack: list[list[Any]] = []
    result: list[Any] | None = None
    for m in _TOKEN.finditer(text):
        token = m.group()
        if result is not None:
            raise fail(_LIST_EXAMPLE, text, f"unexpected {show(token)} after the end of the list")
        if token == "(":
            if len(stack) >= MAX_LIST_DEPTH:
                raise fail(_LIST_EXAMPLE, text, f"lists nest deeper than {MAX_LIST_DEPTH} levels")
            stack.append([])
        elif token == ")":
            if not stack:
                raise fail(_LIST_EXAMPLE, text, f'unmatched ")" at position {m.start()}')
            done = stack.pop()
            if stack:
                stack[-1].append(done)
            else:
                result = done
        elif stack:
            stack[-1].append(token)
        else:
            raise fail(_LIST_EXAMPLE, text, "a list must be enclosed in parentheses")
    if stack:
        raise fail(_LIST_EXAMPLE, text, f'{len(stack)} unclosed "("')
    if result is None:
        raise fail(_LIST_EXAMPLE, text, "the value is empty")
    return result


def _format_atom(item: Any) -> str:
    if isinstance(item, str):
        if _ATOM.fullmatch(item) is None:
            raise ValueFormatError(
                f"cannot put {show(item)} in a list: list items are words without spaces or parentheses"
            )
        return item
    if isinstance(item, bool):
        return format_bool(item)
    if isinstance(item, _NUMBERS):
        return format_number(item)
    scalar = _numpy_scalar(item)
    if scalar is not None:
        return _format_atom(scalar)
    raise ValueFormatError(f"cannot put a {type(item).__name__} in a list")


def _format_items(items: Any, depth: int) -> str:
    if depth > MAX_LIST_DEPTH:
        raise ValueFormatError(f"cannot format a list nested deeper than {MAX_LIST_DEPTH} levels")
    np = _np or _find_numpy()
    if np is None:
        nested: tuple[type, ...] = _SEQUENCES
    else:
        nested = (*_SEQUENCES, np.ndarray)
        if isinstance(items, np.ndarray):
            items = items.tolist()
    parts = [
        _format_items(item, depth + 1) if isinstance(item, nested) else _format_atom(item) for item in items
    ]
    return "(" + " ".join(parts) + ")"


def format_list(items: Sequence[Any] | npt.NDArray[Any]) -> str:
    """Format nested lists, tuples and arrays of numbers, booleans and words."""
    return _format_items(items, 1)


_VECTORS_EXAMPLE = 'a list of vectors like "((1 0) (2 0.1))"'


def parse_vectors(text: str) -> list[Vector]:
    """Parse ``((1.0 0.0) (2.0 0.1))`` into a list of 1-D float64 arrays."""
    import numpy as np

    check_length(text, _VECTORS_EXAMPLE)
    try:
        items = parse_list(text)
    except ValueFormatError as e:
        raise ValueFormatError(e.message.replace(_LIST_EXAMPLE, _VECTORS_EXAMPLE, 1)) from None
    vectors = []
    for i, item in enumerate(items):
        if not isinstance(item, list):
            raise fail(_VECTORS_EXAMPLE, text, f"item {i + 1} ({show(item)}) is not a vector")
        numbers = []
        for token in item:
            x = _to_float(token) if isinstance(token, str) else None
            if x is None:
                why = "nested lists are not numbers" if not isinstance(token, str) else _number_problem(token)
                raise fail(_VECTORS_EXAMPLE, text, f"in vector {i + 1}: {why}")
            numbers.append(x)
        vectors.append(np.array(numbers, dtype=np.float64))
    return vectors


def format_vectors(vs: Iterable[Sequence[float] | npt.NDArray[Any]]) -> str:
    """``((1 0) (2 0.1))``."""
    if _is_array(vs) and vs.ndim != 2:
        raise ValueFormatError(f"expected a 2-D array of vectors, got an array of shape {vs.shape}")
    return "(" + " ".join([format_vector(v) for v in vs]) + ")"


_NAMES_EXAMPLE = 'a list of names like "(location velocity)"'


def parse_names(text: str) -> list[str]:
    """Parse a flat list of names: ``(location velocity behaviors.moveto)``.

    Names are list atoms; their grammar as paths is checked where they are used.
    """
    check_length(text, _NAMES_EXAMPLE)
    try:
        items = parse_list(text)
    except ValueFormatError as e:
        raise ValueFormatError(e.message.replace(_LIST_EXAMPLE, _NAMES_EXAMPLE, 1)) from None
    for i, item in enumerate(items):
        if not isinstance(item, str):
            raise fail(_NAMES_EXAMPLE, text, f"item {i + 1} is a nested list, not a name")
    return items


def format_names(names: Iterable[str]) -> str:
    """``(location velocity)``."""
    return "(" + " ".join([_format_name(n) for n in names]) + ")"


def _format_name(name: str) -> str:
    if not isinstance(name, str):
        raise ValueFormatError(f"expected a name, got a {type(name).__name__}")
    return _format_atom(name)


# ---------------------------------------------------------------------------
# any value but a marker, by its runtime type


def format_plain(obj: Any) -> str:
    """Format ``obj`` by its runtime type, markers aside (see ``format_value``); TypeError for others."""
    if type(obj) is float:  # the commonest value, kept free of the checks below
        return format_float(obj)
    if obj is None:
        return ""
    if isinstance(obj, str):
        return obj
    if isinstance(obj, bool):
        return format_bool(obj)
    if isinstance(obj, _NUMBERS):
        return format_number(obj)
    np = _np or _find_numpy()
    if np is not None and isinstance(obj, np.ndarray):
        if obj.ndim == 0:
            return format_plain(obj.item())
        if obj.ndim == 1:
            return _format_numbers(obj.tolist())
        return format_list(obj)
    if isinstance(obj, _SEQUENCES):
        if obj and np is not None and all(isinstance(v, np.ndarray) for v in obj):
            return format_vectors(obj)
        return format_list(obj)
    if np is not None and isinstance(obj, (np.bool_, np.integer, np.floating)):
        return format_plain(obj.item())
    raise TypeError(f"no value format for a {type(obj).__name__}")
