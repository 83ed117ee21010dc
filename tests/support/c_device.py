"""The C device library (services/device/c/) from Python tests: build it, run its programs.

``build(target, into)`` runs ``make -C services/device/c BUILD=into target`` and returns the
output; a missing tool (a C compiler, ``make``, ``avr-gcc``, simavr's headers) skips the test with a
reason that says which and how to install it (``bash tests/run.sh`` does, as root or with sudo).
``CProgram`` runs one of the built programs — the example device on the host, or the simavr
harness — reads the line where it says where it is (``listening on HOST:PORT`` or ``serial port
PATH``), and resets (SIGUSR1) or stops it::

    with CProgram([str(into / "host/thermostat"), "--tcp", "127.0.0.1:0"]) as device:
        url = f"tcp://{device.where}"
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import threading
from collections.abc import Sequence
from pathlib import Path
from types import TracebackType

import pytest

ROOT = Path(__file__).resolve().parents[2]
C_DIR = ROOT / "services" / "device" / "c"
INSTALL_HINT = (
    "bash tests/run.sh installs it (Debian: apt-get install gcc make gcc-avr avr-libc simavr libsimavr-dev"
    " gcc-arm-none-eabi libnewlib-arm-none-eabi)"
)
#: What each make target needs on the machine: commands on PATH and files.
NEEDS: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {
    "test": (("make", "cc"), ()),
    "host": (("make", "cc"), ()),
    "avr": (("make", "avr-gcc", "avr-objcopy", "avr-size", "avr-nm"), ("/usr/lib/avr/include/avr/io.h",)),
    "sizes": (("make", "avr-gcc", "avr-size"), ("/usr/lib/avr/include/avr/io.h",)),
    "sim": (("make", "cc"), ("/usr/include/simavr/sim_avr.h", "/usr/include/simavr/parts/uart_pty.h")),
    "cortexm": (
        ("make", "arm-none-eabi-gcc", "arm-none-eabi-objcopy", "arm-none-eabi-size", "arm-none-eabi-nm"),
        ("/usr/lib/arm-none-eabi/newlib/thumb/v7-m/nofp/libc_nano.a",),
    ),
}
BUILD_TIMEOUT = 120.0
START_TIMEOUT = 10.0


def missing(target: str) -> list[str]:
    """The tools and files ``target`` needs that this machine lacks."""
    commands, files = NEEDS[target]
    return [c for c in commands if shutil.which(c) is None] + [f for f in files if not Path(f).exists()]


def require(*targets: str) -> None:
    """Skip the calling test, saying what is missing, unless every target can be built here."""
    lacking = sorted({m for t in targets for m in missing(t)})
    if lacking:
        pytest.skip(f"the C device library needs {', '.join(lacking)}: {INSTALL_HINT}")


def build(target: str, into: Path, profile: str = "") -> str:
    """``make target`` into the folder ``into``, with the profile switches ``profile`` (``-DPS_MINIMAL``);
    the build's output. A failed build fails the test."""
    require(target)
    run = subprocess.run(
        ["make", "--no-print-directory", "-C", str(C_DIR), f"BUILD={into}", f"PROFILE={profile}", target],
        capture_output=True,
        text=True,
        timeout=BUILD_TIMEOUT,
        check=False,
    )
    assert run.returncode == 0, f"make {target} failed ({run.returncode}):\n{run.stdout}\n{run.stderr}"
    return run.stdout


class CProgram:
    """A running C program that prints where it can be reached on its first line."""

    def __init__(self, args: Sequence[str]) -> None:
        self.args = list(args)
        self.proc = subprocess.Popen(
            self.args, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
        )
        self.where = ""
        self._lines: list[str] = []
        self._ready = threading.Event()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()
        if not self._ready.wait(START_TIMEOUT) or not self.where:
            self.stop()
            raise AssertionError(f"{self.args[0]} did not say where it is:\n{self.output}")

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self._lines.append(line)
            for prefix in ("listening on ", "serial port ", "connecting to "):
                if line.startswith(prefix) and not self.where:
                    self.where = line[len(prefix) :].strip()
                    self._ready.set()
        self._ready.set()

    @property
    def output(self) -> str:
        """What the program printed so far."""
        return "".join(self._lines)

    def reset(self) -> None:
        """Press the reset button: SIGUSR1 (the device greets again)."""
        os.kill(self.proc.pid, signal.SIGUSR1)

    def stop(self) -> int:
        """SIGTERM, then SIGKILL (this PID only) if it has not ended; the exit code."""
        return stop_program(self.proc, self._reader)

    def __enter__(self) -> CProgram:
        return self

    def __exit__(
        self, kind: type[BaseException] | None, value: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.stop()


def stop_program(proc: subprocess.Popen[str], reader: threading.Thread) -> int:
    """SIGTERM, then SIGKILL (this PID only) if it has not ended; the exit code, once ``reader`` has
    taken the last of its output."""
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)
    reader.join(5)
    return proc.returncode
