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

import dataclasses
import enum
import inspect
import logging
import math
import sys
import typing
from collections.abc import Callable
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, TypeVar, overload

import numpy as np

from services.kernel.backend import Backend
from services.kernel.model import Access
from services.kernel.values import format_list, format_value, parser_for, type_name

__all__ = [
    "ClassSpec",
    "Member",
    "MemberKind",
    "Namespace",
    "Param",
    "Prop",
    "action",
    "class_spec",
    "functional",
    "query",
]

log = logging.getLogger(__name__)

F = TypeVar("F", bound=Callable[..., Any])

#: Metadata sub-properties every property has (``location.gui``).
META_NAMES = frozenset({"parameters", "gui", "doc"})
#: Reserved for the service's own property list.
RESERVED_NAMES = frozenset({"properties"}) | META_NAMES


class Namespace:
    """Base of the classes whose members are compiled here (:class:`services.kernel.core.Resource`).

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
    #: Bounds a Set from outside must respect (numbers, or each element of a vector;
    #: the class itself may assign anything).
    minimum: float | None = None
    maximum: float | None = None
    #: Unit of the value (``m``, ``m/s``, ``rad``, ``degC``); "" when it has none.
    unit: str | None = None
    #: The values a Set from outside may give, when they are a closed set.
    choices: tuple[Any, ...] | None = None
    #: Elements of a vector, when fixed (6 for a pose).
    length: int | None = None
    #: A ``bytes`` value: what the bytes are (``image/jpeg``, ``image/png``, ``application/x-npy``).
    media_type: str | None = None
    #: A ``bytes`` value: the most bytes a Set may carry (None: what one message can carry).
    max_size: int | None = None
    #: A number or vector: the smallest step the value is known to (0.01 m for a location to the
    #: centimetre); clients show as many decimals as it implies. None: not declared.
    resolution: float | None = None


@dataclass(frozen=True, slots=True)
class _FunctionalOptions:
    access: Access
    gui: str | None = None
    doc: str | None = None
    unit: str | None = None


_FUNCTIONAL_MARK = "__ps_functional__"


def _marked(
    access: Access, fn: F | None, gui: str | None, doc: str | None, unit: str | None
) -> F | Callable[[F], F]:
    options = _FunctionalOptions(access, gui=gui, doc=doc, unit=unit)

    def mark(f: F) -> F:
        setattr(f, _FUNCTIONAL_MARK, options)
        return f

    return mark(fn) if fn is not None else mark


@overload
def action(fn: F, /) -> F: ...


@overload
def action(
    *, gui: str | None = None, doc: str | None = None, unit: str | None = None
) -> Callable[[F], F]: ...


def action(
    fn: F | None = None, /, *, gui: str | None = None, doc: str | None = None, unit: str | None = None
) -> F | Callable[[F], F]:
    """Expose a method as an action: a Set invokes it (``behaviors.moveto``); a Get or Listen never does.

    The first positional parameter after ``self`` receives the Set value, parsed
    by its annotation (a method without one takes no value: a Set with a value
    is INVALID_ARGUMENT); the other parameters are request parameters, passed by
    keyword and parsed by their annotations. A Get is FAILED_PRECONDITION naming
    how to invoke it. ``doc``, ``gui`` and ``unit`` (of the value) are metadata.
    """
    return _marked(Access.ACTION, fn, gui, doc, unit)


@overload
def query(fn: F, /) -> F: ...


@overload
def query(*, gui: str | None = None, doc: str | None = None, unit: str | None = None) -> Callable[[F], F]: ...


def query(
    fn: F | None = None, /, *, gui: str | None = None, doc: str | None = None, unit: str | None = None
) -> F | Callable[[F], F]:
    """Expose a method as a query: a Get calls it with the request parameters (``registry/find``).

    Its author declares that calling it never changes state, so a Get (or a
    Listen naming it exactly) may call it at any time. Every parameter is a
    request parameter, the first positional one also accepted by name; a Set
    is FAILED_PRECONDITION. ``doc``, ``gui`` and ``unit`` (of the answer) are metadata.
    """
    return _marked(Access.QUERY, fn, gui, doc, unit)


@overload
def read_write(fn: F, /) -> F: ...


@overload
def read_write(
    *, gui: str | None = None, doc: str | None = None, unit: str | None = None
) -> Callable[[F], F]: ...


def read_write(
    fn: F | None = None, /, *, gui: str | None = None, doc: str | None = None, unit: str | None = None
) -> F | Callable[[F], F]:
    """Expose a method as a read-write property whose Set does work that must be awaited.

    For a value that is computed by asking others and set by telling them (a
    group's ``velocity``: the members' mean, and a command to every member).
    The method's only parameter is its value, positional-only with the default
    None: a Get calls it without one and must not change state (reads never
    act); a Set calls it with the value, which a Set must carry.
    """
    return _marked(Access.READ_WRITE, fn, gui, doc, unit)


#: The former name of :func:`action`, kept for existing services. A value-less
#: ``@functional`` is an action too and no longer answers a Get: declare reads ``@query``.
functional = action


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
    #: Reads a request's text (or, for a ``bytes`` value, its bytes).
    parse: Callable[[Any], Any]
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
    #: Reads a Set's text (or, for a binary property, its bytes).
    parse: Callable[[Any], Any] | None = None
    readonly: bool = False
    gui: str = "text"
    doc: str = ""
    #: What a client may do: read, read-write, action or query (see :mod:`services.kernel.model`).
    access: Access = Access.READ_WRITE
    #: Actions: the parameter receiving the Set value (None: takes no value).
    value_param: Param | None = None
    #: Functional properties: request parameters a call accepts (a query's value parameter included).
    params: typing.Mapping[str, Param] = field(default_factory=lambda: _NO_PARAMS)
    #: Functional properties: the type of the answer (``None`` for none).
    result_type: Any = None
    is_async: bool = False
    #: The ``NAME.parameters`` text.
    parameters_text: str = "()"
    minimum: float | None = None
    maximum: float | None = None
    unit: str = ""
    #: The values allowed, as value text; empty when any value of the type is.
    choices: tuple[str, ...] = ()
    length: int | None = None
    #: A Set carries bytes (the value's type, or an action's value type, is ``bytes``).
    binary: bool = False
    #: A binary value or answer: its media type ("" when unknown), and the most bytes a Set
    #: may carry (0: what one message can carry).
    media_type: str = ""
    max_size: int = 0
    #: A number or vector: the smallest step its value is known to (None: not declared).
    resolution: float | None = None


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
    "bytes": "bytes",
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


#: The value types a resolution means something for.
_RESOLVED_TYPES = frozenset({"number", "integer", "vector", "vectors"})


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
    hints = _function_hints(fn, cls, name, [p.name for p in params] + ["return"])
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
    if opts.access is Access.READ_WRITE and (
        value_param is None
        or value_param.default is not None
        or sig.parameters[value_param.name].kind is not inspect.Parameter.POSITIONAL_ONLY
        or keyword
    ):
        raise TypeError(
            f"{where}: a @read_write method takes one parameter, its value, positional-only with the "
            "default None (`def name(self, value: T | None = None, /)`): a Get can never carry it"
        )
    if opts.access is Access.QUERY:
        # A query's value, if any, is one more request parameter of the Get.
        accepted: dict[str, Param] = {}
        if value_param is not None:
            if (
                value_param.required
                or sig.parameters[value_param.name].kind is not inspect.Parameter.POSITIONAL_OR_KEYWORD
            ):
                raise TypeError(
                    f"{where}: a query takes request parameters only; give `{value_param.name}` a default "
                    "or declare the method @action"
                )
            accepted[value_param.name] = value_param
        accepted.update(keyword)
        value_param, keyword = None, accepted
    result, result_meta = _split_annotated(hints.get("return", inspect.Parameter.empty))
    value_meta = _split_annotated(value_param.type)[1] if value_param is not None else None
    binary_meta = value_meta if value_meta is not None and value_meta.media_type else result_meta
    media_type = (binary_meta.media_type or "") if binary_meta else ""
    return Member(
        name=name,
        kind=MemberKind.FUNCTIONAL,
        type=value_param.type if value_param else type(None),
        readonly=False,
        gui=opts.gui or ("button" if opts.access is Access.ACTION else _gui_for(result, media_type)),
        doc=opts.doc or _first_line(fn.__doc__),
        access=opts.access,
        value_param=value_param,
        params=MappingProxyType(keyword),
        result_type=None if result is type(None) else result,
        is_async=inspect.iscoroutinefunction(fn),
        parameters_text=_parameters_text(keyword.values()),
        unit=opts.unit or "",
        binary=value_param is not None and _type_word(value_param.type) == "bytes",
        media_type=media_type,
        max_size=_max_size(where, value_meta),
    )


def _max_size(where: str, meta: Prop | None) -> int:
    size = meta.max_size if meta is not None else None
    if size is None:
        return 0
    if not isinstance(size, int) or size <= 0:
        raise TypeError(f"{where}: max_size must be a positive number of bytes, not {size!r}")
    return size


def _gui_for(tp: Any, media_type: str = "") -> str:
    if media_type.startswith("image/"):
        return "image"
    return _GUI_BY_TYPE.get(_type_word(tp), "text")


def _value_member(
    cls: type, name: str, tp: Any, meta: Prop | None, *, kind: MemberKind, readonly: bool, doc: str
) -> Member:
    """An attribute or a computed property, with the metadata of its ``Prop``."""
    where = f"{cls.__qualname__}.{name}"
    choices: tuple[str, ...] = ()
    if meta is not None and meta.choices:
        choices = tuple(c if isinstance(c, str) else format_value(c) for c in meta.choices)
    binary = _type_word(tp) == "bytes"
    media_type = (meta.media_type or "") if meta else ""
    if (media_type or (meta is not None and meta.max_size is not None)) and not binary:
        raise TypeError(f"{where}: media_type and max_size are for a bytes value, not {_type_word(tp)}")
    return Member(
        name=name,
        kind=kind,
        type=tp,
        parse=None if readonly else _parser(tp, where),
        readonly=readonly,
        gui=(meta.gui if meta and meta.gui else _gui_for(tp, media_type)),
        doc=(meta.doc if meta and meta.doc else doc),
        access=Access.READ if readonly else Access.READ_WRITE,
        minimum=meta.minimum if meta else None,
        maximum=meta.maximum if meta else None,
        unit=(meta.unit or "") if meta else "",
        choices=choices,
        length=meta.length if meta else None,
        binary=binary,
        media_type=media_type,
        max_size=_max_size(where, meta),
        resolution=_resolution(where, tp, meta),
    )


def _resolution(where: str, tp: Any, meta: Prop | None) -> float | None:
    """``Prop.resolution``, checked: a positive finite step, on a number or a vector."""
    step = meta.resolution if meta is not None else None
    if step is None:
        return None
    if isinstance(step, bool) or not isinstance(step, int | float) or not math.isfinite(step) or step <= 0:
        raise TypeError(
            f"{where}: resolution must be a positive number (the value's smallest step), not {step!r}"
        )
    if _type_word(tp) not in _RESOLVED_TYPES:
        raise TypeError(f"{where}: resolution is for a number or a vector, not {_type_word(tp)}")
    return float(step)


def _computed_member(cls: type, name: str, prop: property) -> Member:
    hints = _function_hints(prop.fget, cls, name, ["return"]) if prop.fget else {}
    tp, meta = _split_annotated(hints.get("return", Any))
    if prop.fset is not None:
        value_names = [n for n in inspect.signature(prop.fset).parameters][1:2]
        set_hints = _function_hints(prop.fset, cls, name, value_names)
        if value_names and value_names[0] in set_hints:
            tp, _ = _split_annotated(set_hints[value_names[0]])
    readonly = prop.fset is None or (meta is not None and meta.readonly)
    return _value_member(
        cls, name, tp, meta, kind=MemberKind.COMPUTED, readonly=readonly, doc=_first_line(prop.__doc__)
    )


def _attribute_member(cls: type, name: str, annotation: Any) -> Member:
    tp, meta = _split_annotated(annotation)
    if _is_node_type(tp):
        return Member(
            name=name,
            kind=MemberKind.CHILD,
            type=tp,
            readonly=True,
            gui="group",
            doc=_first_line(tp.__doc__),
            access=Access.READ,
        )
    # Parsed even when read-only: the class's own assignments are not parsed, but a bad
    # annotation must fail when the class is compiled.
    member = _value_member(cls, name, tp, meta, kind=MemberKind.ATTRIBUTE, readonly=False, doc="")
    if meta is not None and meta.readonly:
        return dataclasses.replace(member, readonly=True, access=Access.READ)
    return member


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
