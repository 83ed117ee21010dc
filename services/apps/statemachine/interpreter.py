"""Running one chart: the SCXML algorithm (W3C SCXML 1.0, Appendix D) over its checked model.

One asyncio task per running machine takes events from a bounded queue and
runs macrosteps: eventless transitions and internal events until the
configuration is stable, then the next external event. Executable content
runs in document order and may wait (a ``ps:set`` awaits the service's
answer under its time limit); events arriving meanwhile queue up. An error
in executable content skips the rest of its block and raises an internal
event the chart can handle: ``error.execution`` for an expression that
failed, ``error.action`` for a Set, Get or Listen that failed or ran out of
time (``_event.data`` has ``service``, ``property``, ``code`` and ``message``).

Bounds: :data:`MAX_QUEUED_EVENTS` external and internal events,
:data:`MAX_TIMERS` delayed events waiting, :data:`MAX_MICROSTEPS` steps in one
macrostep (an eventless loop stops the machine with status ``failed``).
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import functools
import logging
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

from services.apps.statemachine.binding import PropertyBinding
from services.apps.statemachine.chart import (
    MAX_DELAY,
    MAX_FOREACH,
    SCXML_PROCESSOR,
    SEND_TYPES,
    Action,
    Assign,
    Cancel,
    Chart,
    Content,
    Foreach,
    If,
    Listen,
    Log,
    Param,
    PropertyGet,
    PropertySet,
    Raise,
    Send,
    State,
    Transition,
    is_variable_name,
    parse_duration,
)
from services.apps.statemachine.expressions import (
    FUNCTIONS,
    EvaluationError,
    Expression,
    Record,
    check_size,
    format_chart_value,
    parse_chart_value,
)
from services.kernel.backend import Change, Subscription, close_quietly
from services.kernel.directory import context_for
from services.kernel.errors import NotFound, PropertyError, ResourceExhausted
from services.kernel.values import Value

__all__ = ["MAX_ACTIONS", "MAX_MICROSTEPS", "MAX_QUEUED_EVENTS", "MAX_TIMERS", "Event", "Interpreter"]

log = logging.getLogger(__name__)

#: Events waiting in each of a machine's queues (external and internal).
MAX_QUEUED_EVENTS = 1000
#: Delayed events (``<send delay=...>``) waiting at once in one machine.
MAX_TIMERS = 1000
#: Steps in one macrostep before the machine is stopped as looping without waiting for an event.
#: A mission's chart takes a handful; a thousand is a loop, and each step may cost a
#: 64 KiB expression, so the bound also caps what one macrostep can take of the event loop.
MAX_MICROSTEPS = 1000
#: Steps run before the machine lets other tasks of the event loop run.
_STEPS_PER_TURN = 100
#: Actions (executable content: an assign, a log, a ps:set, ...) one macrostep may run before the
#: machine is stopped: nested ``foreach`` loops multiply (a thousand items each), and no bound on
#: steps catches what runs inside one step.
MAX_ACTIONS = 100_000
#: Actions run before the machine lets other tasks of the event loop run.
_ACTIONS_PER_TURN = 100


@dataclass(slots=True)
class Event:
    """An event as ``_event`` shows it (W3C SCXML 5.10.1); empty fields read as None."""

    name: str
    data: Any = None
    kind: str = "external"
    origin: str = ""
    sendid: str = ""
    origintype: str = ""

    def record(self) -> Record:
        return Record(
            {
                "name": self.name,
                "type": self.kind,
                "sendid": self.sendid or None,
                "origin": self.origin or None,
                "origintype": self.origintype or None,
                "invokeid": None,  # a chart invokes nothing
                "data": self.data,
            }
        )


class _FollowFailed(EvaluationError):
    """``value('SERVICE/PATH')`` of a property the machine could not follow: ``error.action``."""

    def __init__(self, service: str, path: str, error: PropertyError) -> None:
        super().__init__(f"value('{service}/{path}'): {error.code.name}: {error.message}")
        self.service = service
        self.path = path
        self.error = error


@dataclass(eq=False, slots=True)
class _Follow:
    """One property the chart reads with ``value(...)``: its Listen and its latest value."""

    service: str
    path: str
    subscription: Subscription | None = None
    value: Any = None
    error: PropertyError | None = None


class _BlockFailed(Exception):
    """Executable content failed; the rest of its block is skipped (the error event is already queued)."""


class _Stopped(Exception):
    """The machine stopped itself (an eventless loop, a full queue)."""


@dataclass(eq=False, slots=True)
class _ActiveListen:
    spec: Listen
    subscription: Subscription | None = None
    active: bool = True
    last: bool = False
    value: Value | None = None


@dataclass(slots=True)
class _Timer:
    handle: asyncio.TimerHandle
    send_id: str


def _covered(child: State, entering: set[State]) -> bool:
    return any(e is child or e.is_descendant(child) for e in entering)


def _matches(descriptors: Iterable[str], name: str) -> bool:
    """SCXML event matching: ``error`` matches ``error`` and ``error.action``; ``*`` matches every event."""
    for d in descriptors:
        if d in ("*", ".*"):
            return True
        stem = d.removesuffix(".*")
        if name == stem or name.startswith(stem + "."):
            return True
    return False


@dataclass(eq=False)
class Interpreter:
    """One run of a chart; ``on_change`` is called when a macrostep ended (a new stable configuration).

    :attr:`stable` is the configuration at the end of the latest macrostep (W3C SCXML: only
    that one is stable; those passed through by eventless transitions and internal events
    inside a macrostep are not). ``M.state`` shows it; the journal gets every transition.
    """

    chart: Chart
    binding: PropertyBinding
    on_change: Callable[[], None]
    journal: Callable[[str], None]
    name: str = ""
    #: True while someone listens to the configuration: each step then gives them a turn to take it.
    watched: Callable[[], bool] = lambda: False
    #: Who the chart's Gets, Sets and Listens are made for (:data:`services.kernel.directory.CALLER`):
    #: checked against the gateway's rules as that subject; None: as the service's own work.
    caller: object | None = None
    configuration: set[State] = field(default_factory=set)
    variables: dict[str, Any] = field(default_factory=dict)
    status: str = "stopped"
    reason: str = ""
    #: The active state ids, outermost first, at the end of the latest macrostep.
    stable: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        self._external: asyncio.Queue[Event | None] = asyncio.Queue(MAX_QUEUED_EVENTS)
        self._internal: collections.deque[Event] = collections.deque()
        self._history: dict[str, list[State]] = {}
        self._listens: dict[State, list[_ActiveListen]] = {}
        self._timers: dict[int, _Timer] = {}
        self._timer_ids = 0
        self._task: asyncio.Task[None] | None = None
        self._stopping = False
        self._event: Event | None = None
        #: Actions run in the current macrostep (MAX_ACTIONS).
        self._actions = 0
        self._follows: dict[str, _Follow] = {}
        self._functions = {**FUNCTIONS, "In": self._in, "value": self._followed_value}
        self.transitions = 0
        #: Ids made up for sends without one (``idlocation``), counted per run.
        self._send_ids = 0
        #: States whose ``<data>`` has its value (``binding="late"``: set when first entered).
        self._bound: set[str] = set()
        #: The chart's own address as a send target (and its events' origin).
        self._address = location = f"#_scxml_{self.session_id}"
        #: ``_event`` of the event taken last, made once per event, not once per expression.
        self._recorded: tuple[Event | None, Record | None] = (None, None)
        processor = Record({"location": location})
        self._system = {
            "_sessionid": self.session_id,
            "_name": self.chart.chart_name or self.name,
            "_ioprocessors": Record({SCXML_PROCESSOR: processor, "scxml": processor}),
        }

    @property
    def session_id(self) -> str:
        """``_sessionid``: the machine's name, unique in its service (``#_scxml_`` + it is its address)."""
        return self.name

    # -- outside ---------------------------------------------------------------

    @property
    def running(self) -> bool:
        return self._task is not None and not self._task.done()

    def start(self) -> None:
        """Start the machine's task (the initial configuration is entered there)."""
        self.status = "running"
        self.reason = ""
        self._task = asyncio.get_running_loop().create_task(
            self._run(), name=f"statemachine {self.name}", context=context_for(self.caller)
        )

    def send(self, name: str, data: Any = None, origin: str = "") -> None:
        """Queue an external event; ResourceExhausted when the queue is full."""
        try:
            self._external.put_nowait(Event(name, data, "external", origin))
        except asyncio.QueueFull:
            raise ResourceExhausted(
                f"machine {self.name}: {MAX_QUEUED_EVENTS} events are already waiting; event {name!r} refused"
            ) from None

    async def stop(self, wait: float) -> None:
        """Stop: the current step ends, the active states are exited (their onexit runs), timers end.

        After ``wait`` seconds a machine still busy (a Set that does not answer) is cancelled.
        """
        task = self._task
        if task is None or task.done():
            return
        self._stopping = True
        if task is asyncio.current_task():
            return  # the chart stopped itself: its loop ends at the next event
        with contextlib.suppress(asyncio.QueueFull):
            self._external.put_nowait(None)
        done, _ = await asyncio.wait([task], timeout=wait)
        if not done:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)

    def active_ids(self) -> list[str]:
        return [s.id for s in sorted(self.configuration, key=lambda s: s.order)]

    # -- the main loop -------------------------------------------------------------

    async def _run(self) -> None:
        try:
            self._actions = 0
            await self._open_follows()
            self._init_data()
            await self._microstep([self.chart.root.initial] if self.chart.root.initial else [], None)
            await self._main_loop()
            if self.status == "done":
                self.journal("done")
            await self._exit_interpreter()
        except _Stopped as e:
            self.status, self.reason = "failed", str(e)
            self.journal(f"stopped: {e}")
            await self._exit_interpreter(run_onexit=False)
        except asyncio.CancelledError:
            self.status = "stopped"
            await self._exit_interpreter(run_onexit=False)
            raise
        except Exception as e:  # a bug must not leave a machine half running
            log.exception("machine %s failed", self.name)
            self.status, self.reason = "failed", f"internal error: {type(e).__name__}"
            await self._exit_interpreter(run_onexit=False)
        finally:
            self._cancel_timers()
            self.on_change()

    async def _main_loop(self) -> None:
        while not self._finished():
            await self._macrostep()
            if self._finished():
                return
            moved = self._settle()
            self._retest_listens()
            if (moved and self.watched()) or not self._external.empty():
                # One turn of the event loop: a Listen stream on `state` takes this configuration
                # before the next macrostep replaces it (a stream conflates what it has not taken
                # yet). And when the get below would not wait, a chart that sends itself events
                # without a delay, forever, would hold the event loop: let the gateway (and a stop) in.
                await asyncio.sleep(0)
                if self._stopping:
                    return
            event = await self._external.get()
            if event is None or self._stopping:
                return
            self._event = event
            self._actions = 0  # a new macrostep
            enabled = self._select_transitions(event)
            if enabled:
                await self._microstep(enabled, event)

    def _settle(self) -> bool:
        """A macrostep ended: its configuration is the stable one. True when it differs from the last."""
        now = tuple(self.active_ids())
        moved = now != self.stable
        self.stable = now
        self.on_change()
        return moved

    def _finished(self) -> bool:
        return self._stopping or self.status != "running"

    async def _macrostep(self) -> None:
        steps = 0
        while not self._finished():
            trigger: Event | None = None  # an eventless transition; `_event` keeps the last event
            enabled = self._select_transitions(None)
            if not enabled:
                if not self._internal:
                    return
                self._event = trigger = self._internal.popleft()
                enabled = self._select_transitions(self._event)
            if enabled:
                await self._microstep(enabled, trigger)
            steps += 1
            if steps >= MAX_MICROSTEPS:
                raise _Stopped(
                    f"more than {MAX_MICROSTEPS} steps without waiting for an event (an endless loop?)"
                )
            if steps % _STEPS_PER_TURN == 0:
                await asyncio.sleep(0)

    async def _exit_interpreter(self, *, run_onexit: bool = True) -> None:
        self._actions = 0  # the exit is a step of its own
        for state in sorted(self.configuration, key=lambda s: s.order, reverse=True):
            if run_onexit:
                for block in state.onexit:
                    await self._run_block(block)
            await self._close_listens(state)
        if self.status != "done":  # a finished machine keeps showing where it ended
            self.configuration.clear()
        self.stable = tuple(self.active_ids())
        await self._close_follows()
        if self.status == "running":
            self.status = "stopped"

    # -- selecting transitions -------------------------------------------------------

    def _select_transitions(self, event: Event | None) -> list[Transition]:
        enabled: list[Transition] = []
        atomic = sorted((s for s in self.configuration if s.is_atomic), key=lambda s: s.order)
        for state in atomic:
            for s in [state, *state.proper_ancestors()]:
                chosen = next((t for t in s.transitions if self._enabled(t, event)), None)
                if chosen is not None:
                    if chosen not in enabled:
                        enabled.append(chosen)
                    break
        return self._remove_conflicts(enabled)

    def _enabled(self, t: Transition, event: Event | None) -> bool:
        if event is None:
            if t.events:
                return False
        elif not t.events or not _matches(t.events, event.name):
            return False
        if t.cond is None:
            return True
        try:
            return bool(self._evaluate(t.cond))
        except EvaluationError as e:
            self._expression_failed(e, t.where)
            return False

    def _remove_conflicts(self, enabled: list[Transition]) -> list[Transition]:
        filtered: list[Transition] = []
        if len(enabled) < 2:
            return enabled
        for t1 in enabled:
            preempted = False
            remove: list[Transition] = []
            exit1 = self._exit_set([t1])
            for t2 in filtered:
                if exit1 & self._exit_set([t2]):
                    if t1.source.is_descendant(t2.source):
                        remove.append(t2)
                    else:
                        preempted = True
                        break
            if not preempted:
                filtered = [t for t in filtered if t not in remove]
                filtered.append(t1)
        return filtered

    # -- one microstep ---------------------------------------------------------------

    async def _microstep(self, enabled: list[Transition], trigger: Event | None) -> None:
        """Take ``enabled``; ``trigger`` is the event that selected them (None: eventless), for the log."""
        self.transitions += 1
        before = self.active_ids()
        await self._exit_states(enabled)
        for t in enabled:
            await self._run_block(t.actions)
        await self._enter_states(enabled)
        after = self.active_ids()
        if before != after or any(t.targets for t in enabled):  # a state left and entered again too
            on = f" on {trigger.name}" if trigger is not None else ""
            self.journal(f"{' '.join(before) or '()'} -> {' '.join(after) or '()'}{on}")

    def _effective_targets(self, t: Transition) -> list[State]:
        targets: list[State] = []
        for s in t.targets:
            if s.kind == "history":
                if s.id in self._history:
                    found = self._history[s.id]
                else:
                    assert s.initial is not None
                    found = self._effective_targets(s.initial)
            else:
                found = [s]
            targets.extend(x for x in found if x not in targets)
        return targets

    def _domain(self, t: Transition) -> State | None:
        targets = self._effective_targets(t)
        if not targets:
            return None
        if t.source.kind == "root":
            return t.source  # the chart's initial transition
        if t.internal and t.source.is_compound and all(s.is_descendant(t.source) for s in targets):
            return t.source
        return self._lcca([t.source, *targets])

    @staticmethod
    def _lcca(states: list[State]) -> State:
        for anc in states[0].proper_ancestors():
            if anc.is_compound and all(s.is_descendant(anc) for s in states[1:]):
                return anc
        raise AssertionError("every state is inside the root")

    def _exit_set(self, transitions: list[Transition]) -> set[State]:
        out: set[State] = set()
        for t in transitions:
            if t.targets:
                domain = self._domain(t)
                out.update(s for s in self.configuration if domain is not None and s.is_descendant(domain))
        return out

    async def _exit_states(self, enabled: list[Transition]) -> None:
        leaving = sorted(self._exit_set(enabled), key=lambda s: s.order, reverse=True)
        for s in leaving:
            for h in s.history:
                if h.deep:
                    atoms = [x for x in self.configuration if x.is_atomic and x.is_descendant(s)]
                    self._history[h.id] = atoms
                else:
                    self._history[h.id] = [x for x in self.configuration if x.parent is s]
        for s in leaving:
            await self._close_listens(s)
            for block in s.onexit:
                await self._run_block(block)
            self.configuration.discard(s)

    async def _enter_states(self, enabled: list[Transition]) -> None:
        entering: set[State] = set()
        default_entry: set[State] = set()
        history_content: dict[State, list[Action]] = {}
        for t in enabled:
            for s in t.targets:
                self._add_descendants(s, entering, default_entry, history_content)
            domain = self._domain(t)
            for s in self._effective_targets(t):
                self._add_ancestors(s, domain, entering, default_entry, history_content)
        for s in sorted(entering, key=lambda x: x.order):
            self.configuration.add(s)
            if self.chart.late and s.id not in self._bound:
                self._bound.add(s.id)
                self._bind(self.chart.state_data.get(s.id, ()))
            for block in s.onentry:
                await self._run_block(block)
            if s in default_entry and s.initial is not None:
                await self._run_block(s.initial.actions)
            if s in history_content:
                await self._run_block(history_content[s])
            await self._open_listens(s)
            if s.kind == "final":
                self._entered_final(s)

    def _entered_final(self, s: State) -> None:
        parent = s.parent
        if parent is None or parent.kind == "root":
            self.status = "done"
            return
        data = None
        if s.donedata is not None:
            with contextlib.suppress(_BlockFailed):  # error.execution is queued, before the done event
                done = s.donedata
                data = self._event_data((), done.params, done.content, done.where, "")
        self._queue_internal(Event(f"done.state.{parent.id}", data, "internal"))
        grand = parent.parent
        if (
            grand is not None
            and grand.kind == "parallel"
            and all(self._in_final(child) for child in grand.children if child.kind != "history")
        ):
            self._queue_internal(Event(f"done.state.{grand.id}", None, "internal"))

    def _in_final(self, s: State) -> bool:
        if s.kind == "compound":
            return any(c.kind == "final" and c in self.configuration for c in s.children)
        if s.kind == "parallel":
            return all(self._in_final(c) for c in s.children if c.kind != "history")
        return False

    def _add_descendants(
        self, s: State, entering: set[State], default: set[State], content: dict[State, list[Action]]
    ) -> None:
        if s.kind == "history":
            assert s.parent is not None
            if s.id in self._history:
                targets = self._history[s.id]
            else:
                assert s.initial is not None
                content[s.parent] = s.initial.actions
                targets = list(s.initial.targets)
            for x in targets:
                self._add_descendants(x, entering, default, content)
            for x in targets:
                self._add_ancestors(x, s.parent, entering, default, content)
            return
        entering.add(s)
        if s.kind == "compound":
            default.add(s)
            assert s.initial is not None
            for x in s.initial.targets:
                self._add_descendants(x, entering, default, content)
            for x in s.initial.targets:
                self._add_ancestors(x, s, entering, default, content)
        elif s.kind == "parallel":
            for child in s.children:
                if child.kind != "history" and not _covered(child, entering):
                    self._add_descendants(child, entering, default, content)

    def _add_ancestors(
        self,
        s: State,
        upto: State | None,
        entering: set[State],
        default: set[State],
        content: dict[State, list[Action]],
    ) -> None:
        for anc in s.proper_ancestors(upto):
            if anc.kind == "root":
                continue
            entering.add(anc)
            if anc.kind == "parallel":
                for child in anc.children:
                    if child.kind != "history" and not _covered(child, entering):
                        self._add_descendants(child, entering, default, content)

    def _in(self, state_id: Any) -> bool:
        return any(s.id == state_id for s in self.configuration)

    # -- data and expressions ------------------------------------------------------------

    def _init_data(self) -> None:
        for name, _ in self.chart.data:
            self.variables[name] = None
        data = self.chart.state_data.get("", []) if self.chart.late else self.chart.data
        self._bind(data)

    def _bind(self, data: Iterable[tuple[str, Expression | None]]) -> None:
        for name, expr in data:
            if expr is None:
                continue
            try:
                self.variables[name] = check_size(self._evaluate(expr))
            except _FollowFailed as e:
                self._expression_failed(e, "")
            except EvaluationError as e:
                self._error_execution(f"data {name}: {e}", "")

    def _evaluate(self, expr: Expression, extra: Mapping[str, Any] | None = None) -> Any:
        event = self._event
        if event is not self._recorded[0]:
            # ``_event`` is unbound (None) before the first event.
            self._recorded = (event, event.record() if event is not None else None)
        scope: dict[str, Any] = {**self.variables, **self._system, "_event": self._recorded[1]}
        if extra:
            scope.update(extra)
        return expr.evaluate(scope, self._functions)

    def _queue_internal(self, event: Event) -> None:
        if len(self._internal) >= MAX_QUEUED_EVENTS:
            raise _Stopped(f"more than {MAX_QUEUED_EVENTS} internal events waiting (a loop of <raise>?)")
        self._internal.append(event)

    def _error_execution(self, message: str, where: str, sendid: str = "") -> None:
        self._error_event("error.execution", message, where, sendid)

    def _error_event(self, name: str, message: str, where: str, sendid: str = "") -> None:
        self.journal(f"{name}: {where + ': ' if where else ''}{message}")
        data = Record({"message": message, "where": where})
        self._queue_internal(Event(name, data, "platform", sendid=sendid))

    def _expression_failed(self, e: EvaluationError, where: str) -> None:
        """An expression failed: error.action when it read a property not followed, else error.execution."""
        if isinstance(e, _FollowFailed):
            self._error_action(e.service, e.path, e.error, where)
        else:
            self._error_execution(str(e), where)

    def _error_action(self, service: str, path: str, e: PropertyError, where: str) -> None:
        self.journal(f"error.action: {service}/{path}: {e.code.name}: {e.message}")
        log.warning("machine %s: %s/%s failed: %s: %s", self.name, service, path, e.code.name, e.message)
        data = Record(
            {"service": service, "property": path, "code": e.code.name, "message": e.message, "where": where}
        )
        self._queue_internal(Event("error.action", data, "platform"))

    # -- executable content ---------------------------------------------------------------

    async def _run_block(self, block: list[Action]) -> None:
        try:
            for action in block:
                await self._act(action)
        except _BlockFailed:
            pass

    def _kept(self, value: Any, where: str) -> Any:
        """``value``, when it is small enough to keep in a variable or an event (check_size)."""
        try:
            return check_size(value)
        except EvaluationError as e:
            self._error_execution(str(e), where)
            raise _BlockFailed from None

    def _value(self, expr: Expression, where: str, extra: Mapping[str, Any] | None = None) -> Any:
        try:
            return self._evaluate(expr, extra)
        except EvaluationError as e:
            self._expression_failed(e, where)
            raise _BlockFailed from None

    async def _act(self, action: Action) -> None:
        self._actions += 1
        if self._actions > MAX_ACTIONS:
            raise _Stopped(f"more than {MAX_ACTIONS} actions without waiting for an event (an endless loop?)")
        if self._actions % _ACTIONS_PER_TURN == 0:
            await asyncio.sleep(0)
        if isinstance(action, Raise):
            self._queue_internal(Event(action.event, None, "internal"))
        elif isinstance(action, Assign):
            if action.location not in self.variables:
                self._error_execution(self._not_writable("assign to", action.location), action.where)
                raise _BlockFailed
            self.variables[action.location] = self._kept(self._value(action.expr, action.where), action.where)
        elif isinstance(action, Log):
            value = format_chart_value(self._value(action.expr, action.where)) if action.expr else ""
            self.journal(f"log {action.label}: {value}".rstrip(": "))
        elif isinstance(action, If):
            for cond, body in action.branches:
                if cond is None or self._value(cond, action.where):
                    for inner in body:
                        await self._act(inner)
                    break
        elif isinstance(action, Foreach):
            await self._foreach(action)
        elif isinstance(action, Send):
            self._send(action)
        elif isinstance(action, Cancel):
            send_id = action.send_id
            if action.sendidexpr is not None:
                send_id = format_chart_value(self._value(action.sendidexpr, action.where))
            for key, timer in list(self._timers.items()):
                if timer.send_id == send_id:
                    timer.handle.cancel()
                    del self._timers[key]
        elif isinstance(action, PropertySet):
            await self._property_set(action)
        elif isinstance(action, PropertyGet):
            await self._property_get(action)

    @staticmethod
    def _not_writable(what: str, location: str) -> str:
        if location.startswith("_") and location in ("_event", "_sessionid", "_name", "_ioprocessors"):
            return f"{what} {location!r}, a system variable (read-only)"
        if not is_variable_name(location):
            return f"{what} {location[:60]!r}, which is not a variable's name"
        return f"{what} {location!r}, which is not declared in <datamodel>"

    async def _foreach(self, action: Foreach) -> None:
        for location in (action.item, action.index):
            if location and not is_variable_name(location):
                self._error_execution(self._not_writable("foreach into", location), action.where)
                raise _BlockFailed
        items = self._value(action.array, action.where)
        if not isinstance(items, list | tuple | str):
            self._error_execution(f"foreach over a {type(items).__name__}", action.where)
            raise _BlockFailed
        if len(items) > MAX_FOREACH:
            self._error_execution(f"foreach over more than {MAX_FOREACH} items", action.where)
            raise _BlockFailed
        for index, item in enumerate(list(items)):
            self.variables[action.item] = self._kept(item, action.where)
            if action.index:
                self.variables[action.index] = index
            for inner in action.body:
                await self._act(inner)

    def _send(self, action: Send) -> None:
        where = action.where
        send_id = action.send_id
        if not send_id and action.idlocation:
            self._send_ids += 1
            send_id = f"{self.session_id}.send{self._send_ids}"
        if action.idlocation:
            if action.idlocation not in self.variables:
                self._error_execution(self._not_writable("idlocation", action.idlocation), where)
                raise _BlockFailed
            self.variables[action.idlocation] = send_id
        name = action.event
        if action.eventexpr is not None:
            name = format_chart_value(self._value(action.eventexpr, where))
        assert name is not None
        target = action.target
        if action.targetexpr is not None:
            target = format_chart_value(self._value(action.targetexpr, where))
        kind = action.type
        if action.typeexpr is not None:
            kind = format_chart_value(self._value(action.typeexpr, where))
        if kind not in SEND_TYPES:
            self._error_execution(
                f"type {kind[:60]!r}: the only event processor is {SCXML_PROCESSOR}", where, send_id
            )
            raise _BlockFailed
        internal = target == "#_internal"
        if target and not internal and target != self._address:
            if target.startswith("#_scxml_"):
                # W3C SCXML 6.2.4: a session that cannot be reached is error.communication.
                why = f"target {target[:60]!r}: no such session; a chart sends only to itself"
                self._error_event("error.communication", why, where, send_id)
            else:
                self._error_execution(f"target {target[:60]!r}: a chart sends only to itself", where, send_id)
            raise _BlockFailed
        event_data = (
            self._event_data(action.namelist, action.params, action.content, where, send_id)
            if action.params or action.namelist or action.content is not None
            else None
        )
        delay = action.delay
        if action.delayexpr is not None:
            raw = self._value(action.delayexpr, where)
            seconds = parse_duration(raw) if isinstance(raw, str) else raw
            if (
                isinstance(seconds, bool)
                or not isinstance(seconds, int | float)
                or not 0 <= seconds <= MAX_DELAY
            ):
                bad = (
                    f"delayexpr gave {raw!r}, not a time like '1s' or '500ms' or seconds up to {MAX_DELAY:g}"
                )
                self._error_execution(bad, where, send_id)
                raise _BlockFailed
            delay = float(seconds)
        if internal:  # W3C SCXML 6.2.4: to the internal queue, after what is there already
            self._queue_internal(Event(name, event_data, "internal", sendid=action.send_id))
            return
        event = Event(name, event_data, "external", self._address, action.send_id, SCXML_PROCESSOR)
        if delay <= 0:
            self._post(event)
            return
        if len(self._timers) >= MAX_TIMERS:
            self._error_execution(f"more than {MAX_TIMERS} delayed events waiting", action.where)
            raise _BlockFailed
        self._timer_ids += 1
        key = self._timer_ids

        def fire() -> None:
            self._timers.pop(key, None)
            self._post(event)

        handle = asyncio.get_running_loop().call_later(delay, fire)
        self._timers[key] = _Timer(handle, send_id)

    def _event_data(
        self, namelist: Iterable[str], params: list[Param], content: Content | None, where: str, send_id: str
    ) -> Any:
        """The data of an event: ``<content>``'s value, or a record of the namelist and the params
        (None when there are none); _BlockFailed (error.execution queued) when one cannot be read."""
        if content is not None:
            if content.expr is None:
                return content.value
            return self._kept(self._value(content.expr, content.where), content.where)
        data: dict[str, Any] = {}
        for variable in namelist:
            if variable not in self.variables:
                self._error_execution(self._not_writable("namelist names", variable), where, send_id)
                raise _BlockFailed
            data[variable] = self.variables[variable]
        for param in params:
            if param.expr is None:
                if param.location not in self.variables:
                    self._error_execution(
                        self._not_writable("param reads", param.location), param.where, send_id
                    )
                    raise _BlockFailed
                data[param.name] = self.variables[param.location]
            else:
                data[param.name] = self._kept(self._value(param.expr, param.where), param.where)
        return Record(data) if data else None

    def _post(self, event: Event) -> None:
        """An event the chart sent itself: to the external queue, as SCXML's <send> does."""
        try:
            self._external.put_nowait(event)
        except asyncio.QueueFull:
            self.journal(f"event {event.name} dropped: {MAX_QUEUED_EVENTS} events already waiting")
            log.warning("machine %s: event %s dropped, the queue is full", self.name, event.name)

    def _cancel_timers(self) -> None:
        for timer in self._timers.values():
            timer.handle.cancel()
        self._timers.clear()

    def _params(self, params: list[tuple[str, str | Expression]], where: str) -> dict[str, str]:
        return {n: v if isinstance(v, str) else format_chart_value(self._value(v, where)) for n, v in params}

    async def _property_set(self, action: PropertySet) -> None:
        if action.expr is not None:
            value = format_chart_value(self._value(action.expr, action.where))
        else:
            value = action.value or ""
        params = self._params(action.params, action.where)
        target = f"{action.service}/{action.path}"
        try:
            await self.binding.set(action.service, action.path, value, params, action.timeout)
        except PropertyError as e:
            self._error_action(action.service, action.path, e, action.where)
            raise _BlockFailed from None
        self.journal(f"set {target} {value[:80]}".rstrip())
        if action.done:
            self._queue_internal(Event(action.done, None, "internal"))

    async def _property_get(self, action: PropertyGet) -> None:
        if action.location not in self.variables:
            undeclared = f"ps:get into {action.location!r}, which is not declared in <datamodel>"
            self._error_execution(undeclared, action.where)
            raise _BlockFailed
        params = self._params(action.params, action.where)
        try:
            text = await self.binding.get(action.service, action.path, params, action.timeout)
        except PropertyError as e:
            self._error_action(action.service, action.path, e, action.where)
            raise _BlockFailed from None
        self.variables[action.location] = parse_chart_value(text)

    # -- properties read by value(...) --------------------------------------------------

    async def _open_follows(self) -> None:
        """One Listen (and a Get of the current value) on each property the chart reads with value()."""
        for service, path in self.chart.followed:
            follow = _Follow(service, path)
            self._follows[f"{service}/{path}"] = follow
            try:
                follow.subscription = await self.binding.listen(
                    service, path, functools.partial(self._follow_changed, follow)
                )
                text = await self.binding.get(service, path)
            except PropertyError as e:
                follow.error = e
                self.journal(f"follow {service}/{path}: {e.code.name}: {e.message}")
                log.warning("machine %s: cannot follow %s/%s: %s", self.name, service, path, e.message)
                continue
            if follow.error is None and follow.value is None:
                follow.value = parse_chart_value(text)

    @staticmethod
    def _follow_changed(follow: _Follow, change: Change) -> None:
        if change.removed:
            follow.error = NotFound(f"{follow.service}/{follow.path} was removed")
            follow.value = None
        else:
            follow.error = None
            follow.value = parse_chart_value(change.value)

    async def _close_follows(self) -> None:
        follows, self._follows = self._follows, {}
        for follow in follows.values():
            if follow.subscription is not None:
                await close_quietly(follow.subscription)

    def _followed_value(self, prop: Any) -> Any:
        """``value('SERVICE/PATH')``: the latest value heard, read without waiting."""
        follow = self._follows.get(str(prop))
        if follow is None:  # the chart's properties are followed from the start: a stopped machine
            raise EvaluationError(f"value({prop!r}): the machine does not follow it now")
        if follow.error is not None:
            raise _FollowFailed(follow.service, follow.path, follow.error)
        return follow.value

    # -- listens -------------------------------------------------------------------------

    async def _open_listens(self, state: State) -> None:
        if not state.listens:
            return
        opened = self._listens.setdefault(state, [])
        for spec in state.listens:
            active = _ActiveListen(spec)
            opened.append(active)
            try:
                active.subscription = await self.binding.listen(
                    spec.service,
                    spec.path,
                    lambda change, a=active: self._heard(a, change),  # type: ignore[misc]
                )
                current = await self.binding.get(spec.service, spec.path)
            except PropertyError as e:
                self._error_action(spec.service, spec.path, e, spec.where)
                continue
            if active.active:
                self._test(active, current)

    async def _close_listens(self, state: State) -> None:
        for active in self._listens.pop(state, []):
            active.active = False
            if active.subscription is not None:
                await close_quietly(active.subscription)

    def _heard(self, active: _ActiveListen, change: Change) -> None:
        if active.active and not change.removed:
            self._test(active, change.value)

    def _retest_listens(self) -> None:
        """A condition reads chart variables too (a new threshold): test it again with the last value."""
        for listens in self._listens.values():
            for active in listens:
                if active.active and active.value is not None and active.spec.cond is not None:
                    self._test(active, active.value)

    def _test(self, active: _ActiveListen, text: Value) -> None:
        active.value = text
        spec = active.spec
        value = parse_chart_value(text)
        if spec.cond is None:
            hit, edge = True, True
        else:
            try:
                hit = bool(self._evaluate(spec.cond, {"_value": value}))
            except EvaluationError as e:
                hit = False
                if active.last or not active.active:
                    return
                self.journal(f"listen {spec.service}/{spec.path}: {e}")
            edge = hit and not active.last
        active.last = hit
        if edge:
            origin = f"{spec.service}/{spec.path}"
            try:
                self._external.put_nowait(Event(spec.event, value, "external", origin))
            except asyncio.QueueFull:
                self.journal(f"event {spec.event} from {origin} dropped: the queue is full")
