"""``psctl`` as a user runs it: a real subprocess against a gateway, its exit code and output."""

from __future__ import annotations

import subprocess
import sys

PSCTL = [sys.executable, "-m", "clients.cli"]


def psctl(target: str, *args: str, timeout: float = 60.0) -> subprocess.CompletedProcess[str]:
    """Run ``psctl -t TARGET ARGS...``; never raises on a non-zero exit (tests check it)."""
    return subprocess.run(
        [*PSCTL, "-t", target, *args], capture_output=True, text=True, timeout=timeout, check=False
    )
