"""The call layer: a Get or Set request → one bounded backend call → its answer.

Every front end goes through :class:`Calls`, in the engine's own types
(:mod:`gateway.engine.types`): a :class:`GetCall`, :class:`SetCall` or
:class:`DescribeCall` in, a :class:`GetReply`, the Set's value or the model out. The
fronts differ only in how they wait. :meth:`Calls.start_get` and
:meth:`Calls.start_set` resolve the service and path (raising at once on a bad
one) and start the call, returning its :class:`~gateway.engine.handle.CallHandle`:
done already when an in-process service answered without waiting, else done
when the backend answers (a line-protocol proxy resolves its reply from its
reader: no task, one timer).

A Get whose path (or one of whose ``more`` paths) has ``*`` segments is a
snapshot, as gNMI's Get with a wildcard path: each pattern is expanded by the
service itself to its readable matches (:meth:`services.kernel.backend.Backend.match_properties`,
which walks only what the pattern names and never builds the ``properties`` list),
and the response lists every match with its concrete path in ``more`` (its
``value`` stays empty); see ``docs/errors.md``. Such a Get is never started
inline (:func:`is_snapshot`): it always goes through :meth:`Calls.get`.

Every path is checked by the :class:`~gateway.engine.guard.Guard` for the caller's
subject before its backend is asked: each path of a Get (``more`` included;
a pattern's matches that the subject may not read are skipped), and each Set
as the operation it is (write, invoke, register, unregister, admin). Every
Set's outcome is audited. When the guard checks, the subject is also put in
:data:`services.kernel.directory.CALLER` before the backend is asked, so that the calls
a system service makes for this one (a group's members, a wildcard into them)
are checked as the same subject (:mod:`gateway.engine.behalf`).

Every value a Get answers carries its source time (:meth:`Calls.value_time`): when the gateway
heard it change, when a Listen (or the history, :mod:`gateway.engine.history`) follows the
property and its latest change is the value read; else when the answer arrived.

Every Set is also checked against the licences the registry holds
(:mod:`gateway.engine.licensing`): a Set or an action on a service (or subtree) that
someone else holds a licence on is FAILED_PRECONDITION naming the holder and the
expiry, whether the service is in-process, a proxy or another gateway's. Reads
are never refused for a licence.
"""

from __future__ import annotations

import asyncio
import functools
from collections.abc import Callable, Coroutine, Mapping
from time import time_ns
from typing import Any

from gateway.engine.guard import REGISTRY, Guard
from gateway.engine.handle import AnsweredCall, AwaitedCall, CallHandle, RepliedCall
from gateway.engine.identity import ANONYMOUS
from gateway.engine.licensing import check_set
from gateway.engine.router import Router, bounded_call, check_path, finish_call
from gateway.engine.rules import Operation, Subject
from gateway.engine.sizes import SURELY_FITS_CHARS, check_fits, reply_size
from gateway.engine.status import to_property_error
from gateway.engine.types import DescribeCall, GetCall, GetReply, PropertyValue, SetCall, is_snapshot
from gateway.federation import VIA
from services.apps.registry import Licences
from services.kernel.backend import Backend
from services.kernel.directory import CALLER
from services.kernel.eager import Started, step
from services.kernel.errors import Code, InvalidArgument, NotFound, PropertyError, ResourceExhausted
from services.kernel.model import ServiceModel
from services.kernel.paths import is_pattern, validate_pattern
from services.kernel.values import Value

__all__ = ["Calls", "is_snapshot"]

#: (service, path, parameters, backend) of one path a Get reads.
_Ref = tuple[str, str, Mapping[str, str], Backend]


class Calls:
    """Get and Set against the router, shared by the unary calls and Session."""

    def __init__(
        self,
        router: Router,
        call_timeout: float,
        max_get_paths: int,
        guard: Guard | None = None,
        heard_at: Callable[[str, str, Value], int] | None = None,
    ) -> None:
        """``heard_at(service, path, value)``: when the gateway heard ``value`` become the value of
        the property, 0 when it does not know (the listen hub's topics: :meth:`Topics.heard_at`)."""
        self.router = router
        self.heard_at = heard_at
        self.timeout = call_timeout
        self.max_get_paths = max_get_paths
        self.guard = guard or Guard()
        #: The registry's licences every Set is checked against; None: no licences (no registry yet).
        self.licences: Licences | None = None
        #: Whether a ``ps-via`` hop is another gateway of this one's cluster (whose forwarded Sets
        #: were checked against the licences where the client called); None: not in a cluster.
        self.peer_hop: Callable[[str], bool] | None = None

    def forwarded_by_peer(self) -> bool:
        """Whether the call being served was forwarded by another gateway of this one's cluster."""
        if self.peer_hop is None:
            return False
        chain = VIA.get()
        return len(chain) >= 2 and self.peer_hop(chain[-2])

    def session_ended(self, subject: Subject) -> None:
        """The Session of ``subject`` ended: the licences acquired on it are lost."""
        if self.licences is not None and subject.session:
            self.licences.release_session(subject.session)

    def _backend(self, service: str, verb: str) -> Backend:
        if not service:
            raise InvalidArgument(f"{verb} needs a service name")
        return self.router.backend(service)

    async def describe(
        self, call: DescribeCall, time_limit: float, subject: Subject = ANONYMOUS
    ) -> ServiceModel:
        """The whole model of the call's service, checked as a read of the service itself."""
        service = call.service
        backend = self._backend(service, "Describe")
        if self.guard.checks:
            self.guard.require(subject, service, "", Operation.READ)
            CALLER.set(subject)
        return await bounded_call(backend.describe(), time_limit, lambda: f"{service}: describe")

    def start_get(self, call: GetCall, time_limit: float, subject: Subject = ANONYMOUS) -> CallHandle:
        """Start reading the call's one path (``more`` is :meth:`get`'s)."""
        service = call.service
        backend = self._backend(service, "Get")
        path = check_path(call.path)
        if self.guard.checks:
            self.guard.require(subject, service, path, Operation.READ)
            CALLER.set(subject)
        params = call.parameters
        if backend.answers_inline:
            return _inline(backend.get(path, params), time_limit, service, "get", path, backend=backend)
        replied = RepliedCall(backend)
        replied.future = backend.start_get(path, params, time_limit, replied.replied)
        if replied.future is not None:
            return replied
        # A proxy's call is stepped inside whichever task awaits it (its timeouts belong there).
        what = functools.partial("{}: get {}".format, service, path)
        return AwaitedCall(bounded_call(backend.get(path, params), time_limit, what), backend)

    def start_set(self, call: SetCall, time_limit: float, subject: Subject = ANONYMOUS) -> CallHandle:
        """Start writing the call's value; the handle's value is the service's answer.

        Checked and audited: a refusal raises here; the outcome of the Set is recorded when it is known.
        """
        service = call.service
        guard = self.guard
        if guard.checks or service == REGISTRY or self.licences is not None:
            # Checked deeper as this subject: the calls a service makes for it (by the rules and
            # against the licences others hold), and the registry's admin check and licence holder.
            CALLER.set(subject)
        try:
            backend = self._backend(service, "Set")
            path = check_path(call.path)
            operation = guard.set_operation(subject, service, path, call.value)
            if not self.forwarded_by_peer():
                check_set(self.licences, subject, service, path)
        except PropertyError as exc:
            if exc.code not in (Code.PERMISSION_DENIED, Code.UNAUTHENTICATED):  # already audited
                guard.audited(subject, service, call.path, Operation.WRITE, exc)
            raise
        if operation is None:
            return AwaitedCall(
                self._set_after_model(call, backend, path, time_limit=time_limit, subject=subject), backend
            )
        try:
            handle = self._start_set(call, backend, path, time_limit)
        except Exception as exc:
            guard.audited(subject, service, path, operation, exc)
            raise
        if handle.done:
            guard.audited(subject, service, path, operation, None)
            return handle
        record = functools.partial(guard.audited, subject, service, path, operation)
        return AwaitedCall(_audited(handle, record), backend)

    def _start_set(self, call: SetCall, backend: Backend, path: str, time_limit: float) -> CallHandle:
        service = call.service
        coro = backend.set(path, call.value, call.parameters)
        if backend.answers_inline:
            return _inline(coro, time_limit, service, "set", path, backend=backend)
        what = functools.partial("{}: set {}".format, service, path)
        return AwaitedCall(bounded_call(coro, time_limit, what), backend)

    async def _set_after_model(
        self, call: SetCall, backend: Backend, path: str, *, time_limit: float, subject: Subject
    ) -> Value:
        """A Set the rules treat differently as a write and as an action: the model tells which it is."""
        service = call.service
        describe = bounded_call(
            backend.describe(), time_limit, functools.partial("{}: describe for set {}".format, service, path)
        )
        operation = await self.guard.set_operation_from_model(subject, service, path, describe)
        try:
            answer = await self._start_set(call, backend, path, time_limit)
        except Exception as exc:
            self.guard.audited(subject, service, path, operation, exc)
            raise
        self.guard.audited(subject, service, path, operation, None)
        return answer

    async def get(self, call: GetCall, time_limit: float, subject: Subject = ANONYMOUS) -> GetReply:
        """Read the call's path and its ``more`` paths (a snapshot when one has ``*``); all or nothing."""
        if not call.more and not is_pattern(call.path):
            # One path, the commonest Get: an in-process answer is not awaited, and an answer
            # too short to outgrow a message is not measured.
            handle = self.start_get(call, time_limit, subject)
            value = handle.result() if handle.done else await handle
            reply = GetReply(value, (), self.value_time(call.service, call.path, call.parameters, value))
            if len(value) <= SURELY_FITS_CHARS:
                return reply
        else:
            if self.guard.checks:
                CALLER.set(subject)
            if is_snapshot(call):
                reply = GetReply("", await self._snapshot(call, time_limit, subject))
            else:
                # Every path is resolved (and counted) first, so that a bad one fails the call
                # before any backend is asked.
                refs = self._resolve_more(call, subject)
                value = await self.start_get(call, time_limit, subject)
                when = self.value_time(call.service, call.path, call.parameters, value)
                reply = GetReply(value, await self._read(refs, time_limit), when)
        check_fits(
            reply_size(reply.value, reply.more),
            lambda: f"{call.service}: get {call.path}" + (f" and {len(call.more)} more" if call.more else ""),
        )
        return reply

    def value_time(self, service: str, path: str, params: Mapping[str, str], value: Value) -> int:
        """The source time of ``value`` just read from ``path`` of ``service`` (ns since the epoch):
        when the gateway heard it change, if something follows the property and its latest change
        is this value; else now, when the answer arrived."""
        heard_at = self.heard_at
        if heard_at is not None and not params:
            heard = heard_at(service, path, value)
            if heard:
                return heard
        return time_ns()

    async def set(self, call: SetCall, time_limit: float, subject: Subject = ANONYMOUS) -> Value:
        """Write the call's value; the service's answer is the value returned."""
        handle = self.start_set(call, time_limit, subject)
        answer = handle.result() if handle.done else await handle
        # A service method that returns nothing answers an empty value (empty bytes stay binary).
        if answer is None:
            answer = ""
        if len(answer) > SURELY_FITS_CHARS:
            check_fits(reply_size(answer), lambda: f"{call.service}: set {call.path}")
        return answer

    def _check_count(self, paths: int) -> None:
        if paths > self.max_get_paths:
            raise ResourceExhausted(
                f"a Get may read at most {self.max_get_paths} paths, this one reads {paths}"
            )

    def _resolve(
        self,
        service: str,
        path: str,
        params: Mapping[str, str],
        subject: Subject,
        *,
        pattern: bool = False,
    ) -> _Ref:
        try:
            backend = self.router.backend(service)
            path = validate_pattern(path) if pattern else check_path(path)
            if self.guard.checks and not is_pattern(path):
                self.guard.require(subject, service, path, Operation.READ)
        except PropertyError as exc:
            # Names are clipped: an echo of a huge bad name must not outgrow the status message.
            raise type(exc)(f"{service[:80]}/{path[:256]}: {exc.message}", exc.code) from None
        return service, path, params, backend

    def _resolve_more(self, call: GetCall, subject: Subject) -> list[_Ref]:
        """The call's ``more`` paths, counted and resolved; raises on the first bad one."""
        self._check_count(len(call.more) + 1)
        return [
            self._resolve(ref.service or call.service, ref.path, ref.parameters, subject) for ref in call.more
        ]

    async def _snapshot(self, call: GetCall, time_limit: float, subject: Subject) -> list[PropertyValue]:
        """Every path of the Get, each pattern expanded to the readable properties it matches."""
        asked = [(call.service, call.path, call.parameters)]
        asked += [(ref.service or call.service, ref.path, ref.parameters) for ref in call.more]
        self._check_count(len(asked))
        resolved = [
            self._resolve(service, path, params, subject, pattern=True) for service, path, params in asked
        ]
        refs: list[_Ref] = []
        for service, path, params, backend in resolved:
            if not is_pattern(path):
                refs.append((service, path, params, backend))
            else:
                refs += [
                    (service, name, params, backend)
                    for name in await self._matches(service, path, backend, time_limit, subject)
                ]
            self._check_count(len(refs))
        return await self._read(refs, time_limit)

    async def _matches(
        self, service: str, pattern: str, backend: Backend, time_limit: float, subject: Subject
    ) -> list[str]:
        """The values of ``service`` that ``pattern`` matches, in the service's order.

        A snapshot holds values a Listen could follow: actions (never read), queries and
        properties that need a parameter (``file`` of a storage service), and namespaces (not
        values) are skipped, and so is what the
        subject may not read.
        """
        found = await bounded_call(
            backend.match_properties(pattern),
            time_limit,
            functools.partial("{}: match {}".format, service, pattern),
        )
        guard = self.guard
        names = [
            p.name
            for p in found
            if p.access.listenable
            and not p.needs_parameters
            and p.type != "namespace"
            and guard.may(subject, service, p.name, Operation.READ)
        ]
        if not names:
            raise NotFound(f"{service}/{pattern}: no readable property of {service} matches")
        return names

    async def _read(self, refs: list[_Ref], time_limit: float) -> list[PropertyValue]:
        """Read every ref: one backend's paths one after another, backends side by side."""
        groups: dict[int, list[int]] = {}
        for i, (_, _, _, backend) in enumerate(refs):
            groups.setdefault(id(backend), []).append(i)
        values: list[Value | BaseException] = [""] * len(refs)

        async def read_group(indexes: list[int]) -> None:
            # One backend's paths are read one after another, as a device would answer them.
            for i in indexes:
                service, path, params, backend = refs[i]
                try:
                    values[i] = await bounded_call(
                        backend.get(path, params),
                        time_limit,
                        functools.partial("{}: get {}".format, service, path),
                    )
                except Exception as exc:
                    values[i] = exc
                    return

        if len(groups) == 1:
            await read_group(next(iter(groups.values())))
        elif groups:
            await asyncio.gather(*(read_group(ix) for ix in groups.values()))
        out = []
        for (service, path, params, _), value in zip(refs, values, strict=True):
            if isinstance(value, BaseException):
                err = to_property_error(value, f"{service}: get {path}")
                raise type(err)(f"{service}/{path}: {err.message}", err.code) from None
            out.append(PropertyValue(service, path, value, self.value_time(service, path, params, value)))
        return out


def _inline(
    coro: Coroutine[Any, Any, Value],
    time_limit: float,
    service: str,
    verb: str,
    path: str,
    *,
    backend: Backend,
) -> CallHandle:
    """Step an in-process call here, in the caller's task: an answer at once costs no task and no timer."""
    first = step(coro)
    if isinstance(first, Started):
        what = functools.partial("{}: {} {}".format, service, verb, path)
        return AwaitedCall(finish_call(first, time_limit, what), backend)
    return AnsweredCall(first if first is not None else "")


async def _audited(handle: CallHandle, record: Callable[[BaseException | None], None]) -> Value:
    """A started Set's value, its outcome recorded (``record``: see :meth:`Guard.audited`)."""
    try:
        value = await handle
    except BaseException as exc:
        record(exc)
        raise
    record(None)
    return value
