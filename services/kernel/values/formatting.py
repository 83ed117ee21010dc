"""Formatting any value by its runtime type: the one entry point for results and parameters."""

from __future__ import annotations

from typing import Any

from services.kernel.values.grammar import format_float, format_plain
from services.kernel.values.markers import Marker, format_marker

__all__ = ["format_result", "format_value"]


def format_value(obj: Any) -> str:
    """Format ``obj`` by its runtime type; TypeError for a type that has no value format.

    ``None`` is the empty text, ``str`` as is, ``bool`` as ``true``/``false``,
    numbers in their shortest exact form, a 1-D array as a vector, a 2-D array
    or nested sequences as a list, a sequence of arrays as vectors and a
    :class:`Marker` as XML.
    """
    # The commonest values first, by exact type: a Get of text or a number costs two checks.
    cls = type(obj)
    if cls is float:
        return format_float(obj)
    if cls is str:
        return obj  # type: ignore[no-any-return]
    if isinstance(obj, Marker):
        return format_marker(obj)
    return format_plain(obj)


def format_result(obj: Any) -> str | bytes:
    """A property's value or a method's answer as it travels: bytes (a binary value) as they
    are, anything else as :func:`format_value` writes it."""
    cls = type(obj)
    if cls is bytes:
        return obj  # type: ignore[no-any-return]
    if cls is not str and cls is not float and isinstance(obj, bytes | bytearray | memoryview):
        return bytes(obj)
    return format_value(obj)
