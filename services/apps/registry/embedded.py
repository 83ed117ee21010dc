"""The embedded registry store: this gateway's registrations in memory, and in a JSON file if asked.

The default :class:`~services.apps.registry.store.RegistryStore`: one gateway, no server to run. With a
path (``[registry] persist``) the registrations are written to it through
:class:`~services.apps.registry.persistence.RegistrationsFile` (a burst written once, off the event
loop) and read back at the next start.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from services.apps.registry.persistence import Registration, RegistrationsFile
from services.apps.registry.store import EMBEDDED

__all__ = ["EmbeddedStore"]


class EmbeddedStore:
    """Registrations kept in this gateway's memory, and in ``persist`` (a JSON file) when given."""

    def __init__(self, persist: Path | None = None) -> None:
        self._records: dict[str, Registration] = {}
        self._file = RegistrationsFile(persist, lambda: self._records) if persist is not None else None

    def __repr__(self) -> str:
        where = f"persist={str(self._file.path)!r}" if self._file is not None else "in memory"
        return f"EmbeddedStore({where})"

    @property
    def shared(self) -> bool:
        """False: only this gateway sees what it holds."""
        return False

    @property
    def location(self) -> str:
        """``embedded``."""
        return EMBEDDED

    @property
    def read_only(self) -> str:
        """Always empty: memory and a local file are always there to write to."""
        return ""

    def watch_read_only(self, listener: Callable[[], None]) -> Callable[[], None]:
        """Nothing to watch: the embedded store is never read-only."""
        return _nothing

    async def start(self) -> None:
        """Nothing to connect to."""

    async def aclose(self) -> None:
        """Write the file if a write is waiting."""
        if self._file is not None:
            await self._file.flush()

    async def load(self) -> list[tuple[str, str, dict[str, str]]]:
        """The registrations in the file (none without one, or when it is missing or unreadable)."""
        if self._file is None:
            return []
        loaded = await self._file.load()
        for name, url, options in loaded:
            self._records[name] = (url, options)
        return loaded

    async def save(self, name: str, url: str, options: dict[str, str]) -> None:
        """Keep the registration; the file is written soon after (a burst at once)."""
        self._records[name] = (url, dict(options))
        if self._file is not None:
            self._file.save_soon()

    async def drop(self, name: str) -> None:
        """Forget the registration of ``name``."""
        if self._records.pop(name, None) is not None and self._file is not None:
            self._file.save_soon()


def _nothing() -> None:
    """The unwatch of a watch that never reports."""
