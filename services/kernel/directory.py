"""How a service reaches other services: the gateway's directory of backends.

System services (the registry, groups of robots) hold other services. They
never import the gateway; the gateway hands them an object that satisfies
:class:`Directory` (its router), and tests can hand them a small in-memory one.

**On whose behalf.** A call a service makes while it serves a client's request (a
group fanning a Set out to its members, a wildcard expanding into them) is made
on that client's behalf: the gateway's directory checks it against the rules as
that client, for the member's own service and path. Who that is travels in
:data:`CALLER`, which the gateway sets when it starts a client's call, and which
tasks started during the call inherit. A service's own work is done as nobody
(None), which no rule refuses: its background tasks (:func:`own_context`), its
reactions to services joining and leaving, and whatever it wraps in
:func:`own_work` (the registry's probe of a new registration, a chart's storage).
A service that acts later for someone (a state machine's chart) runs that work in
:func:`context_for` them.
"""

from __future__ import annotations

import contextlib
import contextvars
from collections.abc import Callable, Iterator, Mapping
from typing import Any, Protocol

from services.kernel.backend import Backend, BackendInfo

#: Called with (name, backend) when a service appears, (name, None) when it goes.
DirectoryListener = Callable[[str, Backend | None], None]

#: Who the calls made now are made for: the subject of the client's call being served (the
#: gateway's own type, opaque here), the name of a subject a service's configuration names (a
#: ``str``), or None: a service's own work. See the module docstring.
CALLER: contextvars.ContextVar[object | None] = contextvars.ContextVar("caller", default=None)


def context_for(caller: object | None) -> contextvars.Context:
    """A copy of the current context in which calls are made for ``caller`` (None: as nobody).

    Hand it to ``loop.create_task(coro, context=...)`` to run a task for someone, or as
    a service's own work.
    """
    context = contextvars.copy_context()
    context.run(CALLER.set, caller)
    return context


def own_context() -> contextvars.Context:
    """A new, empty context in which calls are a service's own work (for its background tasks).

    Empty, not a copy: nothing of the task that happens to start the work carries over, not the
    client it serves, not the trail of its call, not the service a gateway's log lines name for it.
    A group's refresh started by a device's reconnection is the group's work, not the device's.
    """
    context = contextvars.Context()
    context.run(CALLER.set, None)
    return context


@contextlib.contextmanager
def own_work() -> Iterator[None]:
    """Make the calls inside the ``with`` block as the service itself, not for the client being served."""
    # The old value is put back, not reset by token: a call stepped first in one context may
    # finish in another (a task's copy), where a token of the first is refused.
    before = CALLER.get()
    CALLER.set(None)
    try:
        yield
    finally:
        CALLER.set(before)


class Directory(Protocol):
    """The live set of services behind one gateway."""

    def names(self) -> list[str]:
        """Names of every service right now."""
        ...

    def __contains__(self, name: object) -> bool:
        """Whether ``name`` is served right now, down or not (a dict lookup: no list is made)."""
        ...

    def backend(self, name: str) -> Backend:
        """The backend serving ``name``; raises ``NotFound``."""
        ...

    def watch(self, listener: DirectoryListener) -> Callable[[], None]:
        """Call ``listener`` on every join and leave; returns a function that stops watching."""
        ...

    async def register(self, name: str, url: str, options: Mapping[str, Any] | None = None) -> BackendInfo:
        """Create a backend for ``url`` (``tcp://``, ``serial://``, ``grpc://``) and serve it as ``name``.

        Raises ``InvalidArgument`` for a malformed URL or name, ``AlreadyExists``
        for a taken name, ``Unavailable`` when the device cannot be reached.
        """
        ...

    async def serve(self, name: str, backend: Backend) -> None:
        """Start ``backend``, an in-process one a service made (a replay's recorded services), and
        serve it as ``name`` beside every other service, until :meth:`unregister`.

        Raises ``InvalidArgument`` for a malformed name and ``AlreadyExists`` for a taken one;
        the backend is closed when it cannot be served.
        """
        ...

    async def unregister(self, name: str) -> None:
        """Stop serving ``name`` and close its backend; raises ``NotFound``."""
        ...
