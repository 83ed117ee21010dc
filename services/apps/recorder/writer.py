"""One recording's writer: a thread of its own, fed through a bounded intake, never the event loop.

The follow's callback (on the event loop) hands each batch to :meth:`RecordingWriter.offer`,
which only appends it to the intake. When the intake holds :attr:`max_queued_events` events or
:attr:`max_queued_bytes` bytes already, the batch is dropped, counted (``dropped``), and the next
change written of each property that lost one carries ``gap``: a slow disk costs values, never
memory, and never the loop's time.

The thread writes the intake into the current :class:`~services.apps.recorder.layout.RecordingFile`,
closes a chunk at least every second, starts the next file at ``max_file_bytes`` or
``max_file_seconds``, reports growth to the :class:`~services.apps.recorder.budget.DiskBudget`,
and ends the recording at its own ``max_bytes`` or ``max_seconds``. A full disk (``ENOSPC``) ends
it with ``failed: disk full``; any other error of the file system with ``failed: <why>``.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import IO

from services.apps.recorder.budget import DiskBudget
from services.apps.recorder.layout import CHUNK_BYTES, CHUNK_SECONDS, RecordingFile, ServiceInfo, file_name
from services.kernel.follow import FollowedEvent

__all__ = ["Limits", "RecordingWriter"]

log = logging.getLogger(__name__)

RECORDING = "recording"
STOPPED = "stopped"
#: Distinct properties remembered as having lost a value to a full intake (beyond, the oldest
#: are forgotten: their next value is then written without ``gap``, which the ``dropped`` count says).
MAX_LOST_KEYS = 100_000


@dataclass(frozen=True, slots=True)
class Limits:
    """The bounds of one recording: per file (rotation), in all, and on its intake (0: none)."""

    max_file_bytes: int
    max_file_seconds: float
    max_bytes: int = 0
    max_seconds: float = 0.0
    max_queued_events: int = 50_000
    max_queued_bytes: int = 16 * 1024 * 1024


#: The blocking lookup of a service's type and model, made on the writer thread.
Describe = Callable[[str], ServiceInfo]


class RecordingWriter:
    """Writes one recording on its own thread; see the module docstring."""

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
        on_end: Callable[[RecordingWriter], None],
        open_file: Callable[[Path], IO[bytes]] | None = None,
    ) -> None:
        self.name = name
        self.selectors = selectors
        self.folder = folder
        self.version = version
        self.limits = limits
        self._budget = budget
        self._describe = describe
        #: Called on the writer thread once the recording ended by itself (a limit, an error).
        self._on_end = on_end
        self._open_file = open_file or _open_new
        self.started_ns = time.time_ns()
        self._started = time.monotonic()
        self._ended: float | None = None
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
        self.dropped = 0
        self._cond = threading.Condition()
        self._intake: deque[tuple[list[FollowedEvent], int]] = deque()
        self._queued_events = 0
        self._queued_bytes = 0
        self._lost: dict[tuple[str, str], None] = {}
        self._stopping = False
        self._services: dict[str, ServiceInfo] = {}
        self._thread = threading.Thread(target=self._run, name=f"recorder {name}", daemon=True)

    # -- the event loop's side -------------------------------------------------------------

    def start(self) -> None:
        self._thread.start()

    def offer(self, events: list[FollowedEvent]) -> None:
        """Hand a batch to the writer (never blocks); dropped and counted when the intake is full."""
        size = sum(len(e.value) for e in events)
        with self._cond:
            if self._stopping or self._ended is not None:
                return  # stopped, or ended by itself: its follow is being closed
            limits = self.limits
            if (
                self._queued_events + len(events) > limits.max_queued_events
                or self._queued_bytes + size > limits.max_queued_bytes
            ):
                self.dropped += len(events)
                lost = self._lost
                for e in events:
                    lost[e.service, e.path] = None
                while len(lost) > MAX_LOST_KEYS:
                    del lost[next(iter(lost))]
                return
            self._intake.append((events, time.time_ns()))
            self._queued_events += len(events)
            self._queued_bytes += size
            self._cond.notify()

    def stop(self) -> None:
        """Ask the thread to write what it holds, finish the file and end (see :meth:`join`)."""
        with self._cond:
            self._stopping = True
            self._cond.notify()

    def join(self, timeout: float | None = None) -> None:
        self._thread.join(timeout)

    @property
    def running(self) -> bool:
        """The thread has not ended yet (a stopped recording's thread may still finish its file)."""
        return self._thread.is_alive()

    @property
    def duration(self) -> float:
        end = self._ended if self._ended is not None else time.monotonic()
        return end - self._started

    def removed(self, path: Path) -> None:
        """The budget removed one of this recording's files."""
        with self._cond:
            if path.parent == self.folder and path.name in self.files:
                self.files = [f for f in self.files if f != path.name]

    # -- the thread --------------------------------------------------------------------------

    def _run(self) -> None:
        current: RecordingFile | None = None
        path: Path | None = None
        stream: IO[bytes] | None = None
        file_started = 0.0
        counted = 0
        index = 0
        try:
            while True:
                with self._cond:
                    if not self._intake and not self._stopping:
                        self._cond.wait(CHUNK_SECONDS / 2)
                    taken = self._intake
                    self._intake = deque()
                    self._queued_events = self._queued_bytes = 0
                    stopping = self._stopping
                for events, log_ns in taken:
                    for event in events:
                        if current is None or self._rotate_due(current, file_started):
                            if current is not None and stream is not None and path is not None:
                                counted = self._finish(current, stream, path, counted)
                            index += 1
                            path = self.folder / file_name(self.name, index)
                            stream = self._open_file(path)
                            self._budget.opened(path)
                            with self._cond:
                                self.files = [*self.files, path.name]
                            current = RecordingFile(
                                stream,
                                name=self.name,
                                selectors=self.selectors,
                                started_ns=self.started_ns,
                                index=index,
                                version=self.version,
                                # Rotation by size is judged at closed chunks: small ones keep a
                                # file near its max_file_bytes.
                                chunk_bytes=min(CHUNK_BYTES, max(4096, self.limits.max_file_bytes // 4)),
                            )
                            file_started = time.monotonic()
                            counted = 0
                        self._write(current, event, log_ns)
                if current is not None:
                    current.tick()
                    counted = self._count(current, counted)
                if stopping or self._limit_reached():
                    break
        except OSError as exc:
            self._fail(exc)
        except Exception as exc:
            log.exception("recording %s failed", self.name)
            self._fail(exc)
        finally:
            if current is not None and stream is not None and path is not None:
                try:
                    self._finish(current, stream, path, counted)
                except Exception as exc:
                    # The file keeps what its closed chunks hold (a reader streams them).
                    log.warning("recording %s: could not finish %s: %s", self.name, path.name, exc)
            self._ended = time.monotonic()
            if self.state == RECORDING:
                self.state = STOPPED
            if not self._stopping:
                self._on_end(self)

    def _rotate_due(self, current: RecordingFile, file_started: float) -> bool:
        limits = self.limits
        if current.messages == 0:
            return False
        if limits.max_file_bytes and current.size >= limits.max_file_bytes:
            return True
        return bool(limits.max_file_seconds) and time.monotonic() - file_started >= limits.max_file_seconds

    def _limit_reached(self) -> bool:
        limits = self.limits
        if limits.max_bytes and self.size >= limits.max_bytes:
            self.reason = f"max_size reached ({limits.max_bytes} bytes)"
            return True
        if limits.max_seconds and self.duration >= limits.max_seconds:
            self.reason = f"max_duration reached ({limits.max_seconds:g} s)"
            return True
        return False

    def _write(self, current: RecordingFile, event: FollowedEvent, log_ns: int) -> None:
        service = event.service
        info = self._services.get(service)
        if info is None:
            info = self._services[service] = self._describe(service)
        if not current.has_service(service):
            current.add_service(service, info)
        extra_gap = False
        if self._lost:
            key = (service, event.path)
            with self._cond:
                extra_gap = key in self._lost
                if extra_gap:
                    del self._lost[key]
        before = current.messages
        current.write(event, log_ns, info, extra_gap)
        self.messages += current.messages - before
        self.events += 1
        if event.gap or extra_gap:
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

    def _finish(self, current: RecordingFile, stream: IO[bytes], path: Path, counted: int) -> int:
        try:
            current.finish()
            counted = self._count(current, counted, enforce=False)
        finally:
            self._budget.closed(path)
            # What could not be written (a full disk) is lost; the recording's state said so already.
            with contextlib.suppress(OSError):
                stream.close()
        return counted

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
