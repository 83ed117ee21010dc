"""A lease: a deadline on the monotonic clock that its holder renews, or loses by letting it lapse.

The registry has one mechanism for "yours for so long": a registered service's
liveness lease (``services.<name>.lease``, renewed by the service itself) and a
licence (``licences.<id>``, exclusive use of a service for ``Tout`` seconds,
renewed by its holder) are both a :class:`Lease`; only what happens when one
lapses differs (the service is ``down``; the licence ends).
"""

from __future__ import annotations

import math
import time

from services.kernel.errors import InvalidArgument
from services.kernel.values import format_number, parse_number

__all__ = ["MAX_LEASE", "Lease", "check_lease", "now", "parse_lease", "wall_clock"]

#: A lease longer than a day is a mistake rather than a plan.
MAX_LEASE = 86_400.0


def now() -> float:
    """The clock of leases and of time spent down (monotonic seconds)."""
    return time.monotonic()


def wall_clock() -> float:
    """Unix seconds, to the millisecond (``last_seen``, a licence's ``granted`` and ``expires``)."""
    return round(time.time(), 3)


def check_lease(seconds: float, longest: float = MAX_LEASE, what: str = "a lease") -> float:
    """``seconds`` as a lease length (0 to ``longest``), or InvalidArgument."""
    if not (math.isfinite(seconds) and 0 <= seconds <= longest):
        raise InvalidArgument(f"{what} is 0 to {format_number(longest)} seconds, got {seconds}")
    return float(seconds)


def parse_lease(text: str) -> float:
    """The ``lease`` request parameter of a registration."""
    try:
        return check_lease(parse_number(text))
    except InvalidArgument as e:
        raise InvalidArgument(f"bad parameter lease: {e.message}") from None


class Lease:
    """A deadline ``seconds`` from when it was (re)newed; no deadline at all when never given one."""

    __slots__ = ("_until", "_wall_until")

    def __init__(self, seconds: float | None = None) -> None:
        self._until: float | None = None  # now()
        self._wall_until = 0.0
        if seconds is not None:
            self.renew(seconds)

    def renew(self, seconds: float) -> None:
        """Run out ``seconds`` from now."""
        self._until = now() + seconds
        self._wall_until = wall_clock() + seconds

    def end(self) -> None:
        """No deadline any more (a service that is polled again)."""
        self._until = None
        self._wall_until = 0.0

    @property
    def held(self) -> bool:
        """A deadline is set (it may have passed)."""
        return self._until is not None

    @property
    def until(self) -> float | None:
        """The deadline on the :func:`now` clock; None without one."""
        return self._until

    @property
    def wall_until(self) -> float:
        """The deadline in unix seconds (for people and other machines); 0 without one."""
        return round(self._wall_until, 3)

    def lapsed(self, at: float | None = None) -> bool:
        """The deadline passed before ``at`` (a :func:`now` time; default: now)."""
        return self._until is not None and (now() if at is None else at) > self._until

    def left(self, at: float | None = None) -> float:
        """Seconds until the deadline (0 once passed, or without one)."""
        if self._until is None:
            return 0.0
        return max(0.0, self._until - (now() if at is None else at))
