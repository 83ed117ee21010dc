"""One budget for the large values every Listen reader has been handed and not yet written.

A reader that stops reading (a client that never reads its socket, or reads slower than a camera
renders) holds what it was being written until its connection takes it: at most one value each,
since its stream's conflating queue keeps only the latest value meanwhile. Many such readers of
a large binary value (a 4 MB frame) would still add up to gigabytes, so the bytes they hold count
against one total, ``limits.max_pending_binary``: a reader whose next value would pass it is ended
with RESOURCE_EXHAUSTED naming that key (a gRPC Listen's status, an event stream's
``event: error``, a live image's end), and what it held is free again.

Only values over :data:`COUNTED_BYTES` count: a smaller one fits the socket's own buffer, and the
readers of text values (at most 64 KiB each) are never refused for it.
"""

from __future__ import annotations

from services.kernel.errors import ResourceExhausted

#: A message, value or part of at least this many bytes counts against the budget: the high-water
#: mark of an asyncio transport's write buffer, what a connection holds anyway.
COUNTED_BYTES = 64 * 1024
#: The copies of a large gRPC message (a Listen's, a Session's) counted while it is written: this
#: one, grpc's, and the one before it that grpc may still be writing to a reader that does not
#: read (measured: about three for readers that announce a large window and never read).
GRPC_COPIES = 3


class PayloadBudget:
    """Bytes of large values handed to readers and not yet taken by their connections, in all."""

    __slots__ = ("held", "limit")

    def __init__(self, limit: int) -> None:
        self.limit = limit
        #: Bytes counted right now (read by the tests and the metrics).
        self.held = 0

    def take(self, size: int) -> bool:
        """Count ``size`` bytes a reader is about to be written; False (nothing counted) when they
        would take the total past the limit: end that reader with :meth:`refusal`. A size under
        :data:`COUNTED_BYTES` always fits and is not counted."""
        if size < COUNTED_BYTES:
            return True
        if self.held + size > self.limit:
            return False
        self.held += size
        return True

    def give_back(self, size: int) -> None:
        """The reader's connection took (or dropped) what :meth:`take` counted."""
        if size >= COUNTED_BYTES:
            self.held -= size

    def refusal(self, size: int, what: str) -> ResourceExhausted:
        """The error that ends a reader whose ``size`` bytes for ``what`` did not fit."""
        return ResourceExhausted(
            f"{what}: {size} bytes would take the values waiting on slow readers past"
            f" limits.max_pending_binary ({self.limit} bytes, {self.held} held now); read faster,"
            " or try again"
        )
