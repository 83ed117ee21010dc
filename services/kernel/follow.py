"""How an application follows the gateway's changes as a Listen does, without the gateway.

A recorder, or a keeper of recent history, wants every change a Listen of some selectors
would hear: the same wildcards, the current values first, ``gap`` when values may have been
lost, ``conflated`` when a reader fell behind. Applications never import the gateway
(``services`` is below it); the gateway hands such a service a :data:`Follow` when it builds it,
as it hands a group its :class:`~services.kernel.directory.Directory`, and a test hands it a
small in-memory one.

**Whose rights.** A follow opened while a client's call is served (the caller in
:data:`services.kernel.directory.CALLER`: a recording started by a Set) hears only what that
caller may read: an exact selector it may not read is refused (PERMISSION_DENIED) and a wildcard
skips what it may not read, as that caller's own Listen would. One opened as a service's own work
(no caller: a configuration's selectors) is not checked.
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from typing import NamedTuple

from services.kernel.backend import Subscription
from services.kernel.values import Value

__all__ = ["Follow", "FollowedEvent", "OnEvents"]


class FollowedEvent(NamedTuple):
    """One change a follow hears, as a Listen event carries it (its fields in the order of the
    engine's own event).

    A named tuple, not a dataclass: a follower of every change of a busy gateway (a recorder)
    takes thousands a second, and a tuple is made in a third of the time and handed on as it is
    (the recorder pickles them, a batch at once, for its writer process)."""

    service: str
    #: The property's dotted path.
    path: str
    #: Text, or bytes for a binary property (empty when ``removed``).
    value: Value
    #: The follow's own number for it: 1, 2, 3 … in order, without holes.
    sequence: int
    #: The value's time in nanoseconds since the epoch: when the gateway heard it.
    time_ns: int
    #: Values of the property this one replaced while the follower was behind.
    conflated: int = 0
    #: Values may have been lost before this one.
    gap: bool = False
    #: The property is gone (its service left); ``value`` is empty.
    removed: bool = False


#: Called on the event loop with the changes heard, in order; it must not block (hand them to a
#: thread of one's own) and should not raise (what it raises is logged, and the follow goes on).
OnEvents = Callable[[list[FollowedEvent]], None]

#: ``await follow(["*/location", "scout1/battery"], on_events)``: follow ``SERVICE/PATH``
#: selectors (``*`` for any service, ``*`` segments in the path, as a Listen takes them) until the
#: returned subscription is closed. Raises INVALID_ARGUMENT for a bad selector,
#: RESOURCE_EXHAUSTED beyond the gateway's Listen limits, PERMISSION_DENIED for an exact
#: selector the caller may not read (see the module docstring).
Follow = Callable[[list[str], OnEvents], Awaitable[Subscription]]
