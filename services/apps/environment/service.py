"""The environment model service: what the cameras, robots and sensors report, fused (docs/environment.md).

It Listens to its sources through the gateway's directory (:mod:`services.apps.environment.sources`),
keeps the fused markers (:class:`~services.apps.environment.fusion.MarkerFusion`) and the grid
layers (:mod:`services.apps.environment.grid`), and offers them as properties:

* ``markers`` (the ids) and ``markers.<id>`` (one fused marker; appears and disappears);
* ``grid`` (the layer names), ``grid.<layer>`` (float32 ``.npy``), ``grid.<layer>.info``,
  ``grid.<layer>.image`` (a PNG heat map);
* ``find`` (markers by class, ``near`` and ``area``, nearest first), ``observe`` (push a
  marker seen), ``clear``, ``count``, ``sources``, ``ttl``, ``gate``.
"""

from __future__ import annotations

import asyncio
import itertools
import logging
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import replace
from typing import Annotated, Any

from services.apps.environment.fusion import MarkerFusion, Observation, Update
from services.apps.environment.grid import GridSpec, HitLayer, Layer, MeanLayer
from services.apps.environment.nodes import LAYER_META, NPY, GridLayers, LayerNode, MarkerNode, MarkerTable
from services.apps.environment.observations import (
    MAX_LIST_MARKERS,
    fused_marker,
    observation_of,
    parse_marker_list,
    write_marker_list,
)
from services.apps.environment.options import (
    Reading,
    Selector,
    grid_spec,
    location_depth,
    location_path,
    number,
    selectors,
)
from services.apps.environment.options import readings as parse_readings
from services.apps.environment.sources import Follow, fixed
from services.kernel.backend import NO_PARAMS, Notify, Subscription
from services.kernel.core import LocalService, Marker, Prop, Resource, action, query
from services.kernel.directory import Directory
from services.kernel.errors import InvalidArgument, PropertyError
from services.kernel.model import PropertyModel
from services.kernel.values import Value, ValueFormatError, Vector, parse_number, parse_vector

__all__ = ["EnvironmentModel", "EnvironmentService"]

log = logging.getLogger(__name__)

#: Most markers ``find`` answers with: a hundred markers stay well inside one value's length.
MAX_FIND = 100
#: Seconds between notices of a grid layer's change: a layer is re-read (and a PNG made) per
#: notice by whoever listens, not per reading.
GRID_NOTICE_S = 0.5
#: Seconds between notices of the ``markers`` list's change.
LIST_NOTICE_S = 0.1
#: Longest pause between two expiry sweeps, seconds.
EXPIRY_SWEEP_S = 1.0
#: Defaults of the options (docs/configuration.md).
DEFAULT_CAMERA_VARIANCE = 0.01  # σ 10 cm
DEFAULT_ROBOT_VARIANCE = 0.0025  # σ 5 cm: a robot's own odometry
DEFAULT_PROCESS_NOISE = 0.05  # m²/s: an object walks about 22 cm in a second unseen
#: The layers every model has, with their units.
TEMPERATURE = "temperature"
OCCUPANCY = "occupancy"
#: The class of a robot's own marker: the resource type a camera gives a robot it sees, so that
#: a camera's sighting of a robot and the robot's own report fuse into one marker.
ROBOT_CLASS = "mobile_robot"


class _LayerSubscription(Subscription):
    __slots__ = ("_node", "_token")

    def __init__(self, node: LayerNode, token: int) -> None:
        self._node = node
        self._token = token

    async def close(self) -> None:
        self._node.listeners.pop(self._token, None)


class EnvironmentService(LocalService):
    """Serves an :class:`EnvironmentModel`: the class wrapper, and what it cannot say alone.

    * ``grid.<layer>`` is a namespace (``info``, ``image`` under it) whose own value is binary,
      the layer as ``.npy``: this class answers its Get, Listen, ``media_type`` and model.
    * ``class`` is a word Python keeps for itself, so ``find``'s keyword is ``kind``; a Get of
      ``find`` with ``class=...`` is taken as ``kind=...``.
    """

    obj: EnvironmentModel

    def __init__(self, obj: Resource, url: str = "local") -> None:
        super().__init__(obj, url)
        self._layer_tokens = itertools.count()

    def _layer(self, path: str) -> LayerNode | None:
        head, _, name = path.partition(".")
        return self.obj.layer_nodes.get(name) if head == "grid" else None

    async def get(self, path: str, params: Mapping[str, str] = NO_PARAMS) -> Value:
        node = self._layer(path)
        if node is not None:
            if params:
                raise InvalidArgument(f"`{path}` takes no parameters")
            return node.npy()
        head, _, meta = path.rpartition(".")
        if meta in LAYER_META and self._layer(head) is not None:
            if params:
                raise InvalidArgument(f"`{path}` takes no parameters")
            return LAYER_META[meta]
        if path == "find" and "class" in params:
            if "kind" in params:
                raise InvalidArgument("`find`: give class or kind, not both")
            params = {("kind" if k == "class" else k): v for k, v in params.items()}
        return await super().get(path, params)

    async def listen(self, path: str, notify: Notify, params: Mapping[str, str] = NO_PARAMS) -> Subscription:
        node = self._layer(path)
        if node is None:
            return await super().listen(path, notify, params)
        token = next(self._layer_tokens)
        node.listeners[token] = notify
        return _LayerSubscription(node, token)

    def model_of(self, prop: PropertyModel) -> PropertyModel:
        # Nodes with a value of their own, which the class wrapper calls namespaces: typed,
        # they are values a wildcard Get (`markers.*`) reads and a client knows how to parse.
        if self._layer(prop.name) is not None:
            return replace(prop, type="bytes", media_type=NPY, doc=LAYER_META["doc"], gui="bytes")
        if prop.name in ("markers", "grid"):
            return replace(prop, type="names", gui="list")
        if prop.name.startswith("markers.") and prop.type == "namespace":
            return replace(prop, type="marker", gui="marker")
        return prop


class EnvironmentModel(Resource):
    """What the cameras, robots and sensors report, fused: markers and grid layers."""

    resource_type = "environment_model"
    served_by = EnvironmentService

    count: Annotated[int, Prop(readonly=True, doc="fused markers now")]
    ttl: Annotated[float, Prop(readonly=True, unit="s", doc="a marker not seen for this long expires")]
    gate: Annotated[
        float, Prop(readonly=True, doc="association gate, standard deviations of the predicted distance")
    ]
    markers: MarkerTable
    grid: GridLayers

    def __init__(
        self,
        *,
        directory: Directory | None = None,
        markers: Sequence[str] = (),
        robots: Sequence[str] = (),
        readings: Sequence[Any] = (),
        grid: Mapping[str, Any] | None = None,
        ttl: float = 30.0,
        gate: float = 4.0,
        max_distance: float = 1.0,
        max_markers: int = 10_000,
        process_noise: float = DEFAULT_PROCESS_NOISE,
        camera_variance: float = DEFAULT_CAMERA_VARIANCE,
        robot_variance: float = DEFAULT_ROBOT_VARIANCE,
        clock: Callable[[], float] = time.time,
    ) -> None:
        self._directory = directory
        self._clock = clock
        self._marker_sources = selectors(markers, "markers")
        self._robot_sources = selectors(robots, "robots")
        self._readings = parse_readings(readings)
        if (self._marker_sources or self._robot_sources or self._readings) and directory is None:
            raise InvalidArgument(
                "an environment model with sources runs inside a gateway (it needs a directory)"
            )
        if isinstance(max_markers, bool) or not isinstance(max_markers, int):
            raise InvalidArgument(f"max_markers must be an integer, got {max_markers!r}")
        self.ttl = number(ttl, "ttl", 0.0, 86_400.0 * 365, low_open=True)
        self.gate = number(gate, "gate", 0.0, 100.0, low_open=True)
        try:
            self.fusion = MarkerFusion(
                gate=self.gate,
                max_distance=number(max_distance, "max_distance", 0.0, 1e6, low_open=True),
                ttl=self.ttl,
                max_markers=max_markers,
                process_noise=number(process_noise, "process_noise", 0.0, 1e6),
            )
        except ValueError as e:
            raise InvalidArgument(str(e)) from None
        self._camera_variance = number(camera_variance, "camera_variance", 0.0, 1e6, low_open=True)
        self._robot_variance = number(robot_variance, "robot_variance", 0.0, 1e6, low_open=True)
        self.spec: GridSpec = grid_spec(grid)
        self.layers: dict[str, Layer] = {
            TEMPERATURE: MeanLayer(TEMPERATURE, self.spec, unit="degC"),
            OCCUPANCY: HitLayer(OCCUPANCY, self.spec),
        }
        for reading in self._readings:
            self.layers.setdefault(reading.layer, MeanLayer(reading.layer, self.spec))
        self.count = 0
        self.markers = MarkerTable(self.fusion)
        self.grid = GridLayers(self.layers)
        self.layer_nodes = {name: LayerNode(layer) for name, layer in self.layers.items()}
        for name, node in self.layer_nodes.items():
            self.grid.attach(name, node)
        self._marker_nodes: dict[str, MarkerNode] = {}
        # Readings that came before their location was known, and readings that were not numbers.
        self._unplaced = 0
        self._unreadable = 0
        self._locations: dict[tuple[str, str], tuple[float, float]] = {}
        # (service, path) of each robot location followed → the marker it feeds.
        self._robot_markers: dict[tuple[str, str], str] = {}
        # (service, path) of each camera's markers followed → the markers its latest list fed.
        self._camera_sightings: dict[tuple[str, str], tuple[str, ...]] = {}
        # The cell each object of a camera's last list was in, by the object's own id.
        self._camera_cells: dict[tuple[str, str], dict[str, tuple[int, int] | None]] = {}
        self._follows: list[Follow] = []
        self._depths: dict[int, int] = {}
        self._notices: dict[str, asyncio.TimerHandle] = {}
        self._unwatch: Callable[[], None] | None = None

    # -- properties ----------------------------------------------------------------------

    @property
    def sources(
        self,
    ) -> Annotated[
        list[Any],
        Prop(
            doc="each source: (service role pattern state paths); role: markers, robots, readings or "
            "locations (of the readings); state: starting, absent, retrying, idle or following"
        ),
    ]:
        return [[f.service, f.role, f.pattern or "-", f.state, f.following] for f in self._follows]

    @property
    def skipped(
        self,
    ) -> Annotated[
        list[Any],
        Prop(
            doc="readings put on no layer: (unplaced N) came before their location, (unreadable N) were "
            "not numbers"
        ),
    ]:
        return [["unplaced", self._unplaced], ["unreadable", self._unreadable]]

    @query(
        doc="markers by class, inside area (x0 y0 x1 y1), with fields where=color=(1 0 0)&..., "
        "nearest to near (x y) first; class is also accepted for kind"
    )
    def find(
        self, *, kind: str = "", near: str = "", area: str = "", where: str = "", count: int = 10
    ) -> str:
        """Up to ``count`` fused markers as a list of markers, ``(<marker>..</marker> ...)``."""
        if not 1 <= count <= MAX_FIND:
            raise InvalidArgument(f"count must be from 1 to {MAX_FIND}, got {count}")
        centre = _numbers(near, 2, "near", "(x y)") if near else None
        box = _numbers(area, 4, "area", "(x0 y0 x1 y1)") if area else None
        found = self.fusion.find(
            kind,
            None if centre is None else (centre[0], centre[1]),
            None if box is None else (box[0], box[1], box[2], box[3]),
            count,
            _fields(where),
        )
        return write_marker_list([fused_marker(m) for m in found])

    @action(
        doc="fuse one marker seen (location, and class, id, variance or confidence, colour...); "
        "answers the fused marker's id"
    )
    def observe(self, marker: Marker, *, source: str = "observe") -> str:
        """Fuse ``marker`` as a camera's sighting by ``source``; its cell counts on ``occupancy``."""
        if not source or len(source) > 64:
            raise InvalidArgument("source is 1 to 64 characters")
        try:
            obs = observation_of(marker, source, self._camera_variance, "object")
        except (ValueFormatError, ValueError) as e:
            raise InvalidArgument(str(e)) from None
        return self.fuse(obs, occupancy=True).marker.id

    @action(doc="forget every marker and every grid value")
    def clear(self) -> None:
        for marker in self.fusion.clear():
            self._detach_marker(marker.id)
        for layer in self.layers.values():
            layer.clear()
            self._notice_layer(layer.name)
        self._notice_list()

    # -- the model, for the sources and for tests -------------------------------------------

    def fuse(self, obs: Observation, *, occupancy: bool) -> Update:
        """Fuse ``obs`` now; with ``occupancy`` its position counts as a hit on ``occupancy``."""
        update = self.fusion.observe(obs, self._clock())
        for gone in update.evicted:
            self._detach_marker(gone.id)
        marker = update.marker
        if update.created:
            node = MarkerNode(self.fusion, marker.id)
            self._marker_nodes[marker.id] = node
            self.markers.attach(marker.id, node)
            self.count = len(self.fusion)
            self._notice_list()
        else:
            known = self._marker_nodes.get(marker.id)
            if known is not None:
                known.changed()
        if occupancy:
            hits = self.layers[OCCUPANCY]
            assert isinstance(hits, HitLayer)
            hits.add(obs.position[0], obs.position[1])
            self._notice_layer(OCCUPANCY)
        return update

    def record(self, layer: str, x: float, y: float, value: float) -> bool:
        """Put a reading taken at (x, y) on a mean layer; False when it falls outside the grid."""
        target = self.layers.get(layer)
        if not isinstance(target, MeanLayer):
            raise InvalidArgument(f"no mean layer {layer!r}: the layers are {', '.join(self.layers)}")
        placed = target.add(x, y, value)
        if placed:
            self._notice_layer(layer)
        return placed

    def expire(self) -> list[str]:
        """Forget the markers not seen for ``ttl`` seconds; returns their ids.

        A robot whose location is followed counts as seen: its Listen would have told of a move.
        So does a marker in a followed camera's latest list: a camera tells only of changes, and a
        still scene is still in view.
        """
        now = self._clock()
        for marker_id in set(self._robot_markers.values()):
            self.fusion.touch(marker_id, now)
        for sighted in self._camera_sightings.values():
            for marker_id in sighted:
                self.fusion.touch(marker_id, now)
        gone = self.fusion.expire(now)
        for marker in gone:
            self._detach_marker(marker.id)
        return [m.id for m in gone]

    def layer_npy(self, layer: str) -> bytes:
        return self._layer_node(layer).npy()

    def layer_png(self, layer: str) -> bytes:
        return self._layer_node(layer).png()

    # -- lifecycle -------------------------------------------------------------------------

    async def start(self) -> None:
        self._ps_spawn(self._expire_loop(), "environment: expiry")
        directory = self._directory
        if directory is None:
            return
        for sel in self._marker_sources:
            self._start(
                Follow(
                    sel.service,
                    fixed(sel.pattern or "markers"),
                    self._camera_markers(sel.service),
                    self._camera_gone(sel.service),
                    role="markers",
                ),
                directory,
            )
        for sel in self._robot_sources:
            self._start(
                Follow(
                    sel.service,
                    _robot_pattern(sel),
                    self._robot_location(sel.service),
                    self._robot_gone(sel.service),
                    role="robots",
                ),
                directory,
            )
        for reading in self._readings:
            service = reading.selector.service
            pattern = reading.selector.pattern
            assert pattern is not None
            key = len(self._follows)
            self._start(
                Follow(
                    service,
                    self._location_pattern(key, reading),
                    self._location_of(service),
                    self._location_gone(service),
                    role="locations",
                ),
                directory,
            )
            self._start(
                Follow(
                    service,
                    fixed(pattern),
                    self._reading(service, key, reading.layer),
                    _ignore,
                    role="readings",
                ),
                directory,
            )

        def on_directory(name: str, backend: object) -> None:
            for follow in self._follows:
                if follow.service == name:
                    if backend is None:
                        follow.service_left()
                    else:
                        follow.service_joined()

        self._unwatch = directory.watch(on_directory)

    async def stop(self) -> None:
        if self._unwatch is not None:
            self._unwatch()
            self._unwatch = None
        for handle in self._notices.values():
            handle.cancel()
        self._notices.clear()

    def _start(self, follow: Follow, directory: Directory) -> None:
        self._follows.append(follow)
        self._ps_spawn(follow.run(directory.backend), f"environment: follow {follow.service} {follow.role}")

    async def _expire_loop(self) -> None:
        period = min(self.ttl / 4, EXPIRY_SWEEP_S)
        while True:
            await asyncio.sleep(period)
            self.expire()

    # -- what the sources bring ----------------------------------------------------------------

    def _camera_markers(self, service: str) -> Callable[[str, str], None]:
        def on_value(path: str, value: str) -> None:
            self._camera_sightings.pop((service, path), None)
            try:
                seen = parse_marker_list(value)
            except PropertyError as e:
                log.debug("environment: %s/%s: %s", service, path, e.message)
                return
            fed: list[str] = []
            # A camera sends its whole list whenever anything in view changes: an object that
            # stays in its cell is not a new sighting of it and does not count on occupancy again.
            before = self._camera_cells.pop((service, path), {})
            cells: dict[str, tuple[int, int] | None] = {}
            for marker in seen:
                try:
                    obs = observation_of(marker, service, self._camera_variance, "object")
                except (PropertyError, ValueError) as e:
                    log.debug("environment: a marker of %s/%s: %s", service, path, e)
                    continue
                cell = self.spec.index(obs.position[0], obs.position[1])
                fresh = not obs.id or obs.id not in before or before[obs.id] != cell
                fed.append(self.fuse(obs, occupancy=fresh).marker.id)
                if obs.id and len(cells) < MAX_LIST_MARKERS:
                    cells[obs.id] = cell
            self._camera_sightings[(service, path)] = tuple(fed)
            self._camera_cells[(service, path)] = cells

        return on_value

    def _camera_gone(self, service: str) -> Callable[[str], None]:
        def on_gone(path: str) -> None:
            self._camera_sightings.pop((service, path), None)
            self._camera_cells.pop((service, path), None)

        return on_gone

    def _robot_location(self, service: str) -> Callable[[str, str], None]:
        def on_value(path: str, value: str) -> None:
            where = _position(value)
            if where is None:
                return
            segments = path.split(".")
            name = segments[-2] if len(segments) >= 2 else service
            obs = Observation.at(ROBOT_CLASS, where, self._robot_variance, name, id=name)
            self._robot_markers[(service, path)] = self.fuse(obs, occupancy=False).marker.id

        return on_value

    def _robot_gone(self, service: str) -> Callable[[str], None]:
        def on_gone(path: str) -> None:
            self._robot_markers.pop((service, path), None)

        return on_gone

    def _location_pattern(self, key: int, reading: Reading) -> Callable[[list[str]], str | None]:
        pattern = reading.selector.pattern
        assert pattern is not None

        def choose(names: list[str]) -> str | None:
            depth = location_depth(pattern, reading.location, names)
            if depth is None:
                return None
            self._depths[key] = depth
            return ".".join([*pattern.split(".")[:depth], "location"])

        return choose

    def _location_of(self, service: str) -> Callable[[str, str], None]:
        def on_value(path: str, value: str) -> None:
            where = _position(value)
            if where is None:
                self._locations.pop((service, path), None)
            else:
                self._locations[(service, path)] = (where[0], where[1])

        return on_value

    def _location_gone(self, service: str) -> Callable[[str], None]:
        def on_gone(path: str) -> None:
            self._locations.pop((service, path), None)

        return on_gone

    def _reading(self, service: str, key: int, layer: str) -> Callable[[str, str], None]:
        def on_value(path: str, value: str) -> None:
            if not value:
                return
            try:
                reading = parse_number(value)
            except PropertyError:
                self._unreadable += 1
                self.changed("skipped")
                return
            depth = self._depths.get(key)
            where = None if depth is None else self._locations.get((service, location_path(path, depth)))
            if where is None:
                self._unplaced += 1
                self.changed("skipped")
                return
            self.record(layer, where[0], where[1], reading)

        return on_value

    # -- notices -----------------------------------------------------------------------------

    def _detach_marker(self, marker_id: str) -> None:
        if self._marker_nodes.pop(marker_id, None) is not None:
            self.markers.detach(marker_id)
        self.count = len(self.fusion)
        self._notice_list()

    def _notice_list(self) -> None:
        self._notice("", LIST_NOTICE_S, self.markers.changed)

    def _notice_layer(self, name: str) -> None:
        node = self.layer_nodes.get(name)
        if node is not None:
            self._notice(name, GRID_NOTICE_S, lambda: node.layer_changed(f"grid.{name}"))

    def _notice(self, key: str, delay: float, fire: Callable[[], None]) -> None:
        """Call ``fire`` within ``delay`` seconds, once for however many notices come meanwhile."""
        if key in self._notices:
            return
        try:
            loop = asyncio.get_running_loop()
        except RuntimeError:  # no loop (a test of the object alone): at once
            fire()
            return

        def later() -> None:
            self._notices.pop(key, None)
            fire()

        self._notices[key] = loop.call_later(delay, later)

    def _layer_node(self, layer: str) -> LayerNode:
        node = self.layer_nodes.get(layer)
        if node is None:
            raise InvalidArgument(f"no layer {layer!r}: the layers are {', '.join(self.layers)}")
        return node


def _ignore(path: str) -> None:
    pass


def _robot_pattern(sel: Selector) -> Callable[[list[str]], str | None]:
    """The robots' locations of ``sel``: its pattern, or ``robots.*.location`` of a group, or ``location``."""
    if sel.pattern is not None:
        return fixed(sel.pattern)

    def choose(names: list[str]) -> str | None:
        if any(n.startswith("robots.") and n.endswith(".location") for n in names):
            return "robots.*.location"
        return "location" if "location" in names else None

    return choose


def _position(text: str) -> tuple[float, float, float] | None:
    """x y z of a location vector (2, 3 or 6 numbers); None when there is none."""
    try:
        vector: Vector = parse_vector(text)
    except PropertyError:
        return None
    if len(vector) < 2 or not all(math.isfinite(float(v)) for v in vector[:3]):
        return None
    z = float(vector[2]) if len(vector) >= 3 else 0.0
    return float(vector[0]), float(vector[1]), z


def _fields(where: str) -> dict[str, str]:
    """``colour=red&source=camera1`` → the fields a marker must have (each equal)."""
    wanted: dict[str, str] = {}
    for pair in where.split("&") if where else ():
        name, equals, value = pair.partition("=")
        if not equals or not name.strip():
            raise InvalidArgument(f"where is field=value pairs joined by &, got {where!r}")
        wanted[name.strip()] = value.strip()
    return wanted


def _numbers(text: str, n: int, what: str, form: str) -> list[float]:
    try:
        vector = parse_vector(text)
    except PropertyError:
        raise InvalidArgument(f"{what} is {form}, got {text!r}") from None
    if len(vector) != n:
        raise InvalidArgument(f"{what} is {form}: {n} numbers, got {len(vector)}")
    return [float(v) for v in vector]
