"""Changes made on disk, by anyone, reported as file names: a thin layer over ``watchfiles``.

``watchfiles.awatch`` (Rust ``notify``: inotify on Linux, FSEvents, kqueue,
ReadDirectoryChangesW) blocks in one worker thread until the OS reports a
change, so an idle directory costs no polling. Changes are gathered for
:data:`STEP_MS` after the last one (at most :data:`DEBOUNCE_MS`), then
handed over as relative names (each with whether it was deleted); the
service's own temporary files are left out.

When the watch fails or the directory itself is removed, it is opened again
after a growing pause (at most :data:`RETRY_MAX` seconds) once the directory
is back, and the service is told that anything may have changed.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Callable
from pathlib import Path

import watchfiles

from services.apps.storage.names import TEMP_PREFIX

__all__ = ["DEBOUNCE_MS", "STEP_MS", "DirectoryWatcher"]

log = logging.getLogger(__name__)

#: A burst of changes is reported once it has been quiet this long (ms): a file written in
#: several writes becomes one report, and a listener hears of a change within about this.
STEP_MS = 20
#: A burst that goes on is still reported after this long (ms).
DEBOUNCE_MS = 200
#: The watching thread looks up from the OS this often (ms), so that stopping never waits longer.
_WAKE_MS = 500
#: Seconds between attempts to watch a directory that cannot be watched, growing up to this.
RETRY_MAX = 5.0

#: ``changed(names)``: each relative name that changed → whether it was deleted (or moved away);
#: None when anything may have changed (the watch was lost and opened again).
Changed = Callable[[dict[str, bool] | None], None]


class DirectoryWatcher:
    """Reports changes below ``root`` to ``changed``, from :meth:`start` until :meth:`aclose`."""

    def __init__(self, root: Path, changed: Changed) -> None:
        self.root = root
        self._changed = changed
        self._stop = asyncio.Event()
        self._task: asyncio.Task[None] | None = None

    def start(self) -> None:
        if self._task is None:
            self._task = asyncio.get_running_loop().create_task(self._run(), name=f"watch {self.root}")

    async def _run(self) -> None:
        pause = 0.1
        while not self._stop.is_set():
            try:
                async for changes in watchfiles.awatch(
                    self.root,
                    watch_filter=None,
                    debounce=DEBOUNCE_MS,
                    step=STEP_MS,
                    rust_timeout=_WAKE_MS,
                    stop_event=self._stop,
                    recursive=True,
                    ignore_permission_denied=True,
                ):
                    pause = 0.1
                    names: dict[str, bool] = {}
                    for kind, path in changes:
                        name = self._relative(path)
                        if name is not None:
                            names[name] = names.get(name, False) or kind is watchfiles.Change.deleted
                    if names:
                        self._changed(names)
                    if not self.root.is_dir():
                        # The directory itself went: its watch hears nothing more. Watch it again
                        # once it is back (made again by someone); until then calls are UNAVAILABLE.
                        raise FileNotFoundError(f"{self.root} was removed")
                return  # stopped
            except (OSError, RuntimeError) as exc:
                # watchfiles raises FileNotFoundError for a missing directory, RuntimeError for a watch lost.
                log.warning("cannot watch %s (%s); trying again in %.1f s", self.root, exc, pause)
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._stop.wait(), pause)
            pause = min(pause * 2, RETRY_MAX)
            self._changed(None)

    def _relative(self, path: str) -> str | None:
        try:
            rel = Path(path).relative_to(self.root)
        except ValueError:
            return None
        name = rel.as_posix()
        if name == "." or any(part.startswith(TEMP_PREFIX) for part in rel.parts):
            return None
        return name

    async def aclose(self) -> None:
        """Stop watching (the worker thread returns within about half a second). Idempotent."""
        self._stop.set()
        task, self._task = self._task, None
        if task is not None:
            try:
                await asyncio.wait_for(task, 2 * _WAKE_MS / 1000 + 1)
            except TimeoutError:
                log.warning("the watch of %s did not stop in time", self.root)
            except Exception:
                log.exception("the watch of %s failed", self.root)
