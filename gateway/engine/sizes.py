"""How big a message may be, and the check every answer passes before it is sent.

A gRPC client refuses a message over its receive limit with a bare "message
larger than max" and drops the call (in a Session, every other request with
it). So the gateway batches well under that limit and turns an answer that
cannot fit into RESOURCE_EXHAUSTED naming the call.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

from services.kernel.errors import ResourceExhausted
from services.kernel.values import Value, value_size
from services.kernel.values.binary import MAX_BINARY_SIZE, MAX_MESSAGE_BYTES

if TYPE_CHECKING:
    from gateway.engine.types import PropertyValue

__all__ = [
    "BATCH_BYTES",
    "MAX_ANSWER_BYTES",
    "MAX_BINARY_SIZE",
    "MAX_MESSAGE_BYTES",
    "SURELY_FITS_CHARS",
    "check_fits",
    "reply_size",
]

# MAX_MESSAGE_BYTES: the largest message a gRPC client accepts unless it asks for more (grpc's
# default); the gateway's own receive limit is the same, so one value a client could Set always
# fits. MAX_BINARY_SIZE: the default max_size of a binary property (one message's worth).
#: Batching (events in one ListenResponse, replies in one SessionResponse) stops at about this
#: many bytes, well under MAX_MESSAGE_BYTES: a batch of values that fit one by one must never
#: add up to a message the client refuses (it would drop the whole stream).
BATCH_BYTES = 1024 * 1024
#: The largest Get or Set answer sent: a client's limit less room for a Session's envelope.
MAX_ANSWER_BYTES = MAX_MESSAGE_BYTES - 1024
#: An answer carrying one value of at most this many characters fits whatever they are (UTF-8
#: takes at most 4 bytes a character; a binary value's length is its size): such an answer
#: need not be measured.
SURELY_FITS_CHARS = (MAX_ANSWER_BYTES - 16) // 4


#: Most bytes a field's tag and length take in a message (a one-byte tag, a five-byte length).
_FIELD_HEAD = 6


def reply_size(value: Value, more: Sequence[PropertyValue] = ()) -> int:
    """The most bytes an answer of ``value`` and ``more`` takes in a message of the contract.

    Counted on the engine's own types, each field with the widest head it could have, so that
    an answer that passes :func:`check_fits` fits whichever front carries it.
    """
    size = _FIELD_HEAD + value_size(value)
    for item in more:
        names = len(item.service.encode()) + len(item.path.encode())
        size += 4 * _FIELD_HEAD + names + value_size(item.value)
    return size


def check_fits(size: int, what: Callable[[], str]) -> None:
    """Raise RESOURCE_EXHAUSTED when an answer of ``size`` bytes is too big for a client to receive."""
    if size > MAX_ANSWER_BYTES:
        raise ResourceExhausted(
            f"{what()}: the answer is {size} bytes, more than one message may carry "
            f"({MAX_ANSWER_BYTES} bytes); read fewer paths per Get, or ask for a smaller value"
        )
