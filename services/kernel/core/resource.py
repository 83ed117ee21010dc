"""The base class of every service object."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable
from typing import Any, ClassVar, Protocol

from services.kernel.backend import Backend
from services.kernel.core.metadata import RESERVED_NAMES, MemberKind, Namespace, class_spec
from services.kernel.directory import own_context
from services.kernel.errors import AlreadyExists, InvalidArgument, NotFound
from services.kernel.paths import validate_service_name

__all__ = ["Resource"]

log = logging.getLogger(__name__)

#: Called on a structural change below a resource: (path of the added or removed child, removed?).
TreeWatcher = Callable[[str, bool], None]


class BackendFactory(Protocol):
    """What ``Resource.served_by`` names: a LocalService subclass, called with the object and its URL."""

    def __call__(self, obj: Any, url: str, /) -> Backend: ...


def _is_functional(cls: type, name: str) -> bool:
    """A functional property named like a lifecycle hook (``behaviors.stop``) is not the hook."""
    member = class_spec(cls).members.get(name)
    return member is not None and member.kind is MemberKind.FUNCTIONAL


class Resource(Namespace):
    """A Property Service object written as a plain Python class.

    Annotated public attributes are read/write properties, ``@property`` is a
    computed read-only property, ``@functional`` methods are functional
    properties and attributes holding a Resource or Backend are namespaces.
    Assigning an exposed attribute notifies its listeners. See
    ``docs/architecture.md``, "Writing a service: the class wrapper".
    """

    #: Reported as ``BackendInfo.type`` (``mobile_robot``, ``sensor``, ``registry``, ...).
    resource_type: ClassVar[str] = "resource"
    #: The Backend that serves this class (:func:`services.kernel.core.serve`); None: ``LocalService``.
    #: A class with a property the class wrapper cannot express alone names a ``LocalService``
    #: subclass here (a storage service's ``file``: read, written and followed with a parameter).
    served_by: ClassVar[BackendFactory | None] = None

    # Per-instance bookkeeping, created in __new__ so subclasses need not call super().__init__().
    _ps_watch: dict[str, list[Callable[[], None]]]
    _ps_children: dict[str, Resource | Backend]
    _ps_parent: Resource | None
    _ps_name: str
    _ps_tree_watchers: list[TreeWatcher]
    _ps_running: bool
    _ps_tasks: set[asyncio.Task[None]]

    def __new__(cls, *args: Any, **kwargs: Any) -> Resource:
        self = super().__new__(cls)
        init = object.__setattr__
        init(self, "_ps_watch", {})
        init(self, "_ps_children", {})
        init(self, "_ps_parent", None)
        init(self, "_ps_name", "")
        init(self, "_ps_tree_watchers", [])
        init(self, "_ps_running", False)
        init(self, "_ps_tasks", set())
        return self

    def __setattr__(self, name: str, value: Any) -> None:
        if name[0] == "_":  # private: never a property, never watched
            object.__setattr__(self, name, value)
            return
        if isinstance(value, _NAMESPACE_TYPES):
            self._ps_put_child(name, value, as_attribute=True)
            return
        if name in self._ps_children:
            self._ps_drop_child(name)
        object.__setattr__(self, name, value)
        callbacks = self._ps_watch.get(name)
        if callbacks:
            for callback in tuple(callbacks):
                callback()

    # -- notifications -------------------------------------------------------

    def changed(self, name: str = "") -> None:
        """Tell listeners that property ``name`` (a computed one) may have a new value.

        With no name: this namespace's own value (``_value``) may have changed.
        Listeners hear of it only when the formatted text actually differs.
        """
        callbacks = self._ps_watch.get(name)
        if callbacks:
            for callback in tuple(callbacks):
                callback()

    # -- children --------------------------------------------------------------

    def attach(self, name: str, obj: Resource | Backend) -> None:
        """Add child namespace ``name`` while running; ``properties`` changes and its listeners hear it."""
        validate_service_name(name)
        if name in self._ps_children:
            raise AlreadyExists(f"{name!r} is already a child of this {type(self).__name__}")
        if name in RESERVED_NAMES or name in class_spec(type(self)).members:
            raise AlreadyExists(f"{name!r} is already a property of this {type(self).__name__}")
        if not isinstance(obj, Resource | Backend):
            raise InvalidArgument(f"only a Resource or a Backend can be attached, not a {type(obj).__name__}")
        self._ps_put_child(name, obj, as_attribute=False)

    def detach(self, name: str) -> Resource | Backend:
        """Remove child namespace ``name``; listeners of its properties get a removal. Returns the child."""
        if name not in self._ps_children:
            raise NotFound(f"{type(self).__name__} has no child {name!r}")
        child = self._ps_children[name]
        self._ps_drop_child(name)
        if self.__dict__.get(name) is child:
            object.__delattr__(self, name)
        return child

    def create_on_set(self, name: str, rest: str) -> bool:
        """A Set of ``name.rest`` where this service has no ``name``: make it here and return True.

        By default False, and the Set is NOT_FOUND. A service whose children are
        made by a Set (a state machine service: a Set of ``M.definition`` loads
        machine ``M``) attaches the child here; the Set then goes to it. Called
        on the service's root object only.
        """
        return False

    def children(self) -> dict[str, Resource | Backend]:
        """The child namespaces right now, in order (a copy)."""
        return dict(self._ps_children)

    def _ps_put_child(self, name: str, obj: Resource | Backend, *, as_attribute: bool) -> None:
        if name in RESERVED_NAMES:
            raise AlreadyExists(f"{name!r} is reserved for the service itself")
        old = self._ps_children.get(name)
        if old is obj:
            return
        if old is not None:
            self._ps_drop_child(name)
        if isinstance(obj, Resource):
            if obj._ps_parent is not None:
                raise InvalidArgument(
                    f"{type(obj).__name__} is already attached as {obj._ps_name!r} elsewhere"
                )
            object.__setattr__(obj, "_ps_parent", self)
            object.__setattr__(obj, "_ps_name", name)
        self._ps_children[name] = obj
        if as_attribute:
            object.__setattr__(self, name, obj)
        if self._ps_running and isinstance(obj, Resource):
            self._ps_spawn(obj._ps_start_tree(), f"start {name}")
        self._ps_structure_changed(name, removed=False)

    def _ps_drop_child(self, name: str) -> None:
        obj = self._ps_children.pop(name)
        if isinstance(obj, Resource):
            object.__setattr__(obj, "_ps_parent", None)
            if obj._ps_running:
                self._ps_spawn(obj._ps_stop_tree(), f"stop {name}")
        self._ps_structure_changed(name, removed=True)

    def _ps_structure_changed(self, name: str, *, removed: bool) -> None:
        self.changed()  # the namespace's own value (its names) changed
        node: Resource | None = self
        rel = name
        while node is not None:
            for watcher in tuple(node._ps_tree_watchers):
                watcher(rel, removed)
            if node._ps_parent is None:
                break
            rel = f"{node._ps_name}.{rel}"
            node = node._ps_parent

    # -- lifecycle ---------------------------------------------------------------

    async def start(self) -> None:
        """Start background work; called when the service starts, after the children started.

        A class may instead expose a functional property named ``start`` or ``stop``
        (``behaviors.stop``); it is then a property only, not a lifecycle hook.
        """

    async def stop(self) -> None:
        """Stop background work; called when the service stops, before the children stop."""

    async def _ps_start_tree(self) -> None:
        if self._ps_running:
            return
        object.__setattr__(self, "_ps_running", True)
        for child in list(self._ps_children.values()):
            if isinstance(child, Resource):
                await child._ps_start_tree()
        if not _is_functional(type(self), "start"):
            await self.start()

    async def _ps_stop_tree(self) -> None:
        if not self._ps_running:
            return
        object.__setattr__(self, "_ps_running", False)
        try:
            if not _is_functional(type(self), "stop"):
                await self.stop()
        finally:
            for child in list(self._ps_children.values()):
                if isinstance(child, Resource):
                    await child._ps_stop_tree()
            tasks = list(self._ps_tasks)
            for task in tasks:
                task.cancel()
            if tasks:
                await asyncio.gather(*tasks, return_exceptions=True)

    def _ps_spawn(self, coro: Any, what: str) -> None:
        # Background work is the service's own, whichever client's call started it.
        task: asyncio.Task[None] = asyncio.get_running_loop().create_task(
            coro, name=what, context=own_context()
        )
        self._ps_tasks.add(task)

        def done(t: asyncio.Task[None]) -> None:
            self._ps_tasks.discard(t)
            if not t.cancelled() and t.exception() is not None:
                log.error("%s of %s failed", what, type(self).__name__, exc_info=t.exception())

        task.add_done_callback(done)


# A tuple, not ``Resource | Backend``: the union would be built anew on every assignment.
_NAMESPACE_TYPES = (Resource, Backend)


async def start_tree(obj: Resource) -> None:
    """Start ``obj`` and its Resource children (their ``start`` hooks), children first; idempotent."""
    await obj._ps_start_tree()


async def stop_tree(obj: Resource) -> None:
    """Stop ``obj`` and then its Resource children, cancelling their tasks; idempotent."""
    await obj._ps_stop_tree()
