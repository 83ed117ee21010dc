"""Running a coroutine's first step at once, and the rest only if it must wait.

A Get on an in-process service usually finishes without waiting. Stepping
the coroutine by hand (``coro.send(None)``) answers it with no task and no
timer; only when it yields (it waits on a future) is the rest awaited, in
the same task, through :func:`resume`. Used by the gateway's router and
Session handler and by the line-protocol device side.
"""

from __future__ import annotations

import types
from collections.abc import Coroutine, Generator
from typing import Any, TypeVar

T = TypeVar("T")


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
