"""A value into and out of the contract's messages: text in ``value``, bytes in ``data``.

The presence of ``data`` (proto3 ``optional``) says a value is binary, so an empty binary value
stays binary; ``value`` is then "" (docs/architecture.md, "Binary values").
"""

from __future__ import annotations

from typing import Protocol

from services.kernel.errors import InvalidArgument
from services.kernel.values import Value


class Carrier(Protocol):
    """A message with a ``value`` text field and an ``optional bytes data`` field."""

    value: str
    data: bytes

    def HasField(self, field_name: str) -> bool: ...


def received(message: Carrier) -> Value:
    """The value ``message`` carries: its ``data`` when present, else its ``value``."""
    if message.HasField("data"):
        if message.value:
            raise InvalidArgument(
                "a value is either text (value) or bytes (data), not both: leave value empty"
            )
        return message.data
    return message.value


def put(message: Carrier, value: Value) -> None:
    """Put ``value`` into ``message``: bytes into ``data``, text into ``value``."""
    if isinstance(value, bytes):
        message.data = value
    else:
        message.value = value
