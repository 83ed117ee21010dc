"""The vision service: a simulated camera (see ``docs/vision.md``).

:class:`Camera` is the Resource: its pose, optics and settings, ``markers``
(every thing in view), ``data`` (how many) and ``frame`` (a JPEG of the
view). It sees the static objects of its configuration and the robots of the
gateway, found in the directory and followed by a Listen on their
``location``; a camera mounted on a robot follows that robot's ``location``
the same way.

Frames cost CPU only while someone watches: a Listen of ``frame`` starts a
render loop at ``rate_hz`` and the last Listen leaving stops it; a Get with
nobody listening renders one frame (or answers the one rendered less than a
period ago). :class:`CameraService`, the LocalService subclass that serves a
Camera, sees those Gets and Listens, and the Gets and Listens of ``markers``
with its parameter ``frame`` (a read property of the class wrapper takes none).
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import itertools
import logging
import math
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Annotated, Any

import numpy as np

from services.apps.location_following import LocationFollower
from services.apps.vision.geometry import mounted_pose
from services.apps.vision.render import Renderer, View
from services.apps.vision.scene import ROBOT_SIZE, Sighting, Thing, look, parse_objects, robot_colour
from services.kernel.backend import NO_PARAMS, UNKNOWN_TYPE, Backend, Change, Notify, Subscription, tell_each
from services.kernel.core import LocalService, Prop, Resource
from services.kernel.directory import Directory
from services.kernel.errors import InvalidArgument, PropertyError, ReadOnly, ResourceExhausted
from services.kernel.model import ParameterModel, PropertyModel
from services.kernel.paths import validate_service_name
from services.kernel.values import Value, Vector, format_number
from services.kernel.values.markers import format_markers

__all__ = ["Camera", "CameraService"]

log = logging.getLogger(__name__)

#: Frames per second at most: what a display shows; each frame costs the gateway ~1.4 ms to draw
#: and encode at 640x480 (docs/vision.md), so even 60 Hz leaves most of a core to the rest.
MAX_RATE_HZ = 60.0
MIN_RATE_HZ = 0.1
DEFAULT_RATE_HZ = 15.0
#: JPEG quality: above 95 Pillow's encoder grows the file for nothing the eye sees.
MIN_QUALITY, MAX_QUALITY = 1, 95
#: Field of view, degrees: a pinhole cannot see 180 degrees.
MIN_FOV, MAX_FOV = 1.0, 179.0
MIN_RANGE, MAX_RANGE = 0.1, 1000.0
#: Resolution bounds, pixels: 4K is the largest a frame may be (a 4K JPEG still fits a message).
MIN_SIDE, MAX_WIDTH, MAX_HEIGHT = 16, 3840, 2160
#: Updates of what is seen per second at most, however often the robots move.
MAX_UPDATE_HZ = 50.0
#: Services followed at most (each is one Listen on its location).
DEFAULT_MAX_FOLLOWED = 100
MAX_FOLLOWED = 1000
#: Listens of ``markers`` in the camera's frame at once.
MAX_CAMERA_FRAME_LISTENERS = 1024
#: Seconds a followed service gets to answer its Listen; one that does not is asked again,
#: less and less often, up to every RETRY_MAX_S.
FOLLOW_TIMEOUT_S = 5.0
RETRY_MAX_S = 10.0
FRAMES = ("world", "camera")


def _number(value: Any, what: str, low: float, high: float, unit: str = "") -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not low <= value <= high:
        shown = f" {unit}" if unit else ""
        bounds = f"from {format_number(low)} to {format_number(high)}{shown}"
        raise InvalidArgument(f"{what} must be a number {bounds}, got {value!r}")
    return float(value)


def _pose(value: Sequence[float] | Vector, what: str) -> Vector:
    try:
        numbers = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InvalidArgument(
            f"{what} must be 2, 3 or 6 numbers (x y [z [roll pitch yaw]]), got {value!r}"
        ) from None
    if numbers.ndim != 1 or len(numbers) not in (2, 3, 6) or not np.all(np.isfinite(numbers)):
        raise InvalidArgument(
            f"{what} must be 2, 3 or 6 finite numbers (x y [z [roll pitch yaw]]), got {value!r}"
        )
    pose = np.zeros(6)
    pose[: len(numbers)] = numbers
    return pose


def _resolution(value: Sequence[float] | Vector) -> tuple[int, int]:
    try:
        numbers = [float(v) for v in value]
    except (TypeError, ValueError):
        numbers = []
    if (
        len(numbers) != 2
        or not all(x.is_integer() for x in numbers)
        or not (MIN_SIDE <= numbers[0] <= MAX_WIDTH and MIN_SIDE <= numbers[1] <= MAX_HEIGHT)
    ):
        raise InvalidArgument(
            f"resolution must be (width height) in pixels, {MIN_SIDE} to {MAX_WIDTH} by {MIN_SIDE} to "
            f"{MAX_HEIGHT}, got {value!r}"
        )
    return int(numbers[0]), int(numbers[1])


class _Listener(Subscription):
    """One Listen of ``markers`` in the camera's frame."""

    def __init__(self, camera: Camera, token: int) -> None:
        self._camera = camera
        self._token = token

    async def close(self) -> None:
        self._camera._camera_listeners.pop(self._token, None)


class _FrameWatch(Subscription):
    """A Listen of ``frame``: while one is open, the camera renders at its rate."""

    def __init__(self, camera: Camera, inner: Subscription) -> None:
        self._camera = camera
        self._inner = inner
        self._open = True

    async def close(self) -> None:
        if self._open:
            self._open = False
            self._camera._unwatch_frames()
        await self._inner.close()


class CameraService(LocalService):
    """Serves a :class:`Camera`: the class wrapper's calls, plus what frames and camera-frame markers need."""

    def __init__(self, obj: Resource, url: str = "local") -> None:
        if not isinstance(obj, Camera):
            raise TypeError(f"CameraService serves a Camera, not a {type(obj).__name__}")
        super().__init__(obj, url)
        self.camera = obj

    async def get(self, path: str, params: Mapping[str, str] = NO_PARAMS) -> Value:
        if path == "frame":
            await self.camera.fresh_frame()
        elif path == "markers":
            return self.camera.markers_in(_frame_param(params))
        elif path == "markers.parameters":
            return MARKERS_PARAMETERS
        return await super().get(path, params)

    async def listen(self, path: str, notify: Notify, params: Mapping[str, str] = NO_PARAMS) -> Subscription:
        if path == "markers" and _frame_param(params) == "camera":
            return self.camera.listen_camera_markers(notify)
        if path == "frame":
            sub = await super().listen(path, notify, params)
            self.camera._watch_frames()
            return _FrameWatch(self.camera, sub)
        return await super().listen(path, notify, params)

    def model_of(self, prop: PropertyModel) -> PropertyModel:
        return dataclasses.replace(prop, parameters=(FRAME_PARAMETER,)) if prop.name == "markers" else prop


#: ``markers`` takes a parameter, which a read property of the class wrapper cannot declare:
#: CameraService reads it, says it in ``markers.parameters`` and in the model.
MARKERS_DOC = "every thing in view as a marker (id, class, location, color, confidence), nearest first"
MARKERS_PARAMETERS = "((frame text world))"
FRAME_PARAMETER = ParameterModel(
    "frame",
    "text",
    required=False,
    default="world",
    doc="the frame of the locations: world, or camera (x forward, y left, z up, from the camera)",
)


def _frame_param(params: Mapping[str, str]) -> str:
    extra = sorted(k for k in params if k != "frame")
    if extra:
        raise InvalidArgument(f"`markers` has no parameter `{extra[0]}`; it accepts: `frame`")
    frame = params.get("frame", "world")
    if frame not in FRAMES:
        raise InvalidArgument(f"bad parameter `frame` for `markers`: {frame!r}; use world or camera")
    return frame


class Camera(Resource):
    """A simulated camera: what it sees as markers and as JPEG frames (see ``docs/vision.md``)."""

    resource_type = "camera"
    served_by = CameraService

    mount: Annotated[
        str, Prop(readonly=True, doc='the robot service the camera rides on ("" when it stands fixed)')
    ]
    quality: Annotated[
        int,
        Prop(minimum=MIN_QUALITY, maximum=MAX_QUALITY, gui="slider", doc="JPEG quality of frame, 1 to 95"),
    ]
    followed: Annotated[
        list[str],
        Prop(readonly=True, doc="the services whose location the camera follows (robots it may see)"),
    ]

    def __init__(
        self,
        *,
        directory: Directory | None = None,
        location: Sequence[float] = (0.0, 0.0, 1.0),
        mount: str = "",
        mount_offset: Sequence[float] = (0.1, 0.0, 0.3),
        fov: float = 60.0,
        range: float = 10.0,  # the option's name in a configuration
        resolution: Sequence[int] = (640, 480),
        rate_hz: float = DEFAULT_RATE_HZ,
        quality: int = 75,
        objects: Iterable[Mapping[str, Any]] = (),
        types: Sequence[str] = ("mobile_robot",),
        max_followed: int = DEFAULT_MAX_FOLLOWED,
    ) -> None:
        self._directory = directory
        self._fixed_pose = _pose(location, "location")
        if not isinstance(mount, str):
            raise InvalidArgument(f"mount must be a service name or empty, got {mount!r}")
        if mount:
            validate_service_name(mount)
        self.mount = mount
        self._offset = _pose(mount_offset, "mount_offset")
        self._mount_pose: Vector | None = None
        self._fov = _number(fov, "fov", MIN_FOV, MAX_FOV, "degrees")
        self._range = _number(range, "range", MIN_RANGE, MAX_RANGE, "m")
        self._size = _resolution(resolution)
        self._rate = _number(rate_hz, "rate_hz", MIN_RATE_HZ, MAX_RATE_HZ, "Hz")
        if (
            isinstance(quality, bool)
            or not isinstance(quality, int)
            or not MIN_QUALITY <= quality <= MAX_QUALITY
        ):
            raise InvalidArgument(
                f"quality must be a whole number from {MIN_QUALITY} to {MAX_QUALITY}, got {quality!r}"
            )
        self.quality = quality
        self._objects = parse_objects(objects)
        if isinstance(types, str) or not all(isinstance(t, str) and t for t in types):
            raise InvalidArgument(f"types must be a list of resource types, got {types!r}")
        self._types = frozenset(types)
        if (
            isinstance(max_followed, bool)
            or not isinstance(max_followed, int)
            or not 0 <= max_followed <= MAX_FOLLOWED
        ):
            raise InvalidArgument(
                f"max_followed must be a whole number from 0 to {MAX_FOLLOWED}, got {max_followed!r}"
            )
        self._max_followed = max_followed
        self.followed = []
        self._count = 0
        # What the camera sees.
        self._robots: dict[str, Thing] = {}
        self._sightings: list[Sighting] = []
        self._markers = {"world": "()", "camera": "()"}
        self._update_pending = False
        self._updated_at = -math.inf
        self._camera_listeners: dict[int, Notify] = {}
        self._tokens = itertools.count()
        # Following.
        self._follower = LocationFollower(
            self._on_location,
            timeout=lambda: FOLLOW_TIMEOUT_S,
            retry_max=RETRY_MAX_S,
            on_answer=self._on_answer,
            what="camera",
        )
        self._mount_follower = LocationFollower(
            self._on_mount_location,
            timeout=lambda: FOLLOW_TIMEOUT_S,
            retry_max=RETRY_MAX_S,
            what="camera mount",
        )
        self._unwatch: Callable[[], None] | None = None
        self._running = False
        self._refused_warned = False
        # Frames.
        self._renderer: Renderer | None = None
        self._frame = b""
        self._frame_at = -math.inf
        self._frames = 0
        self._watchers = 0
        self._render_task: asyncio.Task[None] | None = None
        self._rendering: asyncio.Future[bytes] | None = None
        self._executor: ThreadPoolExecutor | None = None
        self._update()

    # -- properties ----------------------------------------------------------------

    @property
    def location(
        self,
    ) -> Annotated[
        Vector,
        Prop(
            gui="pose",
            unit="m, rad",
            length=6,
            doc="x y z roll pitch yaw in the world frame; follows the robot when mounted (then read-only)",
        ),
    ]:
        """Where the camera is and where it looks (yaw)."""
        if self.mount:
            if self._mount_pose is None:
                return self._fixed_pose
            return mounted_pose(self._mount_pose, self._offset)
        return self._fixed_pose

    @location.setter
    def location(self, value: Vector) -> None:
        if self.mount:
            raise ReadOnly(
                f"the camera rides on {self.mount}: its location follows that robot; Set mount_offset instead"
            )
        self._fixed_pose = _pose(value, "location")
        self._moved()

    @property
    def mount_offset(
        self,
    ) -> Annotated[
        Vector, Prop(unit="m, rad", length=6, doc="pose on the robot it rides on, in the robot's frame")
    ]:
        """The camera's place on its robot: x forward, y left, z up, and its roll pitch yaw."""
        return self._offset

    @mount_offset.setter
    def mount_offset(self, value: Vector) -> None:
        self._offset = _pose(value, "mount_offset")
        self._moved()

    @property
    def fov(
        self,
    ) -> Annotated[
        float,
        Prop(minimum=MIN_FOV, maximum=MAX_FOV, unit="deg", gui="slider", doc="horizontal field of view"),
    ]:
        """Horizontal field of view, degrees."""
        return self._fov

    @fov.setter
    def fov(self, value: float) -> None:
        self._fov = _number(value, "fov", MIN_FOV, MAX_FOV, "degrees")
        self._optics_changed()

    @property
    def range(
        self,
    ) -> Annotated[
        float, Prop(minimum=MIN_RANGE, maximum=MAX_RANGE, unit="m", doc="the farthest the camera sees")
    ]:
        """The farthest distance on the ground at which the camera sees a thing, m."""
        return self._range

    @range.setter
    def range(self, value: float) -> None:
        self._range = _number(value, "range", MIN_RANGE, MAX_RANGE, "m")
        self._optics_changed()

    @property
    def resolution(
        self,
    ) -> Annotated[Vector, Prop(unit="px", length=2, doc="width and height of frame, pixels")]:
        """Width and height of ``frame``."""
        return np.array(self._size, dtype=np.float64)

    @resolution.setter
    def resolution(self, value: Vector) -> None:
        self._size = _resolution(value)
        self._optics_changed()

    @property
    def rate_hz(
        self,
    ) -> Annotated[
        float,
        Prop(
            minimum=MIN_RATE_HZ,
            maximum=MAX_RATE_HZ,
            unit="Hz",
            doc="frames per second while someone listens to frame",
        ),
    ]:
        """Frames per second rendered while ``frame`` has listeners."""
        return self._rate

    @rate_hz.setter
    def rate_hz(self, value: float) -> None:
        self._rate = _number(value, "rate_hz", MIN_RATE_HZ, MAX_RATE_HZ, "Hz")
        self.changed("rate_hz")

    @property
    def frame(
        self,
    ) -> Annotated[
        bytes,
        Prop(readonly=True, media_type="image/jpeg", gui="image", doc="what the camera sees, a JPEG image"),
    ]:
        """The latest frame rendered (JPEG)."""
        return self._frame

    @property
    def markers(self) -> Annotated[str, Prop(readonly=True, gui="markers", doc=MARKERS_DOC)]:
        """The markers of the things in view, nearest first, located in the world frame."""
        return self.markers_in("world")

    def markers_in(self, frame: str) -> str:
        """The markers of the things in view, nearest first, located in ``frame`` (world or camera)."""
        if frame not in FRAMES:
            raise InvalidArgument(f"bad parameter `frame` for `markers`: {frame!r}; use world or camera")
        self._settle()
        return self._markers[frame]

    @property
    def data(self) -> Annotated[int, Prop(readonly=True, gui="number", doc="the number of objects in view")]:
        """How many things are in view now (the standard property of a sensor)."""
        self._settle()
        return self._count

    def _settle(self) -> None:
        """Bring what is seen up to date now when an update is due (a read right after a Set)."""
        if self._update_pending:
            self._update()

    # -- what is seen -----------------------------------------------------------------

    def sightings(self) -> list[Sighting]:
        """The things in view now, nearest first."""
        return list(self._sightings)

    def _things(self) -> list[Thing]:
        return [*self._objects, *self._robots.values()]

    def _moved(self) -> None:
        self.changed("location")
        self._schedule_update()

    def _optics_changed(self) -> None:
        self._renderer = None
        self._schedule_update()

    def _schedule_update(self) -> None:
        # Many robots move in the same instant, and a hundred robots at 20 Hz move 2,000 times a
        # second: what is seen is worked out at most MAX_UPDATE_HZ times a second (a read of
        # markers or data in between works it out at once).
        if self._update_pending:
            return
        try:
            loop = asyncio.get_running_loop()
        except RuntimeError:  # no loop (a test building the object): at once
            self._update()
            return
        self._update_pending = True
        wait = self._updated_at + 1.0 / MAX_UPDATE_HZ - loop.time()
        if wait > 0:
            loop.call_later(wait, self._settle)  # nothing to do if a read settled it meanwhile
        else:
            loop.call_soon(self._settle)

    def _update(self) -> None:
        self._update_pending = False
        with contextlib.suppress(RuntimeError):  # built outside a loop: no time to keep yet
            self._updated_at = asyncio.get_running_loop().time()
        self._sightings = look(self.location, self._range, math.radians(self._fov), self._things())
        world = format_markers([s.marker("world") for s in self._sightings])
        camera = format_markers([s.marker("camera") for s in self._sightings])
        self._markers = {"world": world, "camera": camera}
        if self._count != len(self._sightings):
            self._count = len(self._sightings)
            self.changed("data")
        self.changed("markers")
        if self._camera_listeners:
            tell_each(self._camera_listeners, Change("markers", camera), what="markers (camera frame)")

    def listen_camera_markers(self, notify: Notify) -> Subscription:
        """Call ``notify`` whenever the markers in the camera's frame change (CameraService's Listen)."""
        if len(self._camera_listeners) >= MAX_CAMERA_FRAME_LISTENERS:
            raise ResourceExhausted(
                f"markers (camera frame): {MAX_CAMERA_FRAME_LISTENERS} listeners already; close one first"
            )
        token = next(self._tokens)
        self._camera_listeners[token] = _only_changes(notify, self._markers["camera"])
        return _Listener(self, token)

    # -- following robots ---------------------------------------------------------------

    async def start(self) -> None:
        self._running = True
        if self._directory is not None:
            self._unwatch = self._directory.watch(self._on_directory)
            for name in self._directory.names():
                self._consider(name)

    async def stop(self) -> None:
        self._running = False
        if self._unwatch is not None:
            self._unwatch()
            self._unwatch = None
        self._watchers = 0  # the service's Listens end with it
        if self._render_task is not None:
            self._render_task.cancel()
            await asyncio.gather(self._render_task, return_exceptions=True)
            self._render_task = None
        await self._follower.aclose()
        await self._mount_follower.aclose()
        if self._executor is not None:
            self._executor.shutdown(wait=True)
            self._executor = None

    def _on_directory(self, name: str, backend: Backend | None) -> None:
        if not self._running:
            return
        if backend is None:
            if name == self.mount:
                self._mount_follower.forget(name)
            if name in self.followed:
                full = len(self.followed) >= self._max_followed
                self._forget(name)
                if full and self._directory is not None:  # a place is free: the next one takes it
                    for other in self._directory.names():
                        if other != name:
                            self._consider(other)
        else:
            self._consider(name)

    def _consider(self, name: str) -> None:
        assert self._directory is not None
        try:
            backend = self._directory.backend(name)
        except PropertyError:
            return  # gone again already
        if backend.serves(self) or backend.on_demand:
            return  # itself; or a dormant service, which a mere watcher must not wake
        if name == self.mount:
            self._mount_follower.follow(name, backend)
            return
        if backend.info.type not in self._types and backend.info.type != UNKNOWN_TYPE:
            return
        if name in self.followed:
            return
        if len(self.followed) >= self._max_followed:
            if not self._refused_warned:
                self._refused_warned = True
                log.warning(
                    "camera: following %d services already (max_followed); %r and later ones are not seen",
                    self._max_followed,
                    name,
                )
            return
        self.followed = [*self.followed, name]
        self._follower.follow(name, backend)

    def _on_answer(self, name: str, backend: Backend) -> None:
        # A proxy's type is known once its device answered: drop what is not a thing to see.
        if backend.info.type not in self._types:
            self._forget(name)

    def _forget(self, name: str) -> None:
        self._follower.forget(name)
        if name in self.followed:
            self.followed = [n for n in self.followed if n != name]
        if self._robots.pop(name, None) is not None:
            self._schedule_update()

    def _on_location(self, name: str, vector: Vector | None) -> None:
        if vector is None or vector.size < 2:
            if self._robots.pop(name, None) is not None:
                self._schedule_update()
            return
        where = np.zeros(3)
        n = min(3, vector.size)
        where[:n] = vector[:n]
        old = self._robots.get(name)
        if old is not None and np.array_equal(old.location, where):
            return
        self._robots[name] = Thing(name, "mobile_robot", where, robot_colour(name), ROBOT_SIZE)
        self._schedule_update()

    def _on_mount_location(self, name: str, vector: Vector | None) -> None:
        if vector is None:
            return  # the robot is away: the camera stays where it last was
        pose = np.zeros(6)
        n = min(6, vector.size)
        pose[:n] = vector[:n]
        self._mount_pose = pose
        self._moved()

    # -- frames --------------------------------------------------------------------------

    def _watch_frames(self) -> None:
        self._watchers += 1
        if self._render_task is None or self._render_task.done():
            self._render_task = asyncio.get_running_loop().create_task(
                self._render_loop(), name="camera frames"
            )

    def _unwatch_frames(self) -> None:
        self._watchers = max(0, self._watchers - 1)
        if self._watchers == 0 and self._render_task is not None:
            self._render_task.cancel()
            self._render_task = None

    async def _render_loop(self) -> None:
        loop = asyncio.get_running_loop()
        due = loop.time()
        while self._watchers > 0:
            await self._render_now()
            due += 1.0 / self._rate
            now = loop.time()
            due = max(due, now)  # fell behind (a slow machine): skip the missed frames rather than burst
            await asyncio.sleep(due - now)

    async def fresh_frame(self) -> bytes:
        """A frame no older than one period (two while the render loop runs, so that a Get
        never renders a frame of its own between two of the loop's): the latest, or one now."""
        age = asyncio.get_running_loop().time() - self._frame_at
        periods = 2.0 if self._render_task is not None else 1.0
        if self._frame and age < periods / self._rate:
            return self._frame
        return await self._render_now()

    async def _render_now(self) -> bytes:
        if self._rendering is not None and not self._rendering.done():
            return await asyncio.shield(self._rendering)  # a render under way serves every waiter
        view, renderer = self._view()
        if self._executor is None:
            self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="camera")
        loop = asyncio.get_running_loop()
        self._rendering = loop.run_in_executor(self._executor, renderer.encode, view)
        frame = await asyncio.shield(self._rendering)
        self._frame = frame
        self._frame_at = loop.time()
        self.changed("frame")
        return frame

    def render_once(self) -> bytes:
        """Render and encode the current view here and now (a benchmark's baseline; the service
        itself renders on its own thread and keeps the frame)."""
        view, renderer = self._view()
        return renderer.encode(view)

    def _view(self) -> tuple[View, Renderer]:
        """A snapshot of what to draw, taken on the loop (the thread that draws it sees no later change)."""
        eye = float(self.location[2])
        renderer = self._renderer
        if renderer is None or renderer.eye != eye or (renderer.width, renderer.height) != self._size:
            renderer = Renderer(self._size[0], self._size[1], math.radians(self._fov), eye, self._range)
            self._renderer = renderer
        self._frames += 1
        return View(tuple(self._sightings), self._frames, time.time(), self.quality), renderer


def _only_changes(notify: Notify, first: str) -> Notify:
    """``notify``, called only when the value differs from the last one it was given."""
    last: list[Value] = [first]

    def deliver(change: Change) -> None:
        if change.value != last[0]:
            last[0] = change.value
            notify(change)

    return deliver
