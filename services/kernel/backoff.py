"""Pauses between tries of something that may answer later: the first, doubled after each try, capped.

The gateway's wildcard Listens try again a service they could not reach, and a served
Resource tries again to follow the property list of a Backend child it could not reach;
both wait these pauses (:func:`wait_to_retry`), so a part that is away long costs one try
per ``longest`` seconds, and a proxy that connects again ends the pause at once.
"""

from __future__ import annotations

import asyncio
from collections.abc import Iterator

from services.kernel.backend import Backend
from services.kernel.errors import PropertyError

__all__ = ["pauses", "wait_to_retry"]

#: A ``wait_connected`` that returns within this many seconds did not wait: the backend was
#: connected already (or has no connection to wait for), so the failure was not about reach.
_AT_ONCE_S = 0.001


def pauses(first: float, longest: float) -> Iterator[float]:
    """``first``, ``2 * first``, ... up to ``longest``, then ``longest`` for ever (seconds)."""
    if not 0 < first <= longest:
        raise ValueError(f"backoff pauses need 0 < first <= longest, got {first} and {longest}")
    pause = first
    while True:
        yield pause
        pause = min(pause * 2, longest)


async def wait_to_retry(backend: Backend, pause: float) -> None:
    """Wait ``pause`` seconds before trying ``backend`` again, or less: until a proxy that was
    not connected is connected again (:meth:`Backend.wait_connected`), so that a device that is
    back is tried at once, not at the end of a pause of up to ``longest`` seconds."""
    loop = asyncio.get_running_loop()
    started = loop.time()
    try:
        await backend.wait_connected(pause)
    except PropertyError:
        return  # still not connected after the whole pause: try again now
    waited = loop.time() - started
    if waited < _AT_ONCE_S:
        # Connected all along, or a backend without connections: it refused for another reason
        # (a device that answers UNAVAILABLE itself); wait the whole pause.
        await asyncio.sleep(pause - waited)
