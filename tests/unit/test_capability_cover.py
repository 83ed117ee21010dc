"""Covering a capability set with as few providers as possible: greedy covers, exact is smallest."""

from __future__ import annotations

import itertools

from hypothesis import given, settings
from hypothesis import strategies as st

from services.apps.registry.scheduling import EXACT_LIMIT, cover, exact_cover, greedy_cover

CAPS = [f"c{i}" for i in range(6)]

offers_strategy = st.dictionaries(
    st.sampled_from([f"p{i}" for i in range(7)]),
    st.frozensets(st.sampled_from(CAPS), max_size=4),
    max_size=7,
)
universe_strategy = st.frozensets(st.sampled_from(CAPS), min_size=1, max_size=6)
scores_strategy = st.lists(st.floats(0, 1), min_size=7, max_size=7)


def smallest_by_brute_force(universe: frozenset[str], offers: dict[str, frozenset[str]]) -> int | None:
    names = sorted(offers)
    for k in range(1, len(names) + 1):
        for combo in itertools.combinations(names, k):
            if universe <= frozenset().union(*(offers[n] for n in combo)):
                return k
    return None


def covers(universe: frozenset[str], offers: dict[str, frozenset[str]], chosen: list[str]) -> bool:
    return universe <= frozenset().union(*(offers[n] for n in chosen)) if chosen else not universe


@settings(max_examples=300, deadline=None)
@given(universe_strategy, offers_strategy, scores_strategy)
def test_the_greedy_cover_is_a_cover_whenever_one_exists(universe, offers, scores):  # type: ignore[no-untyped-def]
    score = {f"p{i}": s for i, s in enumerate(scores)}
    chosen = greedy_cover(universe, offers, score)
    best = smallest_by_brute_force(universe, offers)
    if best is None:
        assert chosen is None
    else:
        assert chosen is not None and covers(universe, offers, chosen)
        assert len(set(chosen)) == len(chosen)
        assert len(chosen) >= best


@settings(max_examples=300, deadline=None)
@given(universe_strategy, offers_strategy, scores_strategy)
def test_the_exact_cover_is_as_small_as_brute_force_finds(universe, offers, scores):  # type: ignore[no-untyped-def]
    score = {f"p{i}": s for i, s in enumerate(scores)}
    chosen = exact_cover(universe, offers, score)
    best = smallest_by_brute_force(universe, offers)
    if best is None:
        assert chosen is None
    else:
        assert chosen is not None and covers(universe, offers, chosen)
        assert len(chosen) == best


def test_among_smallest_covers_the_exact_one_has_the_lowest_score() -> None:
    offers = {
        "cheap": frozenset({"video", "ptz"}),
        "dear": frozenset({"video", "ptz"}),
        "m": frozenset({"mobile"}),
    }
    chosen = exact_cover(frozenset({"video", "ptz", "mobile"}), offers, {"cheap": 0.1, "dear": 0.9, "m": 0.5})
    assert sorted(chosen or []) == ["cheap", "m"]


def test_greedy_can_use_more_providers_than_exact() -> None:
    # The textbook case: greedy takes the big set first and then needs both halves anyway.
    offers = {
        "big": frozenset({"a2", "a3", "b2", "b3"}),
        "left": frozenset({"a1", "a2", "a3"}),
        "right": frozenset({"b1", "b2", "b3"}),
    }
    universe = frozenset({"a1", "a2", "a3", "b1", "b2", "b3"})
    assert sorted(greedy_cover(universe, offers, {}) or []) == ["big", "left", "right"]
    assert sorted(exact_cover(universe, offers, {}) or []) == ["left", "right"]


def test_the_switch_to_greedy_is_past_the_exact_limit() -> None:
    wide = frozenset(f"k{i}" for i in range(EXACT_LIMIT + 1))
    # One provider per capability plus one that has all: both rules find the single provider,
    # and beyond the limit ``cover`` still answers (greedily) on a universe exact would find slow.
    offers = {f"p{i}": frozenset({f"k{i}"}) for i in range(EXACT_LIMIT + 1)} | {"all": wide}
    assert cover(wide, offers, {}) == ["all"]
    assert cover(frozenset({"nobody"}), offers, {}) is None
