"""Where a replay stands in its recording, as the wall clock moves it: position, speed, playing.

Pure arithmetic on a clock the caller gives (``time.monotonic`` in service, a fake one in tests):
the position is the one at the last change of speed, pause, play or seek, plus the wall time
since then times the speed, and never past the end.
"""

from __future__ import annotations

import time
from collections.abc import Callable

__all__ = ["Timeline"]


class Timeline:
    """A replay's clock: seconds from the recording's start, moved by the wall clock while playing."""

    def __init__(self, duration_s: float, clock: Callable[[], float] = time.monotonic) -> None:
        self.duration_s = max(0.0, duration_s)
        self._clock = clock
        self._speed = 1.0
        self._playing = False
        #: The position at ``_since`` (the clock's time of the last change).
        self._at = 0.0
        self._since = clock()

    @property
    def playing(self) -> bool:
        return self._playing

    @property
    def speed(self) -> float:
        return self._speed

    def position(self) -> float:
        """Seconds from the recording's start, now."""
        if not self._playing:
            return self._at
        return min(self.duration_s, self._at + (self._clock() - self._since) * self._speed)

    def _anchor(self) -> None:
        self._at = self.position()
        self._since = self._clock()

    def play(self) -> None:
        self._anchor()
        self._playing = True

    def pause(self) -> None:
        self._anchor()
        self._playing = False

    def set_speed(self, speed: float) -> None:
        """Play at ``speed`` times the recorded pace from now on (the position so far is kept)."""
        self._anchor()
        self._speed = speed

    def seek(self, position_s: float) -> None:
        """Stand at ``position_s`` (bounded to the recording), playing or paused as before."""
        self._at = min(max(0.0, position_s), self.duration_s)
        self._since = self._clock()

    def wait_until(self, position_s: float) -> float | None:
        """Wall seconds until the position reaches ``position_s`` (0: reached); None while paused."""
        now = self.position()
        if now >= position_s:
            return 0.0
        if not self._playing:
            return None
        return (position_s - now) / self._speed
