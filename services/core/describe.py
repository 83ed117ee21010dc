"""The typed model of a tree of Resources: every property with its type, access and metadata.

:func:`describe_tree` walks the tree as ``properties`` lists it (members in
definition order, children depth-first) and asks each Backend child for its
own model, whose names it puts under the child's name.
"""

from __future__ import annotations

import asyncio
import dataclasses
import inspect
import logging
from typing import Any

from services.backend import Backend
from services.core.metadata import Member, MemberKind, Param, class_spec
from services.core.resource import Resource
from services.core.tree import LIST_CONCURRENCY, direct_names
from services.errors import PropertyError
from services.model import Access, ParameterModel, PropertyModel
from services.values import format_value, type_name

__all__ = ["describe_tree", "type_word"]

log = logging.getLogger(__name__)


def type_word(tp: Any) -> str:
    """The data type word of an annotation (:data:`services.model.DATA_TYPES`)."""
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
    gate = asyncio.Semaphore(LIST_CONCURRENCY)

    async def model_of(prefix: str, backend: Backend) -> list[PropertyModel]:
        async with gate:
            try:
                model = await backend.describe()
            except PropertyError as e:
                log.debug("cannot describe the properties under %s: %s", prefix[:-1], e.message)
                return []
        return [_prefixed(prefix, p) for p in model.properties]

    described = await asyncio.gather(*(model_of(prefix, backend) for _, prefix, backend in remote))
    # Insert from the back so that earlier positions stay valid.
    for (position, _, _), models in zip(reversed(remote), reversed(described), strict=True):
        out[position:position] = models
    return tuple(out)


def _prefixed(prefix: str, model: PropertyModel) -> PropertyModel:
    return dataclasses.replace(model, name=prefix + model.name)
