"""The registrations file: what was registered by Set, kept across restarts.

The file is JSON, ``{"services": {NAME: {"url": URL, "options": {...}}}}``,
replaced atomically (a temporary file, then ``os.replace``). Reading and
writing happen on a worker thread, never on the event loop: a slow disk must
not stall every other call. One write runs at a time; registrations that
arrive meanwhile are written by the next one, a burst gathered for
``SAVE_DELAY`` seconds first.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import tempfile
from collections.abc import Callable, Mapping
from pathlib import Path

__all__ = ["SAVE_DELAY", "Registration", "RegistrationsFile"]

log = logging.getLogger(__name__)

#: Seconds a burst of registrations is gathered before the file is written once.
SAVE_DELAY = 0.2

#: name → (url, options) of one registration made by Set.
Registration = tuple[str, dict[str, str]]


class RegistrationsFile:
    """Loads the registrations from ``path`` and saves ``snapshot()`` to it when asked."""

    def __init__(self, path: Path, snapshot: Callable[[], Mapping[str, Registration]]) -> None:
        self.path = path
        self._snapshot = snapshot
        self._dirty = False
        self._now = asyncio.Event()
        self._writer: asyncio.Task[None] | None = None

    async def load(self) -> list[tuple[str, str, dict[str, str]]]:
        """(name, url, options) of every saved registration; none when the file is missing or unreadable."""
        path = self.path
        try:
            text = await asyncio.to_thread(path.read_text)
        except FileNotFoundError:
            return []
        except OSError as e:
            log.error("cannot read the registrations in %s: %s", path, e)
            return []
        try:
            saved = json.loads(text)["services"]
            return [
                (str(n), str(v["url"]), {str(k): str(x) for k, x in v.get("options", {}).items()})
                for n, v in saved.items()
            ]
        except (ValueError, KeyError, TypeError, AttributeError) as e:
            log.error("ignoring %s: not a registrations file (%s)", path, e)
            return []

    def save_soon(self) -> None:
        """Write the registrations after ``SAVE_DELAY`` (a burst of changes is written once)."""
        self._dirty = True
        if self._writer is None or self._writer.done():
            self._now.clear()
            self._writer = asyncio.get_running_loop().create_task(
                self._write_soon(), name="registry: save registrations"
            )

    async def flush(self) -> None:
        """Write what is waiting now, and wait until it is written (the registry stops)."""
        writer = self._writer
        if writer is None:
            return
        self._now.set()
        await asyncio.shield(writer)

    async def _write_soon(self) -> None:
        with contextlib.suppress(TimeoutError):  # the delay is over, or ``flush`` cut it short
            await asyncio.wait_for(self._now.wait(), SAVE_DELAY)
        while self._dirty:
            self._dirty = False
            data = {
                "services": {n: {"url": u, "options": o} for n, (u, o) in sorted(self._snapshot().items())}
            }
            try:
                await asyncio.to_thread(_write_json, self.path, data)
            except OSError as e:
                log.error("cannot save the registrations to %s: %s", self.path, e)


def _write_json(path: Path, data: object) -> None:
    """Replace ``path`` with ``data`` as JSON, atomically (runs on a worker thread)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.NamedTemporaryFile("w", dir=path.parent, prefix=path.name, delete=False) as f:
        json.dump(data, f, indent=1)
    os.replace(f.name, path)
