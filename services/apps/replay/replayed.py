"""One recorded service served again: the recorded model, the values where the replay stands.

A :class:`ReplayedService` is an ordinary :class:`~services.kernel.backend.Backend`: Get,
Listen, Describe and wildcards work on it as on the service that was recorded, and its
listeners hear each recorded change (with its ``gap`` and ``removed``) when the replay reaches
it. What tells it apart is its mark: the model's ``doc`` and the registry's URL say
``replayed from …``, and every Set is FAILED_PRECONDITION saying so.
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping

from services.apps.replay.recording import RecordedService
from services.kernel.backend import (
    NO_PARAMS,
    Backend,
    BackendInfo,
    Change,
    Notify,
    Subscription,
    tell_each,
)
from services.kernel.errors import FailedPrecondition, NotFound, ReadOnly, Unavailable
from services.kernel.model import Access, PropertyModel, ServiceModel
from services.kernel.values import Value, format_names

__all__ = ["REPLAY_SCHEME", "ReplayedService"]

#: The scheme of a replayed service's URL in the registry (``replay:demo-0001.mcap``).
REPLAY_SCHEME = "replay"
#: The property every service lists its properties in.
_PROPERTIES = "properties"


class _Listening(Subscription):
    def __init__(self, listeners: dict[int, Notify], token: int) -> None:
        self._listeners = listeners
        self._token = token

    async def close(self) -> None:
        self._listeners.pop(self._token, None)


class ReplayedService(Backend):
    """A recorded service served from its recording; the replay tells it each change (:meth:`apply`)."""

    answers_inline = True

    def __init__(self, recorded: RecordedService, source: str, position: object) -> None:
        """``source``: what it is replayed from, as its mark shows it; ``position``: an object whose
        text says where the replay stands (named in the answer to a Get of a value not recorded yet)."""
        self.name = recorded.name
        self.mark = f"replayed from {source}"
        self.info = BackendInfo(type=recorded.type, url=f"{REPLAY_SCHEME}:{source}")
        recorded_doc = recorded.model.doc
        self.model = ServiceModel(
            type=recorded.type,
            properties=recorded.model.properties,
            doc=f"{self.mark}: {recorded_doc}" if recorded_doc else self.mark,
        )
        self._props: dict[str, PropertyModel] = {p.name: p for p in recorded.model.properties}
        self._position = position
        #: The value of each property where the replay stands (none before its first change).
        self._values: dict[str, Value] = {}
        #: The properties removed where the replay stands (NOT_FOUND, as they were then).
        self._removed: set[str] = set()
        self._listeners: dict[str, dict[int, Notify]] = {}
        self._tokens = itertools.count()

    # -- what the replay does ----------------------------------------------------

    def apply(self, path: str, value: Value, *, gap: bool = False, removed: bool = False) -> None:
        """The replay reached a change of ``path``: hold it and tell its listeners."""
        listed = path not in self._removed
        if removed:
            self._values.pop(path, None)
            self._removed.add(path)
        else:
            self._values[path] = value
            self._removed.discard(path)
        listeners = self._listeners.get(path)
        if listeners:
            tell_each(listeners, Change(path, "" if removed else value, gap, removed), what=self.name)
        if listed == removed:
            self._tell_properties()  # it went, or came back: wildcard Listens look at the list again

    def forget(self, path: str) -> None:
        """The replay went back to before ``path``'s first change: it has no value (not removed)."""
        had = path in self._values
        self._values.pop(path, None)
        if path in self._removed:
            self._removed.discard(path)
            self._tell_properties()
        listeners = self._listeners.get(path)
        if had and listeners:
            tell_each(listeners, Change(path, "", gap=True, removed=True), what=self.name)

    def values(self) -> dict[str, Value]:
        """The values held now (a copy)."""
        return dict(self._values)

    def removed(self) -> set[str]:
        """The properties removed where the replay stands (a copy)."""
        return set(self._removed)

    def _tell_properties(self) -> None:
        followers = self._listeners.get(_PROPERTIES)
        if followers:
            tell_each(followers, Change(_PROPERTIES, self._names()), what=self.name)

    def _names(self) -> str:
        return format_names([name for name in self._props if name not in self._removed])

    # -- Backend -----------------------------------------------------------------

    def _read_only(self, path: str) -> ReadOnly:
        return ReadOnly(f"{self.name}.{path} is {self.mark}: read-only")

    def _model_of(self, path: str) -> PropertyModel | None:
        prop = self._props.get(path)
        if path in self._removed:
            raise NotFound(f"{self.name}.{path} is {self.mark}: it was removed before {self._position} s")
        if prop is None and path not in self._values:
            raise NotFound(f"{self.name} ({self.mark}) has no property {path[:200]!r}")
        return prop

    async def get(self, path: str, params: Mapping[str, str] = NO_PARAMS) -> Value:
        if path == _PROPERTIES:
            return self._names()
        prop = self._model_of(path)
        if prop is not None and prop.access is Access.ACTION:
            raise FailedPrecondition(f"{self.name}.{path} is an action ({self.mark}): it has no value")
        value = self._values.get(path)
        if value is None:
            raise Unavailable(
                f"{self.name}.{path} is {self.mark}: no value of it is recorded before {self._position} s"
            )
        return value

    async def set(self, path: str, value: Value, params: Mapping[str, str] = NO_PARAMS) -> Value:
        if path != _PROPERTIES:
            self._model_of(path)
        raise self._read_only(path)

    async def listen(self, path: str, notify: Notify, params: Mapping[str, str] = NO_PARAMS) -> Subscription:
        if path != _PROPERTIES:
            prop = self._model_of(path)
            if prop is not None and prop.access is Access.ACTION:
                raise FailedPrecondition(f"{self.name}.{path} is an action ({self.mark}): it has no value")
        # ``properties`` changes only when the recording removes a property or a seek brings it back.
        listeners = self._listeners.setdefault(path, {})
        token = next(self._tokens)
        listeners[token] = notify
        return _Listening(listeners, token)

    async def describe(self) -> ServiceModel:
        return self.model

    async def match_properties(self, pattern: str, under: str = "") -> list[PropertyModel]:
        # A property removed where the replay stands is not there to follow, as it was not then.
        matching = await super().match_properties(pattern, under)
        return [p for p in matching if p.name not in self._removed]

    async def aclose(self) -> None:
        self._listeners.clear()
