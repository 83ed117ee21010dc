"""The scheduler's decisions, without I/O: rules (a)–(f) of the seed and its five steps.

The registry (``services.apps.registry.dispatch``) gives it a snapshot of the providers and
the clock; it answers with a :class:`Plan` (providers chosen and reserved), or queues the request,
or raises a :class:`~services.kernel.errors.PropertyError` saying why not. The caller then wakes the
dormant providers of the plan and grants their licences, and :meth:`Scheduler.commit`\\s the plan
— or :meth:`Scheduler.abort`\\s it when any step failed, so nothing stays half-allocated.

Rules (the seed's, and how each is kept here):

(a) a consumer cannot provide for others at the same time: a consumer holding an allocation is
    never chosen, and a provider serving someone cannot request (FAILED_PRECONDITION);
(b) one provider serves one consumer at a time: a provider in an allocation or a plan is busy;
(c) a consumer may hold several allocations, from one or several providers (at most
    :data:`MAX_ALLOCATIONS_PER_CONSUMER`);
(d) the consumer rejects providers with the ``exclude`` option; a provider rejects by refusing
    its licence (held by someone else): the plan is aborted and made again without it;
(e) a consumer cannot request the same capability set again while it holds or awaits it
    (FAILED_PRECONDITION); a licence lasts at most ``Tout`` (:attr:`Scheduler.tout`);
(f) every robot may request (a consumer need not be registered) and every registered service
    that declares capabilities may be chosen.

Steps: (1) wait for a request; (2) a release records the QoS assessments and frees the
providers, a request goes on; (3) no provider offers the capabilities: the request is recorded in
:attr:`Scheduler.unserved` and NOT_FOUND says which are missing; (4) every provider that could
serve is busy: the request waits (at most ``wait`` ≤ ``Tr`` seconds, retried on every release,
expiry and table change; RESOURCE_EXHAUSTED past the queue's bounds); (5) otherwise the providers
with the lowest score (cost against QoS, :func:`~services.apps.registry.scheduling.cost.rank_scores`)
are chosen, ready ones first: dormant ones only when the ready ones cannot serve.
"""

from __future__ import annotations

import itertools
from collections import deque
from collections.abc import Callable, Iterable, Mapping
from dataclasses import replace

from services.apps.registry.scheduling.cost import drive_distance, rank_scores
from services.apps.registry.scheduling.cover import cover
from services.apps.registry.scheduling.model import (
    Allocation,
    Plan,
    Provider,
    ProviderState,
    Request,
    Waiting,
)
from services.apps.registry.scheduling.qos import QosBook, QosRecord
from services.apps.registry.scheduling.queue import DEFAULT_MAX_QUEUED, RequestQueue
from services.kernel.errors import (
    FailedPrecondition,
    InvalidArgument,
    NotFound,
    ResourceExhausted,
    Unavailable,
)

__all__ = [
    "DEFAULT_TOUT",
    "DEFAULT_TR",
    "MAX_ALLOCATIONS_PER_CONSUMER",
    "MAX_COUNT",
    "MAX_ENDED",
    "MAX_UNSERVED",
    "Scheduler",
]

#: Added to a dormant provider's score (scores are 0 to 1): a smallest cover takes as few dormant
#: providers as it can, and a team takes every free ready one before waking any.
DORMANT_PENALTY = 2.0
#: Seconds a licence lasts at most (the seed's ``Tout``) unless the config says otherwise.
DEFAULT_TOUT = 600.0
#: Seconds a request may wait for a busy provider (the seed's ``Tr``) unless the config says otherwise.
DEFAULT_TR = 30.0
#: Allocations one consumer may hold at once (rule c, bounded).
MAX_ALLOCATIONS_PER_CONSUMER = 32
#: Providers one request may ask for as a team.
MAX_COUNT = 64
#: Requests no provider could serve, kept for reading (step 3), newest last.
MAX_UNSERVED = 100
#: Ended allocations kept so that their consumer can still release them with an assessment.
MAX_ENDED = 256


class Scheduler:
    """Allocations, the queue and the QoS book of one registry; decisions without I/O."""

    def __init__(
        self, *, tout: float = DEFAULT_TOUT, tr: float = DEFAULT_TR, max_queued: int = DEFAULT_MAX_QUEUED
    ) -> None:
        self.tout = tout
        self.tr = tr
        self.queue = RequestQueue(max_queued)
        self.qos = QosBook()
        self.allocations: dict[str, Allocation] = {}
        #: Ended (released or expired) allocations, newest last.
        self.ended: deque[Allocation] = deque(maxlen=MAX_ENDED)
        #: (consumer, capabilities, why) of requests no provider could serve, newest last.
        self.unserved: deque[tuple[str, frozenset[str], str]] = deque(maxlen=MAX_UNSERVED)
        self._reserved: dict[str, str] = {}  # provider -> plan id
        self._plans: dict[str, Plan] = {}
        self._retried: dict[str, Waiting] = {}  # plan id -> the waiting request it came from
        self._ids = itertools.count(1)

    # -- who is busy ---------------------------------------------------------------

    def holder(self, provider: str) -> str | None:
        """The consumer a provider serves (or the plan reserving it), None when it is free."""
        for allocation in self.allocations.values():
            if provider in allocation.live():
                return allocation.consumer
        plan = self._reserved.get(provider)
        return self._plans[plan].request.consumer if plan is not None else None

    def unsure(self, request: Request) -> set[str]:
        """Providers the scheduler would not give ``request`` whatever their state: busy ones,
        consumers, the consumer itself and those it excludes."""
        return self._busy() | self._consumers() | {request.consumer} | request.exclude

    def _busy(self) -> set[str]:
        busy = set(self._reserved)
        for allocation in self.allocations.values():
            busy.update(allocation.live())
        return busy

    def _consumers(self) -> set[str]:
        return {a.consumer for a in self.allocations.values()} | {
            p.request.consumer for p in self._plans.values()
        }

    # -- step 2: a request ------------------------------------------------------------

    def submit(self, request: Request, providers: Iterable[Provider], now: float) -> Plan | Waiting:
        """Decide on a new request: a reserved :class:`Plan`, or the request queued (:class:`Waiting`).

        Raises InvalidArgument (bad options), FailedPrecondition (rules a and e), NotFound (no
        provider offers what is asked: step 3), Unavailable (the providers are down and it may
        not wait), ResourceExhausted (the queue or the consumer's bound is full).
        """
        self._check(request)
        id = f"r{next(self._ids)}"
        plan = self._plan(id, request, list(providers))
        if plan is not None:
            return plan
        if request.wait <= 0:
            raise Unavailable(
                f"every provider of {_names(request.capabilities)} is busy; "
                f"ask again, or let the request wait (wait = up to {self.tr:g} s)"
            )
        return self.queue.add(id, request, now)

    def _check(self, request: Request) -> None:
        if not 1 <= request.count <= MAX_COUNT:
            raise InvalidArgument(f"count must be 1 to {MAX_COUNT}, got {request.count}")
        if not 0 < request.duration <= self.tout:
            raise InvalidArgument(
                f"duration must be more than 0 and at most Tout = {self.tout:g} s, got {request.duration:g}"
            )
        if not 0 <= request.wait <= self.tr:
            raise InvalidArgument(f"wait must be 0 to Tr = {self.tr:g} s, got {request.wait:g}")
        if not 0 <= request.weight <= 1:
            raise InvalidArgument(f"weight must be 0 to 1, got {request.weight:g}")
        consumer = request.consumer
        serving = self.holder(consumer)
        if serving is not None:
            raise FailedPrecondition(
                f"rule (a): {consumer} is providing for {serving} and cannot be a consumer at the same time"
            )
        mine = [a for a in self.allocations.values() if a.consumer == consumer]
        for allocation in mine:
            if allocation.capabilities == request.capabilities:
                raise FailedPrecondition(
                    f"rule (e): {consumer} already holds {_names(request.capabilities)} "
                    f"(allocation {allocation.id}, providers {' '.join(allocation.providers)}); "
                    "release it before asking again"
                )
        for waiting in self.queue:
            if waiting.request.consumer == consumer and waiting.request.capabilities == request.capabilities:
                raise FailedPrecondition(
                    f"rule (e): {consumer} already waits for {_names(request.capabilities)} "
                    f"(request {waiting.id})"
                )
        if len(mine) >= MAX_ALLOCATIONS_PER_CONSUMER:
            raise ResourceExhausted(
                f"{consumer} holds {len(mine)} allocations "
                f"(at most {MAX_ALLOCATIONS_PER_CONSUMER}); release one first"
            )

    def _plan(self, id: str, request: Request, providers: list[Provider]) -> Plan | None:
        """Steps 3–5: a reserved plan, None when the request must wait; raises when it cannot be served."""
        wanted = request.capabilities
        # The consumer itself: never a provider here. Rule (d): the consumer's refusals.
        offering = [
            p
            for p in providers
            if p.name != request.consumer and p.name not in request.exclude and p.capabilities & wanted
        ]
        self._check_possible(request, offering)
        # Rule (a): a provider that is a consumer now is busy until its allocations end.
        consumers = self._consumers()
        relevant = [p for p in offering if p.name not in consumers]
        busy = self._busy()
        free = [p for p in relevant if p.name not in busy and p.state is not ProviderState.BUSY]
        ready = [p for p in free if p.state is ProviderState.READY]
        dormant = [p for p in free if p.state is ProviderState.DORMANT]
        # Step 5: ready ones first; the dormant are woken only when the ready cannot serve.
        for pool in (ready, ready + dormant):
            chosen, costs = self._choose(request, pool, {d.name for d in dormant})
            if chosen is not None:
                wake = tuple(p for p in chosen if p in {d.name for d in dormant})
                plan = Plan(id, request, tuple(chosen), wake, costs)
                self._plans[id] = plan
                for name in chosen:
                    self._reserved[name] = id
                return plan
        # Step 4: could the providers that are busy (or down) serve it once free?
        usable = [p for p in offering if p.state is not ProviderState.DOWN]
        if self._choose(request, usable)[0] is None:
            down = sorted(p.name for p in offering if p.state is ProviderState.DOWN)
            if request.wait > 0:
                return None  # a provider coming back up is a table change: retried then
            raise Unavailable(
                f"the providers that could serve {_names(wanted)} are down ({' '.join(down[:8])})"
            )
        return None

    def _check_possible(self, request: Request, relevant: list[Provider]) -> None:
        """Step 3: NotFound, and the request recorded, when no provider (in any state) can serve it."""
        wanted = request.capabilities
        offered: set[str] = set()
        for p in relevant:
            offered |= p.capabilities
        missing = wanted - offered
        why = ""
        if missing:
            why = f"no provider offers {_names(missing)}"
            if len(missing) < len(wanted):
                why += f" (needed with {_names(wanted - missing)}: no composition covers the set)"
        elif request.count > 1:
            whole = [p for p in relevant if wanted <= p.capabilities]
            if len(whole) < request.count:
                why = (
                    f"{request.count} providers offering all of {_names(wanted)} were asked for; "
                    f"{len(whole)} exist"
                )
        if why:
            self.unserved.append((request.consumer, wanted, why))
            if request.exclude and not missing:
                why += f", not counting those excluded ({' '.join(sorted(request.exclude))})"
            raise NotFound(why)

    def _choose(
        self, request: Request, pool: list[Provider], dormant: set[str] | None = None
    ) -> tuple[list[str] | None, dict[str, float]]:
        """The providers of ``pool`` for ``request`` and their costs; None when the pool cannot serve.
        ``dormant`` ones score :data:`DORMANT_PENALTY` more: a ready one is used before any is woken."""
        if not pool:
            return None, {}
        costs = {
            p.name: (p.cost if p.cost is not None else drive_distance(p.location, request.location))
            for p in pool
        }
        qos = self.qos
        means = {name: r.mean for name in costs if (r := qos.get(name)) is not None}
        scores = rank_scores(costs, means, request.weight, request.cost_scale)
        for name in dormant or ():
            if name in scores:
                scores[name] += DORMANT_PENALTY
        if request.count > 1:
            whole = sorted(
                (p.name for p in pool if request.capabilities <= p.capabilities), key=lambda n: (scores[n], n)
            )
            if len(whole) < request.count:
                return None, {}
            chosen = whole[: request.count]
        else:
            offers = {p.name: p.capabilities for p in pool}
            found = cover(request.capabilities, offers, scores)
            if found is None:
                return None, {}
            chosen = found
        return chosen, {n: costs[n] for n in chosen}

    # -- after the plan -------------------------------------------------------------

    def commit(self, plan: Plan, licences: Mapping[str, str], now: float, holder: str = "") -> Allocation:
        """The plan's licences were all granted (to ``holder``): it becomes an allocation until
        ``now + duration``."""
        self._unreserve(plan)
        self._retried.pop(plan.id, None)
        if set(licences) != set(plan.providers):
            raise InvalidArgument("an allocation needs one licence for each provider of its plan")
        allocation = Allocation(
            plan.id,
            plan.request.consumer,
            plan.request.capabilities,
            {p: licences[p] for p in plan.providers},
            now,
            now + plan.request.duration,
            holder,
        )
        self.allocations[plan.id] = allocation
        return allocation

    def abort(self, plan: Plan) -> None:
        """Waking or licensing failed: the plan's providers are free again."""
        self._unreserve(plan)

    def requeue(self, plan: Plan, refused: Iterable[str], now: float) -> Waiting | None:
        """A plan made for a waiting request was aborted because ``refused`` rejected it (rule d):
        the request waits again, without them, until its own deadline. None when it is past."""
        waiting = self._retried.pop(plan.id, None)
        if waiting is None or waiting.deadline <= now:
            return None
        request = replace(waiting.request, exclude=waiting.request.exclude | frozenset(refused))
        again = replace(waiting, request=request)
        return again if self.queue.put_back(again) else None

    def _unreserve(self, plan: Plan) -> None:
        self._plans.pop(plan.id, None)
        for name in plan.providers:
            if self._reserved.get(name) == plan.id:
                del self._reserved[name]

    # -- releases and expiry ------------------------------------------------------------

    def find(self, id: str) -> Allocation | None:
        """A live or recently ended allocation."""
        live = self.allocations.get(id)
        if live is not None:
            return live
        return next((a for a in reversed(self.ended) if a.id == id), None)

    def release(
        self, id: str, consumer: str, assessments: Mapping[str, float]
    ) -> tuple[Allocation, dict[str, QosRecord]]:
        """End allocation ``id`` of ``consumer`` and record its assessments (step 2).

        An allocation that already expired can still be released once, to record the
        assessments. NotFound for an unknown id, FailedPrecondition for someone else's or one
        already released, InvalidArgument for an assessment of a provider not in it.
        """
        allocation = self.find(id)
        if allocation is None:
            raise NotFound(f"no allocation {id!r} (it may have ended long ago)")
        if allocation.consumer != consumer:
            raise FailedPrecondition(f"allocation {id} is held by {allocation.consumer}, not {consumer}")
        if allocation.status == "released":
            raise FailedPrecondition(f"allocation {id} was released already")
        strangers = sorted(set(assessments) - set(allocation.licences))
        if strangers:
            raise InvalidArgument(
                f"qos: {' '.join(strangers)} did not serve allocation {id} "
                f"(its providers: {' '.join(allocation.providers)})"
            )
        records = {p: self.qos.record(p, s) for p, s in assessments.items()}
        if allocation.status == "active":
            self._end(allocation, "released")
        allocation.status = "released"
        return allocation, records

    def expire(self, now: float) -> list[Allocation]:
        """End the allocations whose licences ran out (``Tout``); their providers are free."""
        gone = [a for a in self.allocations.values() if a.expires_at <= now]
        for allocation in gone:
            for provider in allocation.live():
                allocation.ended[provider] = "expired"
            self._end(allocation, "expired")
        return gone

    def end_licence(self, licence_id: str, how: str) -> Allocation | None:
        """A licence of an allocation ended outside a release (``expired``, ``lost``, ``released``):
        its provider is free; the allocation ends with its last licence. None when no allocation has it."""
        for allocation in self.allocations.values():
            for provider, held in allocation.licences.items():
                if held == licence_id and provider not in allocation.ended:
                    allocation.ended[provider] = how
                    if not allocation.live():
                        self._end(allocation, "expired" if how == "expired" else "lost")
                    return allocation
        return None

    def _end(self, allocation: Allocation, status: str) -> None:
        self.allocations.pop(allocation.id, None)
        allocation.status = status
        self.ended.append(allocation)

    # -- step 4: the queue ------------------------------------------------------------

    def retry(
        self, providers: Callable[[Waiting], Iterable[Provider]], now: float
    ) -> tuple[list[Plan], list[Waiting]]:
        """Try the waiting requests again, first come first served; ``providers(waiting)`` gives
        the providers as that request sees them (with the costs it asked for).

        Returns the plans made (reserved, taken off the queue) and the requests dropped: overdue,
        or no longer possible (an error recorded in :attr:`unserved`).
        """
        dropped = self.queue.overdue(now)
        plans: list[Plan] = []
        for waiting in self.queue:
            try:
                plan = self._plan(waiting.id, waiting.request, list(providers(waiting)))
            except (NotFound, Unavailable):
                self.queue.remove(waiting.id)
                dropped.append(waiting)
                continue
            if plan is not None:
                self.queue.remove(waiting.id)
                self._retried[plan.id] = waiting
                plans.append(plan)
        return plans, dropped

    def next_deadline(self) -> float | None:
        """When the next allocation expires or the next waiting request is overdue."""
        times = [a.expires_at for a in self.allocations.values()]
        queued = self.queue.next_deadline()
        if queued is not None:
            times.append(queued)
        return min(times, default=None)


def _names(capabilities: Iterable[str]) -> str:
    return "(" + " ".join(sorted(capabilities)) + ")"
