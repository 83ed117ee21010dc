"""From a type annotation to a value parser: what the class wrapper uses for arguments.

:func:`parser_for` turns an annotation (``float``, ``Vector``,
``list[str]``, ``Optional[Marker]``, ``Annotated[int, ...]``) into the
parser of the value grammar that reads it (``bytes``, a binary value, is taken as
it is); :func:`type_name` gives the word for it in ``NAME.parameters`` and docs.

A type alias (``type Pose = NDArray[np.float64]``, and numpy's own
``NDArray`` since numpy 2.5, where ``NDArray[np.float64]`` is a subscripted
alias rather than ``np.ndarray[...]``) reads as the type it stands for.
"""

from __future__ import annotations

import functools
import inspect
import sys
import types
import typing
from collections.abc import Callable
from typing import Any

from services.kernel.values.grammar import (
    parse_bool,
    parse_int,
    parse_list,
    parse_names,
    parse_number,
    parse_vector,
    parse_vectors,
)
from services.kernel.values.markers import Marker, parse_marker

__all__ = ["parse_as", "parser_for", "type_name"]


def _identity(text: str) -> str:
    return text


def _bytes_identity(data: Any) -> bytes:
    # The class wrapper hands a binary property only bytes (it refuses text before parsing).
    return bytes(data)


def _parse_floats(text: str) -> list[float]:
    return [float(x) for x in parse_vector(text)]


def _type_alias_kinds() -> tuple[Any, ...]:
    """The classes of type aliases: typing's (Python 3.12+) and typing_extensions' (any Python)."""
    kinds = [getattr(typing, "TypeAliasType", None)]
    try:
        import typing_extensions

        kinds.append(getattr(typing_extensions, "TypeAliasType", None))
    except ImportError:  # only aliases made with typing_extensions need it, and they import it
        pass
    return tuple({kind for kind in kinds if isinstance(kind, type)})


_TYPE_ALIAS_KINDS = _type_alias_kinds()
# An alias naming itself (type A = B; type B = A) is an error, not a hang.
_MAX_ALIAS_DEPTH = 32


def _resolve_alias(tp: Any) -> Any:
    """The type ``tp`` stands for when it is a type alias or a subscripted generic alias; else ``tp``."""
    for _ in range(_MAX_ALIAS_DEPTH):
        if isinstance(tp, _TYPE_ALIAS_KINDS):
            tp = tp.__value__
            continue
        origin = typing.get_origin(tp)
        if not isinstance(origin, _TYPE_ALIAS_KINDS):
            return tp
        value = origin.__value__
        try:
            tp = value[typing.get_args(tp)]  # NDArray[np.float64] -> np.ndarray[shape, np.dtype[float64]]
        except TypeError:  # the value takes no parameters: what it names is the type
            tp = value
    raise TypeError(f"unsupported value type {tp!r}: a type alias that does not end")


def _is_vector_type(tp: Any) -> bool:
    # An annotation that names numpy's array was written by code that imported numpy; numpy
    # itself is not imported for this check, so the client SDK loads without it.
    np = sys.modules.get("numpy")
    if np is None:
        return False
    tp = _resolve_alias(tp)
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
    item_tp = _resolve_alias(item_tp)
    if item_tp is str:
        return parse_names
    if _is_vector_type(item_tp):
        return parse_vectors
    if item_tp is float:
        return _parse_floats
    if item_tp is Any:
        return parse_list
    if item_tp not in (int, bool):
        raise TypeError(f"unsupported list item type {item_tp!r} for a value")
    item_parser = _build_parser(item_tp)

    def parse_items(text: str) -> list[Any]:
        items = parse_names(text)
        return [item_parser(item) for item in items]

    return parse_items


def _build_parser(tp: Any) -> Callable[[str], Any]:
    tp = _resolve_alias(tp)
    if tp is float:
        return parse_number
    if tp is int:
        return parse_int
    if tp is bool:
        return parse_bool
    if tp is str or tp is Any or tp is inspect.Parameter.empty:
        return _identity
    if tp is bytes:
        return _bytes_identity
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
        text_inner = inner is str or inner is bytes

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
    tp = _resolve_alias(tp)
    if tp is bool:
        return "boolean"
    if tp is int:
        return "integer"
    if tp is float:
        return "number"
    if tp is str or tp is Any or tp is inspect.Parameter.empty:
        return "text"
    if tp is bytes:
        return "bytes"
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
        item_tp = _resolve_alias(typing.get_args(tp)[0])
        if item_tp is str:
            return "names"
        if _is_vector_type(item_tp):
            return "vectors"
        return "list"
    raise TypeError(f"unsupported value type {tp!r}")
