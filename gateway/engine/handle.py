"""The handle of a started Get or Set: done at once, or done later.

:meth:`gateway.engine.calls.Calls.start_get` and :meth:`~gateway.engine.calls.Calls.start_set` give one
:class:`CallHandle` whatever the backend: an in-process service that answered without waiting
gives one that is :attr:`~CallHandle.done` already; a proxy's reply or a call that has to wait
gives one that completes later. Whoever started it reads it one way: its value at once when it
is done, else ``await handle`` (in the awaiting task, no task of its own) or
:meth:`~CallHandle.add_done_callback` (the call then runs in a task of its own, and the callback
has the handle once it is done).

A pending handle names the :attr:`~CallHandle.backend` that serves it: a caller that started a
batch of calls tells each backend to send what it holds (:meth:`services.kernel.backend.Backend.flush`).
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Coroutine, Generator
from typing import Any

from services.kernel.backend import Answer, Backend
from services.kernel.values import Value

__all__ = ["AnsweredCall", "AwaitedCall", "CallHandle", "RepliedCall"]

#: What a handle's done-callback is called with: the handle itself.
DoneCallback = Callable[["CallHandle"], None]


class CallHandle:
    """A started call; see the module docstring. One done-callback a handle."""

    __slots__ = ()

    #: The backend serving a call that is not done yet (None: nothing to flush).
    backend: Backend | None = None

    @property
    def done(self) -> bool:
        """Whether the call has ended (with a value, an error, or cancelled)."""
        raise NotImplementedError

    def result(self) -> Value:
        """The call's value; raises its error (or CancelledError, or InvalidStateError when not done)."""
        raise NotImplementedError

    def exception(self) -> BaseException | None:
        """The call's error, None when it answered; raises CancelledError when it was cancelled."""
        raise NotImplementedError

    def cancelled(self) -> bool:
        """Whether the call was cancelled before it ended."""
        return False

    def add_done_callback(self, callback: DoneCallback) -> None:
        """Call ``callback(self)`` once the call is done (at once when it is)."""
        raise NotImplementedError

    def cancel(self) -> None:
        """Stop waiting for the call (a pending one ends cancelled; a done one stays as it is)."""

    def __await__(self) -> Generator[Any, Any, Value]:
        raise NotImplementedError


class AnsweredCall(CallHandle):
    """A call that answered at once: its value is here."""

    __slots__ = ("value",)

    done = True

    def __init__(self, value: Value) -> None:
        self.value = value

    def result(self) -> Value:
        return self.value

    def exception(self) -> BaseException | None:
        return None

    def add_done_callback(self, callback: DoneCallback) -> None:
        callback(self)

    def __await__(self) -> Generator[Any, Any, Value]:
        return self.value
        yield  # a generator that returns at once  # pragma: no cover


class RepliedCall(CallHandle):
    """A call a proxy sent: its reply comes from the proxy's reader (no task, no timer of its own).

    A successful reply is handed over in the reader itself (:meth:`replied`, the ``then`` of
    :meth:`services.kernel.backend.Backend.start_get`), a loop turn before the future's done-callbacks
    run; an error, a time-out or a cancellation comes through the future.
    """

    __slots__ = ("_answer", "_callback", "backend", "future")

    def __init__(self, backend: Backend) -> None:
        self.backend = backend
        #: The reply's future, from :meth:`services.kernel.backend.Backend.start_get`.
        self.future: asyncio.Future[Answer] | None = None
        self._answer: Answer | None = None
        self._callback: DoneCallback | None = None

    def replied(self, answer: Answer) -> None:
        """The successful reply, straight from the proxy's reader."""
        self._answer = answer
        self._fire()

    def _fire(self, _: object = None) -> None:
        callback = self._callback
        if callback is not None:
            self._callback = None
            callback(self)

    def _future(self) -> asyncio.Future[Answer]:
        if self.future is None:
            raise asyncio.InvalidStateError("the call was not sent")
        return self.future

    @property
    def done(self) -> bool:
        return self._answer is not None or self._future().done()

    def result(self) -> Value:
        answer = self._answer
        if answer is None:
            answer = self._future().result()
        return answer.value

    def exception(self) -> BaseException | None:
        return None if self._answer is not None else self._future().exception()

    def cancelled(self) -> bool:
        return self._answer is None and self._future().cancelled()

    def add_done_callback(self, callback: DoneCallback) -> None:
        if self._answer is not None:
            callback(self)
            return
        self._callback = callback
        self._future().add_done_callback(self._fire)

    def cancel(self) -> None:
        self._future().cancel()

    def __await__(self) -> Generator[Any, Any, Value]:
        answer = yield from self._future().__await__()
        return answer.value


class AwaitedCall(CallHandle):
    """A call that has to wait: a coroutine of its value, run where it is awaited, or in a task
    of its own once a done-callback is added."""

    __slots__ = ("_callback", "_coro", "_task", "backend")

    def __init__(self, coro: Coroutine[Any, Any, Value], backend: Backend | None = None) -> None:
        self._coro = coro
        self.backend = backend
        self._task: asyncio.Task[Value] | None = None
        self._callback: DoneCallback | None = None

    @property
    def done(self) -> bool:
        return self._task is not None and self._task.done()

    def _started(self) -> asyncio.Task[Value]:
        if self._task is None:
            raise asyncio.InvalidStateError("the call has not run in a task of its own")
        return self._task

    def result(self) -> Value:
        return self._started().result()

    def exception(self) -> BaseException | None:
        return self._started().exception()

    def cancelled(self) -> bool:
        return self._task is not None and self._task.cancelled()

    def add_done_callback(self, callback: DoneCallback) -> None:
        self._callback = callback
        task = self._task
        if task is None:
            task = self._task = asyncio.get_running_loop().create_task(self._coro)
        task.add_done_callback(self._fire)

    def _fire(self, _: asyncio.Task[Value]) -> None:
        callback = self._callback
        if callback is not None:
            callback(self)

    def cancel(self) -> None:
        if self._task is not None:
            self._task.cancel()
        else:
            self._coro.close()

    def __await__(self) -> Generator[Any, Any, Value]:
        if self._task is not None:
            return (yield from self._task.__await__())
        return (yield from self._coro.__await__())
