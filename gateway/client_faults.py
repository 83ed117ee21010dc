"""Failures a client causes: one rate-limited line each, never a traceback.

A malformed HTTP request, a call cancelled while its message was being sent: the client's doing,
nothing in the gateway to debug, and something any client can repeat as fast as it likes. Each is
one line, at most ``BURST`` at once and ``RATE`` a second after that (the audit's
:class:`~gateway.audit.TokenBucket`); what the bucket drops is counted, and the next line written
says how many were left out. A client's bad token is not here: the audit records that refusal, under
its own rate.

Libraries that log such failures with a traceback of their own (``aiohttp.server``,
``grpc._cython.cygrpc``) get a :class:`ClientFaultFilter` on their logger: configured, not patched.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

from grpc._cython import cygrpc  # type: ignore[attr-defined]

from gateway.audit import TokenBucket

__all__ = [
    "CLIENT_FAULTS",
    "ClientFaultFilter",
    "FaultLines",
    "filter_client_faults",
    "filter_grpc_client_faults",
]

#: Lines a second once a burst is spent: a flood of bad requests costs a line a second.
RATE = 1.0
#: Lines written at once before the rate applies (a few mistakes are all seen).
BURST = 20
#: Longest message kept of a client fault: an exception's text may quote what the client sent.
MAX_CHARS = 300


class FaultLines:
    """Client-fault lines through a token bucket; see the module docstring."""

    def __init__(
        self, rate: float = RATE, burst: int = BURST, clock: Callable[[], float] = time.monotonic
    ) -> None:
        self._bucket = TokenBucket(rate, burst, clock)
        #: Lines dropped since the last one written.
        self.suppressed = 0

    def admit(self) -> int | None:
        """Whether a line may be written now: None when not (it is counted), else how many were
        dropped before it (the count starts again)."""
        if not self._bucket.take():
            self.suppressed += 1
            return None
        dropped, self.suppressed = self.suppressed, 0
        return dropped


def one_line(message: str, dropped: int = 0) -> str:
    """``message`` on one line, clipped, with the count of the lines left out before it."""
    text = " ".join(message.split())
    if len(text) > MAX_CHARS:
        text = text[: MAX_CHARS - 3] + "..."
    return f"{text} ({dropped} more like it not logged)" if dropped else text


#: The gateway process's one budget of client-fault lines, shared by every front end.
CLIENT_FAULTS = FaultLines()


class ClientFaultFilter(logging.Filter):
    """On a library's logger: a record whose exception is one of ``faults`` (a client's doing)
    becomes one rate-limited line at ``level``, its message and ``meaning`` (else the exception's
    text), without the traceback; the bucket's overflow is dropped, and so is the line when
    ``level`` is not logged. Any other record passes unchanged (a bug still shows its traceback)."""

    def __init__(
        self,
        faults: tuple[type[BaseException], ...],
        level: int = logging.WARNING,
        meaning: str = "",
        lines: FaultLines = CLIENT_FAULTS,
    ) -> None:
        super().__init__()
        self.faults = faults
        self.level = level
        self.meaning = meaning
        self.lines = lines

    def filter(self, record: logging.LogRecord) -> bool:
        fault = record.exc_info[1] if record.exc_info else None
        if not isinstance(fault, self.faults):
            return True
        if not logging.getLogger(record.name).isEnabledFor(self.level):
            return False
        dropped = self.lines.admit()
        if dropped is None:
            return False
        meaning = self.meaning or f"{type(fault).__name__}: {fault}"
        record.msg = one_line(f"{record.getMessage()}: {meaning}", dropped)
        record.args = None
        record.exc_info = record.exc_text = record.stack_info = None
        record.levelno, record.levelname = self.level, logging.getLevelName(self.level)
        return True


def filter_client_faults(
    logger_name: str, faults: tuple[type[BaseException], ...], level: int = logging.WARNING, meaning: str = ""
) -> None:
    """Put a :class:`ClientFaultFilter` for ``faults`` on the logger ``logger_name``, once."""
    logger = logging.getLogger(logger_name)
    if not any(isinstance(f, ClientFaultFilter) and f.faults == faults for f in logger.filters):
        logger.addFilter(ClientFaultFilter(faults, level, meaning))


def filter_grpc_client_faults() -> None:
    """grpc.aio logs a response it could not send with a traceback ("ExecuteBatchError raised in
    core by servicer method"): the client cancelled the call or went away while a message was
    being written to it (a large value on a slow reader, typically). An ordinary end of a call,
    so one rate-limited INFO line."""
    execute_batch_error: type[BaseException] = cygrpc.ExecuteBatchError
    filter_client_faults(
        "grpc._cython.cygrpc",
        (execute_batch_error,),
        logging.INFO,
        "the client went away while a message was being sent to it",
    )
