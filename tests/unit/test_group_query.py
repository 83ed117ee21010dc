"""Registry-style queries (used by ``find`` and by query groups): parsing and the numpy index."""

from __future__ import annotations

import numpy as np
import pytest

from services.apps.query import Query, ServiceIndex, values_equal
from services.kernel.errors import Code, PropertyError


def _index() -> ServiceIndex:
    index = ServiceIndex(capacity=2)  # small, so that growing is exercised
    index.put("scout10", "mobile_robot", True, [5, 6, 0, 0, 0, 0])
    index.put("scout2", "mobile_robot", True, [5, 5, 0, 0, 0, 0])
    index.put("scout1", "mobile_robot", False, [9, 9, 0, 0, 0, 0])
    index.put("lidar", "sensor", True, [5, 5, 2])
    index.put("lamp", "switch", True)
    return index


def test_parse_all_parameters() -> None:
    q = Query.parse(
        {"type": "(mobile_robot sensor)", "near": "(5 5 0)", "radius": "3", "state": "up", "limit": "2"}
        | {"where": "speed=0.5&location.x=%281%29"}
    )
    assert q.types == frozenset({"mobile_robot", "sensor"})
    assert q.near is not None
    np.testing.assert_array_equal(q.near, [5, 5, 0])
    assert (q.radius, q.state, q.limit, q.props) == (3.0, "up", 2, {"speed": "0.5", "location.x": "(1)"})
    assert Query.parse({"type": "sensor"}).types == frozenset({"sensor"})
    assert Query.parse({}).is_empty()


@pytest.mark.parametrize(
    ("params", "words"),
    [
        ({"colour": "red"}, "unknown query parameter 'colour'"),
        ({"near": "(1)"}, "bad query parameter near"),
        ({"near": "five"}, "bad query parameter near"),
        ({"near": "(1 1)", "radius": "-1"}, "cannot be negative"),
        ({"radius": "2"}, "radius needs near"),
        ({"state": "sleepy"}, "expected up or down"),
        ({"limit": "0"}, "positive count"),
        ({"where": "a..b=1"}, "bad query parameter where"),
        ({"where": "speed"}, "property=value pairs"),
        ({"type": "()"}, "bad query parameter type"),
    ],
)
def test_bad_parameters_are_invalid_arguments(params: dict[str, str], words: str) -> None:
    with pytest.raises(PropertyError) as info:
        Query.parse(params)
    assert info.value.code is Code.INVALID_ARGUMENT
    assert words in info.value.message


def test_unknown_parameter_lists_the_known_ones() -> None:
    with pytest.raises(PropertyError) as info:
        Query.parse({"kind": "x"})
    assert "type" in info.value.message and "radius" in info.value.message


def test_select_by_type_state_and_natural_order() -> None:
    index = _index()
    assert index.select(Query()) == ["lamp", "lidar", "scout1", "scout2", "scout10"]
    assert index.select(Query.parse({"type": "mobile_robot"})) == ["scout1", "scout2", "scout10"]
    assert index.select(Query.parse({"type": "mobile_robot", "state": "up"})) == ["scout2", "scout10"]
    assert index.select(Query.parse({"state": "down"})) == ["scout1"]
    assert index.select(Query.parse({"type": "drone"})) == []


def test_select_near_sorts_by_distance_and_skips_unknown_locations() -> None:
    index = _index()
    planar = index.select(Query.parse({"near": "(5 5)", "radius": "3"}))
    assert planar == ["lidar", "scout2", "scout10"]  # lidar ties scout2 in the plane; name order breaks it
    spatial = index.select(Query.parse({"near": "(5 5 0)", "radius": "1.5"}))
    assert spatial == ["scout2", "scout10"]
    everything_by_distance = index.select(Query.parse({"near": "(9 9)"}))
    assert everything_by_distance == ["scout1", "scout10", "lidar", "scout2"]  # lamp has no location


def test_updates_and_removals_are_seen_by_the_next_query() -> None:
    index = _index()
    index.set_location("scout1", [5, 5.5, 0])
    index.set_up("scout1", True)
    assert index.select(Query.parse({"near": "(5 5 0)", "radius": "1", "state": "up"})) == [
        "scout2",
        "scout1",
        "scout10",
    ]
    index.remove("scout2")
    index.remove("nobody")
    index.set_type("lamp", "mobile_robot")
    assert index.select(Query.parse({"type": "mobile_robot"})) == ["lamp", "scout1", "scout10"]
    index.put("scout3", "mobile_robot", True, None)
    assert len(index) == 5 and "scout3" in index and "scout2" not in index
    assert index.select(Query.parse({"type": "mobile_robot"})) == ["lamp", "scout1", "scout3", "scout10"]
    index.set_location("scout1", None)
    assert "scout1" not in index.select(Query.parse({"near": "(0 0)"}))


def test_large_index_matches_a_plain_filter() -> None:
    rng = np.random.default_rng(7)
    index = ServiceIndex()
    points = rng.uniform(0, 100, size=(10_000, 2))
    for i, p in enumerate(points):
        index.put(f"r{i}", "mobile_robot" if i % 3 else "sensor", bool(i % 5), p)
    got = index.select(
        Query.parse({"type": "mobile_robot", "near": "(50 50)", "radius": "10", "state": "up"})
    )
    expected = {
        f"r{i}" for i, p in enumerate(points) if i % 3 and i % 5 and np.hypot(p[0] - 50, p[1] - 50) <= 10
    }
    assert set(got) == expected and len(got) == len(expected) > 0


@pytest.mark.parametrize(
    ("expected", "actual", "equal"),
    [
        ("0.5", "0.50", True),
        ("0.5", " 0.5 ", True),
        ("(1 2)", "(1.0 2.0)", True),
        ("(1 2)", "(1 2 0)", False),
        ("red", "red", True),
        ("red", "blue", False),
        ("1", "(1)", False),
    ],
)
def test_values_compare_by_value(expected: str, actual: str, equal: bool) -> None:
    assert values_equal(expected, actual) is equal
