"""A Cortex-M board in QEMU: the C device library's LM3S6965 firmware with UART0 on a host pty.

``QemuBoard(elf, folder)`` runs ``qemu-system-arm -M lm3s6965evb`` with the firmware, its UART0 on
a new pseudo-terminal (``board.where``: give the gateway ``serial://PATH``) and QEMU's monitor on
a Unix socket in ``folder``. The monitor is the board's reset button (``reset``) and its debugger
(``sram``: the 64 KiB of SRAM as they are now). ``require_qemu()`` skips the calling test, saying
how to install QEMU, where ``qemu-system-arm`` is missing::

    with QemuBoard(into / "cortexm/thermostat.elf", tmp_path) as board:
        url = f"serial://{board.where}?baudrate=115200"
"""

from __future__ import annotations

import re
import shutil
import socket
import subprocess
import threading
from pathlib import Path
from types import TracebackType

import pytest

from support.c_device import stop_program

QEMU = "qemu-system-arm"
INSTALL_HINT = "bash tests/run.sh installs it (Debian: apt-get install qemu-system-arm)"
#: The LM3S6965's SRAM (its data sheet's memory map).
SRAM_START = 0x2000_0000
SRAM_SIZE = 64 * 1024
START_TIMEOUT = 10.0
MONITOR_TIMEOUT = 5.0
_PTY = re.compile(r"char device redirected to (/dev/\S+) \(label serial0\)")


def require_qemu() -> None:
    """Skip the calling test, saying why, unless QEMU's ARM system emulator is on PATH."""
    if shutil.which(QEMU) is None:
        pytest.skip(f"the Cortex-M firmware runs in {QEMU}, which is missing: {INSTALL_HINT}")


class QemuBoard:
    """QEMU's lm3s6965evb running one firmware image, UART0 on a pty, the monitor on a socket."""

    def __init__(self, elf: Path, folder: Path) -> None:
        self._folder = folder
        self._monitor_path = folder / "qemu-monitor.sock"
        self.args = [
            QEMU,
            "-M", "lm3s6965evb",
            "-nodefaults", "-nographic",
            "-kernel", str(elf),
            "-serial", "pty",
            "-monitor", f"unix:{self._monitor_path},server=on,wait=off",
        ]  # fmt: skip
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
            raise AssertionError(f"QEMU did not say where UART0 is:\n{self.output}")

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self._lines.append(line)
            if (found := _PTY.search(line)) and not self.where:
                self.where = found.group(1)
                self._ready.set()
        self._ready.set()

    @property
    def output(self) -> str:
        """What QEMU printed so far."""
        return "".join(self._lines)

    def monitor(self, command: str) -> str:
        """Run one command in QEMU's human monitor; what it answered."""
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
            sock.settimeout(MONITOR_TIMEOUT)
            sock.connect(str(self._monitor_path))
            self._until_prompt(sock)
            sock.sendall(command.encode() + b"\n")
            return self._until_prompt(sock)

    @staticmethod
    def _until_prompt(sock: socket.socket) -> str:
        answer = b""
        while not answer.endswith(b"(qemu) "):
            chunk = sock.recv(4096)
            if not chunk:
                break
            answer += chunk
        return answer.decode(errors="replace")

    def reset(self) -> None:
        """Press the reset button: the core starts again from the vector table and greets."""
        self.monitor("system_reset")

    def sram(self) -> bytes:
        """The SRAM's 64 KiB as they are now (the monitor's ``pmemsave``)."""
        dump = self._folder / "sram.bin"
        # Quoted: unquoted, the monitor reads "SIZE /tmp/..." as a division.
        answer = self.monitor(f'pmemsave {SRAM_START:#x} {SRAM_SIZE} "{dump}"')
        assert dump.exists(), f"pmemsave wrote nothing: {answer}"
        return dump.read_bytes()

    def stop(self) -> int:
        """SIGTERM, then SIGKILL (this PID only) if it has not ended; the exit code."""
        return stop_program(self.proc, self._reader)

    def __enter__(self) -> QemuBoard:
        return self

    def __exit__(
        self, kind: type[BaseException] | None, value: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.stop()


def untouched(sram: bytes, paint: int = 0xA5) -> int:
    """The longest run of bytes still holding the start-up code's paint: SRAM never written."""
    return max((len(run) for run in re.findall(rb"%c+" % paint, sram)), default=0)
