"""The State Machine Service: charts bound to Property Services, exposed as properties like every service.

========================  ====================================================================
property                  meaning
========================  ====================================================================
``machines``              the machines loaded, ``(patrol docking)``
``M.definition``          the chart (SCXML, or the same model in JSON or YAML); a Set loads a new
                          machine ``M`` or replaces a stopped one
``M.start`` / ``M.stop``  actions: run the chart from its initial state / stop it (its active
                          states are exited, their ``onexit`` runs)
``M.remove``              action: remove the machine (stopped) and its stored chart
``M.events``              action: a Set sends the event named by the value (``data=`` parameter:
                          the event's data)
``M.state``               the stable configuration (at the end of the latest macrostep), ``(patrol goto)``
``M.status``              ``stopped``, ``running``, ``done`` or ``failed: why``
``M.variables``           the chart's variables as JSON
``M.log``                 the latest transitions, actions and errors, one a line (bounded)
``M.diagram``             an SVG of the chart with the active states marked
========================  ====================================================================

Charts reach other services through the gateway's directory (see
:mod:`services.apps.statemachine.binding`), and the gateway's rules check every Get,
Set and Listen a chart makes as the subject it runs as: the subject whose Set of
``M.start`` started it last; a chart the configuration loads runs as the
subject ``run_as`` names for its machine (``run_as = {patrol = "operator"}``),
or, started by the configuration (``autostart``) with none named, as the
service itself, unchecked, until a Set replaces its chart or starts it again.

With ``storage = "NAME"`` every chart that is loaded by a Set is written to that storage service as
``FOLDER/M.scxml`` (``.json``, ``.yaml`` after its format), removed with its
machine, and every stored chart is loaded again when the service starts.
"""

from __future__ import annotations

import asyncio
import collections
import importlib.resources
import json
import logging
import math
import re
import time
from collections.abc import Iterable, Mapping
from typing import Annotated, Any

from services.apps.statemachine.binding import DEFAULT_ACTION_TIMEOUT, PropertyBinding
from services.apps.statemachine.chart import Chart, compile_chart
from services.apps.statemachine.diagram import render_svg
from services.apps.statemachine.expressions import format_chart_value, parse_chart_value
from services.apps.statemachine.interpreter import Interpreter
from services.kernel.core import Prop, Resource, action, read_write
from services.kernel.directory import CALLER, Directory, own_work
from services.kernel.errors import (
    DeadlineExceeded,
    FailedPrecondition,
    InvalidArgument,
    NotFound,
    PropertyError,
    ResourceExhausted,
)
from services.kernel.paths import validate_service_name
from services.kernel.values import as_text, format_names, parse_names

__all__ = ["MAX_LOG_ENTRIES", "MAX_MACHINES", "Machine", "StateMachineService", "shipped_chart"]

log = logging.getLogger(__name__)

#: Machines in one service unless its ``max_machines`` option says otherwise.
MAX_MACHINES = 32
#: Lines ``M.log`` keeps (the oldest go first), each clipped to :data:`MAX_LOG_LINE`.
MAX_LOG_ENTRIES = 200
MAX_LOG_LINE = 200
#: Seconds a stop waits for a busy step (a Set under its timeout) before cancelling it, beyond the timeout.
_STOP_GRACE = 1.0
#: Prefix of a chart shipped with the package: ``builtin:patrol``.
BUILTIN = "builtin:"
_EXTENSIONS = {"scxml": "scxml", "json": "json", "yaml": "yaml"}


def shipped_chart(name: str) -> str:
    """The text of a chart shipped in ``services/apps/statemachine/charts/`` (``patrol``)."""
    folder = importlib.resources.files("services.apps.statemachine").joinpath("charts")
    for ext in _EXTENSIONS.values():
        item = folder.joinpath(f"{name}.{ext}")
        if item.is_file():
            return item.read_text(encoding="utf-8")
    known = sorted(p.name.rpartition(".")[0] for p in folder.iterdir() if p.is_file())
    raise InvalidArgument(f"no chart {name!r} is shipped; there are: {', '.join(known)}")


def _read_chart_file(spec: str) -> str:
    if spec.startswith(BUILTIN):
        return shipped_chart(spec[len(BUILTIN) :])
    try:
        with open(spec, encoding="utf-8") as f:
            return f.read()
    except OSError as e:
        raise InvalidArgument(f"cannot read the chart file {spec!r}: {e.strerror or e}") from None


class Machine(Resource):
    """One state machine: its chart, its run, its log."""

    def __init__(self, owner: StateMachineService, name: str) -> None:
        self._owner = owner
        self._name = name
        self._chart: Chart | None = None
        self._run: Interpreter | None = None
        self._log: collections.deque[str] = collections.deque(maxlen=MAX_LOG_ENTRIES)
        self._lock = asyncio.Lock()
        #: The chart loaded now is the configuration's (its ``run_as`` applies to it).
        self._configured = False

    # -- what clients see ------------------------------------------------------------

    @read_write(
        gui="code", doc="the chart (SCXML, JSON or YAML): a Set loads it, or replaces it while stopped"
    )
    async def definition(self, text: str | None = None, /) -> str:
        """Get: the chart's text; Set: load it (the machine must be stopped)."""
        if text is None:
            return self._chart.source if self._chart is not None else ""
        await self._owner.define(self._name, text)
        return ""

    @action(doc="run the chart from its initial state")
    async def start(self) -> None:
        async with self._lock:
            if self._chart is None:
                raise FailedPrecondition(f"machine {self._name} has no chart: Set {self._name}.definition")
            if self._run is not None and self._run.running:
                raise FailedPrecondition(f"machine {self._name} is already running; stop it first")
            named = self._owner.run_as.get(self._name) if self._configured else None
            self._run = Interpreter(
                self._chart,
                self._owner.binding,
                self._refresh,
                self.journal,
                name=self._name,
                watched=lambda: bool(self._ps_watch.get("state")),
                # The configured subject, else whoever starts it now (None: the configuration).
                caller=named if named is not None else CALLER.get(),
            )
            self.journal("start")
            self._run.start()
            self._refresh()

    @action(doc="stop the chart: its active states are exited (their onexit runs)")
    async def stop(self) -> None:
        await self.halt()

    @action(doc="remove this machine (stopped) and its stored chart")
    async def remove(self) -> None:
        await self._owner.remove(self._name)

    @action(doc="send the event named by the value; the parameter data is the event's data")
    async def events(self, name: str, *, data: str = "") -> None:
        run = self._run
        if run is None or not run.running:
            raise FailedPrecondition(f"machine {self._name} is not running: Set {self._name}.start first")
        event = check_client_event(name)
        run.send(event, parse_chart_value(data) if data else None, origin="Set")

    @property
    def state(
        self,
    ) -> Annotated[str, Prop(doc="the active states at the end of the latest macrostep")]:
        return format_names(self._run.stable if self._run is not None else ())

    @property
    def status(self) -> Annotated[str, Prop(doc="stopped, running, done, or failed: why")]:
        run = self._run
        if run is None:
            return "stopped"
        return f"failed: {run.reason}" if run.status == "failed" else run.status

    @property
    def variables(self) -> Annotated[str, Prop(doc="the chart's variables, as JSON")]:
        run = self._run
        values = run.variables if run is not None else {}
        return json.dumps({k: _jsonable(v) for k, v in values.items()}, sort_keys=True)

    @property
    def log(
        self,
    ) -> Annotated[str, Prop(doc=f"the latest {MAX_LOG_ENTRIES} transitions, actions and errors")]:
        return "\n".join(self._log)

    @property
    def diagram(self) -> Annotated[str, Prop(gui="statechart", doc="SVG of the chart, active states marked")]:
        if self._chart is None:
            return ""
        active = list(self._run.stable) if self._run is not None else []
        return render_svg(self._chart, active)

    # -- inside ------------------------------------------------------------------------

    # Plain methods, not properties: the class wrapper would serve a property to clients.
    def loaded_chart(self) -> Chart | None:
        """The chart loaded now, if any."""
        return self._chart

    def is_running(self) -> bool:
        return self._run is not None and self._run.running

    def journal(self, entry: str) -> None:
        ms = int(time.time() * 1000)
        seconds, ms = divmod(ms, 1000)
        minutes, second = divmod(seconds, 60)
        hours, minute = divmod(minutes, 60)
        line = f"{hours % 24:02d}:{minute:02d}:{second:02d}.{ms:03d} {entry}"
        self._log.append(line if len(line) <= MAX_LOG_LINE else line[: MAX_LOG_LINE - 1] + "…")
        self.changed("log")

    def load(self, chart: Chart, *, configured: bool = False) -> None:
        """Load ``chart`` (``configured``: the configuration's, which its ``run_as`` applies to)."""
        if self.is_running():
            raise FailedPrecondition(f"machine {self._name} is running; stop it before replacing its chart")
        self._chart = chart
        self._configured = configured
        self._run = None
        self.journal(f"loaded ({chart.format}, {len(chart.states)} states)")
        for warning in chart.warnings:
            self.journal(f"warning: {warning}")
        self._refresh()
        self.changed("definition")

    async def halt(self) -> None:
        run = self._run
        if run is None or not run.running:
            return
        self.journal("stop")
        await run.stop(self._owner.binding.timeout + _STOP_GRACE)
        self._refresh()

    def _refresh(self) -> None:
        for name in ("state", "status", "variables", "diagram"):
            self.changed(name)


#: An event a client may send: dotted names of letters, digits, ``_`` and ``-`` (as a chart's).
_CLIENT_EVENT = re.compile(r"[A-Za-z0-9_-]+(?:\.[A-Za-z0-9_-]+)*")
#: First segments of the events the machine raises itself (W3C SCXML 5.10.2 reserves error.* and
#: done.*; a chart's transitions trust them to come from the machine, with their data).
RESERVED_EVENT_PREFIXES = ("error", "done")
#: What a machine name is, for a stored chart whose file name is none.
MACHINE_NAME_RULE = "1 to 64 letters, digits, '_' or '-' (one path segment, no dots)"


def check_client_event(name: str) -> str:
    """``name`` when a client may send it as an event; InvalidArgument naming the rule it breaks."""
    event = name.strip()
    if "*" in event:
        raise InvalidArgument(
            f"event {event[:40]!r} refused: '*' is a pattern of a transition's event attribute, not an event"
        )
    if not event or len(event) > 128 or _CLIENT_EVENT.fullmatch(event) is None:
        raise InvalidArgument(
            "an event is one name of at most 128 letters, digits, '_' or '-', in dotted parts "
            f"like 'go' or 'sensor.hot'; got {name[:40]!r}"
        )
    first = event.split(".", 1)[0]
    if first in RESERVED_EVENT_PREFIXES:
        raise InvalidArgument(
            f"event {event!r} refused: names starting with 'error' or 'done' are raised by the machine "
            "itself (error.execution, error.action, done.state.ID) and cannot be sent"
        )
    return event


def _jsonable(value: Any) -> Any:
    if value is None or isinstance(value, bool | int | str):
        return value
    if isinstance(value, float):
        return value if math.isfinite(value) else str(value)
    if isinstance(value, list | tuple):
        return [_jsonable(v) for v in value]
    return format_chart_value(value)


class StateMachineService(Resource):
    """Machines that run charts bound to Property Services (see the module documentation)."""

    resource_type = "statemachine"

    def __init__(
        self,
        *,
        directory: Directory,
        charts: Mapping[str, str] | None = None,
        autostart: Iterable[str] = (),
        storage: str = "",
        folder: str = "statecharts",
        action_timeout: float = DEFAULT_ACTION_TIMEOUT,
        max_machines: int = MAX_MACHINES,
        run_as: Mapping[str, str] | None = None,
    ) -> None:
        if not (
            isinstance(action_timeout, int | float) and math.isfinite(action_timeout) and action_timeout > 0
        ):
            raise InvalidArgument(
                f"action_timeout must be a positive number of seconds, not {action_timeout!r}"
            )
        if isinstance(max_machines, bool) or not isinstance(max_machines, int) or max_machines < 1:
            raise InvalidArgument(f"max_machines must be a positive integer, not {max_machines!r}")
        if charts is not None and (
            not isinstance(charts, Mapping)
            or not all(isinstance(k, str) and isinstance(v, str) for k, v in charts.items())
        ):
            raise InvalidArgument('charts is a table of name = "builtin:NAME" or a file path')
        if isinstance(autostart, str) or not all(isinstance(name, str) for name in autostart):
            raise InvalidArgument('autostart is a list of machine names, like ["patrol"]')
        if run_as is not None and (
            not isinstance(run_as, Mapping)
            or not all(isinstance(k, str) and isinstance(v, str) and v for k, v in run_as.items())
        ):
            raise InvalidArgument('run_as is a table of machine name = "SUBJECT", like {patrol = "operator"}')
        #: Machine → the subject its configured chart runs as.
        self.run_as: dict[str, str] = dict(run_as or {})
        if storage:
            validate_service_name(storage)
        if not all(part and all(c.isalnum() or c in "_-" for c in part) for part in folder.split("/")):
            raise InvalidArgument(f"folder {folder!r}: relative path segments of letters, digits, _ and -")
        self._directory = directory
        self.binding = PropertyBinding(directory, float(action_timeout))
        self._storage = storage
        self._folder = folder
        self._max = max_machines
        self._machines: dict[str, Machine] = {}
        self._autostart = list(autostart)
        for name, spec in (charts or {}).items():
            try:
                validate_service_name(name)
                self._put(name, compile_chart(name, _read_chart_file(spec)), configured=True)
            except InvalidArgument as e:
                raise InvalidArgument(f"chart {name!r} ({spec}): {e.message}") from None
        for name in self.run_as:
            if name not in self._machines:
                raise InvalidArgument(f"run_as names {name!r}, which is not among the charts")
        for name in self._autostart:
            if name not in self._machines:
                raise InvalidArgument(f"autostart names {name!r}, which is not among the charts")

    @property
    def machines(self) -> Annotated[str, Prop(doc="the machines loaded")]:
        return format_names(self._machines)

    def create_on_set(self, name: str, rest: str) -> bool:
        """A Set of ``M.definition`` for a machine not loaded yet makes machine ``M`` (loaded by that Set)."""
        if rest != "definition":
            return False
        if len(self._machines) >= self._max:
            raise ResourceExhausted(f"this service holds at most {self._max} machines")
        self._put(name, None)
        return True

    def _put(self, name: str, chart: Chart | None, *, configured: bool = False) -> Machine:
        machine = self._machines.get(name)
        if machine is None:
            if len(self._machines) >= self._max:
                raise ResourceExhausted(f"this service holds at most {self._max} machines")
            machine = Machine(self, name)
            self.attach(name, machine)
            self._machines[name] = machine
            self.changed("machines")
        if chart is not None:
            machine.load(chart, configured=configured)
        return machine

    def _remove(self, name: str) -> None:
        if self._machines.pop(name, None) is not None:
            self.detach(name)
            self.changed("machines")

    def machine(self, name: str) -> Machine:
        found = self._machines.get(name)
        if found is None:
            raise NotFound(f"no machine {name!r}; there are: {format_names(self._machines)}")
        return found

    async def define(self, name: str, text: str) -> None:
        """Load ``text`` as machine ``name`` (remove it, for an empty text); store it when configured."""
        machine = self.machine(name)
        if machine.is_running():
            raise FailedPrecondition(
                f"machine {name} is running; stop it before replacing or removing its chart"
            )
        if not text.strip():
            self._remove(name)
            await self._store(name, None)
            return
        try:
            chart = compile_chart(name, text)
        except PropertyError:
            if machine.loaded_chart() is None:
                self._remove(name)  # made by this Set: a chart that does not load leaves nothing behind
            raise
        machine.load(chart)
        await self._store(name, chart)

    async def remove(self, name: str) -> None:
        """Remove machine ``name`` (it must be stopped) and its stored chart."""
        if self.machine(name).is_running():
            raise FailedPrecondition(f"machine {name} is running; stop it before removing it")
        self._remove(name)
        await self._store(name, None)

    # -- storage -------------------------------------------------------------------------

    async def _store(self, name: str, chart: Chart | None) -> None:
        if not self._storage:
            return
        # Keeping the chart is the service's own work, not a write for the client who loaded it.
        with own_work():
            await self._write_stored(name, chart)

    async def _write_stored(self, name: str, chart: Chart | None) -> None:
        backend = self._directory.backend(self._storage)
        limit = self.binding.timeout
        try:
            async with asyncio.timeout(limit):
                for ext in _EXTENSIONS.values():
                    keep = chart is not None and ext == _EXTENSIONS[chart.format]
                    if keep and chart is not None:
                        await backend.set("file", chart.source, {"name": f"{self._folder}/{name}.{ext}"})
                    elif await self._stored(backend, f"{self._folder}/{name}.{ext}"):
                        await backend.set("file", "", {"name": f"{self._folder}/{name}.{ext}"})
        except TimeoutError:
            raise DeadlineExceeded(
                f"the chart is loaded but not stored: storage {self._storage!r} did not answer in {limit:g} s"
            ) from None
        except PropertyError as e:
            why = f"the chart is loaded but not stored in {self._storage!r}: {e.message}"
            raise PropertyError(why, e.code) from None

    async def _stored(self, backend: Any, rel: str) -> bool:
        return rel in parse_names(await backend.get("files"))

    async def _load_stored(self) -> None:
        try:
            backend = self._directory.backend(self._storage)
            async with asyncio.timeout(self.binding.timeout):
                files = parse_names(as_text(await backend.get("files"), "files"))
                prefix = self._folder + "/"
                for rel in files:
                    stem, dot, ext = rel[len(prefix) :].rpartition(".")
                    if (
                        not rel.startswith(prefix)
                        or not dot
                        or ext not in _EXTENSIONS.values()
                        or "/" in stem
                    ):
                        continue
                    try:
                        validate_service_name(stem)
                    except InvalidArgument:
                        log.warning(
                            "statemachine: stored chart %s skipped: %r is not a machine name; a machine "
                            "name is %s",
                            rel,
                            stem,
                            MACHINE_NAME_RULE,
                        )
                        continue
                    stored = await backend.get("file", {"name": rel})
                    try:
                        text = as_text(stored, rel)
                        self._put(stem, compile_chart(stem, text))
                    except PropertyError as e:
                        log.warning("statemachine: stored chart %s not loaded: %s", rel, e.message)
                    else:
                        log.info("statemachine: loaded machine %s from %s/%s", stem, self._storage, rel)
        except TimeoutError:
            log.warning("statemachine: storage %r did not answer; no stored charts loaded", self._storage)
        except PropertyError as e:
            log.warning("statemachine: stored charts not loaded from %r: %s", self._storage, e.message)

    # -- lifecycle -------------------------------------------------------------------------

    async def start(self) -> None:
        if self._storage:
            await self._load_stored()
        # Started by the configuration, whichever call woke the service (a dormant one).
        with own_work():
            for name in self._autostart:
                await self._machines[name].start()

    async def stop(self) -> None:
        await asyncio.gather(*(m.halt() for m in self._machines.values()), return_exceptions=True)
