"""The ``listen`` call, written once for every client and session.

:class:`AsyncClient`, :class:`Session` and their blocking twins all offer
the same ``listen``; they differ only in how a stream is started
(:meth:`ListenCalls.start_listen`) and in what it returns.
"""

from __future__ import annotations

from typing import Any, Generic, Literal, TypeVar, Unpack, overload

from clients.aio.requests import ListenOptions, Selector, listen_request
from protos.propertyservice.v1 import property_service_pb2 as pb

__all__ = ["ListenCalls"]

#: What ``listen`` returns without markers (events only) ...
EventsT = TypeVar("EventsT")
#: ... and with ``marks=True`` (events and :class:`~clients.aio.Mark` markers).
ItemsT = TypeVar("ItemsT")


class ListenCalls(Generic[EventsT, ItemsT]):
    """The ``listen`` method of a client or session; a subclass says how a stream starts."""

    @overload
    def listen(
        self,
        service: str,
        prop: str,
        /,
        *more: Selector,
        marks: Literal[False] = ...,
        resume: bool = ...,
        **options: Unpack[ListenOptions],
    ) -> EventsT: ...

    @overload
    def listen(
        self,
        service: str,
        prop: str,
        /,
        *more: Selector,
        marks: Literal[True],
        resume: bool = ...,
        **options: Unpack[ListenOptions],
    ) -> ItemsT: ...

    def listen(
        self,
        service: str,
        prop: str,
        /,
        *more: Selector,
        marks: bool = False,
        resume: bool = False,
        **options: Unpack[ListenOptions],
    ) -> EventsT | ItemsT:
        """Stream events of ``(service, prop)`` and of the further ``(service, property)`` selectors.

        ``*`` in a selector matches one path segment (or every service).
        The current values come first (unless ``updates_only=True``), then
        changes. Options: ``params`` (request parameters), ``min_interval``
        throttles each property (seconds; values in between are conflated),
        ``sample_interval`` sends every value periodically, ``heartbeat``
        asks for keep-alives, ``max_batch`` caps the events of one response.
        With ``marks=True`` the iterator also yields :data:`SYNC` after the
        current values and :data:`HEARTBEAT` for each keep-alive. Close the
        iterator (``aclose()``, ``close()`` or leaving the loop) to end the
        stream; over a session that sends a Cancel.

        A stream the gateway ends raises, UNAVAILABLE when it shuts down. With
        ``resume=True`` (a client's listen, not a session's) the stream is opened
        again after an UNAVAILABLE, with backoff, until the iterator is closed;
        the first event after each resume has ``gap`` set (values may have been
        missed), and sequence numbers start again from 1.
        """
        request = listen_request(service, prop, more, **options)
        result: EventsT | ItemsT = self.start_listen(request, marks, resume)
        return result

    def start_listen(self, request: pb.ListenRequest, marks: bool, resume: bool = False) -> Any:
        """Start the stream for a ready-made ``request`` (what ``listen`` does after building it)."""
        raise NotImplementedError
