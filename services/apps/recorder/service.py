"""The recorder service: record what a Listen of some selectors hears into MCAP files (docs/recording.md).

========================  ====================================================================
property                  meaning
========================  ====================================================================
``start``                 action: record the selectors of its value (``*/location scout1/*``);
                          parameters ``name``, ``max_size`` (bytes), ``max_duration`` (s);
                          answers the recording's name
``stop``                  action: stop the recording its value names (``*``: every one)
``recordings``            JSON: each recording's name, selectors, start, duration, size,
                          message count, files, state (``recording``, ``stopped``,
                          ``failed: why``), gaps, conflated and dropped counts; Listen to follow
``folder``                where the recordings are (``NAME/NAME-0001.mcap`` …)
========================  ====================================================================

**Whose rights.** A recording hears what a Listen of its selectors by the caller who started it
would hear, for as long as it runs: the gateway's follow
(:data:`services.kernel.follow.Follow`) is opened inside the ``start`` call, for its caller, so an
exact selector that caller may not read refuses the start (PERMISSION_DENIED) and a wildcard
leaves out what it may not read. No one can record what they may not read.

The files are written in a process of the recorder's own (:mod:`services.apps.recorder.process`,
started at the first recording), fed in batches by :mod:`services.apps.recorder.feed`, laid out
as :mod:`services.apps.recorder.layout` says, and bounded together by the disk budget
(:mod:`services.apps.recorder.budget`): the gateway's process only hands the changes over.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import re
from datetime import UTC, datetime
from pathlib import Path
from typing import Annotated

from services.apps.recorder.budget import WHEN_FULL, DiskBudget
from services.apps.recorder.feed import RecordingFeed, WriterLink
from services.apps.recorder.writer import RECORDING, Limits
from services.kernel.backend import Subscription, close_quietly
from services.kernel.core import LocalService, Prop, Resource, action
from services.kernel.directory import Directory, own_work
from services.kernel.errors import (
    AlreadyExists,
    FailedPrecondition,
    InvalidArgument,
    NotFound,
    ResourceExhausted,
)
from services.kernel.follow import Follow
from services.kernel.model import ServiceModel
from services.kernel.release import package_version

__all__ = ["Recorder", "RecorderService"]

log = logging.getLogger(__name__)

#: A recording's name: a file name's safe letters, so that it is its folder's and files' name too.
_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]{0,63}")
#: Selectors one recording takes (a Listen's own limit, ``limits.max_selectors``, applies too).
MAX_SELECTORS = 64
#: Recordings listed in ``recordings`` (the oldest stopped ones leave the list first; their files stay).
MAX_LISTED = 200
#: Seconds between refreshes of ``recordings`` while a recording runs (its size and duration grow).
REFRESH_SECONDS = 1.0
#: Seconds the recorder waits for a recorded service's model (read once per service a recording).
DESCRIBE_TIMEOUT = 5.0
#: Seconds the recorder's close waits for the writer to finish each file.
STOP_TIMEOUT = 30.0
#: Seconds a ``stop`` waits for the writer process to finish the file before it answers: within
#: the gateway's call timeout (5 s by default). A process behind by many changes (a loaded
#: machine) finishes later; the recording is ``stopping`` until then.
STOP_ANSWER_SECONDS = 3.0
ALL = "*"


def _iso(time_ns: int) -> str:
    return (
        datetime.fromtimestamp(time_ns / 1e9, UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")
    )


def parse_selectors(text: str) -> list[str]:
    """``*/location scout1/*`` (or the list form ``(*/location scout1/*)``) as selector texts."""
    stripped = text.strip()
    if stripped.startswith("(") and stripped.endswith(")"):
        stripped = stripped[1:-1]
    selectors = list(dict.fromkeys(stripped.split()))
    if not selectors:
        raise InvalidArgument("give what to record: selectors SERVICE/PATH, like */location scout1/*")
    if len(selectors) > MAX_SELECTORS:
        raise InvalidArgument(f"at most {MAX_SELECTORS} selectors a recording, got {len(selectors)}")
    for selector in selectors:
        service, slash, path = selector.partition("/")
        if not slash or not service or not path:
            raise InvalidArgument(
                f"selector {selector[:200]!r} must be SERVICE/PATH, like scout1/location or */location"
            )
    return selectors


class _Recording:
    """A recording this service knows: one it writes (its feed, its follow), or one found on disk."""

    __slots__ = ("files", "name", "selectors", "size", "started_ns", "subscription", "writer")

    def __init__(self, name: str, writer: RecordingFeed | None = None) -> None:
        self.name = name
        self.writer = writer
        self.subscription: Subscription | None = None
        self.selectors: list[str] = writer.selectors if writer is not None else []
        self.started_ns = writer.started_ns if writer is not None else 0
        self.files: list[str] = []
        self.size = 0

    @property
    def active(self) -> bool:
        return self.writer is not None and self.writer.state == RECORDING and self.subscription is not None

    def as_json(self) -> dict[str, object]:
        writer = self.writer
        if writer is None:
            return {
                "name": self.name,
                "selectors": self.selectors,
                "start": _iso(self.started_ns) if self.started_ns else "",
                "duration": 0.0,
                "size": self.size,
                "messages": 0,
                "events": 0,
                "files": [f"{self.name}/{f}" for f in self.files],
                "state": "stopped",
                "reason": "",
                "gaps": 0,
                "conflated": 0,
                "dropped": 0,
            }
        return {
            "name": self.name,
            "selectors": self.selectors,
            "start": _iso(writer.started_ns),
            "duration": round(writer.duration, 3),
            "size": writer.size,
            "messages": writer.messages,
            "events": writer.events,
            "files": [f"{self.name}/{f}" for f in writer.files],
            "state": writer.state,
            "reason": writer.reason,
            "gaps": writer.gaps,
            "conflated": writer.conflated,
            "dropped": writer.dropped,
        }


class RecorderService(LocalService):
    """Serves a :class:`Recorder`: its folder is opened when the service starts and every recording
    is finished when it closes (the ``start`` and ``stop`` names are the recorder's actions, so
    these are the backend's own start and close)."""

    def __init__(self, obj: Resource, url: str = "local") -> None:
        if not isinstance(obj, Recorder):
            raise TypeError(f"RecorderService serves a Recorder, not a {type(obj).__name__}")
        super().__init__(obj, url)
        self.recorder = obj

    async def start(self) -> None:
        await self.recorder.open()
        await super().start()

    async def aclose(self) -> None:
        try:
            await self.recorder.close()
        finally:
            await super().aclose()


class Recorder(Resource):
    """Records what Listens of selectors hear into MCAP files; see the module docstring."""

    resource_type = "recorder"
    served_by = RecorderService

    recordings: Annotated[
        str,
        Prop(
            readonly=True,
            gui="code",
            doc="the recordings as JSON: name, selectors, start, duration (s), size (B), messages, events, "
            "files, state (recording, stopped, failed: why), reason, gaps, conflated, dropped",
        ),
    ]
    folder: Annotated[str, Prop(readonly=True, doc="the folder of the recordings: NAME/NAME-0001.mcap …")]
    max_total_bytes: Annotated[
        int, Prop(readonly=True, unit="B", doc="what every recording together may take")
    ]
    when_full: Annotated[str, Prop(readonly=True, doc="drop_oldest (files) or refuse (stop the recording)")]

    def __init__(
        self,
        *,
        directory: Directory,
        follow: Follow | None = None,
        folder: str = "",
        storage: str = "",
        max_file_bytes: int = 64 * 1024 * 1024,
        max_file_seconds: float = 600.0,
        max_total_bytes: int = 1024 * 1024 * 1024,
        when_full: str = "drop_oldest",
        max_recordings: int = 8,
        max_queued_events: int = 50_000,
    ) -> None:
        """``folder``: where the recordings go; or ``storage``: the storage service in whose folder
        they go (``recordings/``), so that its ``blob`` fetches them. ``max_file_bytes`` and
        ``max_file_seconds``: when a file ends and the next begins; ``max_total_bytes``: every
        recording together; ``when_full``: what then (``drop_oldest`` files, or ``refuse``);
        ``max_recordings``: recordings running at once; ``max_queued_events``: a recording's
        intake (beyond, values are dropped and marked as a gap)."""
        if bool(folder) == bool(storage):
            raise InvalidArgument(
                "give the recordings a place: folder = PATH, or storage = NAME (a storage service's folder)"
            )
        for value, what in ((max_file_bytes, "max_file_bytes"), (max_total_bytes, "max_total_bytes")):
            if not isinstance(value, int) or isinstance(value, bool) or value < 64 * 1024:
                raise InvalidArgument(
                    f"{what} must be a whole number of bytes, at least 65536, got {value!r}"
                )
        if not isinstance(max_file_seconds, int | float) or max_file_seconds <= 0:
            raise InvalidArgument(
                f"max_file_seconds must be a number of seconds above 0, got {max_file_seconds!r}"
            )
        if when_full not in WHEN_FULL:
            raise InvalidArgument(f"when_full must be one of {', '.join(WHEN_FULL)}, got {when_full!r}")
        for value, what in ((max_recordings, "max_recordings"), (max_queued_events, "max_queued_events")):
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise InvalidArgument(f"{what} must be a whole number above 0, got {value!r}")
        self._directory = directory
        self._follow = follow
        self._storage = storage
        self._root = Path(folder).expanduser().absolute() if folder else Path()
        self._max_file_bytes = max_file_bytes
        self._max_file_seconds = float(max_file_seconds)
        self._max_recordings = max_recordings
        self._max_queued_events = max_queued_events
        self._recordings: dict[str, _Recording] = {}
        self._budget: DiskBudget | None = None
        self._link: WriterLink | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._ticker: asyncio.Task[None] | None = None
        self._version = package_version()
        self.recordings = "[]"
        self.folder = str(self._root) if folder else ""
        self.max_total_bytes = max_total_bytes
        self.when_full = when_full

    # -- the service's life -----------------------------------------------------------------

    async def open(self) -> None:
        """Find the folder (the storage service's, when one is named), count what is there."""
        if self._follow is None:
            raise FailedPrecondition(
                "a recorder follows the gateway's changes: it runs only inside a gateway"
            )
        self._loop = asyncio.get_running_loop()
        if self._storage:
            self._root = await self._storage_folder(self._storage) / "recordings"
            self.folder = str(self._root)
        try:
            await asyncio.to_thread(self._root.mkdir, parents=True, exist_ok=True)
        except OSError as exc:
            raise FailedPrecondition(
                f"cannot create the folder {str(self._root)!r}: {exc.strerror or exc}"
            ) from None
        # The writer process keeps the budget (it removes files, it stops recordings); this count,
        # from the files found here and then from what the process reports, refuses a start when
        # the budget is full and when_full is refuse.
        self._budget = DiskBudget(self._root, self.max_total_bytes, self.when_full, self._file_removed)
        await asyncio.to_thread(self._budget.scan)
        try:
            found = await asyncio.to_thread(_found_on_disk, self._root)
        except OSError as exc:
            log.warning("the recordings in %s could not be listed: %s", self._root, exc.strerror or exc)
            found = []
        for recording in found:
            self._recordings[recording.name] = recording
        self._refresh()
        self._ticker = self._loop.create_task(self._tick(), name="recorder refresh")

    async def _storage_folder(self, storage: str) -> Path:
        with own_work():
            try:
                backend = self._directory.backend(storage)
            except NotFound:
                raise FailedPrecondition(
                    f"storage = {storage!r}: there is no such service (the recorder starts after it)"
                ) from None
            folder = await backend.get("directory")
        if not isinstance(folder, str) or not folder:
            raise FailedPrecondition(f"storage = {storage!r} is not a storage service (it has no directory)")
        return Path(folder)

    async def close(self) -> None:
        """Stop every recording (each file is finished: its summary and footer written)."""
        if self._ticker is not None:
            self._ticker.cancel()
            self._ticker = None
        await asyncio.gather(
            *(self._end(r, STOP_TIMEOUT) for r in list(self._recordings.values()) if r.writer is not None),
            return_exceptions=True,
        )
        link, self._link = self._link, None
        if link is not None:
            await link.close()

    async def _tick(self) -> None:
        while True:
            await asyncio.sleep(REFRESH_SECONDS)
            if any(r.active for r in self._recordings.values()):
                self._refresh()

    def _refresh(self) -> None:
        listed = list(self._recordings.values())[-MAX_LISTED:]
        text = json.dumps([r.as_json() for r in listed], separators=(",", ":"))
        if text != self.recordings:
            self.recordings = text

    # -- the actions ------------------------------------------------------------------------

    # An action named like the lifecycle hook is the action, not the hook (the kernel tells them
    # apart): the folder is opened and closed by RecorderService instead.
    @action(
        doc="record what a Listen of the selectors hears (*/location scout1/*); parameters name, "
        "max_size (B), max_duration (s); answers the recording's name"
    )
    async def start(  # type: ignore[override]
        self, selectors: str, *, name: str = "", max_size: int = 0, max_duration: float = 0.0
    ) -> str:
        """Start a recording for the caller (see the module docstring); answers its name."""
        follow, budget = self._follow, self._budget
        if follow is None or budget is None:
            raise FailedPrecondition("the recorder is not running")
        wanted = parse_selectors(selectors)
        if max_size < 0 or max_duration < 0:
            raise InvalidArgument("max_size and max_duration are 0 (no limit) or more")
        if sum(1 for r in self._recordings.values() if r.active) >= self._max_recordings:
            raise ResourceExhausted(
                f"{self._max_recordings} recordings are running already (max_recordings); stop one first"
            )
        if budget.full():
            raise ResourceExhausted(
                f"the recordings take {budget.used} bytes of max_total_bytes ({budget.max_total_bytes}) "
                "and when_full is refuse: remove some first"
            )
        name = self._new_name(name)
        folder = self._root / name
        try:
            await asyncio.to_thread(folder.mkdir)
        except FileExistsError:
            raise AlreadyExists(f"a recording named {name!r} is in {self.folder} already") from None
        except OSError as exc:
            raise FailedPrecondition(f"cannot create {str(folder)!r}: {exc.strerror or exc}") from None
        try:
            link = await self._writer_process(budget)
        except OSError as exc:
            await asyncio.to_thread(_remove_empty, folder)
            raise FailedPrecondition(f"the recorder's writer process did not start: {exc}") from None
        writer = link.open_recording(
            name=name,
            selectors=wanted,
            folder=folder,
            version=self._version,
            limits=Limits(
                max_file_bytes=self._max_file_bytes,
                max_file_seconds=self._max_file_seconds,
                max_bytes=max_size,
                max_seconds=max_duration,
                max_queued_events=self._max_queued_events,
            ),
            on_end=self._ended,
        )
        recording = self._recordings[name] = _Recording(name, writer)
        self._forget_old()
        try:
            # For the caller of this Set: it hears only what that caller may read.
            recording.subscription = await follow(wanted, writer.offer)
        except BaseException:
            writer.stop()
            del self._recordings[name]
            await writer.wait(STOP_TIMEOUT)
            await asyncio.to_thread(_remove_empty, folder)
            raise
        log.info("recording %s started: %s", name, " ".join(wanted))
        self._refresh()
        return name

    @action(doc="stop the recording the value names (* stops every one)")
    async def stop(self, name: str) -> str:  # type: ignore[override]
        """Stop a recording (or every one, ``*``); answers the names stopped."""
        if name == ALL:
            stopping = [r for r in self._recordings.values() if r.active]
        else:
            recording = self._recordings.get(name)
            if recording is None or recording.writer is None:
                raise NotFound(f"no recording named {name[:100]!r} was started here")
            if not recording.active:
                raise FailedPrecondition(f"recording {name!r} is {recording.writer.state} already")
            stopping = [recording]
        await asyncio.gather(*(self._end(r, STOP_ANSWER_SECONDS) for r in stopping))
        self._refresh()
        return " ".join(r.name for r in stopping)

    # -- inside -----------------------------------------------------------------------------

    async def _writer_process(self, budget: DiskBudget) -> WriterLink:
        """The writer process: started at the first recording, and again after one ended."""
        link = self._link
        if link is not None and link.alive:
            return link
        if link is not None:
            await link.close()
        link = WriterLink(
            root=self._root,
            max_total_bytes=budget.max_total_bytes,
            when_full=budget.when_full,
            describe=self._describe,
            on_removed=self._file_removed,
            on_budget=self._budget_used,
        )
        await link.start()
        self._link = link
        return link

    def _forget_old(self) -> None:
        """Keep at most :data:`MAX_LISTED` recordings in mind: the oldest stopped ones go first
        (their files stay, and their names stay taken by their folders)."""
        excess = len(self._recordings) - MAX_LISTED
        if excess <= 0:
            return
        for old in [r for r in self._recordings.values() if not r.active and r.subscription is None][:excess]:
            writer = old.writer
            if writer is None or not writer.running:
                del self._recordings[old.name]

    def _new_name(self, name: str) -> str:
        if name:
            if not _NAME.fullmatch(name):
                raise InvalidArgument(
                    f"bad recording name {name[:100]!r}: 1 to 64 letters, digits, _ . - (not first: . -)"
                )
            if name in self._recordings or (self._root / name).exists():
                raise AlreadyExists(f"a recording named {name!r} exists already")
            return name
        base = "rec-" + datetime.now(UTC).strftime("%Y%m%d-%H%M%S")
        candidate, n = base, 1
        while candidate in self._recordings or (self._root / candidate).exists():
            n += 1
            candidate = f"{base}-{n}"
        return candidate

    async def _end(self, recording: _Recording, within: float) -> None:
        subscription, recording.subscription = recording.subscription, None
        if subscription is not None:
            await close_quietly(subscription)
        writer = recording.writer
        if writer is not None:
            writer.stop()
            await writer.wait(within)

    def _ended(self, writer: RecordingFeed) -> None:
        """The writer process ended the recording (a stop, a limit, an error, or the process itself
        ended): its follow ends too."""
        name = writer.name
        log.info(
            "recording %s %s: %d messages in %d files%s",
            name,
            writer.state,
            writer.messages,
            len(writer.files),
            f" ({writer.reason})" if writer.reason else "",
        )
        recording = self._recordings.get(name)
        if recording is not None and recording.subscription is not None:
            subscription, recording.subscription = recording.subscription, None
            self._ps_spawn(close_quietly(subscription), f"end the follow of {name}")
        self._refresh()

    def _file_removed(self, path: Path) -> None:
        """The budget (in the writer process) removed a file to make room."""
        recording = self._recordings.get(path.parent.name)
        if recording is not None:
            if recording.writer is not None:
                recording.writer.removed(path)
            elif path.name in recording.files:
                recording.files = [f for f in recording.files if f != path.name]

    def _budget_used(self, used: int) -> None:
        if self._budget is not None:
            self._budget.used = used

    async def _describe(self, service: str) -> tuple[str, ServiceModel | None]:
        """For the writer process: the service's type and model (None when it cannot be read)."""
        try:
            async with asyncio.timeout(DESCRIBE_TIMEOUT):
                with own_work():
                    backend = self._directory.backend(service)
                    model = await backend.describe()
        except Exception as exc:
            log.info(
                "recording: the model of %s was not read (%s); its values are recorded as text",
                service,
                exc or type(exc).__name__,
            )
            return "", None
        return backend.info.type, model


def _found_on_disk(root: Path) -> list[_Recording]:
    """The recordings in ``root`` already (a folder with ``.mcap`` files), oldest first: listed as stopped."""
    found = []
    for folder in sorted(p for p in root.iterdir() if p.is_dir()):
        try:
            sizes = {f.name: f.stat().st_size for f in folder.glob("*.mcap") if f.is_file()}
            started_ns = folder.stat().st_mtime_ns
        except OSError:  # removed meanwhile
            continue
        if not sizes:
            continue
        recording = _Recording(folder.name)
        recording.files = sorted(sizes)
        recording.size = sum(sizes.values())
        recording.started_ns = started_ns
        found.append(recording)
    found.sort(key=lambda r: r.started_ns)
    return found[-MAX_LISTED:]


def _remove_empty(folder: Path) -> None:
    with contextlib.suppress(OSError):
        for child in folder.iterdir():
            child.unlink()
        folder.rmdir()
