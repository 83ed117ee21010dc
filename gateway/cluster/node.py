"""One gateway in a cluster: it joins, serves every registration of the cluster, and takes over orphans.

A :class:`ClusterNode` is what a gateway runs when its registry's store is shared
(``[registry] store = "etcd://..."``; docs/scale-out.md):

* **Joining.** It writes its ``gateways/ID`` key (leased: it goes when the gateway dies), reads
  every registration, owner, state and gateway, and watches the store from then on.
* **Serving.** Every registration of the cluster is one router entry here, a
  :class:`~gateway.cluster.switching.SwitchingBackend`: on the owner its target is the service's own
  proxy, on the others a gRPC proxy to the owner's advertised address (calls are forwarded, and the
  federation's ``ps-via`` guard stops a loop), and nothing while nobody owns it. A device that
  dialled in to this gateway's line listener is published (its ``services`` key bound to this
  gateway's lease) and served by its own proxy.
* **Registering.** A Set of ``services.NAME`` on any gateway reaches :meth:`ClusterNode.register`
  through the registry's :class:`~gateway.cluster.directory.ClusterDirectory`: the ``owners`` key is
  created for this gateway, then the ``services`` key, then the proxy is opened; a failure undoes
  them. The owners key goes first, so that no gateway mistakes the new registration for an orphan.
* **States.** The owner runs the liveness checks and writes ``states/NAME``; the others mirror it
  into their registry (``Registry.mirror``), so ``services.*.state`` is the same everywhere.
* **Failover.** A registration whose ``owners`` key expired is taken over by the least-loaded
  live gateway (:mod:`gateway.cluster.failover`), the orphans of one plan claimed together; the
  devices won are opened ``MAX_OPENING`` at a time. Listens through every gateway resume with a gap.
* **Drain and rebalance.** An admin drains a gateway (a ``drains/ID`` key, :meth:`ClusterNode.set_drain`):
  it hands what it owns over (:meth:`_hand_over`) and takes nothing new; a gateway that owns more
  than the others hands some over when one joins or returns, or when an admin asks
  (:mod:`gateway.cluster.moves`). A move closes the device's connection once its calls have ended,
  lets the owners key go, and the others claim it as they claim orphans; meanwhile every gateway
  holds the calls for it (``SwitchingBackend.switch(None, hold=...)``) instead of refusing them.
* **Read-only.** While the store cannot be reached, everything owned and forwarded is served as
  before and registrations are refused (UNAVAILABLE, saying why). When it is back the node writes
  again what the store lost (:meth:`_reassert`): nothing when the lease lived through it, every
  key of this gateway when the lease or the store's data are gone, in batches. For one lease time
  it lets the other gateways do the same before it believes a registration gone.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import time
from collections import Counter
from collections.abc import Callable, Coroutine, Mapping
from typing import Any

from gateway.backends import open_proxy
from gateway.cluster.directory import ClusterDirectory
from gateway.cluster.failover import Takeover
from gateway.cluster.licences import ClusterLicences
from gateway.cluster.moves import rebalance_quota, taking_loads
from gateway.cluster.records import DIAL_IN_PREFIX, DrainOrder, GatewayRecord, Registration, read_gateway
from gateway.cluster.switching import SwitchingBackend
from gateway.cluster.view import ClusterView
from gateway.cluster.writer import LatestWrites
from gateway.config import DEFAULT_REBALANCE_BATCH, DEFAULT_REBALANCE_SPREAD
from gateway.engine.guard import current_subject
from gateway.engine.router import Router
from gateway.peer_protocol import ProtocolMismatch, check_cluster
from gateway.proxies.grpc_proxy import open_grpc_backend
from services.apps.registry import AllowList, Registry
from services.apps.registry.store import Change, Kind, SharedStore
from services.apps.registry.table import GONE
from services.kernel.backend import Backend, BackendInfo
from services.kernel.errors import AlreadyExists, FailedPrecondition, NotFound, PropertyError, Unavailable
from services.kernel.worker_pool import run_bounded

__all__ = [
    "FORWARD_OPTIONS",
    "LEAVE_WAIT",
    "MAX_OPENING",
    "MAX_WRITES",
    "RECONNECT_GRACE",
    "REPORT_PERIOD",
    "ClusterNode",
]

log = logging.getLogger(__name__)

#: Options of the gRPC proxies that forward calls to an owner: a dead owner is replaced within a
#: lease, so its proxy need not wait long between attempts to reach it again.
FORWARD_OPTIONS: Mapping[str, Any] = {"backoff_initial": 0.1, "backoff_max": 2.0}
#: Seconds a gateway that stops spends handing its services over (deleting its keys) at most.
LEAVE_WAIT = 3.0
#: Seconds a registration waits for a name's owner to let the name go when its registration is
#: gone already: unregistered through another gateway, the owner deletes its owners key once it
#: sees that, a moment later (longer on a busy machine).
RELEASE_WAIT = 2.0
#: Seconds between two tries to take such a name.
RELEASE_POLL = 0.05
#: Writes to the store at once when this gateway hands its keys over (leaving).
MAX_WRITES = 64
#: Devices taken over that are being connected at once (a TCP connect, the greeting, a properties
#: Get each): a dead gateway's thousand devices would otherwise be a thousand connections opened
#: in one go, each answer queued behind the others' and behind this gateway's own calls.
MAX_OPENING = 64
#: Seconds a device that dialled in, whose registration left with its gateway (that gateway died,
#: froze past its lease, or stopped), is waited for under its name: its service reads UNAVAILABLE
#: ("reconnecting") meanwhile, and every Listen on it stays open and resumes, with a gap, on the
#: gateway the device dials next. The device is refused elsewhere until the lease has run out,
#: then dials in at its next round (its pause doubles up to 10 s): this covers several rounds.
RECONNECT_GRACE = 20.0
#: Seconds between two writes of this gateway's record with its load and lease (the cluster view):
#: a few writes a minute per gateway, and the view is that fresh.
REPORT_PERIOD = 2.0
#: Seconds a gateway waits after another joined, returned or was undrained before it rebalances:
#: the newcomer has read the cluster by then.
REBALANCE_DELAY = 0.5
#: Folders read when joining and after a reconnect (and the licences, for the licence mirror).
_FOLDERS = (Kind.GATEWAY, Kind.SERVICE, Kind.OWNER, Kind.STATE)


class ClusterNode:
    """This gateway's part in a cluster sharing one registry store (see the module docstring)."""

    def __init__(
        self,
        store: SharedStore,
        router: Router,
        *,
        lease: float,
        allow: AllowList | None = None,
        peer_tls: Mapping[str, str] | None = None,
        max_opening: int = MAX_OPENING,
        reconnect_grace: float = RECONNECT_GRACE,
        rebalance: bool = False,
        rebalance_spread: int = DEFAULT_REBALANCE_SPREAD,
        rebalance_batch: int = DEFAULT_REBALANCE_BATCH,
        version: str = "",
        load: Callable[[], tuple[int, int]] | None = None,
    ) -> None:
        """``lease``: seconds of the store's lease (a dead gateway's keys go within it); ``allow``: what
        this gateway may dial when it takes a registration over (the registry's allow-list);
        ``peer_tls``: the ``grpcs://`` proxy options (``ca``, ``cert``, ``key``) with which calls are
        forwarded to a gateway that serves TLS; ``max_opening``: devices taken over that are
        connected at once; ``reconnect_grace``: seconds the name of a device that dialled in is held
        for it after its registration left with its gateway (:data:`RECONNECT_GRACE`); ``rebalance``:
        hand devices over when another gateway joins or returns with fewer
        (:mod:`gateway.cluster.moves`: ``rebalance_spread``, ``rebalance_batch``); ``version``: this
        gateway's release, shown in the cluster view; ``load``: (calls answered so far, Listen
        streams open now), read every :data:`REPORT_PERIOD` for the view."""
        if max_opening < 1:
            raise ValueError(f"max_opening must be at least 1, got {max_opening}")
        self.store = store
        self.router = router
        self.lease = lease
        self.allow = allow
        self.peer_tls: Mapping[str, str] = dict(peer_tls or {})
        self.reconnect_grace = reconnect_grace
        #: This gateway's id in the cluster (the value of the owners keys it writes).
        self.me = store.gateway_id
        self.view = ClusterView()
        #: The directory the registry is given (registrations go through :meth:`register`).
        self.directory = ClusterDirectory(self.router.directory, self)
        #: The licence claims the registry's licences are checked against.
        self.licences = ClusterLicences(store)
        self.registry: Registry | None = None
        self.record = GatewayRecord(address="")
        #: The router entries of the cluster's registrations, by name.
        self.served: dict[str, SwitchingBackend] = {}
        #: Registrations whose connection this gateway holds, with what their key holds.
        self.owned: dict[str, Registration] = {}
        #: Devices that dialled in here and were published, by name.
        self._dialled: dict[str, Backend] = {}
        #: name → the URL its forwarding proxy dials (the owner's address, over TLS or not).
        self._forwarding: dict[str, str] = {}
        #: Devices that dialled in whose registration left with their gateway: name → the loop time
        #: until which its entry here waits for the device to dial in again (UNAVAILABLE meanwhile).
        self._awaited: dict[str, float] = {}
        #: Names being registered, unregistered or published now: the reconciler leaves them alone.
        self._busy: set[str] = set()
        #: Services taken over whose device is being opened (waiting for one of MAX_OPENING places).
        self._opening: set[str] = set()
        self._open_places = asyncio.Semaphore(max_opening)
        #: Devices taken over being connected now, each holding one of the places (tests, metrics).
        self.connecting = 0
        #: Services owned here whose owners key went: claimed again together, by one task.
        self._reclaiming: set[str] = set()
        self._reclaimer: asyncio.Task[None] | None = None
        self._dirty: dict[str, None] = {}
        #: Names looked at again once the store has settled after a reconnect.
        self._deferred: dict[str, None] = {}
        self._wake = asyncio.Event()
        self._reconciler: asyncio.Task[None] | None = None
        self._tasks: set[asyncio.Task[None]] = set()
        self._writes = LatestWrites(store)
        self._takeover = Takeover(
            self.me, step=min(0.5, lease / 10), plan=self._takeover_plan, attempt=self._take_over
        )
        self._stops: list[Callable[[], None]] = []
        #: Until this loop time, a registration missing from the store is not believed gone (after
        #: a reconnect the other gateways write theirs again) and nothing is taken over.
        self._settling_until = 0.0
        self._resyncing = False
        self.joined = False
        self._stopped = False
        #: Rebalance by policy (``[registry] rebalance``), and its bounds.
        self.rebalance = rebalance
        self.rebalance_spread = rebalance_spread
        self.rebalance_batch = rebalance_batch
        self.version = version
        self._load = load
        #: An admin drained this gateway (a ``drains`` key names it): it hands over and takes nothing.
        self.draining = False
        #: Services this gateway is handing over (a drain, a rebalance), until another owns them.
        self._handing: set[str] = set()
        #: Registered on this gateway while it is drained: handed over once the registry has it up.
        self._hand_over_when_up: set[str] = set()
        #: Seconds every gateway holds the calls for a service that moves (a planned move).
        self.move_hold = max(2.0, lease)
        #: One drain or rebalance at a time.
        self._moving = asyncio.Lock()
        self._owners_changed = asyncio.Event()
        self._rebalancer: asyncio.Task[None] | None = None
        self._rebalance_asked = False
        #: The last move this gateway made: (devices, seconds, why), for the cluster view.
        self.last_move: tuple[int, float, str] | None = None
        #: Called when the cluster view may have changed (the registry's ``cluster`` property).
        self.on_view: Callable[[], None] = lambda: None

    # -- joining and leaving ---------------------------------------------------

    async def start(
        self,
        registry: Registry,
        *,
        address: str,
        http: str = "",
        line: str = "",
        tls: bool = False,
        via: str = "",
    ) -> None:
        """Join: this gateway serves gRPC at ``address`` (as the others dial it; over TLS when
        ``tls``), HTTP at ``http`` and the line protocol at ``line`` ("" when off); ``via`` is its id
        in the ``ps-via`` chain of the calls it forwards. A store that
        cannot be reached now is joined when it is back (the gateway serves read-only until then)."""
        self.registry = registry
        self.record = GatewayRecord(address=address, http=http, line=line, tls=tls, via=via)
        registry.licensing.set_claims(self.licences)
        self.licences.show_in(registry)
        self._stops += [
            self.store.watch(self._on_change),
            self.store.on_reconnect(self._on_reconnect),
            self.router.watch(self._on_router),
            registry.watch_states(self._on_state, members=True),
        ]
        self._reconciler = asyncio.get_running_loop().create_task(self._work(), name="cluster: reconciler")
        self._spawn(self._report(), "cluster: report this gateway's load")
        for name, backend in self.router.items():  # devices that dialled in before the node started
            self._on_router(name, backend)
        try:
            await self._join()
        except ProtocolMismatch:
            raise  # the gateway does not start: nothing it wrote would be understood
        except PropertyError as exc:
            log.warning(
                "cluster: cannot join now (%s); serving read-only until the store is back", exc.message
            )

    async def _join(self) -> None:
        # A live gateway that shares no cluster protocol version with this one would misread what
        # this one writes, and this one what it writes: refuse before writing anything.
        gateways = {gid: read_gateway(text) for gid, text in (await self.store.read(Kind.GATEWAY)).items()}
        check_cluster(
            {gid: record.protocols for gid, record in gateways.items() if record is not None},
            me=self.me,
            store=self.store.location,
        )
        # Owners keys that name this gateway but belong to an earlier run of it (the same id; its
        # lease has not expired yet) are let go now: the services are taken over as orphans.
        for name, owner in (await self.store.read(Kind.OWNER)).items():
            if owner == self.me and name not in self.owned:
                await self._let_go(Kind.OWNER, name, self.me)
        await self._announce()
        await self._read_all()
        self.joined = True

    async def _announce(self) -> None:
        self.record = dataclasses.replace(
            self.record, owned=len(self.owned), version=self.version, draining=self.draining
        )
        await self.store.put(Kind.GATEWAY, self.me, self.record.to_json(), leased=True)

    async def _read_all(self) -> None:
        folders = {kind: await self.store.read(kind) for kind in (*_FOLDERS, Kind.DRAIN)}
        self.view.replace(folders)
        self._spawn(self._follow_drain(), "cluster: follow this gateway's drain")
        self.licences.load(await self.store.read(Kind.LICENCE))
        self._look_at_everything()

    def _look_at_everything(self) -> None:
        """Reconcile every service known here, and look for orphans."""
        for name in sorted({*self.view.registrations, *self.served, *self._dialled}):
            self._mark(name)
        self._takeover.orphaned()

    async def stop(self) -> None:
        """Leave: hand over what this gateway owns (its keys go now, not at the end of the lease)."""
        if self._stopped:
            return
        self._stopped = True
        for stop in self._stops:
            stop()
        self._stops.clear()
        await self._takeover.aclose()
        rebalancer, self._rebalancer = self._rebalancer, None
        if rebalancer is not None:
            rebalancer.cancel()
            await asyncio.gather(rebalancer, return_exceptions=True)
        reconciler, self._reconciler = self._reconciler, None
        if reconciler is not None:
            reconciler.cancel()
            await asyncio.gather(reconciler, return_exceptions=True)
        tasks = list(self._tasks)
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        if self.registry is not None:
            self.registry.licensing.set_claims(None)
        await self.licences.aclose()
        if not self.store.read_only:
            try:
                async with asyncio.timeout(LEAVE_WAIT):
                    await self._leave()
            except (TimeoutError, PropertyError) as exc:
                log.info("cluster: left without handing over (%s); the lease ends it", exc)
        await self._writes.aclose()

    async def _leave(self) -> None:
        async def close(name: str) -> None:
            registration, switching = self.owned.get(name), self.served.get(name)
            if switching is not None and (registration is None or not registration.dialled_in):
                reason = f"service {name!r} is moving to another gateway (stopping)"
                await switching.switch(None, reason=reason)

        async def hand_over(name: str) -> None:
            registration = self.owned.get(name)
            await self._let_go(Kind.OWNER, name, self.me)
            await self._delete(Kind.STATE, name)
            if registration is not None and registration.dialled_in:
                await self._delete(Kind.SERVICE, name)

        # Each device's link closes before its owners key goes: a link still open here once another
        # gateway owns the device would pass on its changes beside the new owner's, and a Listen
        # forwarded here could hear a value newer than the new owner's first one, then go back.
        # A call hung on a device holds its link open: the keys go anyway after a third of the wait.
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(LEAVE_WAIT / 3):
                await run_bounded(sorted(self.owned), close, MAX_WRITES)
        await run_bounded(sorted(self.owned), hand_over, MAX_WRITES)
        await self.store.delete(Kind.GATEWAY, self.me)

    # -- what the store says ---------------------------------------------------

    def _on_change(self, change: Change) -> None:
        if change.kind is Kind.LICENCE:
            self.licences.observe(change.name, change.value)
            return
        before = self.view.gateways.get(change.name) if change.kind is Kind.GATEWAY else None
        for name in self.view.apply(change):
            self._mark(name)
        if change.value is None and change.kind in (Kind.OWNER, Kind.GATEWAY):
            self._takeover.orphaned()
        if change.kind is Kind.OWNER:
            self._owners_changed.set()
        elif change.kind is Kind.DRAIN:
            if change.name == self.me:
                self._spawn(self._follow_drain(), "cluster: follow this gateway's drain")
            elif change.value is not None:
                self._takeover.orphaned()  # a plan made now leaves the drained gateway out
        elif change.kind is Kind.GATEWAY and change.name != self.me:
            self._gateway_changed(before, self.view.gateways.get(change.name))
        self.on_view()

    async def _create(self, kind: Kind, name: str, value: str, *, leased: bool = False) -> bool:
        """Create a key when absent; this gateway's view has it at once (the watch confirms it later)."""
        created = await self.store.create(kind, name, value, leased=leased)
        if created:
            self._on_change(Change(kind, name, value))
        return created

    async def _let_go(self, kind: Kind, name: str, expected: str) -> bool:
        """Delete a key when it still holds ``expected``; the view has it gone at once."""
        deleted = await self.store.replace(kind, name, expected, None)
        if deleted:
            self._on_change(Change(kind, name, None))
        return deleted

    async def _delete(self, kind: Kind, name: str) -> None:
        """Delete a key; the view has it gone at once."""
        await self.store.delete(kind, name)
        self._on_change(Change(kind, name, None))

    def _mark(self, name: str) -> None:
        self._dirty[name] = None
        self._wake.set()

    def _on_reconnect(self) -> None:
        """The store is back: write what it lost of this gateway's keys again (in a task)."""
        self._resyncing = True
        self._settling_until = asyncio.get_running_loop().time() + self.lease
        self._spawn(self._reassert(), "cluster: write the keys again")

    async def _reassert(self) -> None:
        try:
            # The view is the store's already: its watch reported every key, at one revision, before
            # this ran (Store.on_reconnect). Reading the folders again could only go back in time:
            # a read answered after a newer change came through the watch would undo that change
            # (a gateway's record, say, leaving its services forwarded nowhere for good).
            self._look_at_everything()
            written = await self._write_lost()
            self.joined = True
            log.info("cluster: the store is back; written again: %s", written)
        except PropertyError as exc:
            log.warning(
                "cluster: writing the keys again failed (%s); trying at the next reconnect", exc.message
            )
        finally:
            self._resyncing = False
            self._wake.set()

    async def _write_lost(self) -> str:
        """Write the keys of this gateway that the store does not hold as this gateway does.

        A store that kept this gateway's lease kept every key bound to it, and one that took a new
        lease did so once the old one's keys were gone (the store's promise): so comparing with what
        the store holds now is enough. When the lease lived, nothing is written; when it, or the
        store's data, is gone, every key is, in a few bulk writes (the store bounds their size and
        how many are in flight). An owners key is created only if absent: another gateway may have
        taken the service over meanwhile. What was written, for the log.
        """
        view = self.view
        self.record = dataclasses.replace(self.record, owned=len(self.owned))
        announced = view.gateways.get(self.me) != self.record
        if announced:
            await self._announce()
            self._on_change(Change(Kind.GATEWAY, self.me, self.record.to_json()))
        held = sorted(self.owned)
        unowned = [name for name in held if name not in view.owners]
        won = await self._create_many(Kind.OWNER, {name: self.me for name in unowned}, leased=True)
        for name in unowned:
            if name not in won:
                log.info("cluster: %s is owned by %s now", name, view.owners.get(name, "another gateway"))
        mine = [(name, self.owned[name]) for name in held if view.owners.get(name) == self.me]
        # A registration by Set outlives this gateway: written only when the store lost it. One that
        # dialled in is bound to this gateway's lease: written when the store does not hold it so.
        registered = await self._create_many(
            Kind.SERVICE,
            {n: r.to_json() for n, r in mine if not r.dialled_in and n not in view.registrations},
        )
        dialled = {n: r.to_json() for n, r in mine if r.dialled_in and view.registrations.get(n) != r}
        await self._put_many(Kind.SERVICE, dialled, leased=True)
        states: dict[str, str] = {}
        registry = self.registry
        if registry is not None:
            for name, _ in mine:
                if registry.entry_of(name) is not None and view.states.get(name) != registry.state_of(name):
                    states[name] = registry.state_of(name)
        await self._put_many(Kind.STATE, states, leased=True)
        return (
            f"{'the gateway key, ' if announced else ''}{len(won)} owners, "
            f"{len(registered) + len(dialled)} registrations and {len(states)} states of {len(held)} owned"
        )

    async def _create_many(self, kind: Kind, values: Mapping[str, str], *, leased: bool = False) -> set[str]:
        """Create the keys that are absent, in bulk; the view has those created at once."""
        if not values:
            return set()
        created = await self.store.create_many(kind, values, leased=leased)
        for name in sorted(created):
            self._on_change(Change(kind, name, values[name]))
        return created

    async def _put_many(self, kind: Kind, values: Mapping[str, str], *, leased: bool = False) -> None:
        """Write keys in bulk; the view has them at once."""
        if not values:
            return
        await self.store.put_many(kind, values, leased=leased)
        for name, value in values.items():
            self._on_change(Change(kind, name, value))

    def _on_router(self, name: str, backend: Backend | None) -> None:
        """A device dialled in to this gateway's line listener: publish it to the cluster."""
        if backend is None:
            dialled = self._dialled.pop(name, None)
            if dialled is not None and name not in self._busy:
                registration = self.owned.pop(name, None)
                self._spawn(self._unpublish(name, registration), f"cluster: unpublish {name}")
            return
        if backend.info.url.startswith(DIAL_IN_PREFIX) and name not in self.served and name not in self._busy:
            self._spawn(self._publish(name, backend), f"cluster: publish {name}")

    def _on_state(self, name: str, state: str) -> None:
        """The registry's state of a service: the owner reports it to the others."""
        if name in self.owned and state != GONE:
            self._writes.put(Kind.STATE, name, state)
        if name in self._hand_over_when_up and state != "connecting":
            self._hand_over_when_up.discard(name)
            if state == "up" and name in self.owned:
                self._spawn(self._hand_over_locked([name], "drained"), f"cluster: hand {name} over")

    def _spawn(self, coro: Coroutine[Any, Any, None], name: str) -> None:
        task = asyncio.get_running_loop().create_task(coro, name=name)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    # -- registering, unregistering, publishing ---------------------------------

    def _writable(self) -> None:
        reason = self.store.read_only
        if reason:
            raise Unavailable(f"the registry is read-only: {reason}")
        if not self.joined:
            raise Unavailable("the registry is read-only: this gateway has not joined its cluster yet")

    async def register(self, name: str, url: str, options: Mapping[str, Any] | None = None) -> BackendInfo:
        """Register ``name`` at ``url`` in the cluster and own it here (the registry's directory calls).

        AlreadyExists when another gateway owns the name or another registration holds it;
        Unavailable when the store is read-only.
        """
        self._writable()
        if name in self._busy or name in self.router:
            raise AlreadyExists(f"a service named {name!r} already exists")
        registration = Registration(url)
        self._busy.add(name)
        try:
            await self._claim(name, registration, leased=False)
            try:
                proxy = open_proxy(name, url, options or {})
                await proxy.start()
            except BaseException:
                await self._release(name, registration)
                raise
            switching = SwitchingBackend(name, url, declared_type=registration.declared_type)
            await switching.switch(proxy, "owned here")
            self.router.add(name, switching)
            self.served[name] = switching
            self._own(name, registration)
            log.info("cluster: service %s registered at %s, owned here", name, url)
            if self.draining:  # a drained gateway takes no new device: it hands it over once it is up
                self._hand_over_when_up.add(name)
            return switching.info
        finally:
            self._busy.discard(name)
            self._mark(name)

    async def _claim(self, name: str, registration: Registration, *, leased: bool) -> None:
        """Create the owners key, then the services key; AlreadyExists (nothing left) when taken."""
        if not await self._take_owner(name):
            owner = self.view.owners.get(name, "another gateway")
            raise AlreadyExists(f"the name {name!r} is taken in the cluster (owned by gateway {owner})")
        if not await self._create(Kind.SERVICE, name, registration.to_json(), leased=leased):
            await self._let_go(Kind.OWNER, name, self.me)
            held = self.view.registrations.get(name)
            by = f"by {held.url}" if held is not None else "by another registration"
            raise AlreadyExists(f"the name {name!r} is taken in the cluster ({by}); unregister it first")

    async def _take_owner(self, name: str) -> bool:
        """Create the name's owners key. While the name has no registration (its owner is letting
        it go), try again for up to RELEASE_WAIT seconds; False when it stays taken."""
        loop = asyncio.get_running_loop()
        give_up = loop.time() + RELEASE_WAIT
        while not await self._create(Kind.OWNER, name, self.me, leased=True):
            if name in self.view.registrations or loop.time() >= give_up:
                return False
            await asyncio.sleep(RELEASE_POLL)
        return True

    async def _release(self, name: str, registration: Registration) -> None:
        """Undo :meth:`_claim` (the proxy could not be made); never raises."""
        with contextlib.suppress(PropertyError):
            await self._let_go(Kind.SERVICE, name, registration.to_json())
            await self._let_go(Kind.OWNER, name, self.me)

    def _own(self, name: str, registration: Registration) -> None:
        self.owned[name] = registration
        self._forwarding.pop(name, None)
        if self.registry is not None:
            self.registry.mirror(name, None)
        self._count_changed()

    def _count_changed(self) -> None:
        self.record = dataclasses.replace(self.record, owned=len(self.owned))
        self._writes.put(Kind.GATEWAY, self.me, self.record.to_json())
        self.on_view()

    async def unregister(self, name: str) -> None:
        """Remove ``name`` from the cluster (on whichever gateway owns it); Unavailable when read-only."""
        registration = self.view.registrations.get(name) or self.owned.get(name)
        if registration is None and name not in self.served and name not in self._dialled:
            await self.router.unregister(name)  # not the cluster's: this gateway's own
            return
        self._writable()
        self._busy.add(name)
        try:
            await self._delete(Kind.SERVICE, name)
            if name in self.owned:
                await self._let_go(Kind.OWNER, name, self.me)
                await self._delete(Kind.STATE, name)
            await self._drop(name)
        finally:
            self._busy.discard(name)
            self._mark(name)

    async def _publish(self, name: str, backend: Backend) -> None:
        """Publish a device that dialled in here: its keys bound to this gateway's lease."""
        registration = Registration(
            backend.info.url, {"type": backend.info.type} if backend.info.type else {}
        )
        self._busy.add(name)
        try:
            self._writable()
            await self._claim(name, registration, leased=True)
        except PropertyError as exc:
            if isinstance(exc, AlreadyExists):
                log.warning(
                    "cluster: device %s dialled in here, but %s; it is turned away", name, exc.message
                )
                with contextlib.suppress(PropertyError):
                    await self.router.unregister(name)
                return
            log.warning("cluster: device %s served here, not published yet: %s", name, exc.message)
        finally:
            self._busy.discard(name)
        self._dialled[name] = backend
        self._own(name, registration)
        if self.registry is not None and self.registry.entry_of(name) is not None:
            self._writes.put(Kind.STATE, name, self.registry.state_of(name))
        self._mark(name)

    async def _unpublish(self, name: str, registration: Registration | None) -> None:
        """A published device left this gateway's router: its keys go, unless they are another
        gateway's by now (the device dialled in there while this gateway was frozen)."""
        try:
            held = self.view.registrations.get(name)
            if held is not None and registration is not None and held.url == registration.url:
                await self._delete(Kind.SERVICE, name)
            if await self._let_go(Kind.OWNER, name, self.me):
                await self._delete(Kind.STATE, name)
        except PropertyError as exc:
            log.info("cluster: %s left; its keys stay until the lease ends: %s", name, exc.message)
        self._count_changed()
        self._mark(name)  # a registration of the name elsewhere is served here from now on

    # -- reconciling: what the router serves follows the view ------------------

    async def _work(self) -> None:
        loop = asyncio.get_running_loop()
        while True:
            await self._wake.wait()
            self._wake.clear()
            if self._deferred and loop.time() >= self._settling_until:
                self._dirty.update(self._deferred)
                self._deferred.clear()
            if self._resyncing:
                continue  # the reassert wakes it when done
            while self._dirty and not self._resyncing:
                name = next(iter(self._dirty))
                del self._dirty[name]
                if name in self._busy:
                    continue  # marked again when the registration or unregistration is done
                try:
                    await self._reconcile(name)
                except Exception:
                    log.exception("cluster: serving %s failed", name)
            if self._deferred:
                loop.call_later(max(0.0, self._settling_until - loop.time()), self._wake.set)

    async def _reconcile(self, name: str) -> None:
        registration = self.view.registrations.get(name)
        owner = self.view.owners.get(name)
        if registration is None:
            if name in self.served or name in self._dialled:
                if asyncio.get_running_loop().time() < self._settling_until:
                    self._deferred[name] = None  # looked at again once the others wrote theirs again
                    return
                if await self._await_device(name):
                    return
                await self._drop(name)
            if owner == self.me:  # the registration left: so does this gateway's claim on it
                await self._let_go(Kind.OWNER, name, self.me)
                if name in self.view.states:
                    await self._delete(Kind.STATE, name)
            return
        if name in self._dialled:
            if owner is not None and owner != self.me:
                log.warning("cluster: %s is owned by %s now; the device here is turned away", name, owner)
                await self._drop(name)
                self._mark(name)  # served again, forwarded to its owner
                return
            self._show_owner(name)
            return
        switching = self._serve(name, registration)
        if switching is None:
            return
        if self._awaited.pop(name, None) is not None:
            log.info("cluster: %s is back, at %s", name, registration.url)
        switching.info.url = registration.url
        if owner == self.me:
            if name in self._handing:
                pass  # being handed over: its owners key goes next
            elif name not in self.owned or switching.target is None:
                self._open_owned(name, switching)
            else:
                self.owned[name] = registration  # as the key holds it now (the registry adds options)
        elif owner is not None:
            await self._forward(name, owner, switching)
        elif name in self._forwarding and asyncio.get_running_loop().time() < self._settling_until:
            # The store came back without its owners key yet: its owner is writing it again. The
            # calls keep going to it meanwhile; looked at again once the store has settled.
            self._deferred[name] = None
            return
        else:
            await self._orphan(name, registration, switching)
        self._show_owner(name)

    async def _await_device(self, name: str) -> bool:
        """The registration of ``name`` left the cluster: when it was a device that dialled in (it
        left with its gateway, and dials another one), hold its entry, answering UNAVAILABLE, until it
        is back or :attr:`reconnect_grace` has passed. True while it is held."""
        switching = self.served.get(name)
        if switching is None or name in self._dialled or self._stopped:
            return False
        if not switching.info.url.startswith(DIAL_IN_PREFIX):
            return False  # a registration by Set leaves only when unregistered
        loop = asyncio.get_running_loop()
        until = self._awaited.get(name)
        if until is None:
            until = self._awaited[name] = loop.time() + self.reconnect_grace
            self._forwarding.pop(name, None)
            await switching.switch(
                None,
                reason=f"service {name!r} is reconnecting: its device had dialled in to a gateway "
                f"that left the cluster, and dials another one",
            )
            if self.registry is not None:
                self.registry.mirror(name, "connecting")
            self._show_owner(name)
            loop.call_later(self.reconnect_grace, self._mark, name)
            log.info(
                "cluster: %s left with its gateway; waiting %g s for it to dial in again",
                name,
                self.reconnect_grace,
            )
            return True
        if loop.time() < until:
            return True
        del self._awaited[name]
        log.info("cluster: %s did not dial in again within %g s; it is gone", name, self.reconnect_grace)
        return False

    def awaits(self, name: str) -> bool:
        """Whether ``name`` is held for a device that dialled in and is reconnecting (it may dial here)."""
        return name in self._awaited and name in self.served and name not in self.view.registrations

    def inbound(self, name: str) -> Backend | None:
        """The proxy of the device ``name`` that dialled in here and sits in the cluster's entry (it
        dialled in here while it was awaited); None when there is none."""
        switching = self.served.get(name)
        if switching is None or self._dialled.get(name) is not switching:
            return None
        return switching.target

    async def seat(self, name: str, proxy: Backend) -> None:
        """The device ``name``, awaited (:meth:`awaits`), dialled in here: publish it and serve it
        through the entry that held its name, so that every Listen on it resumes with a gap.
        AlreadyExists when it is not awaited (any more) or another gateway took the name first."""
        switching = self.served.get(name)
        until = self._awaited.get(name)
        if switching is None or until is None or not self.awaits(name):
            raise AlreadyExists(f"the name {name!r} is taken")
        registration = Registration(proxy.info.url, {"type": proxy.info.type} if proxy.info.type else {})
        self._writable()
        self._busy.add(name)  # the reconciler leaves it alone until it is served here
        try:
            await self._claim(name, registration, leased=True)
            self._awaited.pop(name, None)
            switching.info.url = registration.url
            self._dialled[name] = switching
            await switching.switch(proxy, "dialled in here")
            self._own(name, registration)
        finally:
            self._busy.discard(name)
            self._mark(name)
        log.info("cluster: %s dialled in here again (%s)", name, registration.url)
        self._spawn(self._reach(name, switching), f"cluster: reach {name}")

    def _show_owner(self, name: str) -> None:
        """``services.NAME.owner`` in this gateway's registry: who holds the connection, as heard."""
        if self.registry is not None:
            self.registry.set_owner(name, self.view.owners.get(name, ""))

    def _serve(self, name: str, registration: Registration) -> SwitchingBackend | None:
        """The router entry of ``name``, made when missing; None when the name is this gateway's own."""
        switching = self.served.get(name)
        if switching is not None:
            return switching
        if name in self.router:
            log.warning(
                "cluster: %s is registered in the cluster, but this gateway serves its own %s", name, name
            )
            return None
        switching = SwitchingBackend(name, registration.url, declared_type=registration.declared_type)
        self.served[name] = switching
        self.router.add(name, switching)
        if self.registry is not None:
            self.registry.mirror(name, self.view.states.get(name, "connecting"))
        return switching

    def _open_owned(self, name: str, switching: SwitchingBackend) -> None:
        """This gateway owns ``name`` now (it took it over): open the device, in a task that waits for
        one of ``MAX_OPENING`` places (a dead gateway's devices are opened side by side, not in turn)."""
        if name not in self._opening:
            self._opening.add(name)
            self._spawn(self._open(name, switching), f"cluster: open {name}")

    async def _open(self, name: str, switching: SwitchingBackend) -> None:
        try:
            async with self._open_places:
                registration = self.view.registrations.get(name)
                if (
                    registration is None
                    or self.view.owners.get(name) != self.me
                    or self.served.get(name) is not switching
                    or self._stopped
                ):
                    return  # it moved on while waiting for a place
                try:
                    proxy = open_proxy(name, registration.url, {})
                    await proxy.start()
                except PropertyError as exc:
                    log.error("cluster: cannot open %s at %s: %s", name, registration.url, exc.message)
                    return
                self.connecting += 1
                try:
                    # The calls held for a planned move go to it once it answers, not before (they
                    # would be refused as "not connected yet"); a device that does not answer is
                    # switched to all the same, and its state says so.
                    try:
                        with contextlib.suppress(PropertyError):
                            await proxy.wait_connected(
                                max(1.0, self.registry.timeout if self.registry else 1.0)
                            )
                    except BaseException:
                        await proxy.aclose()  # stopped meanwhile: the proxy is nobody's
                        raise
                    await switching.switch(proxy, "owned here")
                    self._own(name, registration)
                    log.info("cluster: %s is owned here now (%s)", name, registration.url)
                    await self._reach(name, switching)
                finally:
                    self.connecting -= 1
        finally:
            self._opening.discard(name)

    async def _reach(self, name: str, switching: SwitchingBackend) -> None:
        """Tell the registry once the device taken over answers (it checks it itself from now on)."""
        registry = self.registry
        if registry is None:
            return
        with contextlib.suppress(PropertyError):
            await switching.wait_connected(max(1.0, registry.timeout))
            if name in self.owned and registry.entry_of(name) is not None:
                registry.add(name, switching.info)

    async def _forward(self, name: str, owner: str, switching: SwitchingBackend) -> None:
        record = self.view.gateways.get(owner)
        self._handing.discard(name)
        if name in self.owned:
            log.info("cluster: %s is owned by %s now", name, owner)
            self.owned.pop(name, None)
            self._count_changed()
        if record is None:
            self._forwarding.pop(name, None)
            await switching.switch(
                None, reason=f"service {name!r} is owned by gateway {owner}, which is not in the cluster now"
            )
        elif self._forwarding.get(name) != (url := self._forward_url(record, name)):
            options = {**FORWARD_OPTIONS, **self.peer_tls} if record.tls else FORWARD_OPTIONS
            proxy = open_grpc_backend(name, url, options)
            await proxy.start()
            self._forwarding[name] = url
            await switching.switch(proxy, f"forwarded to gateway {owner} at {record.address}")
        if self.registry is not None:
            self.registry.mirror(name, self.view.states.get(name, "connecting"))

    def is_peer_hop(self, hop: str) -> bool:
        """Whether ``hop`` of a call's ``ps-via`` chain is another gateway of the cluster."""
        return any(
            record.via == hop
            for gateway, record in self.view.gateways.items()
            if gateway != self.me and record.via
        )

    @staticmethod
    def _forward_url(record: GatewayRecord, name: str) -> str:
        """The URL of the gRPC proxy that forwards calls for ``name`` to the gateway of ``record``."""
        return f"{'grpcs' if record.tls else 'grpc'}://{record.address}/{name}"

    async def _orphan(self, name: str, registration: Registration, switching: SwitchingBackend) -> None:
        moving = name in self._handing or self._owner_lives(name)
        if name in self.owned:
            if name not in self._handing:
                # This gateway holds the connection, but its owners key went (its lease lapsed while
                # the store was away): claim it again at once, with the others that went with it.
                self._reclaim(name)
                return
            self.owned.pop(name, None)  # handed over: let go of here, another claims it
            self._count_changed()
        self._forwarding.pop(name, None)
        if moving:
            # A planned move (a drain, a rebalance): its owner lives and let it go; the calls wait
            # for the gateway that claims it instead of being refused.
            await switching.switch(
                None,
                reason=f"service {name!r} is moving to another gateway and has not been claimed "
                f"within {self.move_hold:g} s",
                hold=self.move_hold,
            )
        else:
            await switching.switch(
                None,
                reason=f"service {name!r} has no owner now: its gateway left the cluster, and another "
                f"takes it over within {self.lease:g} s",
            )
        if self.registry is not None:
            self.registry.mirror(name, "connecting")
        self._takeover.orphaned()

    async def _drop(self, name: str) -> None:
        """Stop serving ``name`` (its registration left the cluster); a device that dialled in here
        is hung up on (it dials again, and is registered again)."""
        self._handing.discard(name)
        switching = self.served.pop(name, None)
        dialled = self._dialled.pop(name, None)
        self._forwarding.pop(name, None)
        if name in self.owned:
            self.owned.pop(name, None)
            self._count_changed()
        for backend in (switching, dialled):
            if backend is not None and name in self.router and self.router.lookup(name) is backend:
                self.router.remove(name)
        if switching is not None:
            await switching.aclose()
        if dialled is not None:
            await dialled.aclose()

    # -- failover --------------------------------------------------------------

    def _takeover_plan(self) -> tuple[list[str], dict[str, int]]:
        if self._resyncing or asyncio.get_running_loop().time() < self._settling_until:
            self._spawn(self._replan_later(), "cluster: plan later")
            return [], {}
        return self.view.orphans(), taking_loads(self.view.loads(), self._draining_gateways())

    async def _replan_later(self) -> None:
        await asyncio.sleep(max(0.05, self._settling_until - asyncio.get_running_loop().time()))
        self._takeover.orphaned()

    async def _take_over(self, names: list[str]) -> None:
        """Claim the owners keys of ``names`` still orphans, in one bulk create; the devices won are
        opened by the reconciler (the view has this gateway as their owner at once)."""
        if self._stopped:
            return
        claims: dict[str, str] = {}
        for name in names:
            registration = self.view.registrations.get(name)
            if registration is None or name in self.view.owners or registration.dialled_in:
                continue
            if self.allow is not None:
                try:
                    await self.allow.check(name, registration.url)
                except PropertyError as exc:
                    log.warning("cluster: not taking %s over: %s", name, exc.message)
                    continue
            claims[name] = self.me
        try:
            won = await self._create_many(Kind.OWNER, claims, leased=True)
        except PropertyError as exc:
            log.info("cluster: cannot take %d services over now: %s", len(claims), exc.message)
            return
        if won:
            self._handing.difference_update(won)  # handed over, and no other gateway took them
            log.info("cluster: taking %d of %d orphans over: %s", len(won), len(claims), _few(sorted(won)))

    def _reclaim(self, name: str) -> None:
        """Claim the owners key of ``name`` (owned here, its key gone) again soon, with any others."""
        self._reclaiming.add(name)
        if self._reclaimer is None or self._reclaimer.done():
            self._reclaimer = asyncio.get_running_loop().create_task(
                self._reclaim_all(), name="cluster: claim the owners keys again"
            )
            self._tasks.add(self._reclaimer)
            self._reclaimer.add_done_callback(self._tasks.discard)

    async def _reclaim_all(self) -> None:
        await asyncio.sleep(0)  # the reconciler marks the others that went with it first
        while self._reclaiming and not self._stopped:
            names = sorted(self._reclaiming)
            self._reclaiming.clear()
            claims = {name: self.me for name in names if name in self.owned and name not in self.view.owners}
            with contextlib.suppress(PropertyError):
                await self._create_many(Kind.OWNER, claims, leased=True)

    # -- drain and rebalance: planned moves ---------------------------------------

    def _draining_gateways(self) -> set[str]:
        """The live gateways that take no devices now (drained), this one included when it is."""
        draining = {gateway for gateway, record in self.view.gateways.items() if record.draining}
        draining.update(gateway for gateway in self.view.drains if gateway in self.view.gateways)
        if self.draining or self.me in self.view.drains:
            draining.add(self.me)
        else:
            draining.discard(self.me)  # undrained: its record says so a moment later
        return draining

    def _owner_lives(self, name: str) -> bool:
        """Whether the gateway this one forwarded ``name`` to is still in the cluster (it let go)."""
        url = self._forwarding.get(name)
        return url is not None and any(
            self._forward_url(record, name) == url
            for gateway, record in self.view.gateways.items()
            if gateway != self.me
        )

    async def set_drain(self, gateway: str, drain: bool) -> None:
        """Drain ``gateway`` (it hands over what it owns and takes nothing new), or undrain it (it
        takes devices again; a rebalance brings it some). NotFound for a gateway not in the
        cluster (undraining one is allowed: its order is deleted); FailedPrecondition when no other
        gateway would take its devices; Unavailable when read-only."""
        self._writable()
        if not drain:
            await self._delete(Kind.DRAIN, gateway)
            return
        if gateway not in self.view.gateways:
            raise NotFound(
                f"no gateway {gateway!r} in the cluster (members: {', '.join(sorted(self.view.gateways))})"
            )
        others = set(self.view.gateways) - self._draining_gateways() - {gateway}
        if not others:
            raise FailedPrecondition(
                f"no other gateway takes devices: draining {gateway!r} would leave its devices to nobody"
            )
        subject = current_subject()
        order = DrainOrder(subject.name if subject.authenticated else "anonymous", round(time.time(), 3))
        await self.store.put(Kind.DRAIN, gateway, order.to_json())
        self._on_change(Change(Kind.DRAIN, gateway, order.to_json()))

    async def ask_rebalance(self) -> None:
        """Ask every gateway of the cluster to rebalance once now, whatever its policy (the count of
        requests in this gateway's record grows; each gateway follows it)."""
        self._writable()
        self.record = dataclasses.replace(self.record, rebalance=self.record.rebalance + 1)
        await self.store.put(Kind.GATEWAY, self.me, self.record.to_json(), leased=True)
        self._rebalance_soon(asked=True)

    def _gateway_changed(self, before: GatewayRecord | None, after: GatewayRecord | None) -> None:
        """Another gateway's record changed: it joined, returned, was undrained, or asks for a rebalance."""
        if after is None:
            return
        if before is None or (before.draining and not after.draining):
            self._rebalance_soon(asked=False)
        elif after.rebalance > before.rebalance:
            self._rebalance_soon(asked=True)

    def _rebalance_soon(self, *, asked: bool) -> None:
        self._rebalance_asked |= asked
        if not (self.rebalance or self._rebalance_asked):
            return
        if self._rebalancer is None or self._rebalancer.done():
            self._rebalancer = asyncio.get_running_loop().create_task(
                self._rebalance_rounds(), name="cluster: rebalance"
            )

    async def _rebalance_rounds(self) -> None:
        """Hand devices over, a batch at a time, until this gateway is within the spread."""
        await asyncio.sleep(REBALANCE_DELAY)
        try:
            while not self._stopped and not self.draining and self.joined and not self.store.read_only:
                async with self._moving:
                    names = self._rebalance_pick()
                    if not names:
                        return
                    moved = await self._hand_over(names, "rebalancing")
                if moved == 0:
                    return  # nobody took them (they came back here): the loads are what they can be
        except PropertyError as exc:
            log.info("cluster: rebalancing stopped: %s", exc.message)
        finally:
            self._rebalance_asked = False

    def _rebalance_pick(self) -> list[str]:
        """The devices this gateway hands over in this round of a rebalance (sorted; none: balanced)."""
        movable = sorted(self._movable())
        loads = taking_loads(self.view.loads(), self._draining_gateways())
        quota = rebalance_quota(
            loads, self.me, movable=len(movable), spread=self.rebalance_spread, batch=self.rebalance_batch
        )
        return movable[:quota]

    def _movable(self) -> list[str]:
        """Devices owned here that another gateway can take (not one that dialled in: nobody else
        can dial it), and that are not being registered, opened or handed over now."""
        return [
            name
            for name, registration in self.owned.items()
            if not registration.dialled_in
            and name in self.served
            and name not in self._busy
            and name not in self._handing
            and name not in self._opening
        ]

    async def _follow_drain(self) -> None:
        """This gateway's ``drains`` key came or went: hand everything over, or take devices again."""
        async with self._moving:
            drained = self.me in self.view.drains
            if drained == self.draining:
                return
            self.draining = drained
            self.record = dataclasses.replace(self.record, draining=drained)
            with contextlib.suppress(PropertyError):
                await self.store.put(Kind.GATEWAY, self.me, self.record.to_json(), leased=True)
            self.on_view()
            if not drained:
                log.info("cluster: undrained; this gateway takes devices again")
                return
            log.info("cluster: drained; handing over %d devices", len(self.owned))
            with contextlib.suppress(PropertyError):
                await self._hand_over(sorted(self._movable()), "drained")

    async def _hand_over_locked(self, names: list[str], why: str) -> None:
        async with self._moving:
            with contextlib.suppress(PropertyError):
                await self._hand_over([name for name in names if name in self._movable()], why)

    async def _hand_over(self, names: list[str], why: str) -> int:
        """Hand ``names`` (owned here, movable) over to the other gateways; how many moved.

        Each device's connection is closed once the calls on it have ended, the calls arriving
        meanwhile held (``move_hold``); then the owners and states keys go, in bounded writes, and
        the others claim the devices as orphans, dealt to the least-loaded that take devices. It
        returns once every name is owned elsewhere (or gone), or after two leases.
        """
        if not names:
            return 0
        loop = asyncio.get_running_loop()
        began = loop.time()
        self._handing.update(names)
        reason = f"service {{}} is moving to another gateway ({why})"

        async def close(name: str) -> None:
            switching = self.served.get(name)
            if switching is not None:
                await switching.switch(None, reason=reason.format(repr(name)), hold=self.move_hold)

        async def let_go(name: str) -> None:
            if name in self._handing and await self._let_go(Kind.OWNER, name, self.me):
                await self._delete(Kind.STATE, name)

        try:
            await run_bounded(names, close, MAX_WRITES)
            await run_bounded(names, let_go, MAX_WRITES)
        except PropertyError:
            self._handing.difference_update(names)
            for name in names:
                self._mark(name)  # still owned here: opened again by the reconciler
            raise
        self._takeover.orphaned()
        deadline = began + 2 * self.lease + 5.0

        def moved(name: str) -> bool:
            owner = self.view.owners.get(name)
            return name not in self.view.registrations or (owner is not None and owner != self.me)

        while not all(moved(name) for name in names) and loop.time() < deadline:
            self._owners_changed.clear()
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout_at(deadline):
                    await self._owners_changed.wait()
        count = sum(1 for name in names if moved(name))
        for name in names:
            if self.view.owners.get(name) == self.me:
                # Still this gateway's after the wait (not let go, or claimed back here): served here
                # again, never left closed with calls told it is moving.
                self._handing.discard(name)
                self._mark(name)
        seconds = loop.time() - began
        self.last_move = (count, seconds, why)
        log.info(
            "cluster: handed %d of %d devices over in %.2f s (%s): %s",
            count,
            len(names),
            seconds,
            why,
            _few(sorted(names)),
        )
        self.on_view()
        return count

    # -- the cluster view ---------------------------------------------------------

    def _report_once(self, calls_before: int, period: float) -> int:
        """Write this gateway's record with its load and lease when they changed enough to show;
        the calls counted so far."""
        calls, listens = self._load() if self._load is not None else (0, 0)
        was = self.record
        now = dataclasses.replace(
            was,
            owned=len(self.owned),
            calls_per_s=round(max(0, calls - calls_before) / period, 1),
            listens=listens,
            lease_expires=round(self.store.lease_expires, 1),
            read_only=self.store.read_only,
        )
        self.record = now
        # The expiry moves at every renewal (a third of the lease): written when it has moved by
        # half a lease, so that the one shown is always ahead of the clock, and a few times a lease.
        worth = (
            (now.owned, now.listens, now.read_only) != (was.owned, was.listens, was.read_only)
            or abs(now.calls_per_s - was.calls_per_s) > max(1.0, was.calls_per_s / 10)
            or abs(now.lease_expires - was.lease_expires) >= self.lease / 2
        )
        if not worth:
            self.record = dataclasses.replace(
                now, calls_per_s=was.calls_per_s, lease_expires=was.lease_expires
            )
        elif self.joined and not self.store.read_only:
            self._writes.put(Kind.GATEWAY, self.me, self.record.to_json())
        self.on_view()
        return calls

    async def _report(self) -> None:
        loop = asyncio.get_running_loop()
        calls = self._load()[0] if self._load is not None else 0
        period = min(REPORT_PERIOD, self.lease / 2)
        while True:
            began = loop.time()
            await asyncio.sleep(period)
            calls = self._report_once(calls, loop.time() - began)

    def member_status(self, gateway: str, owned: int | None = None) -> dict[str, object] | None:
        """What the cluster view shows of one gateway (None when it is not in the cluster); ``owned``:
        its count of owners keys when the caller has counted them already."""
        record = self.record if gateway == self.me else self.view.gateways.get(gateway)
        if record is None:
            return None
        now = time.time()
        read_only = self.store.read_only if gateway == self.me else record.read_only
        if read_only:
            health = "read-only"
        elif record.lease_expires and record.lease_expires < now - self.lease:
            health = "silent"  # its record says its lease should have lapsed: frozen, or cut off
        else:
            health = "ok"
        drain = self.view.drains.get(gateway)
        if owned is None:
            owned = len(self.view.owned_by(gateway))
        status: dict[str, object] = {
            "id": gateway,
            "address": record.address,
            "http": record.http,
            "line": record.line,
            "version": record.version,
            "lease_expires": round(self.store.lease_expires, 1)
            if gateway == self.me
            else record.lease_expires,
            "health": health,
            "owned": owned,
            "calls_per_s": record.calls_per_s,
            "listens": record.listens,
            "read_only": read_only,
            "draining": record.draining or drain is not None,
            "drained_by": drain.by if drain is not None else "",
            "drained_at": drain.at if drain is not None else 0.0,
        }
        if gateway == self.me:
            status["moving"] = len(self._handing)
            if self.last_move is not None:
                count, seconds, why = self.last_move
                status["last_move"] = {"devices": count, "seconds": round(seconds, 3), "why": why}
        return status

    def status(self) -> dict[str, object]:
        """The cluster as this gateway sees it: the registry's ``cluster`` property (as JSON)."""
        members = sorted({*self.view.gateways, self.me})
        counts = Counter(self.view.owners.values())
        return {
            "gateway": self.me,
            "store": self.store.location,
            "rebalance": {
                "policy": self.rebalance,
                "spread": self.rebalance_spread,
                "batch": self.rebalance_batch,
            },
            "members": [
                status
                for status in (self.member_status(gateway, counts.get(gateway, 0)) for gateway in members)
                if status is not None
            ],
            "drains": {
                gateway: {"by": order.by, "at": order.at}
                for gateway, order in sorted(self.view.drains.items())
            },
            "services": len(self.view.registrations),
            "unowned": len(self.view.orphans()),
        }

    # -- for devices and people ---------------------------------------------------

    def alternates(self) -> list[str]:
        """The line-protocol addresses of the other live gateways (where a device may dial in)."""
        return sorted(
            record.line
            for gateway, record in self.view.gateways.items()
            if gateway != self.me and record.line
        )

    def owners(self) -> dict[str, str]:
        """Service name → owning gateway id, as this gateway sees it."""
        return dict(self.view.owners)


def _few(names: list[str], shown: int = 5) -> str:
    """The first names of a list for a log line, and how many more."""
    more = f" and {len(names) - shown} more" if len(names) > shown else ""
    return ", ".join(names[:shown]) + more
