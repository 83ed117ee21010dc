"""Marker fusion with scripted observations: known truth, noisy copies, a clock of the test's own."""

from __future__ import annotations

import numpy as np
import pytest

from services.apps.environment import MarkerFusion, Observation


def sighting(
    x: float, y: float, *, kind: str = "box", variance: float = 0.01, source: str = "cam", id: str = ""
):
    return Observation.at(kind, (x, y), variance, source, id=id)


def test_noisy_copies_fuse_closer_to_the_truth_than_a_single_observation() -> None:
    rng = np.random.default_rng(12)
    sigma = 0.1
    fused_errors, single_errors = [], []
    for _ in range(20):
        truth = rng.uniform(-5, 5, size=2)
        fusion = MarkerFusion(gate=4.0, max_distance=1.0, process_noise=0.0)
        noisy = truth + rng.normal(0.0, sigma, size=(10, 2))
        for t, (x, y) in enumerate(noisy):
            update = fusion.observe(sighting(x, y, variance=sigma**2), now=float(t))
        assert len(fusion) == 1 and update.marker.count == 10
        fused_error = float(np.linalg.norm(update.marker.position[:2] - truth))
        errors = np.linalg.norm(noisy - truth, axis=1)
        # Closer than the typical single observation in every trial, and than the last one seen.
        assert fused_error < float(np.median(errors))
        fused_errors.append(fused_error)
        single_errors.extend(errors.tolist())
        # The estimate is the mean of the copies, and its variance R / n.
        assert update.marker.position[:2] == pytest.approx(noisy.mean(axis=0))
        assert update.marker.variance == pytest.approx(sigma**2 / 10)
    # Over the trials, about 1/sqrt(10) of a single observation's error.
    assert np.mean(fused_errors) < 0.5 * np.mean(single_errors)


def test_uncertainty_shrinks_with_each_observation() -> None:
    fusion = MarkerFusion(process_noise=0.0)
    variances = [fusion.observe(sighting(1.0, 1.0), now=float(t)).marker.variance for t in range(5)]
    assert variances == sorted(variances, reverse=True)
    assert variances[-1] == pytest.approx(0.01 / 5)


def test_unseen_markers_grow_uncertain_with_the_process_noise() -> None:
    fusion = MarkerFusion(process_noise=0.1)
    fusion.observe(sighting(0.0, 0.0, variance=0.01), now=0.0)
    # 10 s later the marker's predicted variance is 0.01 + 1.0: a sighting 0.9 m away is within 3 sigma.
    update = fusion.observe(sighting(0.9, 0.0, variance=0.01), now=10.0)
    assert not update.created
    assert update.marker.position[0] == pytest.approx(0.9 * 1.01 / 1.02)


def test_nearby_markers_of_different_classes_stay_apart() -> None:
    fusion = MarkerFusion()
    box = fusion.observe(sighting(1.0, 1.0, kind="box"), now=0.0).marker
    ball = fusion.observe(sighting(1.02, 1.0, kind="ball"), now=0.0).marker
    assert box.id != ball.id and len(fusion) == 2
    fusion.observe(sighting(1.01, 1.0, kind="ball"), now=1.0)
    assert box.count == 1 and ball.count == 2
    assert [m.id for m in fusion.find("ball")] == [ball.id]


def test_the_gate_keeps_far_sightings_apart_and_picks_the_nearest() -> None:
    fusion = MarkerFusion(gate=4.0, process_noise=0.0)
    a = fusion.observe(sighting(0.0, 0.0), now=0.0).marker
    b = fusion.observe(sighting(0.8, 0.0), now=0.0).marker  # 5.7 standard deviations from a: its own marker
    assert a.id != b.id
    update = fusion.observe(sighting(0.7, 0.0), now=1.0)  # nearer b
    assert update.marker is b and len(fusion) == 2


def test_a_source_that_names_its_objects_is_followed_by_name() -> None:
    fusion = MarkerFusion(max_distance=0.5)
    first = fusion.observe(sighting(0.0, 0.0, kind="robot", source="scout1", id="scout1"), now=0.0).marker
    assert first.id == "scout1"
    # It drove 3 m unseen: far beyond the gate, but its own report says who it is.
    moved = fusion.observe(sighting(3.0, 0.0, kind="robot", source="scout1", id="scout1"), now=1.0)
    assert moved.marker is first and not moved.created
    assert first.position[0] == pytest.approx(3.0)
    # A camera's sighting of it nearby is the same robot too.
    seen = fusion.observe(sighting(3.05, 0.0, kind="robot", source="camera1", id="r7"), now=1.5)
    assert seen.marker is first and len(fusion) == 1


def test_markers_expire_after_ttl_on_the_injected_clock() -> None:
    fusion = MarkerFusion(ttl=10.0)
    old = fusion.observe(sighting(0.0, 0.0), now=0.0).marker
    kept = fusion.observe(sighting(5.0, 5.0), now=5.0).marker
    assert fusion.expire(now=10.0) == []  # exactly ttl: not yet
    assert [m.id for m in fusion.expire(now=10.5)] == [old.id]
    assert old.id not in fusion and kept.id in fusion
    fusion.observe(sighting(5.0, 5.0), now=14.0)  # seen again: lives on
    assert fusion.expire(now=20.0) == []
    assert [m.id for m in fusion.expire(now=24.5)] == [kept.id]
    # An expired marker's place is free: a new sighting there makes a new marker.
    assert fusion.observe(sighting(0.0, 0.0), now=30.0).created


def test_past_max_markers_the_least_recently_seen_is_evicted() -> None:
    fusion = MarkerFusion(max_markers=3)
    ids = [fusion.observe(sighting(float(i) * 5, 0.0), now=float(i)).marker.id for i in range(3)]
    fusion.observe(sighting(0.0, 0.0), now=3.0)  # the first is seen again
    update = fusion.observe(sighting(100.0, 0.0), now=4.0)
    assert [m.id for m in update.evicted] == [ids[1]]
    assert len(fusion) == 3 and ids[0] in fusion and ids[1] not in fusion


def test_ids_come_from_the_source_when_free_and_valid() -> None:
    fusion = MarkerFusion()
    assert fusion.observe(sighting(0.0, 0.0, id="crate-1"), now=0.0).marker.id == "crate-1"
    second = fusion.observe(sighting(9.0, 0.0, id="crate-1", source="other"), now=0.0).marker
    assert second.id != "crate-1" and second.id.startswith("box-")
    odd = fusion.observe(sighting(20.0, 0.0, kind="red ball", id="no spaces allowed"), now=0.0).marker
    assert odd.id.startswith("red_ball-")
    assert fusion.observe(sighting(30.0, 0.0, id="properties"), now=0.0).marker.id != "properties"


def test_find_by_class_area_and_nearness() -> None:
    fusion = MarkerFusion()
    for i, (x, y) in enumerate([(0, 0), (2, 0), (4, 0), (6, 0)]):
        fusion.observe(sighting(x, y, id=f"b{i}"), now=0.0)
    fusion.observe(sighting(2.1, 0.0, kind="ball", id="ball"), now=0.0)
    assert [m.id for m in fusion.find("box", near=(5.2, 0.0), count=2)] == ["b3", "b2"]
    assert sorted(m.id for m in fusion.find("box", area=(1.0, -1.0, 4.5, 1.0))) == ["b1", "b2"]
    assert [m.id for m in fusion.find(near=(2.2, 0.0), count=1)] == ["ball"]
    assert fusion.find("tree") == []


def test_association_uses_the_spatial_index_across_cell_borders() -> None:
    fusion = MarkerFusion(max_distance=1.0, process_noise=0.0)
    a = fusion.observe(sighting(0.99, 0.99), now=0.0).marker
    update = fusion.observe(sighting(1.01, 1.01), now=1.0)  # another cell, same marker
    assert update.marker is a and a.cell == ("box", 1, 1)


def test_bad_observations_are_refused() -> None:
    with pytest.raises(ValueError, match="2 or 3 finite numbers"):
        Observation.at("box", (1.0,), 0.1, "cam")
    with pytest.raises(ValueError, match="positive"):
        Observation.at("box", (1.0, 2.0), 0.0, "cam")
    with pytest.raises(ValueError, match="max_markers"):
        MarkerFusion(max_markers=0)
