"""What a Resource class exposes: its members, read once per class from annotations.

The class wrapper never inspects signatures or type hints on a request: the
first use of a class compiles a :class:`ClassSpec` (members in definition
order, each with its parser, flags and metadata) and caches it on the class.
An annotation that does not resolve is a TypeError naming the class, the
member and the annotation, raised then: a member silently typed ``Any``
would take any text.

The compiler knows the classes it describes only by their base
:class:`Namespace`, declared here: it imports nothing of ``resource.py``.
"""

from __future__ import annotations

import enum
import inspect
import logging
import sys
import typing
from collections.abc import Callable
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, TypeVar, overload

import numpy as np

from services.backend import Backend
from services.values import format_list, parser_for, type_name

__all__ = ["ClassSpec", "Member", "MemberKind", "Namespace", "Param", "Prop", "class_spec", "functional"]

log = logging.getLogger(__name__)

F = TypeVar("F", bound=Callable[..., Any])

#: Metadata sub-properties every property has (``location.gui``).
META_NAMES = frozenset({"parameters", "gui", "doc"})
#: Reserved for the service's own property list.
RESERVED_NAMES = frozenset({"properties"}) | META_NAMES


class Namespace:
    """Base of the classes whose members are compiled here (:class:`services.core.Resource`).

    A class-level annotation naming a Namespace (or a Backend) declares a
    child namespace rather than a value. Namespace itself exposes nothing.
    """

    __slots__ = ()


@dataclass(frozen=True, slots=True)
class Prop:
    """Metadata of an exposed attribute: ``Annotated[Vector, Prop(readonly=True, gui="pose")]``."""

    readonly: bool = False
    #: Preferred widget; the default follows the value type.
    gui: str | None = None
    doc: str | None = None
    #: Bounds a Set from outside must respect (numbers only; the class itself may assign anything).
    minimum: float | None = None
    maximum: float | None = None


@dataclass(frozen=True, slots=True)
class _FunctionalOptions:
    gui: str | None = None
    doc: str | None = None


_FUNCTIONAL_MARK = "__ps_functional__"


@overload
def functional(fn: F, /) -> F: ...


@overload
def functional(*, gui: str | None = None, doc: str | None = None) -> Callable[[F], F]: ...


def functional(
    fn: F | None = None, /, *, gui: str | None = None, doc: str | None = None
) -> F | Callable[[F], F]:
    """Expose a method as a functional property: a Set calls it (``behaviors.moveto``).

    The first positional parameter after ``self`` receives the Set value, parsed
    by its annotation; the other parameters are request parameters, passed by
    keyword and parsed by their annotations. A method whose value parameter is
    absent or has a default is a query: a Get calls it too.
    """

    def mark(f: F) -> F:
        setattr(f, _FUNCTIONAL_MARK, _FunctionalOptions(gui=gui, doc=doc))
        return f

    return mark(fn) if fn is not None else mark


class MemberKind(enum.Enum):
    ATTRIBUTE = "attribute"
    COMPUTED = "computed"
    FUNCTIONAL = "functional"
    CHILD = "child"


@dataclass(frozen=True, slots=True)
class Param:
    """One parameter of a functional property."""

    name: str
    type: Any
    parse: Callable[[str], Any]
    #: ``inspect.Parameter.empty`` when required.
    default: Any = inspect.Parameter.empty

    @property
    def required(self) -> bool:
        return self.default is inspect.Parameter.empty


_NO_PARAMS: typing.Mapping[str, Param] = MappingProxyType({})


@dataclass(frozen=True, slots=True)
class Member:
    """One exposed member of a Resource class."""

    name: str
    kind: MemberKind
    type: Any = str
    parse: Callable[[str], Any] | None = None
    readonly: bool = False
    gui: str = "text"
    doc: str = ""
    #: Functional properties: the parameter receiving the Set value (None: takes no value).
    value_param: Param | None = None
    #: Functional properties: request parameters a Set accepts.
    params: typing.Mapping[str, Param] = field(default_factory=lambda: _NO_PARAMS)
    #: Functional queries: request parameters a Get accepts (the value parameter included).
    query_params: typing.Mapping[str, Param] = field(default_factory=lambda: _NO_PARAMS)
    is_async: bool = False
    #: The ``NAME.parameters`` text.
    parameters_text: str = "()"
    minimum: float | None = None
    maximum: float | None = None

    @property
    def needs_value(self) -> bool:
        return self.value_param is not None and self.value_param.required


@dataclass(frozen=True, slots=True)
class ClassSpec:
    """The exposed members of one Resource class, in definition order."""

    members: typing.Mapping[str, Member]
    doc: str
    has_value: bool
    #: Names whose value must stay a Resource or Backend (declared children).
    child_names: frozenset[str] = field(default_factory=frozenset)


_GUI_BY_TYPE = {
    "number": "number",
    "integer": "number",
    "boolean": "switch",
    "vector": "vector",
    "marker": "marker",
    "text": "text",
    "list": "list",
    "names": "list",
    "vectors": "list",
}


def _first_line(doc: str | None) -> str:
    if not doc:
        return ""
    lines = inspect.cleandoc(doc).splitlines()
    return lines[0].strip() if lines else ""


def _split_annotated(tp: Any) -> tuple[Any, Prop | None]:
    if typing.get_origin(tp) is typing.Annotated:
        base, *extras = typing.get_args(tp)
        prop = next((e for e in extras if isinstance(e, Prop)), None)
        return base, prop
    return tp, None


def _is_node_type(tp: Any) -> bool:
    return isinstance(tp, type) and issubclass(tp, Backend | Namespace)


def _type_word(tp: Any) -> str:
    try:
        return type_name(tp)
    except TypeError:
        return "text"


def _evaluate(annotation: Any, globalns: dict[str, Any], localns: dict[str, Any], where: str) -> Any:
    """An annotation (text under ``from __future__ import annotations``) as the object it names."""
    if not isinstance(annotation, str):
        return annotation
    try:
        return eval(annotation, globalns, localns)  # the class's own annotation text
    except Exception as e:
        raise TypeError(
            f"{where}: the annotation {annotation!r} does not resolve ({type(e).__name__}: {e})"
        ) from None


def _module_namespace(obj: Any) -> dict[str, Any]:
    module = sys.modules.get(getattr(obj, "__module__", "") or "")
    return dict(vars(module)) if module else {}


def _class_hints(cls: type) -> dict[str, Any]:
    """The attribute annotations of ``cls`` and its bases, resolved, ``Annotated`` kept."""
    try:
        return typing.get_type_hints(cls, include_extras=True)
    except Exception:
        pass  # one does not resolve: find which; only a member's (a public name) is an error
    hints: dict[str, Any] = {}
    for klass in reversed(cls.__mro__):
        globalns, localns = _module_namespace(klass), dict(vars(klass))
        for name, annotation in inspect.get_annotations(klass).items():
            if not name.startswith("_"):
                hints[name] = _evaluate(annotation, globalns, localns, f"{cls.__qualname__}.{name}")
    return hints


def _function_hints(
    fn: Callable[..., Any], cls: type, member: str, names: typing.Iterable[str]
) -> dict[str, Any]:
    """The annotations of ``fn``'s parameters ``names`` (``return``: its result), resolved."""
    try:
        return typing.get_type_hints(fn, include_extras=True)
    except Exception:
        pass  # one does not resolve: find which; only those the member uses are an error
    raw = inspect.get_annotations(fn)
    globalns = getattr(fn, "__globals__", None) or _module_namespace(fn)
    localns = dict(vars(cls))
    return {
        name: _evaluate(raw[name], globalns, localns, f"{cls.__qualname__}.{member} ({name})")
        for name in names
        if name in raw
    }


def _parser(tp: Any, where: str) -> Callable[[str], Any]:
    try:
        return parser_for(tp)
    except TypeError as e:
        raise TypeError(f"{where}: {e}") from None


def _default_atom(default: Any) -> Any:
    """A parameter default as an item of the ``NAME.parameters`` list."""
    if default is inspect.Parameter.empty:
        return "-"
    if default is None or (isinstance(default, str) and not default):
        return []
    if isinstance(default, np.ndarray):
        return default
    if isinstance(default, str | bool | int | float | list | tuple):
        return default
    return str(default)


def _parameters_text(params: typing.Iterable[Param]) -> str:
    rows = [[p.name, _type_word(p.type), _default_atom(p.default)] for p in params]
    try:
        return format_list(rows)
    except (TypeError, ValueError):
        return format_list([[p.name, _type_word(p.type), "?"] for p in params])


def _functional_member(cls: type, name: str, fn: Callable[..., Any], opts: _FunctionalOptions) -> Member:
    where = f"{cls.__qualname__}.{name}"
    sig = inspect.signature(fn)
    params = list(sig.parameters.values())[1:]  # drop self
    hints = _function_hints(fn, cls, name, [p.name for p in params])
    value_param: Param | None = None
    keyword: dict[str, Param] = {}
    for i, p in enumerate(params):
        if p.kind in (p.VAR_POSITIONAL, p.VAR_KEYWORD):
            raise TypeError(f"{where}: *args and **kwargs cannot be request parameters")
        tp = hints.get(p.name, str)
        param = Param(p.name, tp, _parser(tp, f"{where}({p.name})"), p.default)
        if i == 0 and p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD):
            value_param = param
        elif p.kind is p.POSITIONAL_ONLY:
            raise TypeError(f"{where}: only the value parameter may be positional-only")
        else:
            keyword[p.name] = param
    query: dict[str, Param] = {}
    if (
        value_param is not None
        and not value_param.required
        and sig.parameters[value_param.name].kind is inspect.Parameter.POSITIONAL_OR_KEYWORD
    ):
        query[value_param.name] = value_param
    query.update(keyword)
    required_value = value_param is not None and value_param.required
    listed = list(keyword.values()) if required_value else list(query.values())
    return Member(
        name=name,
        kind=MemberKind.FUNCTIONAL,
        type=value_param.type if value_param else str,
        readonly=False,
        gui=opts.gui or "button",
        doc=opts.doc or _first_line(fn.__doc__),
        value_param=value_param,
        params=MappingProxyType(keyword),
        query_params=MappingProxyType(query),
        is_async=inspect.iscoroutinefunction(fn),
        parameters_text=_parameters_text(listed),
    )


def _computed_member(cls: type, name: str, prop: property) -> Member:
    where = f"{cls.__qualname__}.{name}"
    hints = _function_hints(prop.fget, cls, name, ["return"]) if prop.fget else {}
    tp, meta = _split_annotated(hints.get("return", Any))
    if prop.fset is not None:
        value_names = [n for n in inspect.signature(prop.fset).parameters][1:2]
        set_hints = _function_hints(prop.fset, cls, name, value_names)
        if value_names and value_names[0] in set_hints:
            tp, _ = _split_annotated(set_hints[value_names[0]])
    readonly = prop.fset is None or (meta is not None and meta.readonly)
    parse = None if readonly else _parser(tp, where)
    return Member(
        name=name,
        kind=MemberKind.COMPUTED,
        type=tp,
        parse=parse,
        readonly=readonly,
        gui=(meta.gui if meta and meta.gui else _GUI_BY_TYPE.get(_type_word(tp), "text")),
        doc=(meta.doc if meta and meta.doc else _first_line(prop.__doc__)),
        minimum=meta.minimum if meta else None,
        maximum=meta.maximum if meta else None,
    )


def _attribute_member(cls: type, name: str, annotation: Any) -> Member:
    tp, meta = _split_annotated(annotation)
    if _is_node_type(tp):
        return Member(
            name=name, kind=MemberKind.CHILD, type=tp, readonly=True, gui="group", doc=_first_line(tp.__doc__)
        )
    return Member(
        name=name,
        kind=MemberKind.ATTRIBUTE,
        type=tp,
        parse=_parser(tp, f"{cls.__qualname__}.{name}"),
        readonly=bool(meta and meta.readonly),
        gui=(meta.gui if meta and meta.gui else _GUI_BY_TYPE.get(_type_word(tp), "text")),
        doc=(meta.doc if meta and meta.doc else ""),
        minimum=meta.minimum if meta else None,
        maximum=meta.maximum if meta else None,
    )


def _build_spec(cls: type) -> ClassSpec:
    members: dict[str, Member] = {}
    hints = _class_hints(cls)
    for klass in reversed(cls.__mro__):
        if klass is Namespace or not issubclass(klass, Namespace):
            continue
        for name in inspect.get_annotations(klass):
            if name.startswith("_"):
                continue
            annotation = hints.get(name, Any)
            if typing.get_origin(annotation) is typing.ClassVar or annotation is typing.ClassVar:
                continue
            members[name] = _attribute_member(cls, name, annotation)
        for name, value in klass.__dict__.items():
            if name.startswith("_"):
                continue
            if isinstance(value, property):
                members[name] = _computed_member(cls, name, value)
                continue
            fn = value.__func__ if isinstance(value, staticmethod | classmethod) else value
            opts = getattr(fn, _FUNCTIONAL_MARK, None)
            if isinstance(opts, _FunctionalOptions) and callable(fn):
                members[name] = _functional_member(cls, name, fn, opts)
            elif name in members and members[name].kind in (MemberKind.FUNCTIONAL, MemberKind.COMPUTED):
                del members[name]  # overridden by a plain method or value in a subclass
    for name in members:
        if name in RESERVED_NAMES:
            raise TypeError(f"{cls.__qualname__}.{name}: {name!r} is reserved for the service itself")
    return ClassSpec(
        members=MappingProxyType(members),
        doc=_first_line(cls.__doc__),
        has_value=callable(getattr(cls, "_value", None)),
        child_names=frozenset(n for n, m in members.items() if m.kind is MemberKind.CHILD),
    )


_SPEC_ATTR = "__ps_spec__"


def class_spec(cls: type) -> ClassSpec:
    """The compiled spec of a Resource class (built on first use, then cached on the class)."""
    spec = cls.__dict__.get(_SPEC_ATTR)
    if spec is None:
        spec = _build_spec(cls)
        type.__setattr__(cls, _SPEC_ATTR, spec)
    return typing.cast(ClassSpec, spec)
