"""Running a coroutine's first step at once, and the rest only if it must wait.

A Get on an in-process service usually finishes without waiting. Stepping
the coroutine by hand (``coro.send(None)``) answers it with no task and no
timer; only when it yields (it waits on a future) is the rest awaited, in
the same task or another, through :meth:`Started.rest`. The one helper for
the gateway's call layer and the line-protocol device side.
"""

from __future__ import annotations

import types
from collections.abc import Awaitable, Coroutine, Generator
from typing import Any, Generic, TypeVar

T = TypeVar("T")


class Started(Generic[T]):
    """A coroutine that was stepped once and has to wait: ``await started.rest()`` finishes it."""

    __slots__ = ("coro", "yielded")

    def __init__(self, coro: Coroutine[Any, Any, T], yielded: Any) -> None:
        self.coro = coro
        self.yielded = yielded

    def rest(self) -> Awaitable[T]:
        """The rest of the coroutine, to be awaited once, in whichever task should run it."""
        return resume(self.coro, self.yielded)

    def close(self) -> None:
        """Drop the coroutine without running the rest (its ``finally`` blocks run)."""
        self.coro.close()


def step(coro: Coroutine[Any, Any, T]) -> T | Started[T]:
    """Run ``coro`` up to its first wait: its result when it finished, else a :class:`Started`.

    What the coroutine raises in its first step is raised here. The first step
    runs in the calling task: backends that set timeouts of their own in it
    (``asyncio.timeout`` attaches to the current task) are therefore stepped
    only where :attr:`services.kernel.backend.Backend.answers_inline` says so.
    """
    try:
        yielded = coro.send(None)
    except StopIteration as done:
        return done.value  # type: ignore[no-any-return]
    return Started(coro, yielded)


@types.coroutine
def resume(coro: Coroutine[Any, Any, T], yielded: Any) -> Generator[Any, Any, T]:
    """Go on running ``coro`` (stepped once already; it yielded ``yielded``) inside the awaiting task.

    This is what ``await coro`` does after its first step: every value the
    coroutine yields (a future it waits on) goes to the task, and whatever
    the task sends or throws back goes to the coroutine.
    """
    while True:
        try:
            sent = yield yielded
        except GeneratorExit:
            coro.close()
            raise
        except BaseException as exc:
            try:
                yielded = coro.throw(exc)
            except StopIteration as done:
                return done.value  # type: ignore[no-any-return]
        else:
            try:
                yielded = coro.send(sent)
            except StopIteration as done:
                return done.value  # type: ignore[no-any-return]
