"""A recording read back: its files, its services' models, and its changes in time order.

A recording (docs/recording.md) is one MCAP file or a folder of them (``NAME-0001.mcap``,
``NAME-0002.mcap``, … one recording cut by size or time). Only the contract's records are read:
the metadata ``propertyservice.service`` (each recorded service's type and model) and the
``/_events`` channel (every change as a ``propertyservice.v1.Event``); the JSON and typed channels
beside them are for other tools. Everything here is synchronous file reading: the replay runs it
in a worker thread, the ROS 2 export in its own process.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from google.protobuf.message import DecodeError
from mcap.exceptions import McapError
from mcap.reader import make_reader

from services.apps.recorder.layout import EVENTS_TOPIC, RECORDING_METADATA, SERVICE_METADATA
from services.apps.recorder.reading import RecordedEvent, recorded_events
from services.kernel.errors import InvalidArgument
from services.kernel.model import ServiceModel
from services.kernel.model_codec import model_from_text

__all__ = ["EVENTS_TOPIC", "RecordedEvent", "RecordedService", "Recording"]

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class RecordedService:
    """A service as it was recorded: its name, resource type and model."""

    name: str
    type: str
    model: ServiceModel


def _files_of(path: Path) -> tuple[Path, ...]:
    if path.is_dir():
        files = tuple(sorted(p for p in path.glob("*.mcap") if p.is_file()))
        if not files:
            raise InvalidArgument(f"recording {str(path)!r}: the folder holds no .mcap file")
        return files
    if path.is_file():
        return (path,)
    raise InvalidArgument(f"recording {str(path)!r}: no such file or folder")


class Recording:
    """One recording's files, read through their indexes (the whole file only where it has none)."""

    def __init__(self, path: Path | str) -> None:
        """Opens the files' summaries and metadata; InvalidArgument when one is not a recording."""
        self.path = Path(path)
        self.files = _files_of(self.path)
        #: The recording's name (its metadata's, else the file or folder name).
        self.name = self.path.stem
        #: Every recorded service, by name, in the order first recorded.
        self.services: dict[str, RecordedService] = {}
        start: int | None = None
        end: int | None = None
        #: How many changes the recording holds.
        self.event_count = 0
        for file in self.files:
            first, last = self._read_head(file)
            if first is not None:
                start = first if start is None else min(start, first)
            if last is not None:
                end = last if end is None else max(end, last)
        #: The log time of the first and last change, ns (0 for a recording without any).
        self.start_ns = start or 0
        self.end_ns = end if end is not None else self.start_ns

    @property
    def duration_s(self) -> float:
        """Seconds from the first change to the last."""
        return (self.end_ns - self.start_ns) / 1e9

    def _read_head(self, file: Path) -> tuple[int | None, int | None]:
        """Note the services ``file`` names; return its first and last change's log time."""
        try:
            with file.open("rb") as stream:
                reader = make_reader(stream)
                for record in reader.iter_metadata():
                    self._note(file, record.name, record.metadata)
                summary = reader.get_summary()
                events = None
                if summary is not None:
                    events = [c.id for c in summary.channels.values() if c.topic == EVENTS_TOPIC]
                if summary is not None and summary.statistics is not None and events:
                    stats = summary.statistics
                    count = sum(stats.channel_message_counts.get(i, 0) for i in events)
                    self.event_count += count
                    if not count:
                        return None, None
                    return stats.message_start_time, stats.message_end_time
        except (McapError, OSError, ValueError, EOFError) as exc:
            raise InvalidArgument(f"recording {str(file)!r} cannot be read: {exc}") from None
        # No statistics (a file whose writer stopped before its summary): read its changes.
        first = last = None
        for event in self._events_of(file, None):
            first = event.log_time_ns if first is None else first
            last = event.log_time_ns
            self.event_count += 1
        return first, last

    def _note(self, file: Path, name: str, metadata: dict[str, str]) -> None:
        if name == RECORDING_METADATA and metadata.get("name"):
            self.name = metadata["name"]
        if name != SERVICE_METADATA:
            return
        service = metadata.get("service", "")
        if not service or service in self.services:
            return
        kind = metadata.get("type", "resource") or "resource"
        try:
            model = model_from_text(metadata.get("model", "()"), kind)
        except InvalidArgument as exc:
            raise InvalidArgument(f"recording {str(file)!r}: service {service!r}: {exc.message}") from None
        self.services[service] = RecordedService(service, kind, model)

    def events(self, since_ns: int | None = None) -> Iterator[RecordedEvent]:
        """Every recorded change with a log time after ``since_ns`` (all, with None), oldest first."""
        for file in self.files:
            yield from self._events_of(file, since_ns)

    def _events_of(self, file: Path, since_ns: int | None) -> Iterator[RecordedEvent]:
        try:
            yield from recorded_events(file, since_ns)
        except (DecodeError, OSError) as exc:
            log.warning("recording %s: reading stopped early: %s", file, exc)
