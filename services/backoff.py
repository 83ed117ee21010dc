"""Pauses between tries of something that may answer later: the first, doubled after each try, capped.

The gateway's wildcard Listens try again a service they could not reach, and a served
Resource tries again to follow the property list of a Backend child it could not reach;
both wait these pauses, so a part that is away long costs one try per ``longest`` seconds.
"""

from __future__ import annotations

from collections.abc import Iterator

__all__ = ["pauses"]


def pauses(first: float, longest: float) -> Iterator[float]:
    """``first``, ``2 * first``, ... up to ``longest``, then ``longest`` for ever (seconds)."""
    if not 0 < first <= longest:
        raise ValueError(f"backoff pauses need 0 < first <= longest, got {first} and {longest}")
    pause = first
    while True:
        yield pause
        pause = min(pause * 2, longest)
