"""Binary values: a property of type ``bytes`` (a JPEG frame, a numpy grid) carries raw bytes.

Inside the project a value is :data:`Value`, text or bytes. Everything that only passes values
along (router, listen hub, conflation, Session) hands ``bytes`` on unchanged; the encoders put
``bytes`` in the contract's ``data`` field and ``str`` in ``value``. Logs and audit lines never
show binary content: :func:`loggable` writes ``<N bytes MEDIA>`` instead.
"""

from __future__ import annotations

from services.kernel.values.grammar import ValueFormatError

#: The largest message a gRPC peer accepts unless it asks for more (grpc's default); the
#: gateway's receive limit is the same (``gateway.engine.sizes`` takes it from here).
MAX_MESSAGE_BYTES = 4 * 1024 * 1024
#: The largest value a binary property takes unless its ``max_size`` says otherwise: what one
#: message can carry, less room for the envelope (service and property names, a Session's id).
MAX_BINARY_SIZE = MAX_MESSAGE_BYTES - 1024

#: A property's value: text (the grammar of :mod:`services.kernel.values.grammar`) or, for a
#: property of type ``bytes``, raw bytes.
Value = str | bytes


def value_size(value: Value) -> int:
    """The bytes ``value`` takes on the wire (text as UTF-8)."""
    if isinstance(value, bytes):
        return len(value)
    return len(value) if value.isascii() else len(value.encode())


def loggable(value: Value, media_type: str = "", limit: int = 0) -> str:
    """``value`` as a log line may show it: binary content becomes ``<N bytes MEDIA>``.

    ``limit`` (when not 0) clips text to that many characters.
    """
    if isinstance(value, bytes):
        return f"<{len(value)} bytes {media_type}>" if media_type else f"<{len(value)} bytes>"
    return value[:limit] if limit else value


def kind_word(value: Value) -> str:
    """``bytes`` or ``text``: how a value travels, for error messages."""
    return "bytes" if isinstance(value, bytes) else "text"


def as_text(value: Value, what: str = "the value") -> str:
    """``value`` when it is text; a binary value where text is expected is INVALID_ARGUMENT."""
    if isinstance(value, str):
        return value
    raise ValueFormatError(f"{what} is binary ({len(value)} bytes) where text is expected")
