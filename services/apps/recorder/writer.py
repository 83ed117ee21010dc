"""One recording's writer, in the writer process: batches of changes into its MCAP files.

The writer process (:mod:`services.apps.recorder.process`) holds one :class:`RecordingWriter` a
recording and hands it each batch the recorder sent (:meth:`RecordingWriter.write`); between
batches it calls :meth:`RecordingWriter.tick` a few times a second. The writer writes each change
into the current :class:`~services.apps.recorder.layout.RecordingFile`, closes a chunk at least
every second, starts the next file at ``max_file_bytes`` or ``max_file_seconds``, reports growth
to the :class:`~services.apps.recorder.budget.DiskBudget`, and ends the recording at its own
``max_bytes`` or ``max_seconds``. A full disk (``ENOSPC``) ends it with ``failed: disk full``; any
other error of the file system with ``failed: <why>``.

Nothing here is thread-safe or asynchronous: the process has one thread, which owns every writer.
The bounded intake and the ``gap`` of a change after a dropped one are the recorder's side
(:mod:`services.apps.recorder.writer_process`).
"""

from __future__ import annotations

import contextlib
import errno
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

from services.apps.recorder.budget import DiskBudget
from services.apps.recorder.frames import EventFields
from services.apps.recorder.layout import CHUNK_BYTES, RecordingFile, ServiceInfo, file_name
from services.kernel.follow import FollowedEvent

__all__ = ["RECORDING", "STOPPED", "STOPPING", "Limits", "RecordingCounts", "RecordingWriter"]

log = logging.getLogger(__name__)

RECORDING = "recording"
#: Stopped, and the writer process is still writing what it was handed before the stop.
STOPPING = "stopping"
STOPPED = "stopped"


@dataclass(frozen=True, slots=True)
class Limits:
    """The bounds of one recording: per file (rotation), in all, and on its intake (0: none)."""

    max_file_bytes: int
    max_file_seconds: float
    max_bytes: int = 0
    max_seconds: float = 0.0
    max_queued_events: int = 50_000
    max_queued_bytes: int = 16 * 1024 * 1024


#: The blocking lookup of a service's type and model (the writer process asks the recorder).
Describe = Callable[[str], ServiceInfo]


class RecordingCounts:
    """What a recording shows of itself in ``recordings``: its state, and the figures of what it wrote.

    The writer process keeps them (:class:`RecordingWriter`) and reports :meth:`counts` with each
    batch and at the end; the recorder's intake (:class:`~services.apps.recorder.feed.RecordingFeed`)
    takes them in (:meth:`take_counts`)."""

    def __init__(self) -> None:
        self.state = RECORDING
        #: Why it stopped, when not by a stop: a limit reached, an error.
        self.reason = ""
        #: The files written, oldest first (names in the folder); those the budget removed leave.
        self.files: list[str] = []
        self.size = 0
        self.messages = 0
        self.events = 0
        self.gaps = 0
        self.conflated = 0

    def counts(self) -> dict[str, Any]:
        """The figures, as the writer process sends them: size, messages, events, gaps, conflated, files."""
        return {
            "size": self.size,
            "messages": self.messages,
            "events": self.events,
            "gaps": self.gaps,
            "conflated": self.conflated,
            "files": list(self.files),
        }

    def take_counts(self, counts: dict[str, Any]) -> None:
        """Take in the figures the writer process sent (:meth:`counts`)."""
        self.size = counts["size"]
        self.messages = counts["messages"]
        self.events = counts["events"]
        self.gaps = counts["gaps"]
        self.conflated = counts["conflated"]
        self.files = counts["files"]


class RecordingWriter(RecordingCounts):
    """Writes one recording's files, batch by batch; see the module docstring."""

    def __init__(
        self,
        *,
        name: str,
        selectors: list[str],
        folder: Path,
        version: str,
        limits: Limits,
        budget: DiskBudget,
        describe: Describe,
        started_ns: int | None = None,
        open_file: Callable[[Path], IO[bytes]] | None = None,
    ) -> None:
        super().__init__()
        self.name = name
        self.selectors = selectors
        self.folder = folder
        self.version = version
        self.limits = limits
        self._budget = budget
        self._describe = describe
        self._open_file = open_file or _open_new
        self.started_ns = started_ns if started_ns is not None else time.time_ns()
        self._started = time.monotonic()
        #: The recording has ended (stopped, a limit, an error): it writes nothing more.
        self.ended = False
        self._services: dict[str, ServiceInfo] = {}
        self._current: RecordingFile | None = None
        self._path: Path | None = None
        self._stream: IO[bytes] | None = None
        self._file_started = 0.0
        self._counted = 0
        self._index = 0

    # -- what the process calls -------------------------------------------------------------

    def write(self, groups: list[tuple[int, list[EventFields]]]) -> None:
        """Write the changes of a batch, each group with the time the recorder heard it; an error or
        a limit reached ends the recording (see :attr:`ended`)."""
        if self.ended:
            return
        try:
            for log_ns, events in groups:
                for fields in events:
                    self._write(FollowedEvent._make(fields), log_ns)
            self._after_batch()
        except Exception as exc:
            self._end_with(exc)

    def tick(self) -> None:
        """Between batches: close a chunk open a second, rotate by time, end at ``max_seconds``."""
        if self.ended:
            return
        try:
            self._after_batch()
        except Exception as exc:
            self._end_with(exc)

    def stop(self) -> None:
        """Finish the file (its summary and footer); the recording is ``stopped``."""
        if not self.ended:
            self._close()

    def removed(self, path: Path) -> None:
        """The budget removed one of this recording's files."""
        if path.parent == self.folder and path.name in self.files:
            self.files = [f for f in self.files if f != path.name]

    @property
    def duration(self) -> float:
        return time.monotonic() - self._started

    # -- inside -----------------------------------------------------------------------------

    def _after_batch(self) -> None:
        current = self._current
        if current is not None:
            current.tick()
            self._counted = self._count(current, self._counted)
        if self._limit_reached():
            self._close()

    def _file(self) -> RecordingFile:
        current = self._current
        if current is not None and not self._rotate_due(current):
            return current
        if current is not None:
            self._finish()
        self._index += 1
        path = self._path = self.folder / file_name(self.name, self._index)
        stream = self._stream = self._open_file(path)
        self._budget.opened(path)
        self.files = [*self.files, path.name]
        current = self._current = RecordingFile(
            stream,
            name=self.name,
            selectors=self.selectors,
            started_ns=self.started_ns,
            index=self._index,
            version=self.version,
            # Rotation by size is judged at closed chunks: small ones keep a file near its
            # max_file_bytes.
            chunk_bytes=min(CHUNK_BYTES, max(4096, self.limits.max_file_bytes // 4)),
        )
        self._file_started = time.monotonic()
        self._counted = 0
        return current

    def _rotate_due(self, current: RecordingFile) -> bool:
        limits = self.limits
        if current.messages == 0:
            return False
        if limits.max_file_bytes and current.size >= limits.max_file_bytes:
            return True
        return (
            bool(limits.max_file_seconds) and time.monotonic() - self._file_started >= limits.max_file_seconds
        )

    def _limit_reached(self) -> bool:
        limits = self.limits
        if limits.max_bytes and self.size >= limits.max_bytes:
            self.reason = f"max_size reached ({limits.max_bytes} bytes)"
            return True
        if limits.max_seconds and self.duration >= limits.max_seconds:
            self.reason = f"max_duration reached ({limits.max_seconds:g} s)"
            return True
        return False

    def _write(self, event: FollowedEvent, log_ns: int) -> None:
        current = self._file()
        service = event.service
        info = self._services.get(service)
        if info is None:
            info = self._services[service] = self._describe(service)
        if not current.has_service(service):
            current.add_service(service, info)
        before = current.messages
        current.write(event, log_ns, info)
        self.messages += current.messages - before
        self.events += 1
        if event.gap:
            self.gaps += 1
        self.conflated += event.conflated

    def _count(self, current: RecordingFile, counted: int, *, enforce: bool = True) -> int:
        """Report the file's growth since ``counted`` bytes; the budget may stop the recording
        (unless the file is being finished: its summary is the last of it)."""
        size = current.size
        if size > counted:
            self.size += size - counted
            if not self._budget.grow(size - counted) and enforce:
                raise _BudgetFull()
        return size

    def _finish(self) -> None:
        current, stream, path = self._current, self._stream, self._path
        self._current = self._stream = self._path = None
        if current is None or stream is None or path is None:
            return
        try:
            current.finish()
            self._counted = self._count(current, self._counted, enforce=False)
        finally:
            self._budget.closed(path)
            # What could not be written (a full disk) is lost; the recording's state says so.
            with contextlib.suppress(OSError):
                stream.close()

    def _close(self) -> None:
        """Finish the file and end the recording (its state stays a failure's, if it failed)."""
        self.ended = True
        path = self._path
        try:
            self._finish()
        except Exception as exc:
            # The file keeps what its closed chunks hold (a reader streams them).
            log.warning(
                "recording %s: could not finish %s: %s", self.name, path.name if path else "its file", exc
            )
        if self.state == RECORDING:
            self.state = STOPPED

    def _end_with(self, exc: Exception) -> None:
        if not isinstance(exc, OSError):
            log.exception("recording %s failed", self.name)
        self._fail(exc)
        self._close()

    def _fail(self, exc: BaseException) -> None:
        if isinstance(exc, _BudgetFull):
            self.state = "failed: disk budget full"
            self.reason = (
                f"the recordings take {self._budget.used} bytes, over max_total_bytes "
                f"({self._budget.max_total_bytes}), and when_full is {self._budget.when_full}"
            )
        elif isinstance(exc, OSError) and exc.errno == errno.ENOSPC:
            self.state = "failed: disk full"
            self.reason = f"no space left on the device of {self.folder}: {exc.strerror or exc}"
        elif isinstance(exc, OSError):
            self.state = f"failed: {exc.strerror or exc}"
            self.reason = str(exc)
        else:
            self.state = f"failed: {type(exc).__name__}"
            self.reason = str(exc)[:300]
        log.warning("recording %s %s: %s", self.name, self.state, self.reason)


class _BudgetFull(OSError):
    """The disk budget has no room (and may not make any)."""


def _open_new(path: Path) -> IO[bytes]:
    """The file for ``path``, which must not exist yet (a recording never overwrites one)."""
    return open(path, "xb")
