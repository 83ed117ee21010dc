"""The recorder's disk budget: every recording's files together stay under ``max_total_bytes``.

Each recording's writer (in the writer process) reports what its file grew by
(:meth:`DiskBudget.grow`). Past the budget, ``when_full = "drop_oldest"`` removes the oldest
finished files (by modification time, of any recording; never a file being written) until the
total fits again; ``"refuse"`` (or nothing left to remove) answers False, and the recording that
grew stops with ``failed: disk budget full``.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from pathlib import Path

__all__ = ["WHEN_FULL", "DiskBudget"]

log = logging.getLogger(__name__)

#: What a full budget does: remove the oldest files, or stop the recording that needs room.
WHEN_FULL = ("drop_oldest", "refuse")
_SUFFIX = ".mcap"


class DiskBudget:
    """The bytes every recording under one folder takes, bounded; see the module docstring.

    Shared by the recordings' writers: every method takes the lock (they run on one thread in the
    writer process today; the lock costs nothing there and keeps the budget safe for any caller).
    """

    def __init__(
        self, root: Path, max_total_bytes: int, when_full: str, on_removed: Callable[[Path], None]
    ) -> None:
        self.root = root
        self.max_total_bytes = max_total_bytes
        self.when_full = when_full
        #: Called (in the writer process) with each file removed to make room.
        self._on_removed = on_removed
        self._lock = threading.Lock()
        self._open: set[Path] = set()
        #: Bytes of every recording file under the root, as last counted or reported.
        self.used = 0

    def scan(self) -> None:
        """Count the files there already (blocking: call it off the event loop)."""
        total = 0
        for path in self._files():
            try:
                total += path.stat().st_size
            except OSError:
                continue
        with self._lock:
            self.used = total

    def _files(self) -> list[Path]:
        if not self.root.is_dir():
            return []
        return [p for p in self.root.glob(f"*/*{_SUFFIX}") if p.is_file()]

    def full(self) -> bool:
        """True when nothing more fits and nothing may be removed (``refuse``): a new recording is refused."""
        with self._lock:
            return self.when_full == "refuse" and self.used >= self.max_total_bytes

    def opened(self, path: Path) -> None:
        with self._lock:
            self._open.add(path)

    def closed(self, path: Path) -> None:
        with self._lock:
            self._open.discard(path)

    def grow(self, delta: int) -> bool:
        """Count ``delta`` more bytes; past the budget make room, or answer False when it cannot."""
        with self._lock:
            self.used += delta
            while self.used > self.max_total_bytes:
                if self.when_full != "drop_oldest" or not self._remove_oldest():
                    return False
            return True

    def _remove_oldest(self) -> bool:
        candidates = []
        for path in self._files():
            if path in self._open:
                continue
            try:
                stat = path.stat()
            except OSError:
                continue
            candidates.append((stat.st_mtime_ns, str(path), path, stat.st_size))
        if not candidates:
            return False
        _, _, oldest, size = min(candidates)
        try:
            oldest.unlink()
        except FileNotFoundError:
            pass
        except OSError as exc:
            log.warning("cannot remove %s to make room for recordings: %s", oldest, exc.strerror or exc)
            return False
        self.used -= size
        log.info("removed %s (%d bytes): recordings over max_total_bytes", oldest, size)
        self._on_removed(oldest)
        return True
