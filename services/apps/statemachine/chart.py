"""A chart's model, compiled from its document and checked once, when it is loaded.

The supported SCXML subset (docs/statemachine.md lists it): ``scxml``,
``state``, ``parallel``, ``final``, ``initial``, ``history`` (shallow and
deep), ``transition`` (event, cond, target, type), ``onentry``, ``onexit``,
``datamodel``/``data`` (early or late binding), ``donedata``, and the
executable content ``raise``, ``send`` (to the chart itself, with ``delay``,
``param``/``namelist`` or ``content``), ``cancel``, ``assign``, ``log``,
``if``/``elseif``/``else`` and ``foreach``; plus the Property Service binding
``ps:set``, ``ps:get`` (executable content) and ``ps:listen`` (in a state).
``script`` and ``invoke`` would run code or other documents and are refused.
Every expression is checked by :mod:`services.apps.statemachine.expressions`; what
the standard wants to fail when it runs (text that is no expression, a write to
a system variable) loads with a warning (:attr:`Chart.warnings`) and raises
``error.execution`` there.
"""

from __future__ import annotations

import json
import math
import re
from contextvars import ContextVar
from dataclasses import dataclass, field
from typing import Any, Literal

from services.apps.statemachine.document import ChartError, Node, read_document
from services.apps.statemachine.expressions import (
    FUNCTIONS,
    NOT_AN_EXPRESSION,
    EvaluationError,
    Expression,
    Record,
    check_size,
    compile_expression,
    parse_chart_value,
)
from services.kernel.errors import InvalidArgument
from services.kernel.paths import validate_path, validate_service_name

__all__ = [
    "MAX_FOLLOWED",
    "MAX_STATES",
    "MAX_TIMEOUT",
    "MAX_TRANSITIONS",
    "Action",
    "Assign",
    "Cancel",
    "Chart",
    "Content",
    "DoneData",
    "Foreach",
    "If",
    "Listen",
    "Log",
    "Param",
    "PropertyGet",
    "PropertySet",
    "Raise",
    "Send",
    "State",
    "Transition",
    "compile_chart",
]

#: Most states in one chart.
MAX_STATES = 256
#: Most transitions in one chart.
MAX_TRANSITIONS = 1024
#: Longest delay of a ``send``, seconds: a day (a mission waits hours, not weeks).
MAX_DELAY = 86400.0
#: Longest ``timeout`` of an action (``ps:set``, ``ps:get``), seconds: ten minutes, the gateway's
#: longest call; an action's timeout is more than 0 (``timeout="0"`` is refused at load: it would
#: fail every action that waits, yet pass one that an in-process service answers at once).
MAX_TIMEOUT = 600.0
#: Most properties one chart reads with ``value('SERVICE/PATH')``: the machine holds one Listen on
#: each while it runs.
MAX_FOLLOWED = 32
#: Most iterations of one ``foreach``.
MAX_FOREACH = 1000

_ID = re.compile(r"[A-Za-z_][A-Za-z0-9_.-]{0,63}")
_EVENT = re.compile(r"[A-Za-z0-9_*][A-Za-z0-9_.*-]{0,127}|\.\*")
_VARIABLE = re.compile(r"[A-Za-z][A-Za-z0-9_]{0,63}")
_DURATION = re.compile(r"\s*([0-9]+(?:\.[0-9]*)?|\.[0-9]+)\s*(ms|s|m|min|h)?\s*")
#: The SCXML event processor, the one ``<send>`` type there is (W3C SCXML, appendix C.1); ``scxml``
#: is its short name.
SCXML_PROCESSOR = "http://www.w3.org/TR/scxml/#SCXMLEventProcessor"
SEND_TYPES = ("", SCXML_PROCESSOR, "scxml")
#: Send targets that reach other sessions through ``<invoke>``, which a chart never does.
_INVOKE_TARGETS = ("#_parent", "#_invoke_")
#: The system variables (W3C SCXML 5.10): read-only, every expression may read them.
SYSTEM_VARIABLES = ("_event", "_sessionid", "_name", "_ioprocessors")

StateKind = Literal["root", "atomic", "compound", "parallel", "final", "history"]


@dataclass(eq=False, slots=True)
class Raise:
    event: str
    where: str


@dataclass(eq=False, slots=True)
class Param:
    """``<param name expr|location>`` of a ``<send>`` or a ``<donedata>``: one field of the event's data."""

    name: str
    expr: Expression | None
    #: A variable read by name: one not declared is error.execution when the data is made.
    location: str
    where: str


@dataclass(eq=False, slots=True)
class Content:
    """``<content expr>`` or ``<content>text</content>``: the whole data of an event. Text arrives with
    its white space collapsed; JSON text as records and lists, a number or a vector as one."""

    expr: Expression | None
    text: str
    where: str
    #: The text's value, made once when the chart is loaded.
    value: Any = None


@dataclass(eq=False, slots=True)
class DoneData:
    """``<donedata>`` of a ``<final>``: the data of the ``done.state.ID`` event its parent raises."""

    params: list[Param]
    content: Content | None
    where: str


@dataclass(eq=False, slots=True)
class Send:
    """``<send>`` to the chart itself: its external queue, or ``#_internal`` its internal one."""

    event: str | None
    eventexpr: Expression | None
    delay: float
    delayexpr: Expression | None
    send_id: str
    params: list[Param]
    where: str
    content: Content | None = None
    #: ``""`` (the external queue), ``#_internal``, or any other text: error.execution when sent.
    target: str = ""
    targetexpr: Expression | None = None
    #: The event processor: ``""`` or :data:`SCXML_PROCESSOR` (others: error.execution when sent).
    type: str = ""
    typeexpr: Expression | None = None
    #: A variable that gets the send's id (the ``id`` given, or one made up for each send).
    idlocation: str = ""
    #: Variables whose values go in the event's data, by their names.
    namelist: tuple[str, ...] = ()


@dataclass(eq=False, slots=True)
class Cancel:
    send_id: str
    where: str
    sendidexpr: Expression | None = None


@dataclass(eq=False, slots=True)
class Assign:
    location: str
    expr: Expression
    where: str


@dataclass(eq=False, slots=True)
class Log:
    label: str
    expr: Expression | None
    where: str


@dataclass(eq=False, slots=True)
class If:
    branches: list[tuple[Expression | None, list[Action]]]
    where: str


@dataclass(eq=False, slots=True)
class Foreach:
    array: Expression
    item: str
    index: str
    body: list[Action]
    where: str


@dataclass(eq=False, slots=True)
class PropertySet:
    """``<ps:set property="scout1/behaviors.moveto" expr="marker(home)" timeout="5" done="sent"/>``."""

    service: str
    path: str
    value: str | None
    expr: Expression | None
    params: list[tuple[str, str | Expression]]
    timeout: float | None
    done: str
    where: str


@dataclass(eq=False, slots=True)
class PropertyGet:
    """``<ps:get property="thermo1/data" location="reading"/>``: a Get into a chart variable."""

    service: str
    path: str
    location: str
    params: list[tuple[str, str | Expression]]
    timeout: float | None
    where: str


Action = Raise | Send | Cancel | Assign | Log | If | Foreach | PropertyGet | PropertySet


@dataclass(eq=False, slots=True)
class Listen:
    """``<ps:listen property="scout1/location" event="arrived" cond="distance(_value, goal) &lt; 0.2"/>``.

    While its state is active, every value of the property is tested; the
    event is raised each time the condition becomes true (or on every value,
    without a condition).
    """

    service: str
    path: str
    event: str
    cond: Expression | None
    where: str


@dataclass(eq=False, slots=True)
class Transition:
    source: State
    events: tuple[str, ...]
    cond: Expression | None
    target_ids: tuple[str, ...]
    internal: bool
    actions: list[Action]
    where: str
    targets: tuple[State, ...] = ()

    def label(self) -> str:
        text = " ".join(self.events)
        if self.cond is not None:
            text += f" [{self.cond.text}]"
        return text.strip()


@dataclass(eq=False, slots=True)
class State:
    id: str
    kind: StateKind
    where: str
    parent: State | None = None
    order: int = 0
    depth: int = 0
    children: list[State] = field(default_factory=list)
    transitions: list[Transition] = field(default_factory=list)
    initial: Transition | None = None
    onentry: list[list[Action]] = field(default_factory=list)
    onexit: list[list[Action]] = field(default_factory=list)
    listens: list[Listen] = field(default_factory=list)
    deep: bool = False
    history: list[State] = field(default_factory=list)
    donedata: DoneData | None = None

    def __repr__(self) -> str:
        return f"State({self.id!r}, {self.kind})"

    @property
    def is_compound(self) -> bool:
        return self.kind in ("compound", "root")

    @property
    def is_atomic(self) -> bool:
        return self.kind in ("atomic", "final")

    def proper_ancestors(self, upto: State | None = None) -> list[State]:
        """Ancestors from the parent outwards, stopping before ``upto``."""
        out = []
        node = self.parent
        while node is not None and node is not upto:
            out.append(node)
            node = node.parent
        return out

    def is_descendant(self, other: State) -> bool:
        node = self.parent
        while node is not None:
            if node is other:
                return True
            node = node.parent
        return False


@dataclass(eq=False, slots=True)
class Chart:
    """A loaded chart: its states in document order, its variables, and the text it came from."""

    name: str
    format: str
    source: str
    root: State
    states: dict[str, State]
    ordered: list[State]
    data: list[tuple[str, Expression | None]]
    transitions: list[Transition]
    #: The properties the chart reads with ``value('SERVICE/PATH')``: (service, path), in order.
    followed: tuple[tuple[str, str], ...] = ()
    #: What the chart does that fails when it runs (``error.execution``), found at load: a
    #: malformed expression, an assignment to a system variable. ``M.log`` shows them on load.
    warnings: tuple[str, ...] = ()
    #: ``binding="late"``: a state's ``<data>`` gets its value when the state is first entered.
    late: bool = False
    #: The ``<data>`` of each state (late binding), by state id; the chart's own under ``""``.
    state_data: dict[str, list[tuple[str, Expression | None]]] = field(default_factory=dict)
    #: The ``name`` attribute of ``<scxml>``: ``_name`` (the machine's name when absent).
    chart_name: str = ""

    def state(self, state_id: str) -> State:
        return self.states[state_id]


# -- compiling ------------------------------------------------------------------

_STATE_TAGS = ("state", "parallel", "final", "history")
_EXECUTABLE = ("raise", "send", "cancel", "assign", "log", "if", "foreach", "ps:set", "ps:get")
_REFUSED = {
    "script": "<script> runs code and is not supported; use <assign>, <if> and the ps: elements",
    "invoke": "<invoke> starts other documents and is not supported; use another machine and ps:set",
}


def _check_attrs(node: Node, allowed: tuple[str, ...]) -> None:
    for key in node.attrs:
        if key not in allowed and not key.startswith("xmlns"):
            hint = f"; it takes {', '.join(allowed)}" if allowed else "; it takes none"
            raise node.fail(f"unknown attribute {key!r}{hint}")


#: The expressions of the chart being compiled, with their element and attribute: the names they
#: read are checked once every variable is known (:func:`_check_names`).
_COMPILED: ContextVar[list[tuple[Expression, Node, str, str]] | None] = ContextVar("_COMPILED", default=None)
#: What the chart being compiled does that will fail when it runs (Chart.warnings).
_WARNINGS: ContextVar[list[str] | None] = ContextVar("_WARNINGS", default=None)
#: Names every expression may read besides the chart's variables and functions.
_BUILT_IN_NAMES = frozenset(
    {*SYSTEM_VARIABLES, "true", "True", "false", "False", "null", "None", *FUNCTIONS, "In", "value"}
)


def _warn(node: Node, why: str) -> None:
    warnings = _WARNINGS.get()
    if warnings is not None:
        warnings.append(f"{node.where}: <{node.tag}>: {why}")


def _expr(node: Node, attr: str, text: str | None = None) -> Expression:
    source = node.attrs[attr] if text is None else text
    try:
        expression = compile_expression(source)
    except InvalidArgument as e:
        if not e.message.startswith(NOT_AN_EXPRESSION):
            raise node.fail(f"{attr}={source[:60]!r}: {e.message}") from None
        # Malformed text is an error.execution each time it is evaluated (W3C SCXML 5.9, the
        # standard's tests check the event): the chart loads, with a warning in its log.
        _warn(node, f"{attr}={source[:60]!r}: {e.message}; it raises error.execution when evaluated")
        return Expression.failing(source, e.message)
    compiled = _COMPILED.get()
    if compiled is not None:
        compiled.append((expression, node, attr, source))
    return expression


def _check_names(compiled: list[tuple[Expression, Node, str, str]], declared: set[str]) -> None:
    """Every name an expression reads is a variable (``<data>``, a ``foreach`` item or index), an
    event's or a listen's value, or a function: a misspelt name is refused at load, not at run."""
    known = declared | _BUILT_IN_NAMES
    for _, node, _, _ in compiled:
        if node.tag == "foreach":
            known |= {node.attrs.get("item", ""), node.attrs.get("index", "")} - {""}
    for expression, node, attr, source in compiled:
        for name in sorted(expression.names() - known):
            if name == "_value" and node.tag == "ps:listen" and attr == "cond":
                continue
            why = (
                "'_value' is known only in the cond of a <ps:listen>"
                if name == "_value"
                else f"{name!r} is not declared in <datamodel>"
            )
            raise node.fail(f"{attr}={source[:60]!r}: {why}")


def _duration(node: Node, attr: str, limit: float) -> float:
    text = node.attrs[attr]
    if _DURATION.fullmatch(text) is None:
        raise node.fail(f"{attr}={text!r}: expected a duration like '2s', '500ms', '1.5' (seconds) or '1min'")
    seconds = parse_duration(text, limit)
    if seconds is None:
        raise node.fail(f"{attr}={text!r}: at most {limit:g} s")
    return seconds


def _timeout(node: Node) -> float | None:
    """An action's ``timeout``: more than 0, at most :data:`MAX_TIMEOUT`; None when not given."""
    if "timeout" not in node.attrs:
        return None
    seconds = _duration(node, "timeout", MAX_TIMEOUT)
    if seconds <= 0:
        text = node.attrs["timeout"]
        raise node.fail(f"timeout={text!r}: an action's timeout is more than 0 s (at most {MAX_TIMEOUT:g} s)")
    return seconds


def _events(node: Node, text: str) -> tuple[str, ...]:
    events = tuple(text.split())
    for event in events:
        if _EVENT.fullmatch(event) is None or ".." in event:
            raise node.fail(f"bad event name {event!r}: letters, digits, _ - . and * only")
    return events


def _event(node: Node, attr: str) -> str:
    names = _events(node, node.attrs.get(attr, ""))
    if len(names) != 1 or "*" in names[0]:
        raise node.fail(f"{attr} must be one event name, like 'arrived' or 'sensor.hot'")
    return names[0]


def _variable(node: Node, attr: str) -> str:
    name = node.attrs.get(attr, "")
    if _VARIABLE.fullmatch(name) is None:
        raise node.fail(f"{attr}={name!r}: a variable name is a letter then letters, digits or _")
    return name


def _location(node: Node, attr: str, use: str = "writing") -> str:
    """A location written to at run time: one that is not a variable's name (``_sessionid``,
    ``foo.bar``) is error.execution when written (W3C SCXML 5.4), with a warning at load."""
    name = node.attrs.get(attr, "").strip()
    if _VARIABLE.fullmatch(name) is None:
        why = "a system variable, read-only" if name in SYSTEM_VARIABLES else "not a variable's name"
        _warn(node, f"{attr}={name[:60]!r}: {why}; {use} it raises error.execution")
    return name


def is_variable_name(name: str) -> bool:
    """True when ``name`` can be a chart variable (a letter, then letters, digits or _)."""
    return _VARIABLE.fullmatch(name) is not None


def parse_duration(text: str, limit: float = MAX_DELAY) -> float | None:
    """Seconds of a duration like ``2s``, ``500ms``, ``1.5`` or ``1min`` (CSS2 times and more);
    None when it is not one or is beyond ``limit``."""
    m = _DURATION.fullmatch(text)
    if m is None:
        return None
    scale = {"ms": 0.001, "s": 1.0, None: 1.0, "m": 60.0, "min": 60.0, "h": 3600.0}[m.group(2)]
    seconds = float(m.group(1)) * scale
    return seconds if math.isfinite(seconds) and seconds <= limit else None


def _property(node: Node) -> tuple[str, str]:
    """``property="scout1/behaviors.moveto"``: the service and the property path."""
    text = node.attrs.get("property", "")
    try:
        return split_property(text)
    except InvalidArgument as e:
        raise node.fail(f"property={text!r}: {e.message}") from None


def split_property(text: str) -> tuple[str, str]:
    """``SERVICE/PATH`` as (service, path); InvalidArgument saying what is wrong."""
    service, sep, path = text.partition("/")
    if not sep:
        raise InvalidArgument("expected SERVICE/PATH, like 'scout1/behaviors.moveto'")
    validate_service_name(service)
    validate_path(path)
    return service, path


def _followed(compiled: list[tuple[Expression, Node, str, str]]) -> tuple[tuple[str, str], ...]:
    """The properties the chart's expressions read with ``value(...)``, each checked, at most MAX_FOLLOWED."""
    found: dict[tuple[str, str], None] = {}
    for expression, node, attr, source in compiled:
        for text in expression.text_arguments("value"):
            try:
                key = split_property(text)
            except InvalidArgument as e:
                raise node.fail(f"{attr}={source[:60]!r}: value({text!r}): {e.message}") from None
            found[key] = None
            if len(found) > MAX_FOLLOWED:
                raise node.fail(
                    f"{attr}={source[:60]!r}: a chart reads at most {MAX_FOLLOWED} properties with value()"
                )
    return tuple(found)


def _params(node: Node) -> list[tuple[str, str | Expression]]:
    out: list[tuple[str, str | Expression]] = []
    for child in node.children:
        if child.tag != "ps:param":
            raise child.fail(f"not allowed in <{node.tag}>: it holds only <ps:param name= value=|expr=>")
        _check_attrs(child, ("name", "value", "expr"))
        name = child.attrs.get("name", "")
        if not name or ("value" in child.attrs) == ("expr" in child.attrs):
            raise child.fail("a parameter has a name and exactly one of value or expr")
        out.append((name, child.attrs["value"] if "value" in child.attrs else _expr(child, "expr")))
    return out


class _Compiler:
    def __init__(self) -> None:
        self.states: dict[str, State] = {}
        self.ordered: list[State] = []
        self.transitions: list[Transition] = []
        self.data: list[tuple[str, Expression | None]] = []
        self.state_data: dict[str, list[tuple[str, Expression | None]]] = {}
        self.send_ids: set[str] = set()

    # -- executable content ----------------------------------------------------

    def block(self, node: Node) -> list[Action]:
        return [self.action(child) for child in node.children]

    def action(self, node: Node) -> Action:
        if node.tag in _REFUSED:
            raise node.fail(_REFUSED[node.tag])
        if node.tag == "raise":
            _check_attrs(node, ("event",))
            return Raise(_event(node, "event"), node.where)
        if node.tag == "send":
            return self.send(node)
        if node.tag == "cancel":
            _check_attrs(node, ("sendid", "sendidexpr"))
            if bool(node.attrs.get("sendid")) == ("sendidexpr" in node.attrs):
                raise node.fail("needs sendid, the id of a <send>, or sendidexpr")
            if "sendidexpr" in node.attrs:
                return Cancel("", node.where, _expr(node, "sendidexpr"))
            return Cancel(node.attrs["sendid"], node.where)
        if node.tag == "assign":
            _check_attrs(node, ("location", "expr"))
            if node.children:
                raise node.children[0].fail("<assign> takes its value from expr (or its text), not elements")
            if "expr" not in node.attrs and not node.text.strip():
                raise node.fail("needs expr, the value to assign")
            value = _expr(node, "expr") if "expr" in node.attrs else _expr(node, "expr", node.text)
            return Assign(_location(node, "location"), value, node.where)
        if node.tag == "log":
            _check_attrs(node, ("label", "expr"))
            expr = _expr(node, "expr") if "expr" in node.attrs else None
            return Log(node.attrs.get("label", ""), expr, node.where)
        if node.tag == "if":
            return self.if_(node)
        if node.tag == "foreach":
            _check_attrs(node, ("array", "item", "index"))
            if "array" not in node.attrs:
                raise node.fail("needs array, an expression giving a list")
            index = _location(node, "index") if "index" in node.attrs else ""
            return Foreach(_expr(node, "array"), _location(node, "item"), index, self.block(node), node.where)
        if node.tag == "ps:set":
            return self.property_set(node)
        if node.tag == "ps:get":
            _check_attrs(node, ("property", "location", "timeout"))
            service, path = _property(node)
            return PropertyGet(
                service, path, _variable(node, "location"), _params(node), _timeout(node), node.where
            )
        if node.tag in _STATE_TAGS or node.tag in ("transition", "onentry", "onexit"):
            raise node.fail("a state element is not executable content (is it in the wrong place?)")
        raise node.fail(f"unknown element; executable content is one of {', '.join(_EXECUTABLE)}")

    def send(self, node: Node) -> Send:
        _check_attrs(
            node,
            (
                "event",
                "eventexpr",
                "delay",
                "delayexpr",
                "id",
                "idlocation",
                "target",
                "targetexpr",
                "type",
                "typeexpr",
                "namelist",
            ),
        )
        kind = node.attrs.get("type", "").strip()
        if kind.endswith("#BasicHTTPEventProcessor"):
            raise node.fail(
                f"type={kind!r}: a chart sends only SCXML events (the Basic HTTP processor is not offered)"
            )
        if ("event" in node.attrs) == ("eventexpr" in node.attrs):
            raise node.fail("needs exactly one of event or eventexpr")
        for one, other in (
            ("delay", "delayexpr"),
            ("target", "targetexpr"),
            ("type", "typeexpr"),
            ("id", "idlocation"),
        ):
            if one in node.attrs and other in node.attrs:
                raise node.fail(f"give {one} or {other}, not both")
        target = node.attrs.get("target", "").strip()
        if target.startswith(_INVOKE_TARGETS):
            raise node.fail(
                f"target={target!r}: a chart invokes no other documents, so it has no {target} to send to"
            )
        if target == "#_internal" and ("delay" in node.attrs or "delayexpr" in node.attrs):
            raise node.fail("an event sent to #_internal cannot be delayed")
        if target not in ("", "#_internal") and not target.startswith("#_scxml_"):
            _warn(node, f"target={target!r}: a chart sends only to itself; sending raises error.execution")
        if kind not in SEND_TYPES:
            _warn(node, f"type={kind!r}: not an event processor here; sending raises error.execution")
        namelist = tuple(node.attrs.get("namelist", "").split())
        params, content = self.event_data(node)
        send_id = node.attrs.get("id", "")
        if send_id:
            self.send_ids.add(send_id)
        return Send(
            event=_event(node, "event") if "event" in node.attrs else None,
            eventexpr=_expr(node, "eventexpr") if "eventexpr" in node.attrs else None,
            delay=_duration(node, "delay", MAX_DELAY) if "delay" in node.attrs else 0.0,
            delayexpr=_expr(node, "delayexpr") if "delayexpr" in node.attrs else None,
            send_id=send_id,
            params=params,
            where=node.where,
            content=content,
            target=target,
            targetexpr=_expr(node, "targetexpr") if "targetexpr" in node.attrs else None,
            type=kind,
            typeexpr=_expr(node, "typeexpr") if "typeexpr" in node.attrs else None,
            idlocation=_location(node, "idlocation") if "idlocation" in node.attrs else "",
            namelist=namelist,
        )

    def event_data(self, node: Node) -> tuple[list[Param], Content | None]:
        """The ``<param>`` and ``<content>`` children of a ``<send>`` or ``<donedata>``."""
        params: list[Param] = []
        content: Content | None = None
        for child in node.children:
            if child.tag == "content":
                _check_attrs(child, ("expr",))
                if child.children:
                    raise child.fail("XML content is not supported: give the data as text or with expr")
                if content is not None or ("expr" in child.attrs and child.text.strip()):
                    raise child.fail("one <content>, with expr or text, not both")
                expr = _expr(child, "expr") if "expr" in child.attrs else None
                content = Content(expr, child.text.strip(), child.where, _content_value(child))
            elif child.tag == "param":
                _check_attrs(child, ("name", "expr", "location"))
                name = child.attrs.get("name", "")
                if _VARIABLE.fullmatch(name) is None or ("expr" in child.attrs) == (
                    "location" in child.attrs
                ):
                    raise child.fail("a parameter has a name and one of expr or location")
                expr = _expr(child, "expr") if "expr" in child.attrs else None
                location = _location(child, "location", "reading") if "location" in child.attrs else ""
                params.append(Param(name, expr, location, child.where))
            else:
                raise child.fail(f"<{node.tag}> holds only <param name=... expr=...> and <content>")
        if content is not None and (params or node.attrs.get("namelist")):
            raise node.fail("give the data as <content> or as <param> and namelist, not both")
        return params, content

    def if_(self, node: Node) -> If:
        _check_attrs(node, ("cond",))
        if "cond" not in node.attrs:
            raise node.fail("needs cond")
        branches: list[tuple[Expression | None, list[Action]]] = [(_expr(node, "cond"), [])]
        for child in node.children:
            if child.tag == "elseif":
                _check_attrs(child, ("cond",))
                if branches[-1][0] is None or "cond" not in child.attrs:
                    raise child.fail("<elseif cond=...> comes before <else/>")
                branches.append((_expr(child, "cond"), []))
            elif child.tag == "else":
                _check_attrs(child, ())
                if branches[-1][0] is None:
                    raise child.fail("only one <else/>")
                branches.append((None, []))
            else:
                branches[-1][1].append(self.action(child))
        return If(branches, node.where)

    def property_set(self, node: Node) -> PropertySet:
        _check_attrs(node, ("property", "value", "expr", "timeout", "done"))
        service, path = _property(node)
        if ("value" in node.attrs) == ("expr" in node.attrs):
            raise node.fail('needs exactly one of value (text) or expr (an expression); value="" for none')
        return PropertySet(
            service=service,
            path=path,
            value=node.attrs.get("value"),
            expr=_expr(node, "expr") if "expr" in node.attrs else None,
            params=_params(node),
            timeout=_timeout(node),
            done=_event(node, "done") if "done" in node.attrs else "",
            where=node.where,
        )

    # -- states ----------------------------------------------------------------

    def state(self, node: Node, parent: State) -> State:
        kinds = {"state": "atomic", "parallel": "parallel", "final": "final", "history": "history"}
        allowed = {
            "state": ("id", "initial"),
            "parallel": ("id",),
            "final": ("id",),
            "history": ("id", "type"),
        }[node.tag]
        _check_attrs(node, allowed)
        state_id = node.attrs.get("id", "")
        if _ID.fullmatch(state_id) is None:
            raise node.fail(f"id={state_id!r}: a state id is a letter or _ then letters, digits, _ . or -")
        if state_id in self.states:
            raise node.fail(f"id={state_id!r} is used twice (first at {self.states[state_id].where})")
        if len(self.states) >= MAX_STATES:
            raise node.fail(f"the chart has more than {MAX_STATES} states")
        state = State(state_id, kinds[node.tag], node.where, parent, len(self.ordered), parent.depth + 1)  # type: ignore[arg-type]
        self.states[state_id] = state
        self.ordered.append(state)
        if node.tag == "history":
            if parent.kind not in ("compound", "atomic", "parallel"):
                raise node.fail("a history state belongs in a <state> or <parallel>")
            kind = node.attrs.get("type", "shallow")
            if kind not in ("shallow", "deep"):
                raise node.fail(f"type={kind!r}: 'shallow' or 'deep'")
            state.deep = kind == "deep"
            parent.history.append(state)
            transitions = [c for c in node.children if c.tag == "transition"]
            if len(transitions) != 1 or len(node.children) != 1:
                raise node.fail(
                    "a history state holds one <transition target=...>: where to go the first time"
                )
            state.initial = self.transition(transitions[0], state)
            if state.initial.events or state.initial.cond is not None:
                raise transitions[0].fail("the default transition of a history state has no event or cond")
            return state
        self.contents(node, state)
        if node.tag == "state" and any(c.kind != "history" for c in state.children):
            state.kind = "compound"
        if node.tag == "final" and (state.children or state.transitions or state.listens):
            raise node.fail("a final state holds only <onentry> and <onexit>")
        if node.tag == "state":
            self.initial(node, state)
        return state

    def contents(self, node: Node, state: State) -> None:
        for child in node.children:
            tag = child.tag
            if tag in _STATE_TAGS:
                if state.kind == "history":
                    raise child.fail("not allowed in a history state")
                state.children.append(self.state(child, state))
            elif tag == "transition":
                state.transitions.append(self.transition(child, state))
            elif tag in ("onentry", "onexit"):
                _check_attrs(child, ())
                (state.onentry if tag == "onentry" else state.onexit).append(self.block(child))
            elif tag == "datamodel":
                self.datamodel(child, state)
            elif tag == "ps:listen":
                state.listens.append(self.listen(child))
            elif tag == "donedata":
                if node.tag != "final" or state.donedata is not None:
                    raise child.fail("a <final> has at most one <donedata>, and only a <final> has one")
                _check_attrs(child, ())
                params, content = self.event_data(child)
                state.donedata = DoneData(params, content, child.where)
            elif tag == "initial":
                if node.tag != "state":
                    raise child.fail("only a <state> has an <initial>")
            elif tag in _REFUSED:
                raise child.fail(_REFUSED[tag])
            else:
                raise child.fail(f"not allowed in <{node.tag}>")

    def initial(self, node: Node, state: State) -> None:
        elements = [c for c in node.children if c.tag == "initial"]
        if state.kind != "compound":
            if elements or "initial" in node.attrs:
                raise node.fail("an atomic state has no initial state")
            return
        if elements and "initial" in node.attrs:
            raise node.fail("give the initial state as an attribute or an <initial> element, not both")
        if elements:
            element = elements[0]
            transitions = [c for c in element.children if c.tag == "transition"]
            if len(elements) > 1 or len(transitions) != 1 or len(element.children) != 1:
                raise element.fail("<initial> holds one <transition target=...>")
            state.initial = self.transition(transitions[0], state)
            if state.initial.events or state.initial.cond is not None:
                raise transitions[0].fail("the transition of <initial> has no event or cond")
        else:
            first = next(c for c in state.children if c.kind != "history")
            targets = tuple(node.attrs["initial"].split()) if "initial" in node.attrs else (first.id,)
            state.initial = Transition(state, (), None, targets, False, [], node.where)
            self.transitions.append(state.initial)

    def transition(self, node: Node, source: State) -> Transition:
        _check_attrs(node, ("event", "cond", "target", "type"))
        kind = node.attrs.get("type", "external")
        if kind not in ("external", "internal"):
            raise node.fail(f"type={kind!r}: 'external' or 'internal'")
        if len(self.transitions) >= MAX_TRANSITIONS:
            raise node.fail(f"the chart has more than {MAX_TRANSITIONS} transitions")
        targets = tuple(node.attrs.get("target", "").split())
        cond = _expr(node, "cond") if "cond" in node.attrs else None
        events = _events(node, node.attrs["event"]) if "event" in node.attrs else ()
        if "event" in node.attrs and not events:
            raise node.fail("event is empty; leave it out for a transition without an event")
        if not events and cond is None and not targets and source.kind != "history":
            raise node.fail("a transition needs an event, a cond or a target")
        t = Transition(source, events, cond, targets, kind == "internal", self.block(node), node.where)
        self.transitions.append(t)
        return t

    def listen(self, node: Node) -> Listen:
        _check_attrs(node, ("property", "event", "cond"))
        service, path = _property(node)
        cond = _expr(node, "cond") if "cond" in node.attrs else None
        return Listen(service, path, _event(node, "event"), cond, node.where)

    def datamodel(self, node: Node, state: State) -> None:
        _check_attrs(node, ())
        for child in node.children:
            if child.tag != "data":
                raise child.fail("<datamodel> holds only <data id=... expr=...>")
            if "src" in child.attrs:
                raise child.fail("src=...: a chart never reads files or URLs; give the value with expr")
            _check_attrs(child, ("id", "expr"))
            name = _variable(child, "id")
            if name in (n for n, _ in self.data):
                raise child.fail(f"the variable {name!r} is declared twice")
            item: tuple[str, Expression | None]
            if "expr" in child.attrs:
                item = (name, _expr(child, "expr"))
            elif child.text.strip():
                item = (name, _expr(child, "expr", child.text))
            else:
                item = (name, None)
            self.data.append(item)
            self.state_data.setdefault(state.id, []).append(item)

    # -- resolving targets --------------------------------------------------------

    def resolve(self, root: State) -> None:
        for t in self.transitions:
            found = []
            for target_id in t.target_ids:
                target = self.states.get(target_id)
                if target is None:
                    raise ChartError(f"{t.where}: no state with id {target_id!r}")
                found.append(target)
            t.targets = tuple(found)
        for state in [root, *self.ordered]:
            initial = state.initial
            if initial is None or state.kind == "history":
                continue
            for target in initial.targets:
                if not target.is_descendant(state):
                    inside = state.id or "the chart"
                    raise ChartError(
                        f"{initial.where}: the initial state {target.id!r} is not inside {inside!r}"
                    )


def _from_json(value: Any) -> Any:
    if isinstance(value, dict):
        return Record({str(k): _from_json(v) for k, v in value.items()})
    if isinstance(value, list):
        return [_from_json(v) for v in value]
    return value


def _content_value(node: Node) -> Any:
    """The value of ``<content>``'s text (W3C SCXML B.2: space-normalized; JSON parsed)."""
    text = " ".join(node.text.split())
    if not text:
        return None
    if text[0] in "{[":
        try:
            return check_size(_from_json(json.loads(text)))
        except (ValueError, RecursionError, EvaluationError):
            pass  # not JSON after all (or too big): the text itself
    return parse_chart_value(text)


def _refuse_left_out(node: Node) -> None:
    """The first element left out by design (``<invoke>``, ``<script>``...), in document order,
    is the refusal: a chart that needs one is refused for it, not for what comes before it."""
    for child in node.children:
        if child.tag in _REFUSED:
            raise child.fail(_REFUSED[child.tag])
        _refuse_left_out(child)


def compile_chart(name: str, text: str) -> Chart:
    """Load and check a chart (SCXML, JSON or YAML); ChartError naming the line and what is wrong."""
    fmt, node = read_document(text)
    if node.tag != "scxml":
        raise node.fail("the root element of a chart is <scxml>")
    _refuse_left_out(node)
    _check_attrs(node, ("initial", "name", "version", "datamodel", "binding"))
    model = node.attrs.get("datamodel", "python")
    if model not in ("python", "ps", "null"):
        raise node.fail(
            f"datamodel={model!r}: expressions here are a safe subset of Python;"
            ' write datamodel="python" or leave it out'
        )
    binding = node.attrs.get("binding", "early")
    if binding not in ("early", "late"):
        raise node.fail(f"binding={binding!r}: 'early' or 'late'")
    compiler = _Compiler()
    root = State("", "root", node.where)
    compiled: list[tuple[Expression, Node, str, str]] = []
    warnings: list[str] = []
    token = _COMPILED.set(compiled)
    warned = _WARNINGS.set(warnings)
    try:
        compiler.contents(node, root)
    finally:
        _COMPILED.reset(token)
        _WARNINGS.reset(warned)
    _check_names(compiled, {name for name, _ in compiler.data})
    for expression, at, attr, source in compiled:
        for state_id in expression.text_arguments("In"):
            if state_id not in compiler.states:
                raise at.fail(f"{attr}={source[:60]!r}: In({state_id!r}): no state with id {state_id!r}")
    followed = _followed(compiled)
    if not any(c.kind != "history" for c in root.children):
        raise node.fail("a chart needs at least one <state>, <parallel> or <final>")
    if root.transitions or root.listens or root.onentry or root.onexit:
        raise node.fail("<transition>, <onentry>, <onexit> and <ps:listen> go in a state, not in <scxml>")
    first = next(c for c in root.children if c.kind != "history")
    targets = tuple(node.attrs["initial"].split()) if "initial" in node.attrs else (first.id,)
    root.initial = Transition(root, (), None, targets, False, [], node.where)
    compiler.transitions.append(root.initial)
    compiler.resolve(root)
    states, ordered = compiler.states, compiler.ordered
    return Chart(
        name,
        fmt,
        text,
        root,
        states,
        ordered,
        compiler.data,
        compiler.transitions,
        followed,
        warnings=tuple(warnings),
        late=binding == "late",
        state_data=compiler.state_data,
        chart_name=node.attrs.get("name", ""),
    )
