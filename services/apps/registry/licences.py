"""Licences: exclusive use of a service (or of a subtree of its properties) for a while.

A consumer acquires a licence on a provider for ``duration`` seconds (the
seed's ``Tout``); while it holds it, Sets and actions on the licensed
properties from anyone else are refused (FAILED_PRECONDITION naming the holder
and the expiry); reads stay open. The holder renews it, releases it, or loses
it when it lapses or when the holder vanishes (its Session ends, or the holder
is itself a registered service that is logged off).

A licence's deadline is a :class:`~services.apps.registry.lease.Lease`, the same
mechanism as a registered service's liveness lease: one kind of deadline, two
consequences of lapsing.

:class:`Licences` is owned by the :class:`~services.apps.registry.Registry`; the
scheduler and the registry's ``acquire``/``renew``/``release`` actions call it,
and the gateway's call layer asks :meth:`Licences.check_set` before each Set.
"""

from __future__ import annotations

import asyncio
import collections
import itertools
import logging
import math
import secrets
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Protocol

from services.apps.registry.lease import Lease, check_lease, wall_clock
from services.kernel.errors import (
    FailedPrecondition,
    InvalidArgument,
    NotFound,
    PermissionDenied,
    ResourceExhausted,
)
from services.kernel.paths import validate_path
from services.kernel.values import format_number

__all__ = [
    "DEFAULT_LICENCE_DURATION",
    "DEFAULT_MAX_LICENCES",
    "DEFAULT_MAX_LICENCES_PER_HOLDER",
    "DEFAULT_MAX_LICENCE_DURATION",
    "Licence",
    "LicenceClaims",
    "LicenceListener",
    "Licences",
    "format_time",
]

log = logging.getLogger(__name__)

#: Licences held at once (``[registry] max_licences``): each one is a row every Set is checked
#: against, so a flood of acquisitions is refused rather than slowing every call.
DEFAULT_MAX_LICENCES = 1024
#: Licences one holder may hold when it acquires one (``[registry] max_licences_per_holder``): a
#: holder that locks a few robots for a job is served; one that tries to lock everything is
#: stopped long before it keeps others from :data:`DEFAULT_MAX_LICENCES`.
DEFAULT_MAX_LICENCES_PER_HOLDER = 8
#: Longest licence (``[registry] max_licence_duration``): an hour; a longer job renews.
DEFAULT_MAX_LICENCE_DURATION = 3600.0
#: A licence acquired without a duration.
DEFAULT_LICENCE_DURATION = 30.0
#: Ended licences remembered, so that using one says "expired at ..." rather than "unknown".
_ENDED_KEPT = 256

#: How a licence changed: granted, renewed, released (by its holder), expired (its time ran
#: out), lost (its holder vanished, or the service left), revoked (by an admin).
EVENTS = ("granted", "renewed", "released", "expired", "lost", "revoked")


def format_time(unix: float) -> str:
    """Unix seconds as ISO 8601 UTC to the millisecond (``2026-11-23T01:02:03.456Z``)."""
    import datetime

    moment = datetime.datetime.fromtimestamp(unix, tz=datetime.UTC)
    return moment.strftime("%Y-%m-%dT%H:%M:%S.") + f"{moment.microsecond // 1000:03d}Z"


@dataclass(slots=True, eq=False)
class Licence:
    """One licence: ``holder`` may alone change ``service`` (or its ``subtree``) until it expires."""

    id: str
    service: str
    #: The licensed subtree of the service's properties; "" for the whole service.
    subtree: str
    holder: str
    #: When it was granted, unix seconds.
    granted: float
    #: The Session it is bound to ("" when none): it ends with the Session.
    session: str = ""
    lease: Lease = field(default_factory=Lease)
    #: "held" while it holds; then how it ended (one of :data:`EVENTS` but granted and renewed).
    status: str = "held"

    @property
    def expires(self) -> float:
        """When it runs out on the monotonic clock (:func:`services.apps.registry.lease.now`)."""
        until = self.lease.until
        return until if until is not None else 0.0

    @property
    def expires_at(self) -> float:
        """When it runs out, unix seconds."""
        return self.lease.wall_until

    def left(self) -> float:
        """Seconds it still holds (0 once it lapsed)."""
        return self.lease.left()

    def covers(self, service: str, path: str) -> bool:
        """A Set of ``path`` on ``service`` falls under this licence."""
        if service != self.service:
            return False
        sub = self.subtree
        return not sub or path == sub or path.startswith(sub + ".")

    def overlaps(self, service: str, subtree: str) -> bool:
        """A licence on ``service``/``subtree`` would share properties with this one."""
        if service != self.service:
            return False
        a, b = self.subtree, subtree
        return not a or not b or a == b or a.startswith(b + ".") or b.startswith(a + ".")

    def where(self) -> str:
        """``service`` or ``service/subtree``, for messages."""
        return f"{self.service}/{self.subtree}" if self.subtree else self.service

    def describe(self) -> str:
        """Who holds it and until when, for the messages of refusals."""
        return (
            f"licence {self.id} on {self.where()} is held by {self.holder} until "
            f"{format_time(self.expires_at)} ({format_number(round(self.left(), 1))} s left)"
        )

    def marker(self) -> str:
        """Its value as the ``licences.<id>`` property shows it."""
        parts = {
            "id": self.id,
            "service": self.service,
            "subtree": self.subtree,
            "holder": self.holder,
            "status": self.status,
            "granted": format_time(self.granted),
            "expires": format_time(self.expires_at),
            "left": format_number(round(self.left(), 3)) if self.status == "held" else "0",
        }
        inner = "".join(f"<{k}>{_escape(v)}</{k}>" for k, v in parts.items())
        return f"<licence>{inner}</licence>"


def _escape(text: str) -> str:
    return text.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")


#: Called with the licence and what happened to it (one of :data:`EVENTS`).
LicenceListener = Callable[[Licence, str], None]


class LicenceClaims(Protocol):
    """Where a licence is claimed beyond this registry too: the shared store of a cluster of
    gateways, so that two gateways never grant the same licence (``gateway.cluster``)."""

    async def claim(self, licence: Licence) -> None:
        """Claim ``licence`` (not granted yet): FailedPrecondition, naming the holder, when another
        gateway holds an overlapping one; Unavailable when the claim cannot be made now."""
        ...

    async def renew(self, licence: Licence, seconds: float) -> None:
        """``licence`` is to hold ``seconds`` from now: say so where it is claimed (Unavailable if not)."""
        ...

    def release(self, licence: Licence) -> None:
        """``licence`` ended: let go of its claim (in the background; it never fails the caller)."""
        ...

    def held_elsewhere(self, service: str) -> Sequence[Licence]:
        """The live licences on ``service`` that others granted (other gateways of the cluster), as
        last seen there: a Set on this gateway is checked against them too."""
        ...


class Licences:
    """The licences a registry holds; see the module docstring.

    ``known(service)`` says whether a service exists (a licence on an unknown one is NotFound).
    """

    def __init__(
        self,
        known: Callable[[str], bool],
        *,
        max_licences: int = DEFAULT_MAX_LICENCES,
        max_duration: float = DEFAULT_MAX_LICENCE_DURATION,
        max_per_holder: int = DEFAULT_MAX_LICENCES_PER_HOLDER,
    ) -> None:
        for what, count in (("max_licences", max_licences), ("max_licences_per_holder", max_per_holder)):
            if isinstance(count, bool) or not isinstance(count, int) or count < 1:
                raise InvalidArgument(f"{what} must be a positive whole number, got {count!r}")
        if not (math.isfinite(max_duration) and max_duration > 0):
            raise InvalidArgument(
                f"max_licence_duration must be a positive number of seconds, got {max_duration}"
            )
        self.max_licences = max_licences
        self.max_per_holder = max_per_holder
        self.max_duration = float(max_duration)
        self._known = known
        self._held: dict[str, Licence] = {}
        #: The held licences by service: a Set's check looks only at its service's (a few).
        self._by_service: dict[str, list[Licence]] = {}
        self._ended: collections.OrderedDict[str, Licence] = collections.OrderedDict()
        self._listeners: list[LicenceListener] = []
        self._timer: asyncio.TimerHandle | None = None
        self._serial = itertools.count(1)
        self._claims: LicenceClaims | None = None

    def set_claims(self, claims: LicenceClaims | None) -> None:
        """Claim every licence there too before it is granted (a cluster's shared store); None: only here."""
        self._claims = claims

    # -- reading ---------------------------------------------------------------

    def held(self) -> list[Licence]:
        """The licences held now, oldest first."""
        self._expire_due()
        return list(self._held.values())

    def get(self, licence_id: str) -> Licence:
        """The held licence ``licence_id``; FailedPrecondition when it ended, NotFound when never known."""
        self._expire_due()
        licence = self._held.get(licence_id)
        if licence is not None:
            return licence
        ended = self._ended.get(licence_id)
        if ended is not None:
            raise FailedPrecondition(
                f"licence {licence_id} on {ended.where()} is no longer held: it was {ended.status} "
                f"(it was granted to {ended.holder} until {format_time(ended.expires_at)})"
            )
        raise NotFound(f"no licence {licence_id[:80]!r} (held now: {len(self._held)})")

    def holder_of(self, service: str, path: str = "") -> Licence | None:
        """The licence that covers a Set of ``path`` on ``service`` (any, for ``path`` ""); None when
        free. Licences granted elsewhere (:meth:`LicenceClaims.held_elsewhere`) count too."""
        for licence in self._by_service.get(service, ()):
            if licence.lease.lapsed():
                self._expire_due()
                return self.holder_of(service, path)
            if not path or licence.covers(service, path):
                return licence
        if self._claims is not None:
            for licence in self._claims.held_elsewhere(service):
                if not path or licence.covers(service, path):
                    return licence
        return None

    def check_set(self, service: str, path: str, holder: str) -> None:
        """Raise FailedPrecondition naming holder and expiry when another holds ``service``/``path``."""
        licence = self.holder_of(service, path)
        if licence is not None and licence.holder != holder:
            raise FailedPrecondition(
                f"{service}/{path}: {licence.describe()}; only its holder may change it until then"
            )

    # -- changing --------------------------------------------------------------

    def count_held_by(self, holder: str) -> int:
        """How many licences ``holder`` holds now."""
        self._expire_due()
        return sum(1 for licence in self._held.values() if licence.holder == holder)

    async def grant(
        self,
        service: str,
        holder: str,
        duration: float,
        subtree: str = "",
        *,
        session: str = "",
        limit_holder: bool = True,
    ) -> Licence:
        """Grant ``holder`` a licence on ``service`` (or its ``subtree``) for ``duration`` seconds.

        Raises NotFound (unknown service), InvalidArgument (bad duration or
        subtree), FailedPrecondition (held by another: naming holder and
        expiry; or by the same holder already: renew it), ResourceExhausted
        (``max_licences`` held, or ``max_per_holder`` by this holder).
        ``limit_holder`` False: the holder's own bound is not asked (the
        scheduler, which bounds the allocations of each consumer itself).
        """
        self._expire_due()
        if not holder:
            raise InvalidArgument("a licence needs a holder")
        if not self._known(service):
            raise NotFound(f"no service named {service[:80]!r} in the registry: nothing to license")
        if subtree:
            try:
                validate_path(subtree)
            except InvalidArgument as e:
                raise InvalidArgument(f"bad subtree: {e.message}") from None
        duration = self._duration(duration)
        self._check_free(service, subtree, holder)
        if limit_holder:
            self._check_holder_room(holder)
        licence = Licence(
            id=f"L{next(self._serial)}-{secrets.token_hex(3)}",
            service=service,
            subtree=subtree,
            holder=holder,
            granted=wall_clock(),
            session=session,
            lease=Lease(duration),
        )
        if self._claims is not None:
            await self._claims.claim(licence)
            try:
                self._check_free(service, subtree, holder)  # granted here while the claim was made
                if limit_holder:
                    self._check_holder_room(holder)
            except BaseException:
                self._claims.release(licence)
                raise
        self._held[licence.id] = licence
        self._by_service.setdefault(service, []).append(licence)
        self._schedule()
        self._tell(licence, "granted")
        return licence

    async def renew(self, licence_id: str, duration: float, *, holder: str | None = None) -> Licence:
        """Hold ``licence_id`` for ``duration`` seconds from now; ``holder``: only that holder may."""
        licence = self.get(licence_id)
        self._check_holder(licence, holder, "renew")
        seconds = self._duration(duration)
        if self._claims is not None:
            await self._claims.renew(licence, seconds)
        licence.lease.renew(seconds)
        self._schedule()
        self._tell(licence, "renewed")
        return licence

    async def release(self, licence_id: str, *, holder: str | None = None) -> Licence:
        """End ``licence_id`` now; ``holder``: only that holder may."""
        licence = self.get(licence_id)
        self._check_holder(licence, holder, "release")
        self._end(licence, "released")
        return licence

    def revoke(self, licence_id: str) -> Licence:
        """End ``licence_id`` now, whoever holds it (an admin's act; the caller checks who may)."""
        licence = self.get(licence_id)
        self._end(licence, "revoked")
        return licence

    def release_session(self, session: str) -> list[Licence]:
        """The Session ``session`` ended: its licences are lost."""
        if not session:
            return []
        gone = [lic for lic in self._held.values() if lic.session == session]
        for licence in gone:
            self._end(licence, "lost")
        return gone

    def release_holder(self, holder: str) -> list[Licence]:
        """``holder`` vanished (a registered service logged off): its licences are lost."""
        gone = [lic for lic in self._held.values() if lic.holder == holder]
        for licence in gone:
            self._end(licence, "lost")
        return gone

    def release_service(self, service: str) -> list[Licence]:
        """``service`` left the registry: the licences on it are lost."""
        gone = [lic for lic in self._held.values() if lic.service == service]
        for licence in gone:
            self._end(licence, "lost")
        return gone

    def watch(self, listener: LicenceListener) -> Callable[[], None]:
        """Call ``listener(licence, event)`` on every change; returns a function that stops it."""
        self._listeners.append(listener)

        def unwatch() -> None:
            if listener in self._listeners:
                self._listeners.remove(listener)

        return unwatch

    def close(self) -> None:
        """Stop the expiry timer (the registry stops)."""
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None

    # -- inside ------------------------------------------------------------------

    def _duration(self, duration: float) -> float:
        seconds = check_lease(duration, self.max_duration, "a licence's duration")
        if seconds <= 0:
            raise InvalidArgument("a licence's duration must be more than 0 seconds")
        return seconds

    def _check_free(self, service: str, subtree: str, holder: str) -> None:
        """FailedPrecondition when a licence held here overlaps ``service``/``subtree``;
        ResourceExhausted when ``max_licences`` are held."""
        for licence in self._by_service.get(service, ()):
            if licence.overlaps(service, subtree):
                if licence.holder == holder:
                    raise FailedPrecondition(
                        f"{holder} already holds licence {licence.id} on {licence.where()} until "
                        f"{format_time(licence.expires_at)}: renew or release it rather than acquire again"
                    )
                raise FailedPrecondition(f"{service}: {licence.describe()}")
        if len(self._held) >= self.max_licences:
            raise ResourceExhausted(
                f"the registry holds {self.max_licences} licences already ([registry] max_licences)"
            )

    def _check_holder_room(self, holder: str) -> None:
        held = self.count_held_by(holder)
        if held >= self.max_per_holder:
            raise ResourceExhausted(
                f"{holder} holds {held} licences already, as many as one holder may "
                "([registry] max_licences_per_holder): release one first"
            )

    def _check_holder(self, licence: Licence, holder: str | None, verb: str) -> None:
        if holder is not None and holder != licence.holder:
            raise PermissionDenied(f"only its holder may {verb} it: {licence.describe()}; you are {holder}")

    def _end(self, licence: Licence, how: str) -> None:
        if self._held.pop(licence.id, None) is None:
            return
        on_service = self._by_service.get(licence.service, [])
        if licence in on_service:
            on_service.remove(licence)
        if not on_service:
            self._by_service.pop(licence.service, None)
        licence.status = how
        if self._claims is not None:
            self._claims.release(licence)
        self._ended[licence.id] = licence
        while len(self._ended) > _ENDED_KEPT:
            self._ended.popitem(last=False)
        self._tell(licence, how)
        self._schedule()

    def _expire_due(self) -> None:
        """End every licence whose time ran out (the timer does too; a read never shows a lapsed one)."""
        if not self._held:
            return
        due = [lic for lic in self._held.values() if lic.lease.lapsed()]
        for licence in due:
            self._end(licence, "expired")

    def _schedule(self) -> None:
        """One timer, at the earliest expiry."""
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        if not self._held:
            return
        try:
            loop = asyncio.get_running_loop()
        except RuntimeError:  # no loop: expiry is found by the next read
            return
        soonest = min(lic.left() for lic in self._held.values())
        # A little after the deadline, so that the lease has lapsed when the timer fires.
        self._timer = loop.call_later(soonest + 0.001, self._on_timer)

    def _on_timer(self) -> None:
        self._timer = None
        self._expire_due()
        self._schedule()

    def _tell(self, licence: Licence, event: str) -> None:
        log.info("licence %s on %s (holder %s): %s", licence.id, licence.where(), licence.holder, event)
        for listener in list(self._listeners):
            try:
                listener(licence, event)
            except Exception:
                log.exception("a watcher of licences failed on %s %s", licence.id, event)
