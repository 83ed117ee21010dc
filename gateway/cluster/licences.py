"""Licences across the cluster: compare-and-set on ``licences/SERVICE``, so two gateways never grant the same.

A registry grants a licence after checking its own; in a cluster, every gateway's registry
answers for every service, so the licence is also claimed in the shared store before it is
granted. The key ``licences/SERVICE`` holds the licences on that service as a JSON list (usually
one; several when they cover subtrees that do not overlap)::

    [{"id": "L1-3fa2c1", "subtree": "", "holder": "alice", "gateway": "gw-a", "expires": 1795000000.0}]

The first licence on a service ``create``\\ s the key (only when absent); a further one, a renewal
and a release ``replace`` it only when it still holds what was read (compare-and-set), and read
again when another gateway changed it first. A licence whose ``expires`` has passed counts as
gone: a gateway that died cannot keep a service licensed beyond the licence's own time. The last
licence's release deletes the key.

A second gateway asked for a licence that overlaps one in the key gets the registry's usual
answer, FAILED_PRECONDITION naming the holder and the expiry (and which gateway granted it).

Every gateway also keeps the licences the others granted, as the store's watch shows them
(:meth:`ClusterLicences.observe`), so that a Set on any gateway is checked against every licence
of the cluster: a client that does not hold a licence granted on gateway A is refused on gateway B
too. The check is made once, by the gateway the client called; a call that another gateway of the
cluster forwarded to the owner is not checked again there (its caller is the forwarding gateway,
and the check was made where the client is known).

The same licences are read on every gateway (:meth:`ClusterLicences.show_in`): the registry's
``licences`` lists those held here and those the others granted (:class:`ClusterLicenceList`),
``licences.<id>`` shows each, and ``services.<name>.licence`` names the one held on the service,
whichever gateway granted it; each follows the key's changes and the licence's expiry.
"""

from __future__ import annotations

import asyncio
import json
import logging
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from services.apps.registry import Lease, Licence, Registry
from services.apps.registry.licences import Licences
from services.apps.registry.service import LicenceList, LicenceView
from services.apps.registry.store import Kind, SharedStore
from services.kernel.errors import FailedPrecondition, PropertyError, Unavailable
from services.kernel.values import format_names

__all__ = ["MAX_ATTEMPTS", "ClusterLicenceList", "ClusterLicences"]

log = logging.getLogger(__name__)

#: Times one claim, renewal or release reads the key again after another gateway changed it
#: first; past that the store is too busy with this service and the call says so.
MAX_ATTEMPTS = 16


@dataclass(frozen=True, slots=True)
class _Claim:
    """One licence as the key holds it."""

    id: str
    subtree: str
    holder: str
    gateway: str
    expires: float

    def live(self, at: float) -> bool:
        return self.expires > at

    def as_licence(self, service: str) -> Licence:
        """The licence, for the registry's messages (its time left counted from now)."""
        return Licence(
            id=self.id,
            service=service,
            subtree=self.subtree,
            holder=self.holder,
            granted=0.0,
            lease=Lease(max(0.0, self.expires - time.time())),
        )


def _read(text: str | None) -> list[_Claim]:
    if not text:
        return []
    try:
        items = json.loads(text)
        return [
            _Claim(str(i["id"]), str(i["subtree"]), str(i["holder"]), str(i["gateway"]), float(i["expires"]))
            for i in items
        ]
    except (ValueError, KeyError, TypeError) as exc:
        log.warning("cluster: ignoring a licences key that is not a list of licences (%s): %.200r", exc, text)
        return []


def _write(claims: list[_Claim]) -> str:
    return json.dumps(
        [
            {"id": c.id, "subtree": c.subtree, "holder": c.holder, "gateway": c.gateway, "expires": c.expires}
            for c in claims
        ]
    )


class ClusterLicenceList(LicenceList):
    """The registry's ``licences`` in a cluster: the ids of the licences held here, then of those the
    other gateways granted (one child ``licences.<id>`` each, as for a licence granted here)."""

    def __init__(self, licensing: Licences, claims: ClusterLicences) -> None:
        super().__init__(licensing)
        self._here = licensing
        self._claims = claims

    def _value(self) -> str:
        here = [licence.id for licence in self._here.held()]
        return format_names([*here, *(licence.id for licence in self._claims.elsewhere())])


class ClusterLicences:
    """A registry's :class:`~services.apps.registry.licences.LicenceClaims` on a shared store."""

    def __init__(self, store: SharedStore) -> None:
        self.store = store
        self._releasing: set[asyncio.Task[None]] = set()
        #: The licences other gateways granted, by service, as the store last showed them.
        self._elsewhere: dict[str, list[Licence]] = {}
        #: The registry that shows them (:meth:`show_in`), its list, and their views there by id.
        self._registry: Registry | None = None
        self._list: ClusterLicenceList | None = None
        self._views: dict[str, _RemoteLicenceView] = {}
        #: The timer that reads the licences again when the next one shown expires.
        self._expiry: asyncio.TimerHandle | None = None

    def show_in(self, registry: Registry) -> None:
        """Show the licences the other gateways granted in ``registry`` too (module docstring)."""
        shown = ClusterLicenceList(registry.licensing, self)
        old = registry.licences
        for name, child in old.children().items():  # the views of licences granted here so far
            old.detach(name)
            shown.attach(name, child)
        registry.licences = shown
        self._registry = registry
        self._list = shown
        for service in list(self._elsewhere):
            self._show(service)

    def elsewhere(self) -> list[Licence]:
        """The live licences the other gateways granted, on every service."""
        return [licence for service in list(self._elsewhere) for licence in self.held_elsewhere(service)]

    def observe(self, service: str, value: str | None) -> None:
        """The store's ``licences/SERVICE`` key now holds ``value`` (None: deleted)."""
        me = self.store.gateway_id
        now = time.time()
        held = [c.as_licence(service) for c in _read(value) if c.gateway != me and c.live(now)]
        if held:
            self._elsewhere[service] = held
        else:
            self._elsewhere.pop(service, None)
        self._show(service)

    def load(self, keys: Mapping[str, str]) -> None:
        """Every ``licences`` key, as read when joining or after a reconnect."""
        services = set(self._elsewhere)
        self._elsewhere.clear()
        for service, value in keys.items():
            self.observe(service, value)
        for service in services - set(keys):
            self._show(service)

    def _show(self, service: str) -> None:
        """The registry reads ``service``'s licences as they are now (those of the others included)."""
        registry, shown = self._registry, self._list
        if registry is None or shown is None:
            return
        live = {licence.id: licence for licence in self.held_elsewhere(service)}
        for licence_id, view in list(self._views.items()):
            if licence_id not in live and view.service == service:
                del self._views[licence_id]
                if shown.children().get(licence_id) is view:
                    shown.detach(licence_id)
        for licence_id, licence in live.items():
            if licence_id not in self._views and licence_id not in shown.children():
                self._views[licence_id] = _RemoteLicenceView(licence)
                shown.attach(licence_id, self._views[licence_id])
        shown.changed()
        entry = registry.entry_of(service)
        if entry is not None:
            holder = registry.licensing.holder_of(service)
            entry.set_licence(holder.id if holder is not None else "")
        self._expire_later()

    def _expire_later(self) -> None:
        """Read the licences again when the first one the others granted expires."""
        if self._expiry is not None:
            self._expiry.cancel()
            self._expiry = None
        ends = [licence.expires_at for licences in self._elsewhere.values() for licence in licences]
        if ends and self._registry is not None:
            delay = max(0.0, min(ends) - time.time()) + 0.05
            self._expiry = asyncio.get_running_loop().call_later(delay, self._on_expiry)

    def _on_expiry(self) -> None:
        self._expiry = None
        for service in list(self._elsewhere):
            self._show(service)

    def held_elsewhere(self, service: str) -> Sequence[Licence]:
        held = self._elsewhere.get(service)
        if not held:
            return ()
        live = [licence for licence in held if not licence.lease.lapsed()]
        if len(live) != len(held):
            if live:
                self._elsewhere[service] = live
            else:
                del self._elsewhere[service]
        return live

    async def _current(self, service: str) -> str | None:
        return (await self.store.read(Kind.LICENCE)).get(service)

    async def _swap(self, service: str, old: str | None, claims: list[_Claim]) -> bool:
        """Write ``claims`` where ``old`` was read (delete the key when none are left); False when the
        key changed since."""
        if old is None:
            return not claims or await self.store.create(Kind.LICENCE, service, _write(claims))
        return await self.store.replace(Kind.LICENCE, service, old, _write(claims) if claims else None)

    async def claim(self, licence: Licence) -> None:
        service = licence.service
        mine = _Claim(licence.id, licence.subtree, licence.holder, self.store.gateway_id, licence.expires_at)
        for _ in range(MAX_ATTEMPTS):
            old = await self._current(service)
            now = time.time()
            claims = [c for c in _read(old) if c.live(now)]
            for held in claims:
                other = held.as_licence(service)
                if other.overlaps(service, licence.subtree):
                    raise FailedPrecondition(
                        f"{service}: {other.describe()} (granted by gateway {held.gateway})"
                    )
            if await self._swap(service, old, [*claims, mine]):
                return
        raise Unavailable(
            f"{service}: the licences of this service changed {MAX_ATTEMPTS} times while one was claimed"
        )

    async def renew(self, licence: Licence, seconds: float) -> None:
        await self._change(licence, time.time() + seconds)

    def release(self, licence: Licence) -> None:
        task = asyncio.get_running_loop().create_task(
            self._release(licence), name=f"cluster: release licence {licence.id}"
        )
        self._releasing.add(task)
        task.add_done_callback(self._releasing.discard)

    async def _release(self, licence: Licence) -> None:
        try:
            await self._change(licence, None)
        except PropertyError as exc:
            # It lapses by its own expiry in every gateway's eyes.
            log.info(
                "cluster: licence %s on %s not released in the store: %s",
                licence.id,
                licence.service,
                exc.message,
            )

    async def _change(self, licence: Licence, expires: float | None) -> None:
        """Give ``licence``'s claim a new expiry, or drop it (None); expired claims are dropped too."""
        service = licence.service
        for _ in range(MAX_ATTEMPTS):
            old = await self._current(service)
            now = time.time()
            claims = [c for c in _read(old) if c.live(now) and c.id != licence.id]
            if expires is not None:
                claims.append(
                    _Claim(licence.id, licence.subtree, licence.holder, self.store.gateway_id, expires)
                )
            if old is None and expires is None:
                return
            if await self._swap(service, old, claims):
                return
        raise Unavailable(f"{service}: the licences of this service changed {MAX_ATTEMPTS} times meanwhile")

    async def aclose(self) -> None:
        """Wait for the releases under way."""
        if self._expiry is not None:
            self._expiry.cancel()
            self._expiry = None
        await asyncio.gather(*self._releasing, return_exceptions=True)


class _RemoteLicenceView(LicenceView):
    """``licences.<id>`` of a licence another gateway granted."""

    def __init__(self, licence: Licence) -> None:
        super().__init__(licence)
        self.service = licence.service
