"""Resolving a dotted path in a tree of Resources into a target that can be read, written or watched."""

from __future__ import annotations

import asyncio
import difflib
import inspect
import logging
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from services.kernel.backend import Backend
from services.kernel.core.metadata import META_NAMES, Member, MemberKind, Param, class_spec
from services.kernel.core.resource import Resource
from services.kernel.errors import Code, InvalidArgument, NotFound, PropertyError, ReadOnly, ResourceExhausted
from services.kernel.model import Access
from services.kernel.values import (
    MAX_BINARY_SIZE,
    Marker,
    Value,
    as_text,
    format_names,
    format_number,
    format_result,
    format_value,
    loggable,
    parse_number,
    type_name,
    vector_index,
)

__all__ = ["NeedsAwait", "Target", "all_properties", "direct_names", "remote_prefixes", "resolve"]

log = logging.getLogger(__name__)


class NeedsAwait(Exception):
    """The value cannot be computed synchronously (a remote child, an async query)."""


def direct_names(node: Resource) -> list[str]:
    """The names directly under ``node``: its members in definition order, then attached children."""
    spec = class_spec(type(node))
    children = node._ps_children
    names = [n for n, m in spec.members.items() if m.kind is not MemberKind.CHILD or n in children]
    names.extend(n for n in children if n not in spec.members)
    return names


def _walk(node: Resource, prefix: str, out: list[str], remote: list[tuple[int, str, Backend]]) -> None:
    children = node._ps_children
    for name in direct_names(node):
        full = prefix + name
        out.append(full)
        child = children.get(name)
        if isinstance(child, Resource):
            _walk(child, full + ".", out, remote)
        elif child is not None:
            remote.append((len(out), full + ".", child))


def remote_children(node: Resource) -> list[Backend]:
    """Every Backend child anywhere under ``node`` (each once)."""
    found: list[Backend] = []
    for child in node._ps_children.values():
        if isinstance(child, Resource):
            found.extend(remote_children(child))
        elif all(child is not b for b in found):
            found.append(child)
    return found


def remote_prefixes(node: Resource, backend: Backend, prefix: str = "") -> list[str]:
    """The paths under ``node`` at which ``backend`` is a child (a member of a group: ``robots.scout1``)."""
    found: list[str] = []
    for name, child in node._ps_children.items():
        if child is backend:
            found.append(prefix + name)
        elif isinstance(child, Resource):
            found.extend(remote_prefixes(child, backend, f"{prefix}{name}."))
    return found


def properties_now(root: Resource) -> list[str]:
    """Every property path under ``root``, depth-first; NeedsAwait when a remote child must be asked."""
    out: list[str] = []
    remote: list[tuple[int, str, Backend]] = []
    _walk(root, "", out, remote)
    if remote:
        raise NeedsAwait
    return out


#: Remote children asked for their property lists at once (a group of 1,000
#: proxied members must not be asked one after another, nor all at once).
LIST_CONCURRENCY = 64


async def all_properties(root: Resource) -> list[str]:
    """Every property path under ``root``, depth-first, namespaces included, remote children asked."""
    out: list[str] = []
    remote: list[tuple[int, str, Backend]] = []
    _walk(root, "", out, remote)
    if not remote:
        return out
    gate = asyncio.Semaphore(LIST_CONCURRENCY)

    async def names_of(prefix: str, backend: Backend) -> list[str]:
        async with gate:
            try:
                return await backend.properties()
            except PropertyError as e:
                log.debug("cannot list the properties under %s: %s", prefix[:-1], e.message)
                return []

    listed = await asyncio.gather(*(names_of(prefix, backend) for _, prefix, backend in remote))
    # Insert from the back so that earlier positions stay valid.
    for (position, prefix, _), names in zip(reversed(remote), reversed(listed), strict=True):
        out[position:position] = [prefix + n for n in names]
    return out


def _suggest(name: str, candidates: list[str], prefix: str) -> str:
    close = difflib.get_close_matches(name, candidates, n=3, cutoff=0.6)
    if not close:
        return ""
    return "; did you mean " + " or ".join(f"`{prefix}{c}`" for c in close) + "?"


def _bad_value(path: str, e: PropertyError) -> InvalidArgument:
    return InvalidArgument(f"bad value for `{path}`: {e.message}")


def check_form(path: str, member: Member, value: Value) -> None:
    """A Set's value in the form the property takes: bytes for a binary one (within its
    max_size), text for any other; INVALID_ARGUMENT saying which form to send."""
    if member.binary:
        if isinstance(value, str):
            media = f", {member.media_type}" if member.media_type else ""
            raise InvalidArgument(
                f"`{path}` is binary (type bytes{media}): send its value as bytes (the `data` field;"
                " `\\=BASE64` on a line; `psctl set --file`), "
                "not as text"
            )
        limit = member.max_size or MAX_BINARY_SIZE
        if len(value) > limit:
            raise ResourceExhausted(
                f"`{path}`: a value of {len(value)} bytes is more than `{path}` takes ({limit} bytes)"
            )
    elif isinstance(value, bytes):
        word = type_word_of(member)
        raise InvalidArgument(
            f"`{path}` is text (type {word}): send its value as text (the `value` field), not as bytes"
        )


def type_word_of(member: Member) -> str:
    """The type word of what a Set of ``member`` takes (its value, or an action's value)."""
    tp = member.value_param.type if member.value_param is not None else member.type
    try:
        return type_name(tp)
    except TypeError:
        return "text"


def _check_range(path: str, member: Member, value: Any) -> None:
    """Bounds of a number, or of each element of a vector."""
    if isinstance(value, np.ndarray):
        numbers = [float(x) for x in value.ravel()]
    elif isinstance(value, int | float) and not isinstance(value, bool):
        numbers = [value]
    else:
        return
    low, high = member.minimum, member.maximum
    for x in numbers:
        if (low is not None and x < low) or (high is not None and x > high):
            bounds = f"from {format_number(low)}" if low is not None else ""
            if high is not None:
                bounds += (" " if bounds else "") + f"up to {format_number(high)}"
            raise InvalidArgument(f"bad value for `{path}`: {format_number(x)} is out of range ({bounds})")


class Target:
    """One resolved path: how to Get, Set and watch it."""

    __slots__ = ("path",)

    def __init__(self, path: str) -> None:
        self.path = path

    async def get(self, params: Mapping[str, str]) -> Value:
        return self.peek()

    async def set(self, value: Value, params: Mapping[str, str]) -> Value:
        raise ReadOnly(f"`{self.path}` is read-only")

    def peek(self) -> Value:
        """The current value, synchronously (for change detection); NeedsAwait if it cannot be."""
        raise NeedsAwait

    def hook(self, callback: Callable[[], None]) -> Callable[[], None] | None:
        """Call ``callback`` whenever the value may have changed; returns the unhook function."""
        return None

    def listen_refused(self) -> PropertyError | None:
        """Why a Listen naming this path exactly is refused (an action), or None."""
        return None

    def _no_params(self, params: Mapping[str, str]) -> None:
        if params:
            raise InvalidArgument(
                f"`{self.path}` takes no parameters (got {_some(sorted(params))}); "
                f"see `{self.path}.parameters`"
            )


def _some(names: list[str], shown: int = 5) -> str:
    """The first ``shown`` names and how many more: a request may carry thousands."""
    more = len(names) - shown
    return ", ".join(names[:shown]) + (f" and {more} more" if more > 0 else "")


def _watch_key(owner: Resource, key: str, callback: Callable[[], None]) -> Callable[[], None]:
    owner._ps_watch.setdefault(key, []).append(callback)

    def unhook() -> None:
        callbacks = owner._ps_watch.get(key)
        if callbacks is None:
            return
        try:
            callbacks.remove(callback)
        except ValueError:
            return
        if not callbacks:
            del owner._ps_watch[key]

    return unhook


class MemberTarget(Target):
    """An attribute, computed property or functional property of one Resource."""

    __slots__ = ("member", "owner")

    def __init__(self, path: str, owner: Resource, member: Member) -> None:
        super().__init__(path)
        self.owner = owner
        self.member = member

    async def get(self, params: Mapping[str, str]) -> Value:
        member = self.member
        if member.kind is not MemberKind.FUNCTIONAL:
            if params:
                self._no_params(params)
            return format_result(getattr(self.owner, member.name))
        if member.access is Access.ACTION:
            raise self.is_action()
        return await self._call(None, params)

    def is_action(self) -> PropertyError:
        """The error of a read of an action: reads never invoke one."""
        return PropertyError(
            f"`{self.path}` is an action: Set it to invoke it", code=Code.FAILED_PRECONDITION
        )

    def listen_refused(self) -> PropertyError | None:
        return self.is_action() if self.member.access is Access.ACTION else None

    async def set(self, value: Value, params: Mapping[str, str]) -> Value:
        member = self.member
        if member.kind is MemberKind.FUNCTIONAL:
            if member.access is Access.QUERY:
                raise PropertyError(
                    f"`{self.path}` is a query: Get it (with its parameters); a Set does nothing",
                    code=Code.FAILED_PRECONDITION,
                )
            if member.access is Access.READ_WRITE and not value:
                raise InvalidArgument(f"a Set of `{self.path}` needs a value (a Get reads it)")
            return await self._call(value, params)
        if member.readonly:
            raise ReadOnly(f"`{self.path}` is read-only")
        self._no_params(params)
        check_form(self.path, member, value)
        assert member.parse is not None
        try:
            parsed = member.parse(value)
        except InvalidArgument as e:
            raise _bad_value(self.path, e) from None
        if member.choices and format_value(parsed) not in member.choices:
            raise InvalidArgument(
                f"bad value for `{self.path}`: {value!r} is not one of {', '.join(member.choices)}"
            )
        if member.minimum is not None or member.maximum is not None:
            _check_range(self.path, member, parsed)
        setattr(self.owner, member.name, parsed)
        return format_result(getattr(self.owner, member.name))

    def peek(self) -> Value:
        member = self.member
        if member.kind is not MemberKind.FUNCTIONAL:
            return format_result(getattr(self.owner, member.name))
        if member.access is Access.ACTION:
            return ""
        if member.is_async:
            raise NeedsAwait
        return format_result(getattr(self.owner, member.name)())

    def hook(self, callback: Callable[[], None]) -> Callable[[], None] | None:
        return _watch_key(self.owner, self.member.name, callback)

    def _parse_param(self, param: Param, text: str) -> Any:
        try:
            return param.parse(text)
        except InvalidArgument as e:
            raise InvalidArgument(f"bad parameter `{param.name}` for `{self.path}`: {e.message}") from None

    async def _call(self, value: Value | None, params: Mapping[str, str]) -> Value:
        member = self.member
        accepted = member.params
        kwargs: dict[str, Any] = {}
        for name, text in params.items():
            param = accepted.get(name)
            if param is None:
                known = ", ".join(f"`{n}`" for n in accepted) or "none"
                raise InvalidArgument(f"`{self.path}` has no parameter `{name}`; it accepts: {known}")
            kwargs[name] = self._parse_param(param, text)
        args: list[Any] = []
        value_param = member.value_param
        if value_param is None:
            if value:
                if isinstance(value, bytes):
                    shown = loggable(value)
                else:
                    shown = value if len(value) <= 40 else value[:40] + "..."
                raise InvalidArgument(
                    f"bad value for `{self.path}`: it takes no value (got {shown!r}); Set it to ''"
                )
        elif value is not None and (value not in ("", b"") or value_param.required):
            check_form(self.path, member, value)
            try:
                args.append(value_param.parse(value))
            except InvalidArgument as e:
                raise _bad_value(self.path, e) from None
        for param in accepted.values():
            if param.required and param.name not in kwargs:
                raise InvalidArgument(f"`{self.path}` needs the parameter `{param.name}`")
        result = getattr(self.owner, member.name)(*args, **kwargs)
        if member.is_async or inspect.isawaitable(result):
            result = await result
        return format_result(result)


class SubTarget(Target):
    """An element of a vector (``location.x``) or a field of a marker (``target.location``)."""

    __slots__ = ("member", "owner", "sub")

    def __init__(self, path: str, owner: Resource, member: Member, sub: str) -> None:
        super().__init__(path)
        self.owner = owner
        self.member = member
        self.sub = sub

    def _index(self, vector: np.ndarray[Any, Any]) -> int:
        if "." in self.sub or vector.ndim != 1:
            raise NotFound(f"`{self.path}`: a vector has no sub-property `{self.sub}`")
        try:
            return vector_index(self.sub, len(vector))
        except NotFound as e:
            raise NotFound(f"`{self.path}`: {e.message}") from None

    def peek(self) -> Value:
        value = getattr(self.owner, self.member.name)
        if isinstance(value, np.ndarray):
            return format_number(float(value[self._index(value)]))
        if isinstance(value, Marker):
            try:
                return value.get(self.sub)
            except NotFound as e:
                raise NotFound(f"`{self.path}`: {e.message}") from None
        raise NotFound(f"`{self.path}`: `{self.member.name}` has no sub-properties")

    async def get(self, params: Mapping[str, str]) -> Value:
        if params:
            self._no_params(params)
        return self.peek()

    async def set(self, value: Value, params: Mapping[str, str]) -> Value:
        member = self.member
        current = getattr(self.owner, member.name)
        if not isinstance(current, np.ndarray):
            raise ReadOnly(f"`{self.path}` is read-only: Set `{member.name}` as a whole")
        index = self._index(current)
        if member.readonly:
            raise ReadOnly(f"`{self.path}` is read-only")
        self._no_params(params)
        check_form(self.path, member, value)
        try:
            x = parse_number(as_text(value))
        except InvalidArgument as e:
            raise _bad_value(self.path, e) from None
        new = current.copy()
        new[index] = x
        setattr(self.owner, member.name, new)
        return self.peek()

    def hook(self, callback: Callable[[], None]) -> Callable[[], None] | None:
        return _watch_key(self.owner, self.member.name, callback)


class MetaTarget(Target):
    """``NAME.parameters``, ``NAME.gui``, ``NAME.doc``: fixed text."""

    __slots__ = ("text",)

    def __init__(self, path: str, text: str) -> None:
        super().__init__(path)
        self.text = text

    def peek(self) -> str:
        return self.text


class NamespaceTarget(Target):
    """A child namespace: its value is its own ``_value()`` or the names directly under it."""

    __slots__ = ("node",)

    def __init__(self, path: str, node: Resource | Backend) -> None:
        super().__init__(path)
        self.node = node

    async def get(self, params: Mapping[str, str]) -> str:
        node = self.node
        if isinstance(node, Resource):
            self._no_params(params)
            return self.peek()
        names = await node.properties()
        return format_names([n for n in names if "." not in n])

    async def set(self, value: Value, params: Mapping[str, str]) -> Value:
        raise ReadOnly(f"`{self.path}` is a namespace and cannot be set; see `{self.path}.properties`")

    def peek(self) -> str:
        node = self.node
        if not isinstance(node, Resource):
            raise NeedsAwait
        if class_spec(type(node)).has_value:
            return format_value(node._value())  # type: ignore[attr-defined]
        return format_names(direct_names(node))

    def hook(self, callback: Callable[[], None]) -> Callable[[], None] | None:
        if isinstance(self.node, Resource):
            return _watch_key(self.node, "", callback)
        return None


class PropertiesTarget(Target):
    """The live list of every property path under a Resource."""

    __slots__ = ("root",)

    def __init__(self, path: str, root: Resource) -> None:
        super().__init__(path)
        self.root = root

    async def get(self, params: Mapping[str, str]) -> str:
        self._no_params(params)
        return format_names(await all_properties(self.root))

    def peek(self) -> str:
        return format_names(properties_now(self.root))

    def hook(self, callback: Callable[[], None]) -> Callable[[], None] | None:
        root = self.root

        def watcher(path: str, removed: bool) -> None:
            callback()

        root._ps_tree_watchers.append(watcher)

        def unhook() -> None:
            if watcher in root._ps_tree_watchers:
                root._ps_tree_watchers.remove(watcher)

        return unhook


class RemoteTarget(Target):
    """A path inside a Backend child: requests are forwarded with the prefix cut off."""

    __slots__ = ("backend", "prefix", "rest")

    def __init__(self, path: str, backend: Backend, prefix: str, rest: str) -> None:
        super().__init__(path)
        self.backend = backend
        self.prefix = prefix
        self.rest = rest

    async def get(self, params: Mapping[str, str]) -> Value:
        return await self.backend.get(self.rest, params)

    async def set(self, value: Value, params: Mapping[str, str]) -> Value:
        return await self.backend.set(self.rest, value, params)


def _namespace_meta(path: str, meta: str, doc: str) -> MetaTarget:
    if meta == "parameters":
        return MetaTarget(path, "()")
    if meta == "gui":
        return MetaTarget(path, "group")
    return MetaTarget(path, doc)


def _member_meta(path: str, member: Member, meta: str) -> MetaTarget:
    if meta == MEDIA_TYPE:
        return MetaTarget(path, member.media_type)
    if meta == "parameters":
        return MetaTarget(path, member.parameters_text)
    if meta == "gui":
        return MetaTarget(path, member.gui)
    return MetaTarget(path, member.doc)


#: ``NAME.media_type``: the media type of a binary property (or of a binary answer).
MEDIA_TYPE = "media_type"


def _has_media(member: Member) -> bool:
    return member.binary or bool(member.media_type) or member.result_type is bytes


def resolve(root: Resource, path: str) -> Target:
    """Resolve a valid ``path`` under ``root``; NotFound (with close matches) for an unknown one."""
    if path == "properties":
        return PropertiesTarget(path, root)
    segments = path.split(".")
    node = root
    i = 0
    last = len(segments) - 1
    while True:
        name = segments[i]
        child = node._ps_children.get(name)
        if child is not None:
            if i == last:
                return NamespaceTarget(path, child)
            if not isinstance(child, Resource):
                if i + 1 == last and segments[last] in META_NAMES:
                    # The namespace itself is ours to describe; a Backend has no
                    # top-level `gui` to ask.
                    return _namespace_meta(path, segments[last], "")
                prefix = ".".join(segments[: i + 1])
                return RemoteTarget(path, child, prefix, path[len(prefix) + 1 :])
            following = segments[i + 1]
            if (
                i + 1 == last
                and following in META_NAMES
                and following not in child._ps_children
                and following not in class_spec(type(child)).members
            ):
                return _namespace_meta(path, following, class_spec(type(child)).doc)
            node = child
            i += 1
            continue
        member = class_spec(type(node)).members.get(name)
        if member is None or member.kind is MemberKind.CHILD:
            prefix = ".".join(segments[:i])
            prefix = prefix + "." if prefix else ""
            where = f"`{prefix[:-1]}`" if prefix else "this service"
            raise NotFound(
                f"unknown property `{prefix}{name}`: {where} has no `{name}`"
                + _suggest(name, direct_names(node), prefix)
            )
        if i == last:
            return MemberTarget(path, node, member)
        rest = segments[i + 1 :]
        if len(rest) == 1 and (rest[0] in META_NAMES or (rest[0] == MEDIA_TYPE and _has_media(member))):
            return _member_meta(path, member, rest[0])
        if member.kind is MemberKind.FUNCTIONAL:
            raise NotFound(
                f"unknown property `{path}`: `{name}` is a functional property with no sub-properties"
            )
        target = SubTarget(path, node, member, ".".join(rest))
        target.peek()  # raises NotFound when the sub-property does not exist
        return target
