"""Which of the registry's providers the scheduler needs to see for one request, found with numpy.

With 10,000 services, handing the scheduler every provider as a Python object costs far more than
the decision itself. :class:`Candidates` keeps, per revision of the table, the capabilities of
every service (an inverted index: capability → positions) and the slots of the search index
(locations and up/down as numpy arrays), and for a request computes every relevant provider's
score at once: ``weight · distance / D + (1 − weight) · (1 − QoS)``, ``D`` the largest distance
among them. Providers are then grouped by the part of the request they offer (their capability
mask); of each group only the best ``count + X`` go on, ``X`` counting every provider that might
be unable to serve (not plainly ready, busy, excluded, a consumer). The scheduler picks at most the
best ``count`` eligible ones of any group (a smallest cover takes one per group, a team of ``count``
takes the best ``count`` overall), and at least ``count`` eligible ones of each group are among
those handed on: the narrowing never changes the decision.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

import numpy as np
import numpy.typing as npt

from services.apps.registry.scheduling import DEFAULT_QOS, Provider, ProviderState, Request
from services.apps.registry.table import ServiceTable

__all__ = ["Candidates"]

_STATES = {
    "ready": ProviderState.READY,
    "dormant": ProviderState.DORMANT,
    "active": ProviderState.BUSY,
    "death": ProviderState.DOWN,
}


def provider_state(availability: str) -> ProviderState:
    """The scheduler's view of a registry entry's availability."""
    return _STATES.get(availability, ProviderState.DOWN)


class Candidates:
    """The narrowing described in the module; rebuilt lazily when the table's revision changes."""

    def __init__(self, table: ServiceTable, features: Callable[[str], frozenset[str]]) -> None:
        self._table = table
        self._features = features
        self._revision = -1
        self._names: list[str] = []
        self._caps: list[frozenset[str]] = []
        self._by_cap: dict[str, npt.NDArray[np.intp]] = {}
        self._slots: npt.NDArray[np.intp] = np.zeros(0, dtype=np.intp)
        self._rank: npt.NDArray[np.intp] = np.zeros(0, dtype=np.intp)
        self._position: dict[str, int] = {}
        self._not_ready: set[str] = set()

    def _refresh(self, revision: int) -> None:
        if revision == self._revision:
            return
        names: list[str] = []
        caps: list[frozenset[str]] = []
        not_ready: set[str] = set()
        by_cap: dict[str, list[int]] = {}
        for name, entry in self._table.entries():
            if entry.type == "registry":
                continue
            offered = self._features(name) | {entry.type}
            for capability in offered:
                by_cap.setdefault(capability, []).append(len(names))
            if entry.availability != "ready":
                not_ready.add(name)
            names.append(name)
            caps.append(offered)
        self._names, self._caps, self._not_ready = names, caps, not_ready
        self._by_cap = {c: np.asarray(p, dtype=np.intp) for c, p in by_cap.items()}
        self._slots = self._table.index.slots_of(names)
        # The scheduler breaks ties of score by name (plain string order): so does the narrowing.
        self._rank = np.argsort(np.argsort(np.asarray(names, dtype=object), kind="stable"))
        self._position = {n: i for i, n in enumerate(names)}
        self._revision = revision

    def offering(self, capabilities: frozenset[str], revision: int) -> list[str]:
        """The names of the services offering any of ``capabilities``."""
        self._refresh(revision)
        found: set[int] = set()
        for capability in capabilities:
            positions = self._by_cap.get(capability)
            if positions is not None:
                found.update(positions.tolist())
        return [self._names[i] for i in sorted(found)]

    def narrow(
        self, request: Request, revision: int, qos: Mapping[str, float], unsure: set[str]
    ) -> tuple[list[Provider], float]:
        """The providers the scheduler needs for ``request``, and the cost scale ``D``.

        ``unsure`` names providers that may be unable to serve besides those not ready (busy in
        the scheduler, licensed, excluded, consumers); ``qos`` the mean assessments.
        """
        self._refresh(revision)
        n = len(self._names)
        code = np.zeros(n, dtype=np.int64)
        for bit, capability in enumerate(sorted(request.capabilities)):
            positions = self._by_cap.get(capability)
            if positions is not None:
                code[positions] |= 1 << bit
        relevant = np.flatnonzero(code)
        if relevant.size == 0:
            return [], 0.0
        slots = self._slots[relevant]
        places = self._table.index.planar_at(slots)
        if request.location is not None and request.location.size >= 2:
            offset = places - request.location[:2]
            distance = np.nan_to_num(np.hypot(offset[:, 0], offset[:, 1]), nan=0.0)
        else:
            distance = np.zeros(relevant.size)
        scale = float(distance.max(initial=0.0))
        quality = np.full(relevant.size, DEFAULT_QOS)
        for name, mean in qos.items():
            at = self._position.get(name)
            if at is not None and code[at]:
                quality[np.searchsorted(relevant, at)] = mean
        relative = distance / scale if scale > 0 else distance * 0.0
        score = request.weight * relative + (1.0 - request.weight) * (1.0 - quality)
        down = int(np.count_nonzero(~self._table.index.up_at(slots)))
        limit = request.count + down + len(self._not_ready) + len(unsure)
        # Best first (score, then name, as the scheduler breaks ties), then the
        # first ``limit`` of each capability mask.
        best = np.lexsort((self._rank[relevant], score))
        masks = code[relevant][best]
        by_mask = np.argsort(masks, kind="stable")
        grouped = masks[by_mask]
        starts = np.flatnonzero(np.r_[True, grouped[1:] != grouped[:-1]])
        place = np.arange(grouped.size) - np.repeat(starts, np.diff(np.r_[starts, grouped.size]))
        chosen = best[by_mask[place < limit]]  # positions in ``relevant``
        known = np.all(np.isfinite(places), axis=1)
        providers = []
        for i, at in zip(chosen.tolist(), relevant[chosen].tolist(), strict=True):
            name = self._names[at]
            entry = self._table.get(name)
            if entry is None:
                continue
            location = places[i] if known[i] else None
            providers.append(Provider(name, self._caps[at], provider_state(entry.availability), location))
        return providers, scale
