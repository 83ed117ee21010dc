"""The registry as a Property Service: :class:`Registry` (its properties and ``find``) and
:class:`RegistryService` (a LocalService that also takes Sets on ``services.<name>``)."""

from __future__ import annotations

import asyncio
import collections
import logging
import math
import os
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Annotated

from services.apps.location_following import LocationFollower
from services.apps.query import Query, values_equal
from services.apps.registry.allow import AllowList
from services.apps.registry.dispatch import Dispatcher, QosView
from services.apps.registry.embedded import EmbeddedStore
from services.apps.registry.entry import ServiceEntry, ServiceList, wall_clock
from services.apps.registry.licences import (
    DEFAULT_LICENCE_DURATION,
    DEFAULT_MAX_LICENCE_DURATION,
    DEFAULT_MAX_LICENCES,
    DEFAULT_MAX_LICENCES_PER_HOLDER,
    Licence,
    Licences,
)
from services.apps.registry.liveness import Liveness
from services.apps.registry.registration import (
    DEFAULT_MAX_REGISTRATIONS,
    DEFAULT_REGISTER_TIMEOUT,
    AdminCheck,
    Registrations,
)
from services.apps.registry.scheduling import (
    DEFAULT_MAX_QUEUED,
    DEFAULT_TOUT,
    DEFAULT_TR,
    check_capabilities,
)
from services.apps.registry.store import RegistryStore
from services.apps.registry.table import PLACEHOLDER_TYPE, ServiceTable
from services.kernel.backend import NO_PARAMS, Backend, BackendInfo
from services.kernel.core import LocalService, Prop, Resource, action, query
from services.kernel.directory import Directory, own_context
from services.kernel.errors import InvalidArgument, NotFound, PermissionDenied, PropertyError, Unavailable
from services.kernel.paths import validate_path
from services.kernel.values import (
    MAX_VALUE_LENGTH,
    Value,
    ValueFormatError,
    Vector,
    as_text,
    format_names,
    parse_vector,
)
from services.kernel.worker_pool import run_bounded

__all__ = ["Caller", "CallerSource", "LicenceCheck", "Registry", "RegistryService"]

log = logging.getLogger(__name__)

#: Property Gets running at once for a ``find`` with ``where``.
MAX_CONCURRENT_PROPERTY_GETS = 256
#: Ended licences still shown under ``licences.<id>`` (their status says how they ended).
MAX_ENDED_SHOWN = 64

#: Who is asking for (or renewing, or releasing) a licence: (holder, session). ``holder`` is the
#: caller's proven identity, or a name bound to its Session; ``session`` is the Session the
#: request came on ("" for a unary call), which the licence ends with.
Caller = tuple[str, str]
#: Answers :data:`Caller` for the request being carried out; the gateway installs one.
CallerSource = Callable[[], Caller]
#: Raises when the caller of the current request may not license ``(service, subtree)`` (subtree
#: "" = the whole service): UNAUTHENTICATED or PERMISSION_DENIED naming why; the gateway installs
#: one that asks its rules (:meth:`Registry.set_licence_check`).
LicenceCheck = Callable[[str, str], None]
#: For the current request: which services its caller may be licensed whole (``write`` on the
#: service by the rules), asked without a word for each; None when it may be licensed any. The
#: scheduler's ``request`` picks only those (:meth:`Registry.set_provider_check`); the test is
#: kept with a request that waits, and asked again when it is retried.
ProviderCheck = Callable[[], Callable[[str], bool] | None]
#: The holder name of an anonymous caller on a Session: this prefix and the Session's token.
SESSION_HOLDER_PREFIX = "session-"


def proves_identity(caller: Caller) -> bool:
    """Whether ``caller``'s holder name is an identity it proved (a token or a certificate)."""
    holder, session = caller
    return holder != "local" and holder != SESSION_HOLDER_PREFIX + session


def _local_caller() -> Caller:
    return ("local", "")


def _anyone_may_license(service: str, subtree: str) -> None:
    return None


def _any_provider() -> Callable[[str], bool] | None:
    return None


class LicenceView(Resource):
    """One licence as the ``licences.<id>`` property shows it (a marker; Listen to follow it)."""

    def __init__(self, licence: Licence) -> None:
        self._licence = licence

    def _value(self) -> str:
        return self._licence.marker()


class LicenceList(Resource):
    """The licences: one child namespace each, held or ended lately; its own value lists those held."""

    def __init__(self, licensing: Licences) -> None:
        self._licensing = licensing

    def _value(self) -> str:
        return format_names(lic.id for lic in self._licensing.held())


#: Names a page of ``service_names`` holds by default; and at most (its own limit is one value's size).
NAMES_PAGE = 1000
MAX_NAMES_PAGE = 10_000


def _page_limit(text: str) -> int:
    """The ``limit`` parameter of ``service_names``: a whole number from 1 to :data:`MAX_NAMES_PAGE`."""
    if text == "":
        return NAMES_PAGE
    if not text.isdigit() or not 1 <= int(text) <= MAX_NAMES_PAGE:
        raise InvalidArgument(f"limit: expected a whole number from 1 to {MAX_NAMES_PAGE}, got {text!r:.40}")
    return int(text)


class Registry(Resource):
    """The resource service: who exists, how to reach them, are they alive, find them by parameters."""

    resource_type = "registry"

    services: ServiceList
    period: Annotated[float, Prop(readonly=True, doc="seconds between liveness checks; 0: no checks")]
    timeout: Annotated[float, Prop(readonly=True, doc="seconds a service gets to answer a liveness check")]
    misses: Annotated[int, Prop(readonly=True, doc="missed checks in a row before a service is down")]
    grace: Annotated[float, Prop(readonly=True, doc="seconds a registered service may stay down")]
    revision: Annotated[
        int,
        Prop(readonly=True, doc="counts joins, leaves, changes of type, state, dormancy (Listen to follow)"),
    ]
    licences: LicenceList
    qos: QosView
    tout: Annotated[float, Prop(readonly=True, unit="s", doc="longest allocation of the scheduler (Tout)")]
    tr: Annotated[float, Prop(readonly=True, unit="s", doc="longest wait of a queued request (Tr)")]

    def __init__(
        self,
        *,
        directory: Directory | None = None,
        period: float = 5.0,
        timeout: float = 2.0,
        misses: int = 3,
        grace: float = 60.0,
        register_timeout: float = DEFAULT_REGISTER_TIMEOUT,
        static: Iterable[str] = (),
        persist: str | os.PathLike[str] | None = None,
        store: RegistryStore | None = None,
        restore: bool = True,
        allow: AllowList | None = None,
        max_registrations: int = DEFAULT_MAX_REGISTRATIONS,
        max_licences: int = DEFAULT_MAX_LICENCES,
        max_licence_duration: float = DEFAULT_MAX_LICENCE_DURATION,
        max_licences_per_holder: int = DEFAULT_MAX_LICENCES_PER_HOLDER,
        features: Mapping[str, Iterable[str]] | None = None,
        tout: float = DEFAULT_TOUT,
        tr: float = DEFAULT_TR,
        max_queued: int = DEFAULT_MAX_QUEUED,
    ) -> None:
        """``static`` names come from the gateway's config: they are never removed for being down,
        nor unregistered or replaced from outside (see :meth:`set_admin_check`). ``allow`` says
        which addresses a registration may reach (default: loopback and USB serial adapters).
        ``max_licences``, ``max_licences_per_holder`` and ``max_licence_duration`` bound the
        licences (:attr:`licences`).
        ``features`` gives configured services their capabilities for the scheduler; ``tout``
        (longest allocation, at most ``max_licence_duration``), ``tr`` (longest wait) and
        ``max_queued`` (requests waiting) set the scheduler (:mod:`services.apps.registry.dispatch`).
        ``store`` keeps the registrations made by Set (:mod:`services.apps.registry.store`); without
        one the registry makes the embedded store, written to the file ``persist`` when named,
        and starts and closes it itself; a store handed in is started and closed by its maker.
        ``restore``: register at start what the store keeps; False when the gateways of a cluster
        serve a shared store's registrations themselves (``gateway.cluster``)."""
        for what, value in (("period", period), ("grace", grace)):
            if not (math.isfinite(value) and value >= 0):
                raise InvalidArgument(f"{what} must be zero or a positive number of seconds, got {value}")
        for what, value in (("timeout", timeout), ("register_timeout", register_timeout)):
            if not (math.isfinite(value) and value > 0):
                raise InvalidArgument(f"{what} must be a positive number of seconds, got {value}")
        if isinstance(misses, bool) or not isinstance(misses, int) or misses < 1:
            raise InvalidArgument(f"misses must be a positive whole number, got {misses!r}")
        tout = min(float(tout), float(max_licence_duration))
        for what, value in (("tout", tout), ("tr", tr)):
            if not (math.isfinite(value) and value > 0):
                raise InvalidArgument(f"{what} must be a positive number of seconds, got {value}")
        if isinstance(max_queued, bool) or not isinstance(max_queued, int) or max_queued < 1:
            raise InvalidArgument(f"max_queued must be a positive whole number, got {max_queued!r}")
        if store is not None and persist:
            raise InvalidArgument("persist is the embedded store's file: give a store or persist, not both")
        static = frozenset(static)
        #: Where the registrations made by Set are kept.
        self._store: RegistryStore = (
            store if store is not None else EmbeddedStore(Path(persist) if persist else None)
        )
        self._owns_store = store is None
        self._restores = restore
        self._unwatch_store: Callable[[], None] | None = None
        self._features = {
            name: check_capabilities(caps, f"features of {name}") for name, caps in (features or {}).items()
        }
        self.services = ServiceList()
        self.period = float(period)
        self.timeout = float(timeout)
        self.misses = misses
        self.grace = float(grace)
        self.revision = 0
        self.qos = QosView()
        self.tout = tout
        self.tr = float(tr)
        self._directory = directory
        self._table = ServiceTable(self.services, self._bump)
        #: The licences (exclusive use of a service for a while); see :mod:`services.apps.registry.licences`.
        self.licensing = Licences(
            lambda name: self._table.get(name) is not None,
            max_licences=max_licences,
            max_duration=max_licence_duration,
            max_per_holder=max_licences_per_holder,
        )
        self.licences = LicenceList(self.licensing)
        #: Ids of ended licences still shown under ``licences`` (how they ended), oldest first.
        self._ended_views: collections.deque[str] = collections.deque()
        self.licensing.watch(self._on_licence)
        self._caller: CallerSource = _local_caller
        self._may_license: LicenceCheck = _anyone_may_license
        self._may_provide: ProviderCheck = _any_provider
        self._table.watch_states(self._on_state_for_licences)
        self._registrations = Registrations(
            self._table,
            directory,
            timeout=float(register_timeout),
            forget=self._forget,
            joined=self._on_directory,
            store=self._store,
            allow=allow,
            configured=static,
            max_registrations=max_registrations,
        )
        self._liveness = Liveness(
            self._table,
            directory,
            period=self.period,
            timeout=self.timeout,
            misses=misses,
            grace=self.grace,
            static=static,
            busy=self._left_alone,
            unregister=self.unregister,
            answered=self._learn_type,
        )
        self._locations = LocationFollower(
            self._table.set_location,
            timeout=lambda: self.timeout,
            retry_max=max(1.0, self.period),
            on_answer=self._learn_type,
            what="registry",
        )
        self._table.want_location = self._want_location
        #: Services not reached yet (a proxy before its device greets), each awaited by one task.
        self._reaching: dict[str, asyncio.Task[None]] = {}
        self._unwatch: Callable[[], None] | None = None
        #: Services whose location the scheduler had followed (see :meth:`_locate`).
        self._located: set[str] = set()
        self._dispatcher = Dispatcher(
            self._table,
            self.licensing,
            wake=self.wake,
            locate=self._locate,
            directory=lambda: self._directory,
            features=self.features_of,
            revision=lambda: self.revision,
            changed=self.changed,
            qos=self.qos,
            timeout=self.timeout,
            tout=self.tout,
            tr=self.tr,
            max_queued=max_queued,
        )
        self.licensing.watch(self._dispatcher.on_licence)
        #: Services whose state another gateway reports (it owns them): see :meth:`mirror`.
        self._mirrored: set[str] = set()

    # -- the plain methods the gateway calls ------------------------------

    def names(self) -> list[str]:
        """The known service names, in the order they joined."""
        return self._table.names()

    def entry_states(self) -> dict[tuple[str, str], int]:
        """How many entries are in each (state, availability): at most 3 x 4 keys (the metrics read it)."""
        counts: dict[tuple[str, str], int] = {}
        table = self._table
        for name in table.names():
            entry = table.get(name)
            if entry is not None:
                key = (entry.state, entry.availability)
                counts[key] = counts.get(key, 0) + 1
        return counts

    def add(self, name: str, info: BackendInfo) -> None:
        """Record service ``name``, or refresh it: new type and URL, state up, ``last_seen`` now."""
        self._table.add(name, info, self.renew_lease)
        self._show_features(name)

    def remove(self, name: str) -> None:
        """Forget service ``name``; NotFound if it is not known."""
        self._table.entry(name)
        self._forget(name)

    def set_state(self, name: str, state: str) -> None:
        """Mark ``name`` up or down; going (or staying) up also refreshes ``last_seen``."""
        self._table.set_state(name, state)

    def mirror(self, name: str, state: str | None) -> None:
        """``name`` is owned by another gateway of a cluster, which reports its ``state``: show that
        state, and neither check it nor let its first answer here change it. None: this registry
        follows ``name`` itself again (this gateway owns it now). Nothing for an unknown name."""
        if state is None:
            self._mirrored.discard(name)
            return
        if self._table.get(name) is None:
            return
        self._mirrored.add(name)
        self._table.set_state(name, state)
        entry = self._table.get(name)
        if state == "up" and entry is not None and entry.type == PLACEHOLDER_TYPE:
            # Its owner has heard from its device, which this gateway may have asked for the type
            # too early (before the greeting): ask again.
            directory = self._directory
            if directory is not None and name in directory.names():
                self._start_reaching(name, directory.backend(name))

    def set_owner(self, name: str, owner: str) -> None:
        """In a cluster of gateways: ``owner`` (a gateway id, "" for none) holds ``name``'s connection
        (``services.NAME.owner``). Nothing for an unknown name."""
        entry = self._table.get(name)
        if entry is not None and entry.owner != owner:
            entry.owner = owner
            entry.owner_since = wall_clock() if owner else 0.0

    def _left_alone(self, name: str) -> bool:
        """Liveness leaves ``name`` alone: being (un)registered now, or its state is mirrored."""
        return name in self._mirrored or self._registrations.busy(name)

    def state_of(self, name: str) -> str:
        """``up`` or ``down``; NotFound when ``name`` is not known."""
        return self._table.entry(name).state

    def entry_of(self, name: str) -> ServiceEntry | None:
        """The registry's row of ``name``; None when it does not know it (one lookup, no copy)."""
        return self._table.get(name)

    def watch_states(
        self, listener: Callable[[str, str], None], *, members: bool = False
    ) -> Callable[[], None]:
        """Call ``listener(name, state)`` on every change of state; returns a function that stops it.

        With ``members``, also on every join (its first state) and leave (state ``"gone"``).
        """
        return self._table.watch_states(listener, members=members)

    def states(self) -> list[tuple[str, str]]:
        """(name, state) of every known service, a snapshot."""
        return [(name, entry.state) for name, entry in self._table.entries()]

    def set_location(self, name: str, location: Vector | None) -> None:
        """Record where ``name`` is (None: nowhere); the registry also follows ``location`` itself."""
        self._table.set_location(name, location)

    def renew_lease(self, name: str, seconds: float) -> None:
        """Give ``name`` a lease of ``seconds`` from now (0 ends the lease: it is polled again)."""
        self._table.renew(name, seconds)

    async def register(self, name: str, url: str, params: Mapping[str, str] = NO_PARAMS) -> str:
        """Create the backend for ``url`` and serve it as ``name`` (what a Set on ``services.<name>`` does).

        Raises InvalidArgument (bad name, URL or parameter), AlreadyExists
        (name taken by another URL), Unavailable or DeadlineExceeded (the
        device does not answer; nothing stays registered).
        """
        url = await self._registrations.register(name, url, params)
        if self._show_features(name):
            self._bump()  # the scheduler reads capabilities anew
        return url

    def _show_features(self, name: str) -> bool:
        """Put the capabilities ``name`` declared in ``services.<name>.features``; True when they changed."""
        entry = self._table.get(name)
        features = sorted(self.features_of(name))
        if entry is None or entry.features == features:
            return False
        entry.features = features
        return True

    async def unregister(self, name: str) -> None:
        """Remove service ``name`` (what a Set of ``services.<name>`` to the empty value does)."""
        await self._registrations.unregister(name)

    def set_admin_check(self, may_administer: AdminCheck) -> None:
        """Install the check that lets an admin unregister a configured service.

        ``may_administer(name)`` answers whether the caller of the current
        request may administer service ``name``; the rules engine installs
        one. Without it nobody may: configured services stay.
        """
        self._registrations.may_administer = may_administer

    async def check_all(self) -> None:
        """One round of liveness checks (the loop runs it every ``period``; tests call it directly)."""
        await self._liveness.check_all()

    # -- service states and licences (the SOA layer) ----------------------------

    def availability_of(self, name: str) -> str:
        """death, dormant, ready or active (see ``services.<name>.availability``); NotFound when unknown."""
        return self._table.entry(name).availability

    def set_dormant(self, name: str, dormant: bool) -> None:
        """Record that ``name`` is declared but not running (True) or running again (False)."""
        entry = self._table.get(name)
        if entry is not None and entry.set_dormant(dormant):
            if dormant:  # where it was read while awake (see :meth:`_locate`) no longer counts
                self._table.set_location(name, None)
            self._bump()

    async def wake(self, name: str) -> None:
        """Start ``name`` when it is dormant, and return once it is ready (at once when it runs).

        Raises NotFound (unknown), Unavailable (it cannot be started, or it is down).
        """
        entry = self._table.entry(name)
        if entry.state == "down":
            raise Unavailable(f"service {name!r} is down (death): it cannot be woken")
        directory = self._directory
        if directory is None:
            raise Unavailable("this registry cannot start services: it has no directory")
        await directory.backend(name).wake()
        self.set_dormant(name, False)

    def set_caller(self, caller: CallerSource) -> None:
        """Install what tells who the current request comes from (the holder of licences it acquires)."""
        self._caller = caller

    def set_licence_check(self, may_license: LicenceCheck) -> None:
        """Install the check of who may license what (:data:`LicenceCheck`); without one, anyone may."""
        self._may_license = may_license

    def set_provider_check(self, may_provide: ProviderCheck) -> None:
        """Install which providers the scheduler may license to the caller (:data:`ProviderCheck`);
        without one, any."""
        self._may_provide = may_provide

    @action(doc="acquire an exclusive licence on `service` (or `subtree`) for `duration` s; answers its id")
    async def acquire(
        self, *, service: str, duration: float = DEFAULT_LICENCE_DURATION, subtree: str = ""
    ) -> str:
        """Acquire a licence for the caller; its id is the Set's answer (see :meth:`Licences.grant`).

        The caller must be allowed to change what it locks (:meth:`set_licence_check`), asked
        before anything about the service is told. A dormant provider is woken first: a licence
        is granted on a service that serves, and on a subtree that names at least one of its
        properties. The registry itself (this one, or another gateway's) is never licensed.
        """
        holder, session = self._caller()
        if subtree:
            try:
                validate_path(subtree)
            except InvalidArgument as e:
                raise InvalidArgument(f"bad subtree: {e.message}") from None
        self._may_license(service, subtree)
        entry = self._table.get(service)
        if entry is None:
            raise NotFound(f"no service named {service[:80]!r} in the registry: nothing to license")
        if entry.type == self.resource_type:
            raise InvalidArgument(f"{service!r} is a registry: a registry is never licensed")
        if entry.availability == "dormant":
            await self.wake(service)
        if subtree:
            await self._check_subtree(service, subtree)
        licence = await self.licensing.grant(service, holder, duration, subtree, session=session)
        return licence.id

    async def _check_subtree(self, service: str, subtree: str) -> None:
        """NotFound unless ``subtree`` is a property of ``service`` or has properties below it now."""
        directory = self._directory
        if directory is None:
            raise Unavailable("this registry cannot read the services' properties: it has no directory")
        model = await directory.backend(service).describe()
        below = subtree + "."
        if not any(p.name == subtree or p.name.startswith(below) for p in model.properties):
            raise NotFound(
                f"{service} has no property {subtree[:120]!r} and none below it: nothing to license"
            )

    @action(doc="end licence `licence` now, whoever holds it (an admin's act)")
    async def revoke(self, *, licence: str) -> str:
        """End any licence at once (an admin operation by the rules: only an admin may ask);
        its holder's renew and release then say it was revoked."""
        self.licensing.revoke(licence)
        return ""

    @action(doc="hold licence `licence` for `duration` s from now (its holder only)")
    async def renew(self, *, licence: str, duration: float = DEFAULT_LICENCE_DURATION) -> str:
        """Renew a licence of the caller's; answers its new expiry (ISO 8601 UTC)."""
        from services.apps.registry.licences import format_time

        holder, _ = self._caller()
        renewed = await self.licensing.renew(licence, duration, holder=holder)
        return format_time(renewed.expires_at)

    @action(
        doc="end licence `licence` now (its holder only); or end scheduler allocation `allocation`, "
        "recording `qos` ((provider score) ...), scores 0 to 1"
    )
    async def release(self, *, licence: str = "", allocation: str = "", qos: str = "") -> str:
        """Release a licence of the caller's, or an allocation of the scheduler's with its assessments."""
        holder, _ = self._caller()
        if bool(licence) == bool(allocation):
            raise InvalidArgument("release takes one of the parameters licence or allocation")
        if licence:
            if qos:
                raise InvalidArgument("qos goes with allocation, not with licence")
            await self.licensing.release(licence, holder=holder)
            return ""
        return await self._dispatcher.release(allocation, holder=holder, qos=qos)

    # -- the scheduler --------------------------------------------------------------

    def features_of(self, name: str) -> frozenset[str]:
        """The capabilities ``name`` declared (config ``features`` or registration parameter)."""
        declared = self._features.get(name)
        if declared is not None:
            return declared
        return self._registrations.declared_features(name)

    @action(
        doc="ask for providers of capabilities (survey) or (video ptz mobile); answers "
        "(ID granted ((provider licence) ...)) or (ID queued ())"
    )
    async def request(
        self,
        capabilities: str,
        *,
        consumer: str = "",
        location: str = "",
        count: int = 1,
        duration: float | None = None,
        wait: float | None = None,
        exclude: str = "",
        cost: str = "",
        weight: float = 0.5,
    ) -> str:
        """Choose providers for ``capabilities`` and license them to the caller (see
        :mod:`services.apps.registry.dispatch`). ``consumer``: the robot asking (default: the caller);
        ``location`` (x y): where the work is (default: the consumer's location); ``count``: that many
        providers each offering all capabilities; ``duration`` (default ``tout``); ``wait``: seconds
        to queue when all are busy (default ``tr``; 0: refuse at once); ``exclude``: providers the consumer
        rejects; ``cost``: a property each provider publishes its cost in (default: drive distance);
        ``weight``: cost against QoS, 0 to 1."""
        holder, session = self._caller()
        if consumer and consumer != holder and proves_identity((holder, session)):
            # A robot that proved who it is asks for itself: naming another would spend that
            # robot's turn (rule e) and keep it from providing (rule a).
            raise PermissionDenied(
                f"{holder} may request only as itself: consumer={consumer} names another; "
                f"leave consumer out, or call as {consumer}"
            )
        return await self._dispatcher.request(
            capabilities,
            consumer=consumer,
            holder=holder,
            session=session,
            allowed=self._may_provide(),
            location=location,
            count=count,
            duration=duration,
            wait=wait,
            exclude=exclude,
            cost=cost,
            weight=weight,
        )

    @property
    def requests(
        self,
    ) -> Annotated[str, Prop(doc="waiting requests: ((ID consumer (capabilities) count deadline) ...)")]:
        return self._dispatcher.requests_text()

    @property
    def allocations(
        self,
    ) -> Annotated[
        str, Prop(doc="live allocations: ((ID consumer (capabilities) ((provider licence) ...) expires) ...)")
    ]:
        return self._dispatcher.allocations_text()

    @property
    def unserved(
        self,
    ) -> Annotated[str, Prop(doc="requests no provider could serve: ((consumer (caps)) ...)")]:
        return self._dispatcher.unserved_text()

    def _on_licence(self, licence: Licence, event: str) -> None:
        """Keep ``licences`` and ``services.<name>.licence`` in step with the licences."""
        view = self.licences.children().get(licence.id)
        if event == "granted":
            self.licences.attach(licence.id, LicenceView(licence))
        elif isinstance(view, LicenceView):
            view.changed()
        if event not in ("granted", "renewed"):
            # An ended licence stays readable (a Listen's last event says how it ended) until
            # MAX_ENDED_SHOWN later ones have ended; ``licences`` itself lists the held ones.
            self.licences.changed()
            self._ended_views.append(licence.id)
            while len(self._ended_views) > MAX_ENDED_SHOWN:
                old = self._ended_views.popleft()
                if old in self.licences.children():
                    self.licences.detach(old)
        entry = self._table.get(licence.service)
        if entry is not None:
            held = self.licensing.holder_of(licence.service)
            entry.set_licence(held.id if held is not None else "")

    def _on_state_for_licences(self, name: str, state: str) -> None:
        """A holder that is a registered service and goes down (death) loses its licences."""
        if state == "down":
            self.licensing.release_holder(name)

    # -- following the directory --------------------------------------------

    async def start(self) -> None:
        self._dispatcher.start()
        if self._owns_store:
            await self._store.start()
        self._unwatch_store = self._store.watch_read_only(lambda: self.changed("store"))
        directory = self._directory
        if directory is None:
            return
        self._unwatch = directory.watch(self._on_directory)
        for name in directory.names():
            try:
                self._on_directory(name, directory.backend(name))
            except PropertyError:
                continue
        if self._restores:
            await self._restore()
        self._liveness.start()

    async def stop(self) -> None:
        await self._dispatcher.stop()
        self.licensing.close()
        if self._unwatch is not None:
            self._unwatch()
            self._unwatch = None
        await self._liveness.stop()
        if self._unwatch_store is not None:
            self._unwatch_store()
            self._unwatch_store = None
        await self._registrations.settle()
        if self._owns_store:
            await self._store.aclose()
        reaching = list(self._reaching.values())
        self._reaching.clear()
        for task in reaching:
            task.cancel()
        await asyncio.gather(*reaching, return_exceptions=True)
        await self._locations.aclose()

    def _on_directory(self, name: str, backend: Backend | None) -> None:
        if backend is None:
            self._forget(name)
            return
        self.add(name, backend.info)
        # Its location is followed only once somebody asks (find near=, services.NAME.location):
        # a LISTEN nobody asked for doubles the traffic on a slow serial line. Its type and
        # "up" come as soon as it is reached, which costs the device nothing (no request).
        self._start_reaching(name, backend)

    def _start_reaching(self, name: str, backend: Backend) -> None:
        """Learn ``name``'s type and "up" in the background, once at a time (see :meth:`_reach`)."""
        if name not in self._reaching:
            task = asyncio.get_running_loop().create_task(
                self._reach(name, backend), name=f"reach {name}", context=own_context()
            )
            self._reaching[name] = task
            task.add_done_callback(lambda done: self._reached(name, done))

    async def _reach(self, name: str, backend: Backend) -> None:
        """Wait until ``backend`` is connected (a proxy: its device greeted), then learn its type."""
        pause = 0.05
        while True:
            try:
                await backend.wait_connected(max(1.0, self.period))
                break
            except PropertyError:
                await asyncio.sleep(pause)
                pause = min(pause * 2, max(1.0, self.period))
        self._learn_type(name, backend)

    def _reached(self, name: str, task: asyncio.Task[None]) -> None:
        if self._reaching.get(name) is task:
            del self._reaching[name]
        if not task.cancelled() and task.exception() is not None:
            log.error("waiting for %s failed", name, exc_info=task.exception())

    def _want_location(self, name: str) -> None:
        """Somebody asked where ``name`` is: follow its location from now on (once; on demand)."""
        self._follow_location(name)

    def _follow_location(self, name: str) -> bool:
        """:meth:`_want_location`; True when ``name``'s location is followed now."""
        directory = self._directory
        if directory is None or self._table.get(name) is None:
            return False
        try:
            backend = directory.backend(name)
            if backend.on_demand:  # following a dormant service's location would keep it awake
                return False
            self._locations.follow(name, backend)
        except (PropertyError, RuntimeError):  # not served (any more), or no event loop to follow in
            return False
        return True

    async def _locate(self, names: Iterable[str]) -> None:
        """The scheduler needs to know where ``names`` are: follow those not followed yet, and wait
        (at most ``timeout``) for the locations on the way. Each name is looked at once."""
        if self._directory is None:
            return
        awake: list[str] = []
        for name in names:
            if name not in self._located and self._follow_location(name):
                self._located.add(name)
            elif self._awake_on_demand(name):
                awake.append(name)
        await asyncio.gather(self._locations.settled(self.timeout), *map(self._read_location, awake))

    def _awake_on_demand(self, name: str) -> bool:
        """True when ``name`` is a dormant service that runs now (woken by a call or the scheduler)."""
        entry = self._table.get(name)
        if entry is None or entry.availability in ("dormant", "death") or self._directory is None:
            return False
        try:
            return self._directory.backend(name).on_demand
        except PropertyError:
            return False

    async def _read_location(self, name: str) -> None:
        """Read an awake dormant service's location once: a Listen would keep it from going dormant
        again, and until read it would count as 0 away (nearer than every followed provider)."""
        directory = self._directory
        if directory is None:
            return
        try:
            async with asyncio.timeout(self.timeout):
                text = await directory.backend(name).get("location")
            vector = parse_vector(as_text(text, "location")) if text else None
        except (PropertyError, TimeoutError, ValueFormatError):
            return
        if self._awake_on_demand(name):
            self._table.set_location(name, vector if vector is not None and vector.size else None)

    def _forget(self, name: str) -> None:
        reaching = self._reaching.pop(name, None)
        if reaching is not None:
            reaching.cancel()
        self._mirrored.discard(name)
        if not self._table.forget(name):
            return
        self.licensing.release_holder(name)
        self.licensing.release_service(name)
        self._locations.forget(name)
        self._located.discard(name)
        self._registrations.drop(name)

    def _bump(self) -> None:
        self.revision += 1
        self._dispatcher.table_changed()

    def _learn_type(self, name: str, backend: Backend) -> None:
        """Take the type a device told in its greeting, unless the registration declared one.

        A proxy is served before its device greets, so the entry starts with
        the placeholder type; the device has greeted once it has answered.
        """
        if name in self._mirrored:  # its owner says whether it is up; only its type is learned here
            kind = backend.info.type
            if kind and kind != PLACEHOLDER_TYPE and self._table.get(name) is not None:
                self._table.set_type(name, kind)
            return
        if not self._registrations.declared_type(name):
            self._table.learn_type(name, backend.info.type)

    # -- search --------------------------------------------------------------

    @query(doc="the services' names in name order, a page at a time: after (the last name read), limit")
    async def service_names(self, *, after: str = "", limit: str = "") -> list[str]:
        """The names of the services after ``after`` in name order (from the first when empty), at
        most ``limit`` (:data:`NAMES_PAGE`, at most :data:`MAX_NAMES_PAGE`) and at most what one
        value holds (``services.kernel.values.MAX_VALUE_LENGTH``): the page ends before the name that
        would pass it. An empty page: there are no more.

        ``services`` is one value, so past about 6,000 names it no longer fits in one; this reads
        the same names page by page. Name order keeps the pages right while services join and
        leave: a name registered throughout is read exactly once.
        """
        wanted = _page_limit(limit)
        page: list[str] = []
        size = len("()")
        for name in sorted(self._table.names()):
            if name <= after:
                continue
            size += len(name) + (1 if page else 0)
            if len(page) == wanted or size > MAX_VALUE_LENGTH:
                break
            page.append(name)
        return page

    @query(doc="names of the services matching type, location, state and property values")
    async def find(
        self,
        *,
        type: str = "",
        near: str = "",
        radius: str = "",
        state: str = "",
        limit: str = "",
        where: str = "",
    ) -> list[str]:
        """Find services: ``type`` (a type or a list of types), ``near`` (x y [z]) with ``radius`` metres,
        ``state`` (up or down), ``where`` (property=value pairs joined by &), at most ``limit`` names.

        Sorted nearest first when ``near`` is given, else by name.
        """
        given = {"type": type, "near": near, "radius": radius, "state": state, "limit": limit, "where": where}
        query = Query.parse({k: v for k, v in given.items() if v != ""})
        if query.near is not None:
            for name in self._table.names():
                self._want_location(name)
            # Services followed just now, or that joined a moment ago: their locations are on the way.
            await self._locations.settled(self.timeout)
        names = self._table.index.select(query)
        if query.props:
            names = await self._where(names, query.props)
        if query.limit is not None:
            names = names[: query.limit]
        return names

    async def _where(self, names: list[str], props: Mapping[str, str]) -> list[str]:
        directory = self._directory
        if directory is None:
            raise Unavailable("this registry cannot ask services for their properties: it has no directory")
        timeout = self.timeout
        matching: set[str] = set()

        async def match(name: str) -> None:
            try:
                backend = directory.backend(name)
                async with asyncio.timeout(timeout):
                    for path, expected in props.items():
                        if not values_equal(expected, await backend.get(path)):
                            return
            except (PropertyError, TimeoutError):
                return
            matching.add(name)

        await run_bounded(names, match, MAX_CONCURRENT_PROPERTY_GETS)
        return [n for n in names if n in matching]

    # -- the store -------------------------------------------------------------

    @property
    def store(
        self,
    ) -> Annotated[
        str,
        Prop(
            doc="where registrations are kept: embedded, or etcd://HOST:PORT (read-only: why) "
            "while they cannot change"
        ),
    ]:
        store = self._store
        return f"{store.location} (read-only: {store.read_only})" if store.read_only else store.location

    async def _restore(self) -> None:
        """Register again what the store keeps (the embedded store: the ``persist`` file)."""

        async def one(name: str, url: str, options: dict[str, str]) -> None:
            try:
                await self.register(name, url, options)
            except PropertyError as e:
                log.warning("cannot restore the registration of %s at %s: %s", name, url, e.message)
                self._registrations.keep(name, url, options)  # kept for the next start

        try:
            kept = await self._store.load()
        except PropertyError as e:
            log.warning("cannot read the registrations kept in %s: %s", self._store.location, e.message)
            return
        await asyncio.gather(*(one(*item) for item in kept))


class RegistryService(LocalService):
    """Serves a :class:`Registry`, and turns Sets on ``services.<name>`` into (un)registrations.

    ``services.<name>`` is a namespace with its own value (the URL), which
    the class wrapper treats as read-only; this is the one place it is written.
    """

    def __init__(self, registry: Registry, url: str = "local") -> None:
        super().__init__(registry, url)
        self.registry = registry

    async def set(self, path: str, value: Value, params: Mapping[str, str] = NO_PARAMS) -> Value:
        head, dot, name = path.partition(".")
        if head == "services" and dot and "." not in name:
            value = as_text(value, path)
            if value.strip() == "":
                if params:
                    raise InvalidArgument(f"unregistering {name!r} takes no parameters")
                await self.registry.unregister(name)
                return ""
            return await self.registry.register(name, value, params)
        return await super().set(path, value, params)
