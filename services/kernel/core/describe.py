"""The typed model of a tree of Resources: every property with its type, access and metadata.

:func:`describe_tree` walks the tree as ``properties`` lists it (members in
definition order, children depth-first) and asks each Backend child for its
own model, whose names it puts under the child's name.

:func:`describe_matching` is the same walk narrowed to a wildcard pattern: it visits only
the namespaces the pattern's segments name (``services.*.state`` in a registry of 10,000
services: the 10,000 entries' ``state``, not their 110,000 properties), so a wildcard is
expanded without the ``properties`` list, at any size of tree.
"""

from __future__ import annotations

import asyncio
import dataclasses
import functools
import inspect
import logging
from collections.abc import Awaitable, Callable, Sequence
from typing import Any

from services.kernel.backend import Backend
from services.kernel.core.metadata import Member, MemberKind, Param, class_spec
from services.kernel.core.resource import Resource
from services.kernel.core.tree import LIST_CONCURRENCY, direct_names
from services.kernel.errors import PropertyError
from services.kernel.model import Access, ParameterModel, PropertyModel
from services.kernel.paths import WILDCARD, validate_path, validate_pattern
from services.kernel.values import format_value, type_name

__all__ = ["describe_matching", "describe_tree", "type_word"]

log = logging.getLogger(__name__)


def type_word(tp: Any) -> str:
    """The data type word of an annotation (:data:`services.kernel.model.DATA_TYPES`)."""
    if tp is None or tp is type(None):
        return "none"
    try:
        return type_name(tp)
    except TypeError:
        return "text"


def _default_text(default: Any) -> str:
    if default is inspect.Parameter.empty or default is None:
        return ""
    try:
        return format_value(default)
    except (TypeError, ValueError):
        return str(default)


def _parameter(param: Param) -> ParameterModel:
    return ParameterModel(
        name=param.name,
        type=type_word(param.type),
        required=param.required,
        default=_default_text(param.default),
    )


def _member_model(path: str, member: Member) -> PropertyModel:
    if member.kind is MemberKind.FUNCTIONAL:
        value = member.value_param
        # A read-write one reads and is set as its value; an action or a query has an answer type.
        read_write = member.access is Access.READ_WRITE and value is not None
        return PropertyModel(
            name=path,
            type=type_word(value.type if read_write and value is not None else member.result_type),
            access=member.access,
            unit=member.unit,
            doc=member.doc,
            gui=member.gui,
            value=_parameter(value) if value is not None else None,
            parameters=tuple(_parameter(p) for p in member.params.values()),
            media_type=member.media_type,
            max_size=member.max_size,
        )
    return PropertyModel(
        name=path,
        type=type_word(member.type),
        access=member.access,
        length=member.length,
        unit=member.unit,
        minimum=member.minimum,
        maximum=member.maximum,
        choices=member.choices,
        doc=member.doc,
        gui=member.gui,
        media_type=member.media_type,
        max_size=member.max_size,
        resolution=member.resolution,
    )


def _namespace_model(path: str, node: Resource | Backend) -> PropertyModel:
    doc = class_spec(type(node)).doc if isinstance(node, Resource) else ""
    return PropertyModel(name=path, type="namespace", access=Access.READ, doc=doc, gui="group")


def _walk(
    node: Resource, prefix: str, out: list[PropertyModel], remote: list[tuple[int, str, Backend]]
) -> None:
    spec = class_spec(type(node))
    children = node._ps_children
    for name in direct_names(node):
        path = prefix + name
        child = children.get(name)
        if child is None:
            out.append(_member_model(path, spec.members[name]))
            continue
        out.append(_namespace_model(path, child))
        if isinstance(child, Resource):
            _walk(child, path + ".", out, remote)
        else:
            remote.append((len(out), path + ".", child))


async def describe_tree(root: Resource) -> tuple[PropertyModel, ...]:
    """Every property under ``root`` (as ``properties`` lists them), each with its model."""
    out: list[PropertyModel] = []
    remote: list[tuple[int, str, Backend]] = []
    _walk(root, "", out, remote)
    if not remote:
        return tuple(out)

    async def model_of(backend: Backend) -> Sequence[PropertyModel]:
        return (await backend.describe()).properties

    return await _with_remote(
        out, [(at, prefix, functools.partial(model_of, child)) for at, prefix, child in remote]
    )


def _listed(node: Resource, name: str) -> bool:
    """Whether ``properties`` lists ``name`` directly under ``node`` (as :func:`direct_names` says)."""
    if name in node._ps_children:
        return True
    member = class_spec(type(node)).members.get(name)
    return member is not None and member.kind is not MemberKind.CHILD


#: (position in the answer, the child's name and a dot, the child, the rest of the pattern, of ``under``).
_RemoteMatch = tuple[int, str, Backend, str, str]


class _Matching:
    """One walk of :func:`describe_matching`: what it looks for, and what it found."""

    def __init__(self, segments: list[str], under: list[str]) -> None:
        self.segments = segments
        self.under = under
        self.out: list[PropertyModel] = []
        #: Backend children to ask for the rest of the pattern.
        self.remote: list[_RemoteMatch] = []

    def walk(self, node: Resource, depth: int, prefix: str) -> None:
        segments, under = self.segments, self.under
        segment = segments[depth]
        if depth < len(under):
            # Only the one name ``under`` goes through, if the pattern lets it.
            name = under[depth]
            names = [name] if segment in (WILDCARD, name) and _listed(node, name) else []
        elif segment == WILDCARD:
            names = direct_names(node)
        else:
            names = [segment] if _listed(node, segment) else []
        last = depth + 1 == len(segments)
        children = node._ps_children
        for name in names:
            path = prefix + name
            child = children.get(name)
            if last:
                if child is None:
                    self.out.append(_member_model(path, class_spec(type(node)).members[name]))
                else:
                    self.out.append(_namespace_model(path, child))
            elif isinstance(child, Resource):
                self.walk(child, depth + 1, path + ".")
            elif child is not None:
                rest, rest_under = ".".join(segments[depth + 1 :]), ".".join(under[depth + 1 :])
                self.remote.append((len(self.out), path + ".", child, rest, rest_under))
            # A member's own sub-properties (``location.x``) are not listed: nothing deeper matches.


async def describe_matching(root: Resource, pattern: str, under: str = "") -> tuple[PropertyModel, ...]:
    """The model of every property under ``root`` whose name matches ``pattern``, in the order
    ``properties`` lists them; with ``under``, only ``under`` and the names below it
    (:meth:`services.kernel.backend.Backend.match_properties`).

    Walks only what the pattern names; a Backend child is asked for its own matches of the
    rest of the pattern. A child that cannot answer is left out, as ``properties`` leaves it out.
    """
    segments = validate_pattern(pattern).split(".")
    parts = validate_path(under).split(".") if under else []
    if len(parts) > len(segments):
        return ()  # every match has as many segments as the pattern: none lies below ``under``
    matching = _Matching(segments, parts)
    matching.walk(root, 0, "")
    if not matching.remote:
        return tuple(matching.out)
    asked = [
        (at, prefix, functools.partial(child.match_properties, rest, rest_under))
        for at, prefix, child, rest, rest_under in matching.remote
    ]
    return await _with_remote(matching.out, asked)


async def _with_remote(
    out: list[PropertyModel],
    asked: Sequence[tuple[int, str, Callable[[], Awaitable[Sequence[PropertyModel]]]]],
) -> tuple[PropertyModel, ...]:
    """``out`` with what each Backend child answers (``asked``: where it goes, the child's name
    and a dot, how to ask it) put in at its position, its names under the child's; at most
    ``LIST_CONCURRENCY`` children are asked at once, and one that cannot answer is left out."""
    gate = asyncio.Semaphore(LIST_CONCURRENCY)

    async def answer_of(
        prefix: str, ask: Callable[[], Awaitable[Sequence[PropertyModel]]]
    ) -> list[PropertyModel]:
        async with gate:
            try:
                models = await ask()
            except PropertyError as e:
                log.debug("cannot describe the properties under %s: %s", prefix[:-1], e.message)
                return []
        return [_prefixed(prefix, p) for p in models]

    answers = await asyncio.gather(*(answer_of(prefix, ask) for _, prefix, ask in asked))
    # Insert from the back so that earlier positions stay valid.
    for (position, _, _), models in zip(reversed(asked), reversed(answers), strict=True):
        out[position:position] = models
    return tuple(out)


def _prefixed(prefix: str, model: PropertyModel) -> PropertyModel:
    return dataclasses.replace(model, name=prefix + model.name)
