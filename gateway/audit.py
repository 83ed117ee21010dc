"""The audit trail: every Set, action, registration and refusal, one JSON line each on ``gateway.audit``.

A line holds ``subject``, ``via`` (how the subject was proven), ``service``,
``property``, ``operation``, ``outcome`` (``ok`` or the status code's name)
and, for a failure, ``message``. Lines are rate-limited by a token bucket
(``[audit] rate`` lines per second, bursts of ``[audit] burst``) so that a
flood of requests cannot fill the disk; what the bucket drops is counted and
reported in one ``{"suppressed": N}`` line as soon as it has room again.
"""

from __future__ import annotations

import asyncio
import json
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass

from gateway.engine.rules import Operation, Subject
from services.kernel.errors import Code, PropertyError

log = logging.getLogger("gateway.audit")

OK = "ok"


@dataclass(frozen=True, slots=True)
class AuditSection:
    """``[audit]``: how many audit lines may be written."""

    #: Lines per second on average; 0 = no audit lines at all.
    rate: float = 50.0
    #: Lines written at once before the rate applies.
    burst: int = 200


class TokenBucket:
    """``rate`` tokens a second, at most ``burst`` kept; ``take`` spends one if there is one."""

    def __init__(self, rate: float, burst: int, clock: Callable[[], float] = time.monotonic) -> None:
        self.rate = rate
        self.burst = max(burst, 1)
        self._clock = clock
        self._tokens = float(self.burst)
        self._at = clock()

    def take(self) -> bool:
        now = self._clock()
        self._tokens = min(self.burst, self._tokens + (now - self._at) * self.rate)
        self._at = now
        if self._tokens >= 1.0:
            self._tokens -= 1.0
            return True
        return False


class Audit:
    """Writes audit lines through a token bucket; see the module docstring."""

    def __init__(self, section: AuditSection, clock: Callable[[], float] = time.monotonic) -> None:
        self.enabled = section.rate > 0
        self._bucket = TokenBucket(section.rate, section.burst, clock)
        #: Lines dropped since the last one written.
        self.suppressed = 0

    def record(
        self,
        subject: Subject,
        service: str,
        path: str,
        operation: Operation,
        error: BaseException | None = None,
    ) -> None:
        """Log one request's outcome: ``error`` None = it succeeded."""
        if not self.enabled or not log.isEnabledFor(logging.INFO):
            return
        if not self._bucket.take():
            self.suppressed += 1
            return
        if self.suppressed:
            log.warning(json.dumps({"suppressed": self.suppressed}))
            self.suppressed = 0
        line: dict[str, str] = {
            "subject": subject.name,
            "via": subject.via or "none",
            "service": service,
            "property": path,
            "operation": operation.value,
        }
        if error is None:
            line["outcome"] = OK
        elif isinstance(error, PropertyError):
            line["outcome"], line["message"] = Code(error.code).name, error.message
        elif isinstance(error, asyncio.CancelledError):
            line["outcome"] = Code.CANCELLED.name  # the caller went away before the answer
        else:
            line["outcome"], line["message"] = Code.INTERNAL.name, type(error).__name__
        log.info(json.dumps(line, ensure_ascii=False))
