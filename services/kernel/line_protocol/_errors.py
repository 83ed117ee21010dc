"""The codec's one exception."""

from __future__ import annotations

from services.kernel.errors import Code, PropertyError


class LineProtocolError(PropertyError):
    """A line cannot be decoded or a frame cannot be encoded.

    ``code`` is INVALID_ARGUMENT for a malformed line, RESOURCE_EXHAUSTED for
    a line over the length limit, DATA_LOSS for a checksum mismatch and
    UNIMPLEMENTED for an unknown word. ``tag`` is the line's request tag when
    one could be read, so that the error can be sent back to (or reported
    for) the one request it concerns.
    """

    default_code = Code.INVALID_ARGUMENT

    def __init__(
        self, message: str, code: Code | None = None, tag: str | None = None, *, greeting: bool = False
    ) -> None:
        super().__init__(message, code)
        self.tag = tag
        #: The line was a greeting whose fields cannot be accepted (a refusal, not noise).
        self.greeting = greeting
