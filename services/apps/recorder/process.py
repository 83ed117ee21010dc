"""The recorder's writer process: :func:`main`, started by the recorder (``python -m`` runs it too).

It reads :mod:`~services.apps.recorder.frames` on its standard input and answers on its standard
output; :mod:`services.apps.recorder.writer_process` is the other end. Every recording of one
recorder is written here, one :class:`~services.apps.recorder.writer.RecordingWriter` each, under
one :class:`~services.apps.recorder.budget.DiskBudget`: the MCAP encoding, the compression, the
file I/O, rotation and the budget cost the gateway's process nothing.

**Why a process.** A recorded change costs about 15 µs of encoding (two MCAP messages, a protobuf
``Event``, a JSON message); in a thread of the gateway that time holds the GIL beside the event
loop. Here it runs on a core of its own, and the gateway only hands over batches.

**It never outlives the gateway, and finishes its files.** The end of its input (the recorder
closed the pipe, or the gateway died, even by SIGKILL) finishes every file (summary and footer)
and ends the process. It ignores SIGINT and runs in a session of its own, so that a Ctrl-C meant
for the gateway reaches it only as that end of input, after the gateway has stopped sending.
"""

from __future__ import annotations

import logging
import os
import select
import signal
import sys
import time
from collections import deque
from pathlib import Path
from typing import Any, BinaryIO

from services.apps.recorder.budget import DiskBudget
from services.apps.recorder.frames import FrameReader, frame
from services.apps.recorder.layout import CHUNK_SECONDS, ServiceInfo
from services.apps.recorder.writer import Limits, RecordingWriter

__all__ = ["WriterProcess", "main"]

log = logging.getLogger(__name__)

#: Seconds between ticks of every recording (chunks closed each second, rotation by time,
#: ``max_duration``) when no batch comes.
TICK_SECONDS = CHUNK_SECONDS / 4
#: Seconds the process waits for the recorder's answer to a ``describe`` (the recorder waits 5 s
#: for the service and always answers; past this, the recorder is taken as gone).
DESCRIBE_WAIT = 30.0
_READ_BYTES = 1 << 20


class _Forward(logging.Handler):
    """Sends each log record to the recorder, which logs it in the gateway's log."""

    def __init__(self, process: WriterProcess) -> None:
        super().__init__(logging.INFO)
        self._process = process

    def emit(self, record: logging.LogRecord) -> None:
        try:
            self._process.send(("log", record.levelno, self.format(record)))
        except Exception:
            self.handleError(record)


class WriterProcess:
    """The writer process's one loop: messages in, recordings written, answers out."""

    def __init__(self, read_fd: int, out: BinaryIO) -> None:
        self._read_fd = read_fd
        self._out = out
        self._frames = FrameReader()
        #: Messages read while waiting for a ``describe`` answer, handled after it.
        self._backlog: deque[tuple[Any, ...]] = deque()
        self._writers: dict[str, RecordingWriter] = {}
        self._budget: DiskBudget | None = None
        self._eof = False
        #: The recorder is gone (its end of the pipe closed): nothing more is sent.
        self._deaf = False

    # -- the pipe ---------------------------------------------------------------------------

    def send(self, message: tuple[Any, ...]) -> None:
        if self._deaf:
            return
        try:
            self._out.write(frame(message))
            self._out.flush()
        except OSError:  # the gateway is gone: the files are finished all the same
            self._deaf = True

    def _read(self, timeout: float) -> bool:
        """Read what the pipe holds (waiting at most ``timeout``) into the backlog; False at its end."""
        if self._eof:
            return False
        ready, _, _ = select.select([self._read_fd], [], [], timeout)
        if not ready:
            return True
        try:
            data = os.read(self._read_fd, _READ_BYTES)
        except OSError:
            data = b""
        if not data:
            self._eof = True
            return False
        self._backlog.extend(self._frames.feed(data))
        return True

    # -- the loop ---------------------------------------------------------------------------

    def run(self) -> None:
        """Until the end of input: handle each message, tick the recordings between them."""
        next_tick = time.monotonic() + TICK_SECONDS
        try:
            while True:
                while self._backlog:
                    self._handle(self._backlog.popleft())
                now = time.monotonic()
                if now >= next_tick:
                    self._tick()
                    next_tick = now + TICK_SECONDS
                if not self._read(max(0.0, next_tick - time.monotonic())) and not self._backlog:
                    break
        finally:
            for name in list(self._writers):
                self._end(name)

    def _handle(self, message: tuple[Any, ...]) -> None:
        kind = message[0]
        if kind == "events":
            _, name, groups = message
            writer = self._writers.get(name)
            taken = sum(len(events) for _, events in groups)
            size = sum(len(e[2]) for _, events in groups for e in events)
            if writer is not None:
                writer.write(groups)
                if writer.ended:
                    self._end(name)
                    return
                self.send(("progress", name, taken, size, writer.counts()))
            # A batch for a recording that has ended is not written; the recorder stopped counting it.
        elif kind == "start":
            _, name, selectors, folder, version, started_ns, limits = message
            if self._budget is None:
                raise RuntimeError("a recording started before the folder was opened")
            self._writers[name] = RecordingWriter(
                name=name,
                selectors=selectors,
                folder=Path(folder),
                version=version,
                limits=Limits(**limits),
                budget=self._budget,
                describe=self._describe,
                started_ns=started_ns,
            )
        elif kind == "stop":
            self._end(message[1])
        elif kind == "open":
            _, root, max_total_bytes, when_full = message
            self._budget = DiskBudget(Path(root), max_total_bytes, when_full, self._removed)
            self._budget.scan()
            self.send(("budget", self._budget.used))
        elif kind == "service":
            log.info("an answer about %s came unasked for", message[1])
        else:
            raise ValueError(f"unknown message {kind!r}")

    def _tick(self) -> None:
        for name, writer in list(self._writers.items()):
            writer.tick()
            if writer.ended:
                self._end(name)
        if self._budget is not None and self._writers:
            self.send(("budget", self._budget.used))

    def _end(self, name: str) -> None:
        writer = self._writers.get(name)
        if writer is None:
            return
        try:
            # Still listed while it finishes: the budget may remove one of its own older files to
            # make room for the summary, and the files its end reports must not name that one.
            writer.stop()
        finally:
            del self._writers[name]
        self.send(("ended", name, writer.state, writer.reason, writer.counts()))
        if self._budget is not None:
            self.send(("budget", self._budget.used))

    def _removed(self, path: Path) -> None:
        writer = self._writers.get(path.parent.name)
        if writer is not None:
            writer.removed(path)
        self.send(("removed", str(path)))

    def _describe(self, service: str) -> ServiceInfo:
        """Ask the recorder for the service's type and model, and wait for the answer (the other
        messages that come meanwhile are handled after it, in their order)."""
        self.send(("describe", service))
        if self._deaf:
            return ServiceInfo("", None)
        held: deque[tuple[Any, ...]] = deque()
        deadline = time.monotonic() + DESCRIBE_WAIT
        try:
            while time.monotonic() < deadline:
                while self._backlog:
                    message = self._backlog.popleft()
                    if message[0] == "service" and message[1] == service:
                        _, _, service_type, model = message
                        return ServiceInfo(service_type, model)
                    held.append(message)
                if not self._read(max(0.0, deadline - time.monotonic())):
                    break
            return ServiceInfo("", None)
        finally:
            held.extend(self._backlog)
            self._backlog = held


def main() -> None:
    """Serve the recorder on standard input and output until the end of input."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    out = os.fdopen(os.dup(sys.stdout.fileno()), "wb")
    # Whatever else prints goes to the gateway's log, never into the frames.
    os.dup2(sys.stderr.fileno(), sys.stdout.fileno())
    process = WriterProcess(sys.stdin.fileno(), out)
    handler = _Forward(process)
    handler.setFormatter(logging.Formatter("%(message)s"))
    root = logging.getLogger()
    root.addHandler(handler)
    root.setLevel(logging.INFO)
    process.run()


if __name__ == "__main__":
    main()
