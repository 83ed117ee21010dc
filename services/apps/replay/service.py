"""The replay service: a recording played back as live services (``type = "replay"``).

For each service the recording holds, the replay serves a :class:`ReplayedService` of that name
(or ``prefix`` + name) through the gateway's directory (:meth:`Directory.serve`), so that every
front end, the registry and Listens see it as they see any service. The replay service's own
properties drive the playback: ``speed``, ``loop``, ``seek``, ``play``, ``pause``, and the live
``position`` and ``playing``.

How it plays: a task reads the ``/_events`` channel in batches in a worker thread (a batch is at
most :data:`BATCH_EVENTS` changes and :data:`BATCH_BYTES` of values) and tells each change to its
service when the :class:`Timeline` reaches the change's log time; it runs while paused too, its
next batch read. A seek (and a loop back to the start) reads the recording up to the new position
in the worker thread (from where the replay stands, for a seek forward; else from the start),
keeping only the last value of each property, and tells each property whose value differs there
with ``gap`` set: values were skipped.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Annotated

from services.apps.replay.recording import RecordedEvent, Recording
from services.apps.replay.replayed import ReplayedService
from services.apps.replay.timeline import Timeline
from services.kernel.core import Prop, Resource, action
from services.kernel.directory import Directory, own_context
from services.kernel.errors import AlreadyExists, InvalidArgument, NotFound, PropertyError
from services.kernel.paths import validate_service_name
from services.kernel.values import Value

__all__ = ["BATCH_BYTES", "BATCH_EVENTS", "MAX_SPEED", "MIN_SPEED", "POSITION_PERIOD_S", "Replay"]

log = logging.getLogger(__name__)

#: Changes read from the file at once: a batch is the most a replay holds ahead of its position.
BATCH_EVENTS = 256
#: Bytes of values read at once (binary frames are big: a few of them make a batch).
BATCH_BYTES = 4 * 1024 * 1024
#: The slowest and fastest playback (a hundredth and a thousand times the recorded pace).
MIN_SPEED = 0.01
MAX_SPEED = 1000.0
#: How often a playing replay tells ``position``'s listeners where it stands, in wall seconds.
POSITION_PERIOD_S = 0.25


class _Batches:
    """A recording's changes in batches, read in a worker thread. A batch never ends between two
    changes of one log time: the player tells those in one go, so the cursor (a log time) never
    stands between them."""

    def __init__(self, events: Iterator[RecordedEvent]) -> None:
        self._events = events
        self._held: RecordedEvent | None = None

    def take(self) -> list[RecordedEvent]:
        """The next changes (a batch, and the rest of its last log time's); none at the end."""
        batch: list[RecordedEvent] = []
        size = 0
        if self._held is not None:
            batch.append(self._held)
            size += len(self._held.value)
            self._held = None
        for event in self._events:
            full = len(batch) >= BATCH_EVENTS or size >= BATCH_BYTES
            if full and event.log_time_ns != batch[-1].log_time_ns:
                self._held = event
                break
            batch.append(event)
            size += len(event.value)
        return batch


#: (service, path) → value: the recorded values at one time.
Values = dict[tuple[str, str], Value]


@dataclass
class _State:
    """Every property's value at one log time, and the properties removed by then."""

    values: Values = field(default_factory=dict)
    removed: set[tuple[str, str]] = field(default_factory=set)


def _state_at(recording: Recording, until_ns: int, since: tuple[int, _State] | None = None) -> _State:
    """The state at log time ``until_ns``: read from the start, or from ``since`` (a log time and
    the state then) when it is earlier, so a seek forward reads only what lies between. Worker thread."""
    since_ns, state = since if since is not None else (None, _State())
    for event in recording.events(since_ns):
        if event.log_time_ns > until_ns:
            break
        key = (event.service, event.path)
        if event.removed:
            state.values.pop(key, None)
            state.removed.add(key)
        else:
            state.values[key] = event.value
            state.removed.discard(key)
    return state


def _check_speed(speed: float) -> float:
    if not MIN_SPEED <= speed <= MAX_SPEED:
        raise InvalidArgument(f"speed must be between {MIN_SPEED:g} and {MAX_SPEED:g}, got {speed:g}")
    return float(speed)


class _Position:
    """The replay's position as text, for the answer to a Get of a value not recorded yet."""

    def __init__(self, timeline: Timeline) -> None:
        self._timeline = timeline

    def __str__(self) -> str:
        return f"{self._timeline.position():.3f}"


class Replay(Resource):
    """Plays a recording (an MCAP file or a folder of them) back as live, read-only services."""

    resource_type = "replay"

    recording: Annotated[str, Prop(readonly=True, doc="the recording played: a file or a folder of files")]
    services: Annotated[
        list[str],
        Prop(readonly=True, doc="the services served from the recording, as named here"),
    ]
    duration: Annotated[float, Prop(readonly=True, unit="s", doc="seconds from the first change to the last")]
    loop: Annotated[bool, Prop(doc="at the end, start again from the beginning")]

    def __init__(
        self,
        *,
        recording: str,
        directory: Directory,
        prefix: str = "",
        speed: float = 1.0,
        loop: bool = False,
        autostart: bool = True,
    ) -> None:
        if not isinstance(recording, str) or not recording:
            raise InvalidArgument("a replay needs recording = an .mcap file or a recording's folder")
        if not isinstance(prefix, str):
            raise InvalidArgument(f"prefix must be text, got {prefix!r}")
        for option, given in (("loop", loop), ("autostart", autostart)):
            if not isinstance(given, bool):
                raise InvalidArgument(f"{option} must be true or false, got {given!r}")
        if isinstance(speed, bool) or not isinstance(speed, int | float):
            raise InvalidArgument(f"speed must be a number, got {speed!r}")
        self._recording = Recording(recording)
        self._directory = directory
        self._timeline = Timeline(self._recording.duration_s)
        self._timeline.set_speed(_check_speed(speed))
        self._autostart = autostart
        position = _Position(self._timeline)
        source = self._recording.path.name
        #: Recorded name → the service replaying it.
        self._replayed: dict[str, ReplayedService] = {}
        #: Recorded name → the name it is served as here.
        self._names: dict[str, str] = {}
        for name, recorded in self._recording.services.items():
            served = validate_service_name(prefix + name)
            self._replayed[name] = ReplayedService(recorded, source, position)
            self._names[name] = served
        self.recording = str(self._recording.path)
        self.services = list(self._names.values())
        self.duration = round(self._recording.duration_s, 3)
        self.loop = loop
        #: The log time up to which every change is told (the state the services hold): none yet.
        self._cursor_ns = self._recording.start_ns - 1
        #: Set when the timeline changes (pause, play, speed): the player looks at it again.
        self._retimed = asyncio.Event()
        #: One seek at a time: a second waits for the first to hold its values, then moves on.
        self._seeking = asyncio.Lock()
        self._player: asyncio.Task[None] | None = None
        self._ticker: asyncio.Task[None] | None = None
        self._served: list[str] = []

    # -- properties ------------------------------------------------------------

    @property
    def speed(
        self,
    ) -> Annotated[
        float,
        Prop(minimum=MIN_SPEED, maximum=MAX_SPEED, unit="x", gui="slider", doc="times the recorded pace"),
    ]:
        return self._timeline.speed

    @speed.setter
    def speed(self, value: float) -> None:
        self._timeline.set_speed(_check_speed(value))
        self._retimed.set()
        self.changed("speed")

    @property
    def position(
        self,
    ) -> Annotated[float, Prop(unit="s", doc="seconds from the start where the replay stands")]:
        return round(self._timeline.position(), 3)

    @property
    def playing(self) -> Annotated[bool, Prop(doc="whether the replay plays now (play, pause)")]:
        return self._timeline.playing

    @action(doc="go to this many seconds from the start; playing or paused as before", unit="s")
    async def seek(self, offset: float) -> None:
        if not 0.0 <= offset <= self._timeline.duration_s:
            raise InvalidArgument(
                f"seek to {offset:g} s: the recording runs from 0 to {self._timeline.duration_s:.3f} s"
            )
        await self._go_to(offset)

    @action(doc="play from where the replay stands (from the start when it stands at the end)")
    async def play(self) -> None:
        if self._timeline.playing:
            return
        if self._timeline.position() >= self._timeline.duration_s and self._player is None:
            await self._go_to(0.0)
        self._timeline.play()
        self._follow()

    @action(doc="stop where the replay stands")
    def pause(self) -> None:
        if not self._timeline.playing:
            return
        self._timeline.pause()
        self._retimed.set()
        self._told()

    # -- lifecycle -------------------------------------------------------------

    async def start(self) -> None:
        try:
            for name, replayed in self._replayed.items():
                try:
                    await self._directory.serve(self._names[name], replayed)
                except AlreadyExists:
                    raise AlreadyExists(
                        f"replay of {self.recording}: a service named {self._names[name]!r} is served"
                        " already; give the replay a prefix"
                    ) from None
                self._served.append(self._names[name])
            await self._go_to(0.0)
        except BaseException:
            await self.stop()
            raise
        if self._autostart:
            self._timeline.play()
            self._follow()

    async def stop(self) -> None:
        for task in (self._player, self._ticker):
            if task is not None:
                task.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await task
        self._player = self._ticker = None
        served, self._served = self._served, []
        for name in reversed(served):
            with contextlib.suppress(NotFound):
                await self._directory.unregister(name)

    # -- playing -----------------------------------------------------------------

    def _told(self) -> None:
        self.changed("playing")
        self.changed("position")

    def _follow(self) -> None:
        """Make sure a player follows the timeline, and tell ``playing`` and ``position``. A player
        runs while paused too: it reads its first batch and waits, so that ``play`` starts at once."""
        if self._player is None:
            self._player = asyncio.get_running_loop().create_task(
                self._play(), name="replay player", context=own_context()
            )
        if self._ticker is None:
            self._ticker = asyncio.get_running_loop().create_task(
                self._tick(), name="replay position", context=own_context()
            )
        self._retimed.set()
        self._told()

    async def _go_to(self, position_s: float) -> None:
        """Stand at ``position_s``: each service holds its values there; a change is told with ``gap``."""
        async with self._seeking:
            player, self._player = self._player, None
            if player is not None:
                player.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await player
            await self._rewind(position_s)
            self._follow()

    async def _rewind(self, position_s: float) -> None:
        """Hold the values at ``position_s`` and move the cursor and the timeline there."""
        until_ns = self._recording.start_ns + round(position_s * 1e9)
        since = None
        if until_ns >= self._cursor_ns:
            now = _State()
            for name, replayed in self._replayed.items():
                now.values.update(((name, path), value) for path, value in replayed.values().items())
                now.removed.update((name, path) for path in replayed.removed())
            since = (self._cursor_ns, now)
        state = await asyncio.to_thread(_state_at, self._recording, until_ns, since)
        recorded: dict[str, set[str]] = {}
        for service, path in (*state.values, *state.removed):
            recorded.setdefault(service, set()).add(path)
        for name, replayed in self._replayed.items():
            held, gone = replayed.values(), replayed.removed()
            for path in held.keys() | gone | recorded.get(name, set()):
                value = state.values.get((name, path))
                if value is not None:
                    if held.get(path) != value:
                        replayed.apply(path, value, gap=True)
                elif (name, path) in state.removed:
                    if path not in gone:
                        replayed.apply(path, "", gap=True, removed=True)
                else:
                    replayed.forget(path)  # not recorded yet there
        self._cursor_ns = until_ns
        self._timeline.seek(position_s)

    def _seconds_of(self, event: RecordedEvent) -> float:
        return (event.log_time_ns - self._recording.start_ns) / 1e9

    async def _play(self) -> None:
        """Tell each change after the cursor when the timeline reaches it; at the end, loop or stop."""
        try:
            while True:
                batches = _Batches(self._recording.events(since_ns=self._cursor_ns))
                while batch := await asyncio.to_thread(batches.take):
                    for event in batch:
                        await self._reach(self._seconds_of(event))
                        replayed = self._replayed.get(event.service)
                        if replayed is not None:
                            replayed.apply(event.path, event.value, gap=event.gap, removed=event.removed)
                        self._cursor_ns = event.log_time_ns
                await self._reach(self._timeline.duration_s)
                if not self.loop:
                    self._timeline.pause()
                    self._told()
                    return
                await self._rewind(0.0)
                self._told()
        except PropertyError:
            log.exception("replay of %s stopped", self._recording.path)
        finally:
            if self._player is asyncio.current_task():
                self._player = None

    async def _reach(self, position_s: float) -> None:
        """Return once the timeline stands at ``position_s`` or past it."""
        while (wait := self._timeline.wait_until(position_s)) != 0.0:
            self._retimed.clear()
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(wait):
                    await self._retimed.wait()

    async def _tick(self) -> None:
        """While playing, tell ``position``'s listeners where the replay stands a few times a second."""
        try:
            while True:
                await asyncio.sleep(POSITION_PERIOD_S)
                if self._timeline.playing:
                    self.changed("position")
        finally:
            self._ticker = None
