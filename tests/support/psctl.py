"""``psctl`` as a user runs it: a real subprocess against a gateway, its exit code and output."""

from __future__ import annotations

import signal
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager

PSCTL = [sys.executable, "-m", "clients.cli"]


def psctl(target: str, *args: str, timeout: float = 60.0) -> subprocess.CompletedProcess[str]:
    """Run ``psctl -t TARGET ARGS...``; never raises on a non-zero exit (tests check it)."""
    return subprocess.run(
        [*PSCTL, "-t", target, *args], capture_output=True, text=True, timeout=timeout, check=False
    )


@contextmanager
def ctrl_c_reaches_children() -> Iterator[None]:
    """Start children inside this block with SIGINT as a terminal leaves it (the default action).

    A suite started as a background job of a shell without job control runs with SIGINT ignored,
    and a child inherits that: Python then never turns Ctrl-C into KeyboardInterrupt, so a test of
    what Ctrl-C does would wait in vain. A handler of this process's own is reset to the default
    in a child, so one is set while the block runs.
    """
    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, before)
