"""``python -m gateway.cluster`` running in the background, its output read as it comes.

The command starts etcd, gateways and devices, prints who owns what, and runs until Ctrl-C
(:meth:`ClusterCommand.stop` sends SIGINT to its PID, as a reader's Ctrl-C would)::

    command = ClusterCommand(["--base-port", "0"])
    try:
        command.wait_for("cluster ready")
        ...  # command.lines: what it printed so far
    finally:
        assert command.stop() == 0
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path

from support.gateway_process import ROOT

#: Seconds the command may take to stop everything after Ctrl-C before it is killed by its PID.
STOP_TIMEOUT = 60.0


class ClusterCommand:
    """``python -m gateway.cluster ARGS`` in ``cwd``, its stdout and stderr collected in :attr:`lines`."""

    def __init__(self, args: Sequence[str], *, cwd: Path = ROOT, env: dict[str, str] | None = None) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "gateway.cluster", *args],
            cwd=cwd,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            env={**os.environ, "PYTHONPATH": str(ROOT), "PYTHONUNBUFFERED": "1", **(env or {})},
        )
        self.lines: list[str] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.append(line.rstrip("\n"))

    def wait_for(self, text: str, within: float = 120.0, *, after: int = 0, at_start: bool = False) -> int:
        """Wait until a line from index ``after`` on holds ``text`` (``at_start``: starts with it);
        that line's index. AssertionError with everything printed when the command ends or
        ``within`` seconds pass first."""
        deadline = time.monotonic() + within
        while True:
            lines = enumerate(self.lines[after:], after)
            found = next(
                (i for i, line in lines if (line.startswith(text) if at_start else text in line)), None
            )
            if found is not None:
                return found
            if self.proc.poll() is not None or time.monotonic() > deadline:
                raise AssertionError(f"no {text!r} (exit {self.proc.poll()}):\n" + "\n".join(self.lines))
            time.sleep(0.05)

    def line(self, start: str) -> str:
        """The first line printed that starts with ``start``."""
        return next(line for line in self.lines if line.startswith(start))

    def pids(self) -> dict[str, int]:
        """What the ``processes:`` line names: etcd, each gateway and each device, with its PID."""
        items = (item.split("=") for item in self.line("processes:").split()[1:])
        return {what: int(pid) for what, pid in items}

    def stop(self) -> int:
        """Ctrl-C (SIGINT to its PID), wait, then SIGKILL if it has not ended; its exit status."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(STOP_TIMEOUT)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10)
        self._reader.join(10)
        return self.proc.returncode
