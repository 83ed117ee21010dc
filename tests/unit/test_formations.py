"""Formation geometry: centroid on the target, neighbours ``spacing`` apart, deterministic places."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from services.apps.formations import (
    FORMATIONS,
    centroid,
    formation_offsets,
    formation_targets,
    natural_key,
)
from services.kernel.errors import Code, PropertyError


@pytest.mark.parametrize("formation", FORMATIONS)
@given(n=st.integers(min_value=1, max_value=200), spacing=st.floats(min_value=0.01, max_value=100))
def test_offsets_are_centred(formation: str, n: int, spacing: float) -> None:
    offsets = formation_offsets(formation, n, spacing)
    assert offsets.shape == (n, 2)
    np.testing.assert_allclose(offsets.mean(axis=0), 0.0, atol=1e-9 * spacing * n)


@pytest.mark.parametrize("formation", FORMATIONS)
@given(n=st.integers(min_value=2, max_value=200), spacing=st.floats(min_value=0.01, max_value=100))
def test_no_two_members_closer_than_spacing(formation: str, n: int, spacing: float) -> None:
    offsets = formation_offsets(formation, n, spacing)
    d = np.linalg.norm(offsets[:, None, :] - offsets[None, :, :], axis=2)
    d[np.arange(n), np.arange(n)] = np.inf
    assert d.min() == pytest.approx(spacing, rel=1e-9)


def test_line_is_on_the_x_axis_spacing_apart() -> None:
    offsets = formation_offsets("line", 4, 2.0)
    np.testing.assert_allclose(offsets, [[-3, 0], [-1, 0], [1, 0], [3, 0]])


def test_grid_shape_keeps_a_short_last_row() -> None:
    offsets = formation_offsets("grid", 5, 1.0)
    # 3 columns, 2 rows: 3 places on the first row, 2 on the second.
    ys = sorted(set(np.round(offsets[:, 1], 9)))
    assert len(ys) == 2
    assert sorted(np.round(offsets[:, 0] - offsets[:, 0].min(), 9)) == [0, 0, 1, 1, 2]


def test_circle_points_are_equidistant_from_the_centre() -> None:
    offsets = formation_offsets("circle", 6, 1.5)
    radii = np.linalg.norm(offsets, axis=1)
    # A regular hexagon's side equals its radius.
    np.testing.assert_allclose(radii, 1.5)
    np.testing.assert_allclose(offsets[0], [1.5, 0.0], atol=1e-12)


def test_one_member_stands_on_the_target() -> None:
    for formation in FORMATIONS:
        np.testing.assert_allclose(formation_offsets(formation, 1, 3.0), [[0.0, 0.0]])
        assert formation_offsets(formation, 0).shape == (0, 2)


def test_targets_keep_the_targets_length_and_tail() -> None:
    places = formation_targets(["b", "a", "c"], [5, 5, 0, 0, 0, 1.5], "line", 1.0)
    assert list(places) == ["a", "b", "c"]
    np.testing.assert_allclose(places["a"], [4, 5, 0, 0, 0, 1.5])
    np.testing.assert_allclose(places["c"], [6, 5, 0, 0, 0, 1.5])
    mean = np.mean(list(places.values()), axis=0)
    np.testing.assert_allclose(mean, [5, 5, 0, 0, 0, 1.5])


def test_targets_are_deterministic_in_natural_order() -> None:
    names = [f"scout{i}" for i in (10, 2, 1)]
    assert list(formation_targets(names, [0, 0], "circle")) == ["scout1", "scout2", "scout10"]
    assert sorted(names, key=natural_key) == ["scout1", "scout2", "scout10"]
    first = formation_targets(names, [1, 2], "grid", 0.5)
    second = formation_targets(reversed(names), [1, 2], "grid", 0.5)
    for name in names:
        np.testing.assert_array_equal(first[name], second[name])


@pytest.mark.parametrize(
    ("formation", "n", "spacing", "words"),
    [
        ("vee", 3, 1.0, "unknown formation 'vee'"),
        ("line", 3, 0.0, "spacing must be a positive"),
        ("line", 3, math.nan, "spacing must be a positive"),
        ("line", -1, 1.0, "0 to"),
    ],
)
def test_bad_formation_requests_are_invalid_arguments(
    formation: str, n: int, spacing: float, words: str
) -> None:
    with pytest.raises(PropertyError) as info:
        formation_offsets(formation, n, spacing)
    assert info.value.code is Code.INVALID_ARGUMENT
    assert words in info.value.message


def test_target_needs_two_coordinates() -> None:
    with pytest.raises(PropertyError) as info:
        formation_targets(["a"], [1.0])
    assert info.value.code is Code.INVALID_ARGUMENT


def test_centroid_averages_positions_and_headings() -> None:
    c = centroid([[0, 0, 0, 0, 0, math.radians(179)], [2, 4, 0, 0, 0, math.radians(-179)]])
    np.testing.assert_allclose(c[:3], [1, 2, 0])
    assert abs(abs(c[5]) - math.pi) < 1e-9
    np.testing.assert_allclose(centroid([[1, 1], [3, 3, 3]]), [2, 2, 1.5])
    with pytest.raises(PropertyError):
        centroid([])
