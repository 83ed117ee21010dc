"""The scheduler at work in the registry: providers from the table, licences, waking, the queue's clock.

:class:`Dispatcher` feeds :class:`~services.apps.registry.scheduling.Scheduler` (decisions without I/O)
with the registry's table — each entry's capabilities are its ``type`` and its ``features`` — and
carries its plans out: dormant providers are woken, one licence per provider is granted to the
caller, and only when every step succeeded is the allocation committed. When any step fails, the
licences already granted are released and the plan aborted: nothing stays half-allocated. A
provider whose licence is refused (someone holds it outside the scheduler) has rejected the
allocation (rule d): the plan is made again without it, at most :data:`MAX_ATTEMPTS` times.

Waiting requests are retried whenever a licence ends, an allocation is released, or the table
changes (a service joins, leaves, comes up or goes down), and dropped at their deadline (``Tr``).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import time
from collections.abc import Awaitable, Callable
from dataclasses import replace
from typing import Annotated

import numpy as np

from services.apps.registry.candidates import Candidates, provider_state
from services.apps.registry.licences import Licence, Licences, format_time
from services.apps.registry.scheduling import (
    Allocation,
    Plan,
    Provider,
    Request,
    Scheduler,
    Waiting,
    parse_assessments,
    parse_capabilities,
)
from services.apps.registry.scheduling.qos import MAX_QOS_PROVIDERS
from services.apps.registry.table import ServiceTable
from services.kernel.core import Prop, Resource
from services.kernel.directory import Directory
from services.kernel.errors import (
    FailedPrecondition,
    InvalidArgument,
    NotFound,
    PermissionDenied,
    PropertyError,
    Unavailable,
)
from services.kernel.paths import validate_path
from services.kernel.values import (
    ValueFormatError,
    Vector,
    as_text,
    format_list,
    format_number,
    parse_names,
    parse_number,
    parse_vector,
)
from services.kernel.worker_pool import run_bounded

__all__ = ["MAX_ATTEMPTS", "Dispatcher", "QosEntry", "QosView"]

log = logging.getLogger(__name__)

#: Plans made for one request when providers reject theirs (rule d) or cannot be woken.
MAX_ATTEMPTS = 3
#: Providers asked for a published cost at once.
MAX_CONCURRENT_COST_GETS = 64


class QosEntry(Resource):
    """One provider's QoS record; its own value is the mean of its assessments (0 to 1)."""

    count: Annotated[int, Prop(readonly=True, doc="assessments recorded")]
    last: Annotated[float, Prop(readonly=True, doc="the last assessment, 0 to 1")]

    def __init__(self) -> None:
        self.count = 0
        self.last = 0.0
        self._mean = 0.0

    def _value(self) -> str:
        return self.mean_text()

    def mean_text(self) -> str:
        """The mean to two decimals, as the seed writes its normalised evaluations (0.86)."""
        return format_number(round(self._mean, 2))

    def update(self, count: int, mean: float, last: float) -> None:
        self._mean = mean
        self.count = count
        self.last = last
        self.changed()


class QosView(Resource):
    """``qos``: ``((B 0.86) (C 0))``, the mean assessment of each provider; ``qos.<provider>`` each."""

    def _value(self) -> str:
        return format_list(
            [
                [name, entry.mean_text()]
                for name, entry in self.children().items()
                if isinstance(entry, QosEntry)
            ]
        )


class Dispatcher:
    """Requests and releases of the registry's scheduler, carried out with licences (see the module)."""

    def __init__(
        self,
        table: ServiceTable,
        licensing: Licences,
        *,
        wake: Callable[[str], Awaitable[None]],
        locate: Callable[[list[str]], Awaitable[None]],
        directory: Callable[[], Directory | None],
        features: Callable[[str], frozenset[str]],
        revision: Callable[[], int],
        changed: Callable[[str], None],
        qos: QosView,
        timeout: float,
        tout: float,
        tr: float,
        max_queued: int,
    ) -> None:
        self.scheduler = Scheduler(tout=tout, tr=tr, max_queued=max_queued)
        self._table = table
        self._licensing = licensing
        self._wake = wake
        self._locate = locate
        self._directory = directory
        self._features = features
        self._revision = revision
        self._candidates = Candidates(table, features)
        self._located_at = -1
        self._located_for: set[frozenset[str]] = set()
        self._changed = changed
        self._qos = qos
        self._timeout = timeout
        #: Holder and Session of each waiting request, and the costs it asked providers for.
        self._waiting_callers: dict[str, tuple[str, str]] = {}
        #: Which providers each waiting request's caller may be licensed (absent: any).
        self._waiting_allowed: dict[str, Callable[[str], bool]] = {}
        self._published: dict[str, dict[str, float]] = {}
        self._ours: set[str] = set()  # licence ids the dispatcher itself is releasing
        self._kick = asyncio.Event()
        self._task: asyncio.Task[None] | None = None

    # -- providers as the scheduler sees them --------------------------------------

    def providers(self, published: dict[str, float] | None = None) -> list[Provider]:
        """Every registered service but registries, with its capabilities, state and location."""
        entries = [(name, entry) for name, entry in self._table.entries() if entry.type != "registry"]
        index = self._table.index
        places = index.planar_at(index.slots_of(name for name, _ in entries))
        found = []
        for (name, entry), place in zip(entries, places, strict=True):
            found.append(
                Provider(
                    name,
                    self._features(name) | {entry.type},
                    provider_state(entry.availability),
                    place if bool(np.all(np.isfinite(place))) else None,
                    None if published is None else published.get(name),
                )
            )
        return found

    def providers_for(
        self,
        request: Request,
        published: dict[str, float] | None,
        allowed: Callable[[str], bool] | None = None,
    ) -> tuple[list[Provider], float]:
        """The providers the scheduler needs to see for ``request`` (narrowed as
        :mod:`services.apps.registry.candidates` says) and the cost that scores 1 among them all;
        only those ``allowed`` (the caller may be licensed them: :data:`ProviderCheck`)."""
        refused = self.refused(request.capabilities, allowed)
        if published is not None:
            # Only those that published a cost can be ranked by it.
            priced = [p for p in self.providers(published) if p.cost is not None and p.name not in refused]
            return priced, max(published.values(), default=0.0)
        unsure = self.scheduler.unsure(request) | {lic.service for lic in self._licensing.held()}
        # The refused count as unsure: the narrowing keeps enough others in their place.
        providers, scale = self._candidates.narrow(
            request, self._revision(), self.scheduler.qos.means(), unsure | refused
        )
        if refused:
            providers = [p for p in providers if p.name not in refused]
        return providers, scale

    def refused(self, wanted: frozenset[str], allowed: Callable[[str], bool] | None) -> frozenset[str]:
        """The providers offering any of ``wanted`` that ``allowed`` refuses (none when it is None)."""
        if allowed is None:
            return frozenset()
        return frozenset(n for n in self._candidates.offering(wanted, self._revision()) if not allowed(n))

    def _to_locate(self, wanted: frozenset[str], by_distance: bool) -> list[str]:
        """The providers of ``wanted`` whose locations a request needs, once per capability set and
        table revision: locations are followed from the first time they are needed (a device's
        location is never listened to before someone asks), and the table changes when one joins."""
        revision = self._revision()
        if revision != self._located_at:
            self._located_at, self._located_for = revision, set()
        if not by_distance or wanted in self._located_for:
            return []
        self._located_for.add(wanted)
        return self._candidates.offering(wanted, revision)

    def location_of(self, name: str) -> Vector | None:
        entry = self._table.get(name)
        return entry.location if entry is not None and entry.location.size >= 2 else None

    async def _published_costs(self, prop: str, capabilities: frozenset[str]) -> dict[str, float]:
        """Get ``prop`` from every provider offering one of ``capabilities``; those that do not
        answer a number within the timeout are left out (they cannot be ranked by cost)."""
        directory = self._directory()
        if directory is None:
            raise Unavailable("this registry cannot ask providers for their cost: it has no directory")
        names = [p.name for p in self.providers() if p.capabilities & capabilities]
        costs: dict[str, float] = {}

        async def ask(name: str) -> None:
            try:
                async with asyncio.timeout(self._timeout):
                    value = parse_number(as_text(await directory.backend(name).get(prop), prop))
            except (PropertyError, TimeoutError):
                return
            if math.isfinite(value) and value >= 0:
                costs[name] = value

        await run_bounded(names, ask, MAX_CONCURRENT_COST_GETS)
        return costs

    # -- a request --------------------------------------------------------------------

    async def request(
        self,
        capabilities: str,
        *,
        consumer: str,
        holder: str,
        session: str,
        allowed: Callable[[str], bool] | None = None,
        location: str,
        count: int,
        duration: float | None,
        wait: float | None,
        exclude: str,
        cost: str,
        weight: float,
    ) -> str:
        """What the registry's ``request`` action does: ``(ID granted ((provider licence) ...))`` or
        ``(ID queued ())``; raises with the reason otherwise. Only providers ``allowed`` are picked
        (None: any); when none of those offering the capabilities is, the request is NOT_FOUND as
        when no provider offers them, saying that the rules refuse the others."""
        wanted = parse_capabilities(capabilities)
        if not consumer:
            consumer = holder
        try:
            where = parse_vector(location) if location else None
        except ValueFormatError as e:
            raise InvalidArgument(f"bad parameter location: {e.message}") from None
        if where is not None and not (where.size >= 2 and np.all(np.isfinite(where))):
            raise InvalidArgument("bad parameter location: give at least x and y, e.g. (3 4)")
        try:
            excluded = frozenset(parse_names(exclude)) if exclude else frozenset()
        except ValueFormatError as e:
            raise InvalidArgument(f"bad parameter exclude: {e.message}") from None
        request = Request(
            consumer=consumer,
            capabilities=wanted,
            count=count,
            location=where,
            duration=self.scheduler.tout if duration is None else duration,
            wait=self.scheduler.tr if wait is None else wait,
            exclude=excluded,
            weight=weight,
        )
        if cost:
            try:
                validate_path(cost)
            except InvalidArgument as e:
                raise InvalidArgument(f"bad parameter cost: {e.message}") from None
        published = await self._published_costs(cost, wanted) if cost else None
        await self._locate([consumer, *self._to_locate(wanted, published is None)])
        if where is None:
            request = replace(request, location=self.location_of(consumer))
        rejected: set[str] = set()
        for _ in range(MAX_ATTEMPTS):
            asked = replace(request, exclude=request.exclude | rejected) if rejected else request
            providers, scale = self.providers_for(asked, published, allowed)
            asked = replace(asked, cost_scale=scale)
            try:
                decided = self.scheduler.submit(asked, providers, time.monotonic())
            except NotFound as e:
                if not rejected:
                    raise self._explained(e, self.refused(wanted, allowed), holder) from None
                # Those left cannot serve it: it is the rejections that failed it, not step 3.
                raise Unavailable(
                    f"the providers chosen for {capabilities.strip()[:80]} rejected the allocation or "
                    f"could not be woken ({' '.join(sorted(rejected))}), and the others cannot serve it "
                    f"({e.message}); nothing was allocated"
                ) from None
            if isinstance(decided, Waiting):
                self._waiting_callers[decided.id] = (holder, session)
                if allowed is not None:
                    self._waiting_allowed[decided.id] = allowed
                if published is not None:
                    self._published[decided.id] = published
                self._changed("requests")
                self._kick.set()
                return format_list([decided.id, "queued", []])
            allocation, refused = await self._carry_out(decided, holder, session)
            if allocation is not None:
                return _granted(allocation)
            rejected |= refused
        raise Unavailable(
            f"the providers chosen for {capabilities.strip()[:80]} rejected the allocation "
            f"{MAX_ATTEMPTS} times ({' '.join(sorted(rejected))}); nothing was allocated"
        )

    @staticmethod
    def _explained(error: NotFound, refused: frozenset[str], holder: str) -> NotFound:
        """``error`` (no provider can serve), saying which providers the rules kept out of it."""
        if not refused:
            return error
        names = sorted(refused)
        listed = " ".join(names[:8]) + (f" and {len(names) - 8} more" if len(names) > 8 else "")
        return NotFound(
            f"{error.message}: {holder or 'the caller'} may not write {listed} by the rules, "
            "so none of them is picked"
        )

    async def _carry_out(self, plan: Plan, holder: str, session: str) -> tuple[Allocation | None, set[str]]:
        """Wake, license, commit — or undo all of it. (allocation, None) or (None, providers that refused)."""
        granted: list[Licence] = []
        refused: set[str] = set()
        try:
            for name in plan.wake:
                try:
                    async with asyncio.timeout(self._timeout * 5):
                        await self._wake(name)
                except (PropertyError, TimeoutError) as e:
                    log.warning("scheduler: cannot wake %s for %s: %s", name, plan.id, e)
                    refused.add(name)
            if not refused:
                for name in plan.providers:
                    try:
                        granted.append(
                            await self._licensing.grant(
                                name, holder, plan.request.duration, session=session, limit_holder=False
                            )
                        )
                    except FailedPrecondition:
                        refused.add(name)  # held outside the scheduler: the provider rejects (rule d)
                        break
        except BaseException:
            await self._undo(plan, granted)
            raise
        if refused:
            await self._undo(plan, granted)
            return None, refused
        allocation = self.scheduler.commit(
            plan, {lic.service: lic.id for lic in granted}, time.monotonic(), holder
        )
        self._changed("allocations")
        log.info("scheduler: %s for %s: %s", plan.id, plan.request.consumer, _granted(allocation))
        return allocation, set()

    async def _undo(self, plan: Plan, granted: list[Licence]) -> None:
        for licence in granted:
            self._ours.add(licence.id)
            with contextlib.suppress(PropertyError):
                await self._licensing.release(licence.id)
            self._ours.discard(licence.id)
        self.scheduler.abort(plan)

    # -- a release ----------------------------------------------------------------------

    async def release(self, allocation_id: str, *, holder: str, qos: str) -> str:
        """End an allocation and record the consumer's assessments; answers ``((B 0.86) ...)``,
        the new mean of each provider assessed."""
        assessments = parse_assessments(qos)
        found = self.scheduler.find(allocation_id)
        if found is None:
            raise NotFound(f"no allocation {allocation_id[:40]!r} (it may have ended long ago)")
        if found.holder != holder:
            raise PermissionDenied(
                f"allocation {allocation_id} of {found.consumer} was granted to {found.holder}; "
                f"only it may release it (you are {holder})"
            )
        live = [found.licences[p] for p in found.live()]
        allocation, records = self.scheduler.release(allocation_id, found.consumer, assessments)
        for licence_id in live:
            self._ours.add(licence_id)
            try:
                await self._licensing.release(licence_id)
            except PropertyError as e:
                log.info("scheduler: licence %s of %s had ended: %s", licence_id, allocation.id, e)
            finally:
                self._ours.discard(licence_id)
        for name, record in records.items():
            view = self._qos.children().get(name)
            if not isinstance(view, QosEntry):
                view = QosEntry()
                self._qos.attach(name, view)
            view.update(record.count, record.mean, record.last)
        if len(self._qos.children()) > MAX_QOS_PROVIDERS:
            kept = {name for name, _ in self.scheduler.qos.items()}
            for name in [n for n in self._qos.children() if n not in kept]:
                self._qos.detach(name)  # the book dropped it (least recently assessed)
        if records:
            self._qos.changed()
        self._changed("allocations")
        self._kick.set()
        return format_list([[n, format_number(round(r.mean, 2))] for n, r in records.items()])

    # -- licences that end by themselves ---------------------------------------------------

    def on_licence(self, licence: Licence, event: str) -> None:
        """A licence ended outside a release of the scheduler's (expired, lost, released by hand)."""
        if event in ("granted", "renewed") or licence.id in self._ours:
            return
        if self.scheduler.end_licence(licence.id, event) is not None:
            self._changed("allocations")
            self._kick.set()

    def table_changed(self) -> None:
        """A join, leave or change of state: waiting requests may be served now."""
        if len(self.scheduler.queue):
            self._kick.set()

    # -- the queue's clock ---------------------------------------------------------------

    def start(self) -> None:
        if self._task is None:
            self._task = asyncio.get_running_loop().create_task(self._run(), name="registry scheduler")

    async def stop(self) -> None:
        task, self._task = self._task, None
        if task is not None:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task

    async def _run(self) -> None:
        while True:
            deadline = self.scheduler.queue.next_deadline()
            wait = None if deadline is None else max(0.0, deadline - time.monotonic())
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(wait):
                    await self._kick.wait()
            self._kick.clear()
            try:
                await self.retry()
            except Exception:
                log.exception("scheduler: retrying the waiting requests failed")

    async def retry(self) -> None:
        """One round over the waiting requests (the clock runs it; tests may call it)."""
        if not len(self.scheduler.queue):
            return
        plans, dropped = self.scheduler.retry(
            lambda w: self.providers_for(
                w.request, self._published.get(w.id), self._waiting_allowed.get(w.id)
            )[0],
            time.monotonic(),
        )
        for waiting in dropped:
            self._forget_waiting(waiting.id)
            log.info(
                "scheduler: request %s of %s dropped: waited its %g s",
                waiting.id,
                waiting.request.consumer,
                waiting.request.wait,
            )
        for plan in plans:
            holder, session = self._waiting_callers.get(plan.id, (plan.request.consumer, ""))
            published = self._published.get(plan.id)
            allowed = self._waiting_allowed.get(plan.id)
            self._forget_waiting(plan.id)
            allocation, refused = await self._carry_out(plan, holder, session)
            if allocation is None:
                again = self.scheduler.requeue(plan, refused, time.monotonic())
                log.info(
                    "scheduler: waiting request %s: %s rejected it; %s",
                    plan.id,
                    " ".join(sorted(refused)),
                    "it waits again without them" if again else "its time is up",
                )
                if again is not None:
                    self._waiting_callers[plan.id] = (holder, session)
                    if allowed is not None:
                        self._waiting_allowed[plan.id] = allowed
                    if published is not None:
                        self._published[plan.id] = published
        if plans or dropped:
            self._changed("requests")

    def _forget_waiting(self, id: str) -> None:
        self._waiting_callers.pop(id, None)
        self._waiting_allowed.pop(id, None)
        self._published.pop(id, None)

    # -- what the properties show -------------------------------------------------------

    def requests_text(self) -> str:
        """``((ID consumer (capabilities) count deadline) ...)``: the waiting requests."""
        rows = []
        for w in self.scheduler.queue:
            left = max(0.0, w.deadline - time.monotonic())
            rows.append(
                [
                    w.id,
                    w.request.consumer,
                    sorted(w.request.capabilities),
                    w.request.count,
                    format_time(time.time() + left),
                ]
            )
        return format_list(rows)

    def allocations_text(self) -> str:
        """``((ID consumer (capabilities) ((provider licence) ...) expires) ...)``: the live allocations."""
        rows = []
        for a in self.scheduler.allocations.values():
            left = max(0.0, a.expires_at - time.monotonic())
            rows.append(
                [
                    a.id,
                    a.consumer,
                    sorted(a.capabilities),
                    [[p, a.licences[p]] for p in a.live()],
                    format_time(time.time() + left),
                ]
            )
        return format_list(rows)

    def unserved_text(self) -> str:
        """``((consumer (capabilities)) ...)``: requests no provider could serve, newest last."""
        return format_list([[c, sorted(caps)] for c, caps, _ in self.scheduler.unserved])


def _granted(allocation: Allocation) -> str:
    return format_list([allocation.id, "granted", [[p, lic] for p, lic in allocation.licences.items()]])
