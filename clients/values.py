"""Typed decoding and encoding of property values on the client side.

Values travel as text, in the grammar the services use too
(:mod:`services.kernel.values`); this module is the SDK's view of it. A binary
property (Describe type ``bytes``: a JPEG frame, a numpy grid) reads as
``bytes`` and is Set from ``bytes`` (:data:`Value` is ``str | bytes``).

* number ``0.5`` → ``float`` (finite only)
* vector ``(1 2 3)`` → 1-D ``numpy`` float64 array
* list of vectors ``((1 2) (3 4))`` → ``list`` of arrays
* names ``(a b c)`` → ``list[str]``
* marker ``<marker><location>(1 2)</location></marker>`` → :class:`Marker`,
  parsed with defusedxml (no DTDs, entities or external references)

A text that does not fit raises :class:`ValueFormatError` (a ``ValueError``).
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

from services.kernel import values as grammar
from services.kernel.values import (
    Marker,
    Value,
    ValueFormatError,
    parse_marker,
    parse_names,
    parse_number,
    parse_vector,
    parse_vectors,
)

__all__ = [
    "Marker",
    "Value",
    "ValueFormatError",
    "format_value",
    "outgoing_value",
    "parse_marker",
    "parse_names",
    "parse_number",
    "parse_vector",
    "parse_vectors",
]

if TYPE_CHECKING:
    from typing import TypeAlias

    Vector: TypeAlias = grammar.Vector


def __getattr__(name: str) -> Any:
    # Vector, the type of a parsed vector, is numpy's array: named on first use, so that importing
    # the SDK does not load numpy (it is left out of __all__, which `clients` re-exports with *).
    if name == "Vector":
        return grammar.Vector
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def format_value(value: Any) -> str:
    """The text form of ``value``, as a Set or a request parameter sends it.

    ``str`` as is; ``bool`` as ``true``/``false``; numbers shortest exact;
    a 1-D array or flat sequence of numbers as a vector ``(1 2 3)``; a 2-D
    array or a sequence of sequences as ``((1 2) (3 4))``; a :class:`Marker`
    as XML. Anything else (``None`` included) raises ``TypeError``.
    """
    # A client sends what it means: no None for "empty", no array the grammar would flatten into lists.
    if value is None:
        raise TypeError("no value format for a NoneType")
    numpy = sys.modules.get("numpy")  # an array can only come from a numpy already loaded
    if numpy is not None and isinstance(value, numpy.ndarray) and value.ndim > 2:
        raise ValueFormatError(f"cannot send an array of shape {value.shape}: use 1-D or 2-D")
    if isinstance(value, Sequence) and not isinstance(value, str | list | tuple):
        value = list(value)
    return grammar.format_value(value)


def outgoing_value(value: Any) -> Value:
    """What a Set sends for ``value``: bytes (``bytes``, ``bytearray``, ``memoryview``) as they
    are, for a binary property; anything else as text (:func:`format_value`)."""
    if isinstance(value, bytes | bytearray | memoryview):
        return bytes(value)
    return format_value(value)
