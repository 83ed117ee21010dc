"""Value formats of the Property Service: values travel as text, binary properties as bytes.

The text grammar is part of the contract, and both sides use this one
package: the services and the gateway, and the client SDK (``clients``).
It imports nothing of the project but :mod:`services.kernel.errors`, and numpy and
defusedxml only when a vector or a marker is first parsed (and numpy when
:data:`Vector` is first named), so that the SDK loads without them.

* :mod:`~services.kernel.values.grammar`: numbers, integers, booleans, vectors,
  lists, vectors lists and names; the limits and :class:`ValueFormatError`
* :mod:`~services.kernel.values.markers`: :class:`Marker`, the XML element tree value
* :mod:`~services.kernel.values.formatting`: :func:`format_value`, by runtime type
* :mod:`~services.kernel.values.annotations`: :func:`parser_for` / :func:`parse_as`
  turn a type annotation into a parser (used by the class wrapper)
* :mod:`~services.kernel.values.binary`: :data:`Value` (``str | bytes``), sizes and
  log-safe views of binary values
* :mod:`~services.kernel.values.vector_elements`: :func:`vector_index`, the
  sub-property names of a vector's elements
"""

from typing import TYPE_CHECKING, Any

from services.kernel.values.annotations import parse_as, parser_for, type_name
from services.kernel.values.binary import (
    MAX_BINARY_SIZE,
    MAX_MESSAGE_BYTES,
    Value,
    as_text,
    kind_word,
    loggable,
    value_size,
)
from services.kernel.values.formatting import format_result, format_value
from services.kernel.values.grammar import (
    MAX_LIST_DEPTH,
    MAX_VALUE_LENGTH,
    ValueFormatError,
    format_bool,
    format_list,
    format_names,
    format_number,
    format_vector,
    format_vectors,
    parse_bool,
    parse_int,
    parse_list,
    parse_names,
    parse_number,
    parse_vector,
    parse_vectors,
)
from services.kernel.values.markers import Marker, format_marker, parse_marker
from services.kernel.values.vector_elements import vector_index

if TYPE_CHECKING:
    from services.kernel.values.grammar import Vector

__all__ = [
    "MAX_BINARY_SIZE",
    "MAX_LIST_DEPTH",
    "MAX_MESSAGE_BYTES",
    "MAX_VALUE_LENGTH",
    "Marker",
    "Value",
    "ValueFormatError",
    "Vector",
    "as_text",
    "format_bool",
    "format_list",
    "format_marker",
    "format_names",
    "format_number",
    "format_result",
    "format_value",
    "format_vector",
    "format_vectors",
    "kind_word",
    "loggable",
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
    "value_size",
    "vector_index",
]


def __getattr__(name: str) -> Any:
    # Vector names numpy's array type: made on first use (see grammar.py), so that importing the
    # value grammar does not load numpy.
    if name == "Vector":
        from services.kernel.values import grammar

        return grammar.Vector
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
