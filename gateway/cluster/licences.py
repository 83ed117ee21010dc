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
"""

from __future__ import annotations

import asyncio
import json
import logging
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from services.errors import FailedPrecondition, PropertyError, Unavailable
from services.registry import Lease, Licence
from services.registry.store import Kind, SharedStore

__all__ = ["MAX_ATTEMPTS", "ClusterLicences"]

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


class ClusterLicences:
    """A registry's :class:`~services.registry.licences.LicenceClaims` on a shared store."""

    def __init__(self, store: SharedStore) -> None:
        self.store = store
        self._releasing: set[asyncio.Task[None]] = set()
        #: The licences other gateways granted, by service, as the store last showed them.
        self._elsewhere: dict[str, list[Licence]] = {}

    def observe(self, service: str, value: str | None) -> None:
        """The store's ``licences/SERVICE`` key now holds ``value`` (None: deleted)."""
        me = self.store.gateway_id
        now = time.time()
        held = [c.as_licence(service) for c in _read(value) if c.gateway != me and c.live(now)]
        if held:
            self._elsewhere[service] = held
        else:
            self._elsewhere.pop(service, None)

    def load(self, keys: Mapping[str, str]) -> None:
        """Every ``licences`` key, as read when joining or after a reconnect."""
        self._elsewhere.clear()
        for service, value in keys.items():
            self.observe(service, value)

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
        await asyncio.gather(*self._releasing, return_exceptions=True)
