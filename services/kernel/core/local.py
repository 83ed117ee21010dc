"""Serving a Resource as a Backend, in-process, on the event loop."""

from __future__ import annotations

import asyncio
import functools
import itertools
import logging
from collections.abc import Coroutine, Mapping
from typing import Any

from services.kernel.backend import NO_PARAMS, Backend, BackendInfo, Change, Notify, Subscription, tell_each
from services.kernel.backoff import pauses, wait_to_retry
from services.kernel.core.describe import describe_matching, describe_tree
from services.kernel.core.metadata import class_spec
from services.kernel.core.resource import Resource, start_tree, stop_tree
from services.kernel.core.tree import (
    NeedsAwait,
    RemoteTarget,
    Target,
    all_properties,
    remote_children,
    remote_prefixes,
    resolve,
)
from services.kernel.directory import own_context
from services.kernel.errors import Code, NotFound, PropertyError
from services.kernel.model import PropertyModel, ServiceModel
from services.kernel.paths import validate_path
from services.kernel.values import Value

__all__ = ["LocalService", "serve"]

log = logging.getLogger(__name__)

#: Resolved paths kept per service; a client naming ever new paths cannot grow it without bound.
_MAX_CACHED_PATHS = 4096
#: Seconds before the property list of a Backend child that could not be reached (a member
#: device that is away) is asked for again, doubled up to the second: as the gateway's
#: wildcard Listens try a service again (gateway.engine.listen.stream.RETRY_FIRST_S, RETRY_MAX_S).
REMOTE_LIST_RETRY_FIRST_S = 0.5
REMOTE_LIST_RETRY_MAX_S = 10.0
#: Codes that mean "not now": the child may answer later.
_TRANSIENT = (Code.UNAVAILABLE, Code.DEADLINE_EXCEEDED)


def _compile_tree(obj: Resource) -> None:
    """Compile every class in the tree now, so that a badly written class fails when served, not on a Get."""
    class_spec(type(obj))
    for child in obj._ps_children.values():
        if isinstance(child, Resource):
            _compile_tree(child)


class _Watch:
    """Every listener of one path; fires them when the formatted value really changed."""

    __slots__ = ("_gap", "_pending", "_service", "_unhook", "last", "listeners", "path", "target")

    def __init__(self, service: LocalService, path: str, target: Target) -> None:
        self._service = service
        self.path = path
        self.target = target
        self.listeners: dict[int, Notify] = {}
        self._pending: asyncio.Task[None] | None = None
        #: The value a pending fire delivers follows a gap (see :meth:`fire`).
        self._gap = False
        try:
            self.last: Value | None = target.peek()
        except NeedsAwait:
            self.last = None
        except PropertyError:
            self.last = ""
        self._unhook = target.hook(self.fire)

    def fire(self, gap: bool = False) -> None:
        """The value may have changed; ``gap``: changes before it may have been missed."""
        try:
            value = self.target.peek()
        except NeedsAwait:
            self._gap = self._gap or gap
            if self._pending is None or self._pending.done():
                # Read for every listener (each was checked when it joined), not for whoever
                # made the change: the service's own work.
                self._pending = asyncio.get_running_loop().create_task(
                    self._fire_later(), context=own_context()
                )
            return
        except PropertyError:
            value = ""  # e.g. a marker field that is gone for now
        self.deliver(value, gap=gap)

    async def _fire_later(self) -> None:
        await asyncio.sleep(0)  # coalesce the burst of changes that scheduled this
        try:
            value = await self.target.get(NO_PARAMS)
        except PropertyError:
            value = ""
        gap, self._gap = self._gap, False
        self.deliver(value, gap=gap)

    def deliver(self, value: Value, *, removed: bool = False, gap: bool = False) -> None:
        if value == self.last and not removed:
            return
        self.last = value
        tell_each(self.listeners, Change(self.path, value, gap=gap, removed=removed), what=self.path)

    def close(self) -> None:
        if self._unhook is not None:
            self._unhook()
            self._unhook = None
        if self._pending is not None:
            self._pending.cancel()
            self._pending = None
        self.listeners.clear()


class _LocalSubscription(Subscription):
    __slots__ = ("_service", "_token", "_watch")

    def __init__(self, service: LocalService, watch: _Watch, token: int) -> None:
        self._service = service
        self._watch = watch
        self._token = token

    async def close(self) -> None:
        self._service._drop_listener(self._watch, self._token)


class _ListSubscription(Subscription):
    """A listener of the property list (:meth:`LocalService.listen_properties`)."""

    __slots__ = ("_service", "_token")

    def __init__(self, service: LocalService, token: int) -> None:
        self._service = service
        self._token = token

    async def close(self) -> None:
        self._service._drop_list_listener(self._token)


class _RemoteSubscription(Subscription):
    """A listen forwarded into a Backend child, with its paths put back under the child's name."""

    def __init__(self, service: LocalService, path: str, prefix: str, notify: Notify) -> None:
        self._service = service
        self.path = path
        self.prefix = prefix
        self.notify = notify
        self.inner: Subscription | None = None
        self.closed = False

    def forward(self, change: Change) -> None:
        if self.closed:
            return
        self.notify(Change(f"{self.prefix}.{change.path}", change.value, change.gap, change.removed))

    async def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        self._service._remote.pop(id(self), None)
        if self.inner is not None:
            await self.inner.close()


class LocalService(Backend):
    """Serves a :class:`Resource` (and everything under it) as a Backend.

    All work happens on the event loop: a Get reads the attribute, a Set
    parses and assigns it, a Listen hooks the attribute so that assigning it
    calls the listeners directly. Resolved paths are cached until the tree
    of children changes.
    """

    def __init__(self, obj: Resource, url: str = "local") -> None:
        if not isinstance(obj, Resource):
            raise TypeError(f"LocalService serves a Resource, not a {type(obj).__name__}")
        _compile_tree(obj)
        self.obj = obj
        self.info = BackendInfo(type=obj.resource_type, url=url)
        self._targets: dict[str, Target] = {}
        self._watches: dict[str, _Watch] = {}
        self._remote: dict[int, _RemoteSubscription] = {}
        self._tokens = itertools.count()
        self._closed = False
        #: Listeners of the property list (listen_properties): told where the tree changed.
        self._list_listeners: dict[int, Notify] = {}
        # While the list is followed (a listen on `properties`, or a listener of the list): a
        # listen on the property list of every remote child.
        self._remote_lists: dict[int, tuple[Backend, Subscription]] = {}
        self._remote_lists_lock = asyncio.Lock()
        # Remote children whose list could not be followed (not reachable): one retry task each.
        self._remote_list_retries: dict[int, asyncio.Task[None]] = {}
        self._tasks: set[asyncio.Task[None]] = set()
        obj._ps_tree_watchers.append(self._on_tree)

    #: Reading an attribute answers without waiting: callers step calls inline.
    answers_inline = True

    def serves(self, obj: object) -> bool:
        return obj is self.obj

    def __repr__(self) -> str:
        return f"LocalService({type(self.obj).__name__}, url={self.info.url!r})"

    def _target(self, path: str) -> Target:
        target = self._targets.get(path)
        if target is None:
            target = resolve(self.obj, validate_path(path))
            if len(self._targets) >= _MAX_CACHED_PATHS:
                self._targets.clear()
            self._targets[path] = target
        return target

    async def get(self, path: str, params: Mapping[str, str] = NO_PARAMS) -> Value:
        target = self._targets.get(path) or self._target(path)
        return await target.get(params)

    async def set(self, path: str, value: Value, params: Mapping[str, str] = NO_PARAMS) -> Value:
        try:
            target = self._target(path)
        except NotFound:
            # A service may make a child on a Set (Resource.create_on_set): `M.definition` loads machine M.
            name, _, rest = path.partition(".")
            if not rest or name in self.obj._ps_children or not self.obj.create_on_set(name, rest):
                raise
            target = self._target(path)
        return await target.set(value, params)

    async def listen(self, path: str, notify: Notify, params: Mapping[str, str] = NO_PARAMS) -> Subscription:
        """Listen to ``path``; request parameters do not change what is listened to and are ignored."""
        target = self._target(path)
        refused = target.listen_refused()
        if refused is not None:
            raise refused
        if isinstance(target, RemoteTarget):
            sub = _RemoteSubscription(self, path, target.prefix, notify)
            self._remote[id(sub)] = sub
            try:
                sub.inner = await target.backend.listen(target.rest, sub.forward, params)
            except BaseException:
                self._remote.pop(id(sub), None)
                raise
            if sub.closed:  # the child was detached while the listen was on its way
                await sub.inner.close()
            return sub
        watch = self._watches.get(path)
        if watch is None:
            watch = _Watch(self, path, target)
            self._watches[path] = watch
        token = next(self._tokens)
        watch.listeners[token] = notify
        if path == "properties" and len(watch.listeners) == 1:
            await self._sync_remote_lists()
        return _LocalSubscription(self, watch, token)

    def _drop_listener(self, watch: _Watch, token: int) -> None:
        if watch.listeners.pop(token, None) is None:
            return
        if not watch.listeners:
            watch.close()
            if self._watches.get(watch.path) is watch:
                del self._watches[watch.path]
            if watch.path == "properties":
                self._lists_unfollowed()

    def _drop_list_listener(self, token: int) -> None:
        if self._list_listeners.pop(token, None) is not None and not self._list_listeners:
            self._lists_unfollowed()

    def _lists_unfollowed(self) -> None:
        """A listener of the list left: stop following the remote children's lists if it was the last."""
        if not self._list_followed() and (self._remote_lists or self._remote_list_retries):
            self._spawn(self._sync_remote_lists(), "stop following remote property lists")

    def _list_followed(self) -> bool:
        """Somebody follows the property list: a listen on ``properties``, or a listener of the list."""
        return bool(self._list_listeners) or "properties" in self._watches

    def _on_tree(self, path: str, removed: bool) -> None:
        self._targets.clear()
        if self._remote_tree_changed(path, removed):
            self._spawn(self._sync_remote_lists(), "follow remote property lists")
        if self._list_listeners:
            self._tell_list_listeners(Change(path, ""))
        if not removed:
            return
        below = path + "."
        for watch_path in [p for p in self._watches if p == path or p.startswith(below)]:
            watch = self._watches.pop(watch_path)
            watch.deliver("", removed=True)
            watch.close()
        gone = [s for s in self._remote.values() if s.path == path or s.path.startswith(below)]
        for sub in gone:
            sub.closed = True
            self._remote.pop(id(sub), None)
            sub.notify(Change(sub.path, "", removed=True))
            if sub.inner is not None:
                self.obj._ps_spawn(sub.inner.close(), f"close listen on {sub.path}")

    def _remote_tree_changed(self, path: str, removed: bool) -> bool:
        """Whether the change at ``path`` may change which remote children's lists are followed.

        Only the part of the tree at ``path`` is looked at: a registry of 10,000 entries is not
        walked again on each registration.
        """
        if removed:
            return bool(self._remote_lists or self._remote_list_retries)
        if not self._list_followed():
            return False
        node: Resource | Backend = self.obj
        for name in path.split("."):
            if not isinstance(node, Resource) or name not in node._ps_children:
                return True  # changed again meanwhile: look at the whole tree
            node = node._ps_children[name]
        return not isinstance(node, Resource) or bool(remote_children(node))

    def _tell_list_listeners(self, change: Change) -> None:
        tell_each(self._list_listeners, change, what="the property list")

    def _spawn(self, coro: Coroutine[Any, Any, None], what: str) -> asyncio.Task[None]:
        task = asyncio.get_running_loop().create_task(coro, name=what, context=own_context())
        self._tasks.add(task)

        def done(t: asyncio.Task[None]) -> None:
            self._tasks.discard(t)
            if not t.cancelled() and t.exception() is not None:
                log.error("%s failed", what, exc_info=t.exception())

        task.add_done_callback(done)
        return task

    def _remote_list_changed(self, backend: Backend, change: Change) -> None:
        """The property list of the remote child ``backend`` changed (at ``change.path`` in it)."""
        watch = self._watches.get("properties")
        if watch is not None:
            watch.fire(gap=change.gap)
        if self._list_listeners:
            for prefix in remote_prefixes(self.obj, backend):
                where = f"{prefix}.{change.path}" if change.path else prefix
                self._tell_list_listeners(Change(where, "", gap=change.gap))

    async def _sync_remote_lists(self) -> None:
        """While the property list is followed, follow the list of every remote child."""
        async with self._remote_lists_lock:
            listened = self._list_followed() and not self._closed
            wanted = {id(b): b for b in remote_children(self.obj)} if listened else {}
            for key in [k for k in self._remote_lists if k not in wanted]:
                _, sub = self._remote_lists.pop(key)
                await sub.close()
            for key in [k for k in self._remote_list_retries if k not in wanted]:
                self._remote_list_retries.pop(key).cancel()
            for key, backend in wanted.items():
                if key in self._remote_lists or key in self._remote_list_retries:
                    continue
                try:
                    sub = await backend.listen_properties(
                        functools.partial(self._remote_list_changed, backend)
                    )
                except PropertyError as e:
                    log.debug("cannot follow the property list of %r: %s", backend, e.message)
                    if e.code in _TRANSIENT:
                        self._remote_list_retries[key] = self._spawn(
                            self._follow_remote_list_later(key, backend), f"follow the list of {backend!r}"
                        )
                    continue
                self._remote_lists[key] = (backend, sub)

    async def _follow_remote_list_later(self, key: int, backend: Backend) -> None:
        """Ask a remote child that could not be reached for its list again, less and less often.

        Once it answers, its names join ``properties``, delivered marked as a gap (the listing
        may have missed changes meanwhile). Ends when it answers, or refuses for good, or is no
        longer a child, or nobody listens to ``properties`` (cancelled by the sync).
        """
        mine = asyncio.current_task()
        try:
            for pause in pauses(REMOTE_LIST_RETRY_FIRST_S, REMOTE_LIST_RETRY_MAX_S):
                await wait_to_retry(backend, pause)
                try:
                    sub = await backend.listen_properties(
                        functools.partial(self._remote_list_changed, backend)
                    )
                except PropertyError as e:
                    if e.code in _TRANSIENT:
                        continue
                    log.debug("cannot follow the property list of %r: %s", backend, e.message)
                    return
                async with self._remote_lists_lock:
                    wanted = (
                        self._list_followed()
                        and not self._closed
                        and key not in self._remote_lists
                        and any(b is backend for b in remote_children(self.obj))
                    )
                    if wanted:
                        self._remote_lists[key] = (backend, sub)
                if not wanted:
                    await sub.close()
                    return
                self._remote_list_changed(backend, Change("", "", gap=True))
                return
        finally:
            if self._remote_list_retries.get(key) is mine:
                del self._remote_list_retries[key]

    async def properties(self) -> list[str]:
        return await all_properties(self.obj)

    async def match_properties(self, pattern: str, under: str = "") -> list[PropertyModel]:
        """The matches of ``pattern`` from a walk of only what it names (:func:`describe_matching`):
        no list of every property is made, however big the tree."""
        return [self.model_of(p) for p in await describe_matching(self.obj, pattern, under)]

    async def listen_properties(self, notify: Notify) -> Subscription:
        """Tell ``notify`` where the tree changes (a child attached or detached, a Backend child's
        own list changed), as it changes: the list itself is never formatted for it."""
        token = next(self._tokens)
        self._list_listeners[token] = notify
        if len(self._list_listeners) == 1:
            await self._sync_remote_lists()
        return _ListSubscription(self, token)

    async def describe(self) -> ServiceModel:
        """The model of every property of the object's tree, Backend children's through their own."""
        properties = tuple(self.model_of(p) for p in await describe_tree(self.obj))
        return ServiceModel(type=self.info.type, properties=properties, doc=class_spec(type(self.obj)).doc)

    def model_of(self, prop: PropertyModel) -> PropertyModel:
        """The model of ``prop`` as this service gives it: the class wrapper's, by default.

        A subclass serving what the class wrapper cannot express alone (a property read with a
        parameter, a node typed as a value) refines it here; :meth:`describe` and
        :meth:`match_properties` both give what it answers.
        """
        return prop

    async def start(self) -> None:
        """Start the object's background work, children first."""
        await start_tree(self.obj)

    async def aclose(self) -> None:
        """Stop the object and end every listen. Idempotent."""
        if self._closed:
            return
        self._closed = True
        if self._on_tree in self.obj._ps_tree_watchers:
            self.obj._ps_tree_watchers.remove(self._on_tree)
        for watch in list(self._watches.values()):
            watch.close()
        self._watches.clear()
        self._list_listeners.clear()
        for sub in list(self._remote.values()):
            await sub.close()
        for task in list(self._tasks):
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        await self._sync_remote_lists()
        self._targets.clear()
        await stop_tree(self.obj)


def serve(obj: Resource, url: str = "local") -> Backend:
    """The Backend serving ``obj``: its class's ``served_by`` (a LocalService subclass) or LocalService."""
    served_by = type(obj).served_by
    return LocalService(obj, url) if served_by is None else served_by(obj, url)
