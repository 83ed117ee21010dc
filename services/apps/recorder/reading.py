"""The recorded changes read back: the ``/_events`` channel of every recording file under a folder.

Replay and history read this channel (``propertyservice.v1.Event``), never the JSON channels
that are there for the tools. A file a killed gateway left without its summary is read as far as
its last complete chunk.
"""

from __future__ import annotations

import heapq
import logging
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Channel, Message, Statistics
from mcap.stream_reader import StreamReader

from protos.propertyservice.v1 import property_service_pb2 as pb
from services.apps.recorder.layout import EVENTS_TOPIC
from services.kernel.paths import WILDCARD, compile_pattern
from services.kernel.values import Value

__all__ = ["RecordedEvent", "events_between", "recorded_events"]

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class RecordedEvent:
    """One change as a recording holds it."""

    service: str
    path: str
    #: Text, or bytes for a binary property (empty when ``removed``).
    value: Value
    #: The event's own time (when the gateway heard the value), nanoseconds since the epoch.
    time_ns: int
    #: When the recorder wrote it down (the message's log time).
    log_time_ns: int
    #: The recording's follow's number for it.
    sequence: int
    conflated: int
    gap: bool
    removed: bool


def _event(message: Message) -> RecordedEvent:
    record = pb.Event.FromString(message.data)
    value: Value = record.data if record.HasField("data") else record.value
    return RecordedEvent(
        record.service,
        record.property,
        value,
        record.time.seconds * 1_000_000_000 + record.time.nanos,
        message.log_time,
        record.sequence,
        record.conflated,
        record.gap,
        record.removed,
    )


def _streamed(path: Path) -> Iterator[Message]:
    """The ``/_events`` messages of a file read start to end: every complete chunk of a file that
    was never finished (its writer killed), in the order written."""
    events: set[int] = set()
    with open(path, "rb") as stream:
        try:
            for record in StreamReader(stream, skip_magic=False).records:
                if isinstance(record, Channel) and record.topic == EVENTS_TOPIC:
                    events.add(record.id)
                elif isinstance(record, Message) and record.channel_id in events:
                    yield record
        except (McapError, EOFError, ValueError) as exc:
            # The end of what was written before the writer stopped.
            log.debug("%s ends early: %s", path, exc)


def _file_events(path: Path, since_ns: int | None, after_log_ns: int | None = None) -> Iterator[Message]:
    """The ``/_events`` messages of one file (logged after ``after_log_ns``, when given); a finished
    file is read through its index, which skips the chunks before that."""
    with open(path, "rb") as stream:
        try:
            reader = make_reader(stream)
            summary = reader.get_summary()
        except (McapError, EOFError, ValueError, AssertionError):
            summary = None
        if summary is not None and summary.chunk_indexes:
            statistics: Statistics | None = summary.statistics
            # A message is written after its event was heard: a file whose last message was
            # logged before ``since`` holds no event of the range.
            if since_ns is not None and statistics is not None and statistics.message_end_time < since_ns:
                return
            for _, _, message in reader.iter_messages(
                topics=[EVENTS_TOPIC], log_time_order=False, starting_after=after_log_ns
            ):
                yield message
            return
    for message in _streamed(path):
        if after_log_ns is None or message.log_time > after_log_ns:
            yield message


def recorded_events(path: Path, after_log_ns: int | None = None) -> Iterator[RecordedEvent]:
    """Every change one recording file holds (logged after ``after_log_ns``, when given), in the
    order written; a file its writer never finished is read up to its last complete chunk."""
    for message in _file_events(path, None, after_log_ns):
        yield _event(message)


def events_between(  # noqa: PLR0917 - the signature replay and history call it by (docs/recording.md)
    directory: Path, service_glob: str, path_glob: str, since_ns: int | None, until_ns: int | None, limit: int
) -> list[RecordedEvent]:
    """The first ``limit`` changes (oldest first, by their time) of the properties ``service_glob``
    (a service's name, or ``*``) and ``path_glob`` (``*`` segments, as a Listen's selector) match,
    timed from ``since_ns`` to ``until_ns`` (inclusive; None: open), in every recording file under
    ``directory``."""
    if limit <= 0:
        return []
    path_matches = compile_pattern(path_glob)

    def matching() -> Iterator[tuple[int, int, RecordedEvent]]:
        order = 0
        for file in sorted(directory.rglob("*.mcap")):
            for message in _file_events(file, since_ns):
                event = _event(message)
                if service_glob not in (WILDCARD, event.service):
                    continue
                if not path_matches(event.path):
                    continue
                if since_ns is not None and event.time_ns < since_ns:
                    continue
                if until_ns is not None and event.time_ns > until_ns:
                    continue
                order += 1
                yield event.time_ns, order, event

    # At most ``limit`` held at once, however many the range holds.
    return [event for _, _, event in heapq.nsmallest(limit, matching())]
