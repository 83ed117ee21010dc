"""The recorder's side of its writer process: the process and its pipe, and each recording's intake.

:class:`WriterLink` starts the writer process (:mod:`services.apps.recorder.process`) at the first
recording, sends it :mod:`~services.apps.recorder.frames` on its standard input, and reads its
answers on a task of the event loop: progress, the end of a recording, a file the budget removed,
a question about a service's model (answered from the loop), log lines. When the process ends
(it was killed, it failed), every recording it was writing is ``failed: the writer process
ended``, and the next start starts a new process.

:class:`RecordingFeed` is one recording's intake, on the event loop. The follow's callback hands
it each batch (:meth:`RecordingFeed.offer`), which keeps the changes as plain tuples; every
:data:`BATCH_SECONDS`, or at :data:`BATCH_EVENTS` changes or :data:`BATCH_BYTES` of values, the
batch goes to the process as one frame (one ``pickle.dumps`` of a list of tuples, one write on
the pipe). What the intake holds — changes not sent yet and changes sent that the process has not
reported written — is bounded by ``max_queued_events`` and ``max_queued_bytes``; beyond, a batch
is dropped and counted (``dropped``), and the next change offered of each property that lost one
carries ``gap``. A disk, or a process, slower than the changes costs values, never memory.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import signal
import sys
import time
from collections.abc import Awaitable, Callable
from dataclasses import asdict
from operator import itemgetter
from pathlib import Path
from typing import Any

from services.apps.recorder.frames import HEADER_BYTES, EventFields, frame, read_header, read_payload
from services.apps.recorder.writer import STOPPING, Limits, RecordingCounts
from services.kernel.follow import FollowedEvent
from services.kernel.model import ServiceModel

__all__ = ["BATCH_BYTES", "BATCH_EVENTS", "BATCH_SECONDS", "RecordingFeed", "WriterLink"]

log = logging.getLogger(__name__)

#: Seconds a batch gathers before it goes to the writer process: 20 frames a second at most,
#: a twentieth of a second late at most (a chunk is closed each second anyway).
BATCH_SECONDS = 0.05
#: A batch goes at once when it holds this many changes ...
BATCH_EVENTS = 2000
#: ... or this many bytes of values (a camera's frames), so that a frame stays small.
BATCH_BYTES = 1024 * 1024
#: Distinct properties remembered as having lost a value to a full intake (beyond, the oldest
#: are forgotten: their next value is then written without ``gap``, which the ``dropped`` count says).
MAX_LOST_KEYS = 100_000
#: Seconds the recorder waits for the writer process to end after its input closed.
EXIT_TIMEOUT = 30.0

_VALUE = itemgetter(2)
#: The folder above ``services``: the writer process imports the package from where this one did.
_IMPORT_ROOT = str(Path(__file__).resolve().parents[3])
#: What the writer process runs: the folder is appended to its path (after its own entries, so that
#: it shadows nothing, where PYTHONPATH would come before the standard library).
_WRITER_MAIN = (
    "import sys; sys.path.append(sys.argv[1]); from services.apps.recorder.process import main; main()"
)


class RecordingFeed(RecordingCounts):
    """One recording's bounded intake and what the writer process reported of it; see the module
    docstring. On the event loop only."""

    def __init__(
        self,
        *,
        name: str,
        selectors: list[str],
        limits: Limits,
        started_ns: int,
        send: Callable[[tuple[Any, ...]], None],
        on_end: Callable[[RecordingFeed], None],
    ) -> None:
        super().__init__()
        self.name = name
        self.selectors = selectors
        self.limits = limits
        self.started_ns = started_ns
        self._send = send
        #: Called once the recording ended (a stop, a limit, an error, the process gone).
        self._on_end = on_end
        self._started = time.monotonic()
        self._ended_at: float | None = None
        self.dropped = 0
        self._pending: list[tuple[int, list[EventFields]]] = []
        self._pending_events = 0
        self._pending_bytes = 0
        self._sent_events = 0
        self._sent_bytes = 0
        self._lost: dict[tuple[str, str], None] = {}
        self._timer: asyncio.TimerHandle | None = None
        self._stopping = False
        self._ended = asyncio.Event()

    # -- the follow's side ------------------------------------------------------------------

    def offer(self, events: list[FollowedEvent]) -> None:
        """Take a batch from the follow (never blocks); dropped and counted when the intake is full."""
        if self._stopping or self._ended.is_set():
            return  # stopped, or ended by itself: its follow is being closed
        fields: list[EventFields] = list(map(tuple, events))  # type: ignore[arg-type]
        size = sum(map(len, map(_VALUE, fields)))
        limits = self.limits
        if (
            self._pending_events + self._sent_events + len(fields) > limits.max_queued_events
            or self._pending_bytes + self._sent_bytes + size > limits.max_queued_bytes
        ):
            self.dropped += len(fields)
            lost = self._lost
            for f in fields:
                lost[f[0], f[1]] = None
            while len(lost) > MAX_LOST_KEYS:
                del lost[next(iter(lost))]
            return
        if self._lost:
            self._mark_gaps(fields)
        self._pending.append((time.time_ns(), fields))
        self._pending_events += len(fields)
        self._pending_bytes += size
        if self._pending_events >= BATCH_EVENTS or self._pending_bytes >= BATCH_BYTES:
            self.flush()
        elif self._timer is None:
            self._timer = asyncio.get_running_loop().call_later(BATCH_SECONDS, self.flush)

    def _mark_gaps(self, fields: list[EventFields]) -> None:
        """The first change of each property that lost one to a full intake carries ``gap``."""
        lost = self._lost
        for i, (service, path, value, sequence, time_ns, conflated, gap, removed) in enumerate(fields):
            if (service, path) in lost:
                del lost[service, path]
                if not gap:
                    fields[i] = (service, path, value, sequence, time_ns, conflated, True, removed)

    def flush(self) -> None:
        """Send what the intake gathered to the writer process, as one frame."""
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        if not self._pending or self._ended.is_set():
            return
        pending, self._pending = self._pending, []
        self._sent_events += self._pending_events
        self._sent_bytes += self._pending_bytes
        self._pending_events = self._pending_bytes = 0
        self._send(("events", self.name, pending))

    # -- the recorder's side ----------------------------------------------------------------

    def stop(self) -> None:
        """Send what is gathered and ask the process to finish the recording (see :meth:`wait`)."""
        if self._stopping or self._ended.is_set():
            return
        self.flush()
        self._stopping = True
        self.state = STOPPING
        self._send(("stop", self.name))

    async def wait(self, within: float) -> None:
        """Until the process reports the recording ended (at most ``within`` seconds)."""
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(self._ended.wait(), within)

    @property
    def running(self) -> bool:
        """The process has not reported the end yet (a stopped recording may still be finishing)."""
        return not self._ended.is_set()

    @property
    def duration(self) -> float:
        end = self._ended_at if self._ended_at is not None else time.monotonic()
        return end - self._started

    def removed(self, path: Path) -> None:
        """The budget removed one of this recording's files."""
        if path.name in self.files:
            self.files = [f for f in self.files if f != path.name]

    # -- what the process reports -----------------------------------------------------------

    def progress(self, taken_events: int, taken_bytes: int, stats: dict[str, Any]) -> None:
        """The process wrote ``taken_events`` more changes: the intake has that much more room."""
        self._sent_events = max(0, self._sent_events - taken_events)
        self._sent_bytes = max(0, self._sent_bytes - taken_bytes)
        self.take_counts(stats)

    def ended(self, state: str, reason: str, stats: dict[str, Any]) -> None:
        """The process ended the recording (a stop, a limit, an error) and finished its file."""
        self.take_counts(stats)
        self._end(state, reason)

    def lost(self, why: str) -> None:
        """The process is gone before the recording ended."""
        self._end("failed: the writer process ended", why)

    def _end(self, state: str, reason: str) -> None:
        if self._ended.is_set():
            return
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        self._pending = []
        self._pending_events = self._pending_bytes = self._sent_events = self._sent_bytes = 0
        self.state = state
        self.reason = reason
        self._ended_at = time.monotonic()
        self._ended.set()
        self._on_end(self)


#: The recorder's answer to ``describe``: a service's type and model (None: not read).
DescribeService = Callable[[str], Awaitable[tuple[str, ServiceModel | None]]]


class WriterLink:
    """The writer process of one recorder and its pipe; see the module docstring."""

    def __init__(
        self,
        *,
        root: Path,
        max_total_bytes: int,
        when_full: str,
        describe: DescribeService,
        on_removed: Callable[[Path], None],
        on_budget: Callable[[int], None],
    ) -> None:
        self._root = root
        self._max_total_bytes = max_total_bytes
        self._when_full = when_full
        self._describe = describe
        self._on_removed = on_removed
        self._on_budget = on_budget
        self._process: asyncio.subprocess.Process | None = None
        self._reader: asyncio.Task[None] | None = None
        self._feeds: dict[str, RecordingFeed] = {}
        self._tasks: set[asyncio.Task[None]] = set()
        self._alive = False

    @property
    def alive(self) -> bool:
        """The process runs and its pipe is open: recordings may start on it."""
        return self._alive

    @property
    def pid(self) -> int | None:
        return self._process.pid if self._process is not None else None

    async def start(self) -> None:
        """Start the writer process and open the folder in it."""
        self._process = await asyncio.create_subprocess_exec(
            sys.executable,
            "-c",
            _WRITER_MAIN,
            _IMPORT_ROOT,
            stdin=asyncio.subprocess.PIPE,
            stdout=asyncio.subprocess.PIPE,
            # Its own session: a Ctrl-C for the gateway reaches it as the end of its input only.
            start_new_session=True,
        )
        self._alive = True
        self.send(("open", str(self._root), self._max_total_bytes, self._when_full))
        self._reader = asyncio.get_running_loop().create_task(self._read(), name="recorder writer process")

    def send(self, message: tuple[Any, ...]) -> None:
        """Write a message on the process's input (never waits: the feeds bound what is in flight)."""
        process = self._process
        if not self._alive or process is None or process.stdin is None or process.stdin.is_closing():
            return  # the process is ending: the reader fails its recordings
        process.stdin.write(frame(message))

    def open_recording(
        self,
        *,
        name: str,
        selectors: list[str],
        folder: Path,
        version: str,
        limits: Limits,
        on_end: Callable[[RecordingFeed], None],
    ) -> RecordingFeed:
        """Start a recording in the process; its feed takes the follow's batches."""
        started_ns = time.time_ns()
        feed = RecordingFeed(
            name=name,
            selectors=selectors,
            limits=limits,
            started_ns=started_ns,
            send=self.send,
            on_end=on_end,
        )
        self._feeds[name] = feed
        self.send(("start", name, selectors, str(folder), version, started_ns, asdict(limits)))
        return feed

    async def close(self) -> None:
        """Close the process's input (it finishes its files and ends) and wait for it to end."""
        process = self._process
        if process is None:
            return
        self._alive = False
        if process.stdin is not None:
            process.stdin.close()
        try:
            await asyncio.wait_for(process.wait(), EXIT_TIMEOUT)
        except TimeoutError:
            log.warning("the recorder's writer process (pid %d) did not end: killed", process.pid)
            with contextlib.suppress(ProcessLookupError):
                process.kill()
            await process.wait()
        if self._reader is not None:
            await asyncio.gather(self._reader, return_exceptions=True)
        for task in self._tasks:
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)

    # -- the process's answers --------------------------------------------------------------

    async def _read(self) -> None:
        process = self._process
        assert process is not None and process.stdout is not None
        stdout = process.stdout
        why = ""
        try:
            while True:
                length = read_header(await stdout.readexactly(HEADER_BYTES))
                self._handle(read_payload(await stdout.readexactly(length)))
        except asyncio.IncompleteReadError:
            pass  # its output ended: it is ending
        except Exception as exc:  # a frame this side cannot read: not the process this code starts
            why = f"it sent what it should not ({type(exc).__name__}: {exc})"
            with contextlib.suppress(ProcessLookupError):
                process.kill()
        unexpected, self._alive = self._alive, False
        code = await process.wait()
        if not why:
            why = (
                f"it was killed by {signal.Signals(-code).name}"
                if code < 0 and -code in signal.Signals._value2member_map_
                else f"it exited with status {code}"
            )
        if unexpected:
            log.warning("the recorder's writer process (pid %d) ended: %s", process.pid, why)
        for feed in list(self._feeds.values()):
            feed.lost(f"the recorder's writer process (pid {process.pid}) ended: {why}")
        self._feeds.clear()

    def _handle(self, message: tuple[Any, ...]) -> None:
        kind = message[0]
        if kind == "progress":
            _, name, taken_events, taken_bytes, stats = message
            feed = self._feeds.get(name)
            if feed is not None:
                feed.progress(taken_events, taken_bytes, stats)
        elif kind == "ended":
            _, name, state, reason, stats = message
            feed = self._feeds.pop(name, None)
            if feed is not None:
                feed.ended(state, reason, stats)
        elif kind == "describe":
            task = asyncio.get_running_loop().create_task(self._answer(message[1]))
            self._tasks.add(task)
            task.add_done_callback(self._tasks.discard)
        elif kind == "removed":
            self._on_removed(Path(message[1]))
        elif kind == "budget":
            self._on_budget(message[1])
        elif kind == "log":
            _, level, text = message
            log.log(level, "%s", text)
        else:
            raise ValueError(f"unknown message {kind!r}")

    async def _answer(self, service: str) -> None:
        service_type, model = await self._describe(service)
        self.send(("service", service, service_type, model))
