"""Covering a capability set with as few providers as possible.

Exact when the request names at most :data:`EXACT_LIMIT` capabilities, greedy beyond.

The exact search is a dynamic programme over the subsets of the requested capabilities (a bit
mask each): for every subset the fewest providers that cover it, ties broken by the lowest total
score. Only the best-scored provider of each distinct offer (its offer intersected with the
request) takes part — two providers offering the same capabilities are never both in a smallest
cover — so the work is at most ``2**k * min(n, 2**k)`` steps for ``k`` capabilities and ``n``
providers: 65,536 steps at ``k = 8`` whatever ``n`` is. Past that the classic greedy rule
(take the provider that covers most of what is still missing; ties: lower score, then name)
runs in ``O(k * n)`` and is within a factor ``H(k) = 1 + 1/2 + ... + 1/k`` of the smallest cover.
"""

from __future__ import annotations

from collections.abc import Mapping

__all__ = ["EXACT_LIMIT", "cover", "exact_cover", "greedy_cover"]

#: Requests naming at most this many capabilities get the exact smallest cover.
EXACT_LIMIT = 8


def _masks(
    universe: frozenset[str], offers: Mapping[str, frozenset[str]], score: Mapping[str, float]
) -> tuple[int, dict[int, str]]:
    """The full mask, and the best provider (lowest score, then name) of each distinct useful offer."""
    bit = {name: 1 << i for i, name in enumerate(sorted(universe))}
    best: dict[int, str] = {}
    for provider, offered in offers.items():
        mask = 0
        for capability in offered:
            mask |= bit.get(capability, 0)
        if mask == 0:
            continue
        held = best.get(mask)
        if held is None or (score.get(provider, 0.0), provider) < (score.get(held, 0.0), held):
            best[mask] = provider
    return (1 << len(bit)) - 1, best


def exact_cover(
    universe: frozenset[str], offers: Mapping[str, frozenset[str]], score: Mapping[str, float]
) -> list[str] | None:
    """The fewest providers whose offers cover ``universe`` (lowest total score among those); None
    when no set of them does. Practical for small universes only (see the module's note)."""
    if not universe:
        return []
    full, best = _masks(universe, offers, score)
    choices = sorted(best.items(), key=lambda item: (score.get(item[1], 0.0), item[1]))
    # table[mask] = (providers used, total score, the providers), built in increasing mask order:
    # every step ORs bits in, so a mask's value is final before any larger mask is reached.
    table: list[tuple[int, float, tuple[str, ...]] | None] = [None] * (full + 1)
    table[0] = (0, 0.0, ())
    for mask in range(full + 1):
        here = table[mask]
        if here is None or mask == full:
            continue
        count, total, chosen = here
        for offer, provider in choices:
            grown = mask | offer
            if grown == mask:
                continue
            candidate = (count + 1, total + score.get(provider, 0.0), (*chosen, provider))
            there = table[grown]
            if there is None or candidate[:2] < there[:2]:
                table[grown] = candidate
    done = table[full]
    return None if done is None else list(done[2])


def greedy_cover(
    universe: frozenset[str], offers: Mapping[str, frozenset[str]], score: Mapping[str, float]
) -> list[str] | None:
    """A cover of ``universe`` by the greedy rule; None when all offers together do not cover it."""
    if not universe:
        return []
    full, best = _masks(universe, offers, score)
    choices = [(offer, score.get(p, 0.0), p) for offer, p in best.items()]
    missing = full
    chosen: list[str] = []
    while missing:
        pick: tuple[int, float, str] | None = None
        gain_of_pick = 0
        for offer, s, provider in choices:
            gain = (offer & missing).bit_count()
            if gain == 0:
                continue
            if pick is None or gain > gain_of_pick or (gain == gain_of_pick and (s, provider) < pick[1:]):
                pick, gain_of_pick = (offer, s, provider), gain
        if pick is None:
            return None
        chosen.append(pick[2])
        missing &= ~pick[0]
    return chosen


def cover(
    universe: frozenset[str], offers: Mapping[str, frozenset[str]], score: Mapping[str, float]
) -> list[str] | None:
    """The exact smallest cover up to :data:`EXACT_LIMIT` capabilities, the greedy one beyond."""
    if len(universe) <= EXACT_LIMIT:
        return exact_cover(universe, offers, score)
    return greedy_cover(universe, offers, score)
