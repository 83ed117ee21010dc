"""Bounded waiting for a state that signals nothing: ask again until it holds, or fail saying what.

Every wait here has a deadline, and running out of it fails the test with an
:class:`AssertionError` that names what was awaited and the last answer seen,
so a hung condition reads as a clear failure instead of a test timeout::

    await wait_until(lambda: dev.listeners("a") == 0, what="the subscription closes")
    value = await eventually(lambda: client.get("registry", "services.bot.state"), lambda v: v == "up")
"""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable
from typing import TypeVar

T = TypeVar("T")

#: Seconds a wait lasts unless told otherwise: long enough for a loaded two-core machine.
WAIT = 10.0


class _NoAnswer:
    def __repr__(self) -> str:
        return "no answer yet"


_NO_ANSWER = _NoAnswer()


async def wait_until(
    predicate: Callable[[], bool], *, within: float = WAIT, every: float = 0.01, what: str = ""
) -> None:
    """Check ``predicate()`` every ``every`` seconds until it is true; fail after ``within`` seconds."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + within
    while not predicate():
        if loop.time() >= deadline:
            raise AssertionError(f"{what or _name(predicate)}: not true within {within} s")
        await asyncio.sleep(every)


async def eventually(
    probe: Callable[[], Awaitable[T]],
    ok: Callable[[T], bool] = lambda _: True,
    *,
    within: float = WAIT,
    every: float = 0.05,
    retry_on: tuple[type[BaseException], ...] = (),
    what: str = "",
) -> T:
    """Await ``probe()`` until ``ok(answer)`` holds; return that answer.

    An exception of a type in ``retry_on`` counts as "not yet" (e.g. UNAVAILABLE
    while a service comes back). After ``within`` seconds the test fails with
    the last answer (or exception) in the message; a probe that hangs is cut
    off by the same deadline.
    """
    loop = asyncio.get_running_loop()
    deadline = loop.time() + within
    last: object = _NO_ANSWER
    while True:
        try:
            async with asyncio.timeout_at(deadline):
                answer = await probe()
        except TimeoutError:
            if loop.time() < deadline:
                raise  # the probe's own timeout, not this wait's deadline
            break
        except retry_on as exc:
            last = exc
        else:
            if ok(answer):
                return answer
            last = answer
        if loop.time() + every >= deadline:
            break
        await asyncio.sleep(every)
    raise AssertionError(f"{what or _name(probe)}: not as expected within {within} s; last answer: {last!r}")


def _name(f: Callable[..., object]) -> str:
    return getattr(f, "__qualname__", repr(f))
