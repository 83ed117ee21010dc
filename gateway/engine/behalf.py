"""Calls a system service makes on a client's behalf, checked as that client.

A group reads ``robots.scout1.sensors.battery`` by asking ``scout1`` for
``sensors.battery``; a wildcard Get expands into a member's properties; a chart's
``ps:set`` writes another service. Each of these reaches the other service through
the directory the gateway hands every system service (:class:`gateway.engine.router.RouterDirectory`),
and with rules configured that directory hands out :class:`OnBehalf` backends: every
Get, Set, Listen, Describe and match of one is checked, for its own service and
path, as the caller in :data:`services.kernel.directory.CALLER` — the subject of the
client's call being served (set by the call layer, the listen hub and the line
listener), or the subject a service's configuration names (a chart's ``run_as``).
A Set is also checked against the registry's licences as that caller (the
directory's check, :func:`gateway.engine.licensing.check_set`): a group's Set to a member
someone else holds a licence on is refused for that member, as a direct Set would
be. So the directory wraps its backends once the gateway has licences, with rules
or without.
When the caller is None the call is a service's own work and nothing is checked.
A new system service needs nothing of its own for this: it reaches others through
the directory.

A Listen topic (:mod:`gateway.engine.listen.topics`) is opened once and shared by the
streams of many subjects. The reads made while it opens are noted in a
:class:`Trail` (:data:`TRAIL`); a stream that joins the topic afterwards is checked
for each of them as well, so a viewer cannot follow a member's battery through a
topic an admin opened.
"""

from __future__ import annotations

import asyncio
import contextvars
import functools
from collections.abc import Callable, Mapping
from typing import cast

from gateway.engine.guard import Guard, subject_of
from gateway.engine.rules import Operation, Subject
from services.kernel.backend import NO_PARAMS, Answer, Backend, BackendInfo, LinkCounts, Notify, Subscription
from services.kernel.directory import CALLER
from services.kernel.model import PropertyModel, ServiceModel
from services.kernel.values import Value

__all__ = ["TRAIL", "OnBehalf", "SetLicenceCheck", "Trail", "on_behalf"]

#: Raises when someone else holds a licence on (service, path) that a Set for the subject would change.
SetLicenceCheck = Callable[[Subject, str, str], None]

#: The trail the reads made now are noted in (a Listen topic opening), or None.
TRAIL: contextvars.ContextVar[Trail | None] = contextvars.ContextVar("trail", default=None)


class Trail:
    """The (service, path) reads made on a client's behalf while one Listen topic opened."""

    __slots__ = ("_open", "_reads")

    def __init__(self) -> None:
        # Each distinct read once, and only while the topic opens (under the call timeout): at
        # most one entry per (service, path) the opening reached, however many members it has.
        self._reads: dict[tuple[str, str], None] = {}
        self._open = True

    def note(self, service: str, path: str) -> None:
        """Remember a read (once); nothing once closed (a task the opening left behind)."""
        if self._open:
            self._reads[service, path] = None

    def close(self) -> tuple[tuple[str, str], ...]:
        """The reads noted; nothing is noted after this."""
        self._open = False
        return tuple(self._reads)


def _filtered(
    guard: Guard, service: str, models: list[PropertyModel] | tuple[PropertyModel, ...]
) -> list[PropertyModel]:
    caller = CALLER.get()
    if caller is None:
        return list(models)
    subject = subject_of(caller)
    return [p for p in models if guard.may(subject, service, p.name, Operation.READ)]


class OnBehalf(Backend):
    """The backend of ``service`` as a system service sees it: each call checked as the caller."""

    def __init__(
        self, service: str, inner: Backend, guard: Guard, check_licence: SetLicenceCheck | None = None
    ) -> None:
        self.service = service
        self.inner = inner
        self.guard = guard
        #: Refuses a Set for the caller on what someone else holds a licence on; None: no licences.
        self.check_licence = check_licence

    @property
    def info(self) -> BackendInfo:
        return self.inner.info

    @info.setter
    def info(self, info: BackendInfo) -> None:
        self.inner.info = info

    def __repr__(self) -> str:
        return f"OnBehalf({self.service}, {self.inner!r})"

    def _read(self, path: str) -> None:
        """Raise the refusal (audited) unless the caller may read ``path``; note it on the trail."""
        caller = CALLER.get()
        if caller is not None:
            self.guard.require(subject_of(caller), self.service, path, Operation.READ)
        trail = TRAIL.get()
        if trail is not None:
            trail.note(self.service, path)

    async def get(self, path: str, params: Mapping[str, str] = NO_PARAMS) -> Value:
        self._read(path)
        return await self.inner.get(path, params)

    def start_get(
        self,
        path: str,
        params: Mapping[str, str],
        time_limit: float,
        then: Callable[[Answer], None] | None = None,
    ) -> asyncio.Future[Answer] | None:
        self._read(path)
        return self.inner.start_get(path, params, time_limit, then)

    def flush(self) -> None:
        self.inner.flush()

    async def set(self, path: str, value: Value, params: Mapping[str, str] = NO_PARAMS) -> Value:
        caller = CALLER.get()
        if caller is not None:
            subject = subject_of(caller)
            guard = self.guard
            if guard.set_operation(subject, self.service, path, value) is None:
                await guard.set_operation_from_model(subject, self.service, path, self.inner.describe())
            # After the rules, as for a direct Set: a licence someone else holds refuses it.
            if self.check_licence is not None:
                self.check_licence(subject, self.service, path)
        return await self.inner.set(path, value, params)

    async def listen(self, path: str, notify: Notify, params: Mapping[str, str] = NO_PARAMS) -> Subscription:
        self._read(path)
        return await self.inner.listen(path, notify, params)

    async def listen_current(
        self, path: str, notify: Notify, params: Mapping[str, str] = NO_PARAMS
    ) -> tuple[Subscription, Value]:
        self._read(path)
        return await self.inner.listen_current(path, notify, params)

    async def properties(self) -> list[str]:
        self._read("properties")
        return await self.inner.properties()

    async def describe(self) -> ServiceModel:
        """The model, less the properties the caller may not read."""
        model = await self.inner.describe()
        if CALLER.get() is None:
            return model
        return ServiceModel(
            type=model.type,
            properties=tuple(_filtered(self.guard, self.service, model.properties)),
            doc=model.doc,
        )

    async def match_properties(self, pattern: str, under: str = "") -> list[PropertyModel]:
        """The matches the caller may read: a wildcard into a member skips the rest, as on the member."""
        return _filtered(self.guard, self.service, await self.inner.match_properties(pattern, under))

    async def listen_properties(self, notify: Notify) -> Subscription:
        # Where the list changes carries no value: the names are read when they are matched.
        return await self.inner.listen_properties(notify)

    async def check(self) -> None:
        await self.inner.check()

    def link_counts(self) -> LinkCounts | None:
        return self.inner.link_counts()

    async def wait_connected(self, wait_s: float) -> None:
        await self.inner.wait_connected(wait_s)

    def serves(self, obj: object) -> bool:
        return self.inner.serves(obj)

    async def wake(self) -> None:
        await self.inner.wake()

    async def start(self) -> None:
        await self.inner.start()

    async def aclose(self) -> None:
        await self.inner.aclose()


@functools.cache
def _kind(answers_inline: bool, on_demand: bool) -> type[OnBehalf]:
    """The class for a backend with these class-level capabilities (they are read on the class)."""
    attrs = {"answers_inline": answers_inline, "on_demand": on_demand}
    return cast(type[OnBehalf], type("OnBehalf", (OnBehalf,), attrs))


def on_behalf(
    service: str, backend: Backend, guard: Guard, check_licence: SetLicenceCheck | None = None
) -> OnBehalf:
    """``backend`` (serving ``service``) with every call checked as the caller, each Set by
    ``check_licence`` too; see the module docstring."""
    return _kind(backend.answers_inline, backend.on_demand)(service, backend, guard, check_licence)
