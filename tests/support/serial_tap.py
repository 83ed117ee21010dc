"""A crossed serial cable with a recorder: the bytes between a device's pty and the gateway, line by line.

``WireTap(device_path)`` opens the device's end, makes a new pseudo-terminal for the gateway
(``tap.path``) and copies bytes both ways in a thread, recording each line with its direction:
``("gw", line)`` for what the gateway sent, ``("dev", line)`` for what the device sent. Tests
read the record to see the protocol itself: checksums, greetings, and how many request bytes
the gateway had on the wire before their replies came (``most_unanswered_bytes``)::

    with WireTap(device.where) as tap:
        url = f"serial://{tap.path}?baudrate=115200"
"""

from __future__ import annotations

import contextlib
import os
import re
import select
import threading
import tty
from types import TracebackType

_TAG = re.compile(r"^\$?#([A-Za-z0-9_-]{1,8}) ")
#: Words of the lines a device sends that answer nothing.
_UNSOLICITED = ("EVENT", "GONE", "PING")


class WireTap:
    """Copy bytes between a device's serial end and a pty the gateway opens; record every line."""

    def __init__(self, device_path: str) -> None:
        self.device_fd = os.open(device_path, os.O_RDWR | os.O_NOCTTY)
        tty.setraw(self.device_fd)
        self.master, self._slave = os.openpty()
        tty.setraw(self._slave)  # the gateway's end; kept open here so the master never reads EIO
        self.path = os.ttyname(self._slave)
        self.lines: list[tuple[str, str]] = []
        self._partial = {"gw": b"", "dev": b""}
        self._lock = threading.Lock()
        self._stop_r, self._stop_w = os.pipe()
        #: (marker, noise): once the gateway sends bytes containing ``marker``, ``noise`` follows them
        #: to the device, once (``add_noise``).
        self._noise: list[tuple[bytes, bytes]] = []
        self._thread = threading.Thread(target=self._pump, daemon=True)
        self._thread.start()

    def _pump(self) -> None:
        route = {self.device_fd: (self.master, "dev"), self.master: (self.device_fd, "gw")}
        while True:
            ready, _, _ = select.select([self.device_fd, self.master, self._stop_r], [], [])
            if self._stop_r in ready:
                return
            for fd in ready:
                try:
                    data = os.read(fd, 4096)
                except OSError:
                    continue  # the far side is not open (yet)
                target, who = route[fd]
                with contextlib.suppress(OSError):
                    os.write(target, data + (self._noise_after(data) if who == "gw" else b""))
                self._record(who, data)

    def add_noise(self, marker: bytes, noise: bytes) -> None:
        """Line noise: once the gateway sends bytes that contain ``marker``, ``noise`` reaches the
        device right after them (it is not recorded: the device sees it, the gateway never sent it)."""
        with self._lock:
            self._noise.append((marker, noise))

    def _noise_after(self, data: bytes) -> bytes:
        with self._lock:
            for i, (marker, noise) in enumerate(self._noise):
                if marker in data:
                    del self._noise[i]
                    return noise
        return b""

    def _record(self, who: str, data: bytes) -> None:
        with self._lock:
            *done, self._partial[who] = (self._partial[who] + data).split(b"\n")
            self.lines += [(who, line.decode("utf-8", "replace")) for line in done]

    def record(self) -> list[tuple[str, str]]:
        """The lines so far, in the order they passed."""
        with self._lock:
            return list(self.lines)

    def transcript(self) -> str:
        """The record as text: ``>`` what the gateway sent, ``<`` what the device sent."""
        return "\n".join(f"{'>' if who == 'gw' else '<'} {line}" for who, line in self.record())

    def most_unanswered_bytes(self) -> int:
        """The most request bytes (LF included) the gateway had sent and not yet seen answered."""
        tagged: dict[str, int] = {}
        untagged: list[tuple[str, int]] = []  # (word, bytes), oldest first
        most = 0
        for who, line in self.record():
            tag_match = _TAG.match(line)
            tag = tag_match.group(1) if tag_match else None
            word = line.lstrip("$").split(" ", 2)[1 if tag else 0] if line.strip("$ ") else ""
            if who == "gw":
                if word.upper() in ("CANCEL", "OK", "PONG", "ERR"):
                    continue  # answers nothing, or answers the device
                if tag is not None:
                    tagged[tag] = len(line) + 1
                else:
                    untagged.append((word.upper(), len(line) + 1))
                most = max(most, sum(tagged.values()) + sum(n for _, n in untagged))
            elif word.upper() not in _UNSOLICITED:
                if tag is not None:
                    tagged.pop(tag, None)
                elif word.upper() == "HELLO":  # answers a HELLO, or greets after a reset
                    hellos = [i for i, (w, _) in enumerate(untagged) if w == "HELLO"]
                    if hellos:
                        untagged.pop(hellos[0])
                elif untagged:
                    untagged.pop(0)
        return most

    def close(self) -> None:
        os.write(self._stop_w, b"x")
        self._thread.join(5)
        for fd in (self.device_fd, self.master, self._slave, self._stop_r, self._stop_w):
            os.close(fd)

    def __enter__(self) -> WireTap:
        return self

    def __exit__(
        self, kind: type[BaseException] | None, value: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()
