"""What a provider costs: the distance it must drive, and how cost and QoS rank providers.

The seed measures a mobile robot's work by odometry: the distance driven is
``Σ (vL + vR) / 2 · Δt`` over the wheel speeds ``vL``, ``vR`` sampled every ``Δt``
(:func:`odometry_distance`). Before the work, the scheduler estimates it as the planar
distance from where the provider is to where the consumer needs it (:func:`drive_distance`):
the odometry of a straight drive. A provider may instead publish a cost of its own (a
property the request names in its ``cost`` option); then that number is used as it is.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping

import numpy as np

from services.kernel.errors import InvalidArgument
from services.kernel.values import Vector

__all__ = ["DEFAULT_QOS", "DEFAULT_WEIGHT", "drive_distance", "odometry_distance", "rank_scores"]

#: The QoS assumed of a provider nobody has assessed yet: the middle of the normalised scale,
#: so a new provider is neither preferred to a good one nor put behind a bad one.
DEFAULT_QOS = 0.5
#: How much cost weighs against QoS when ranking (0: QoS only, 1: cost only).
DEFAULT_WEIGHT = 0.5


def drive_distance(start: Vector | None, goal: Vector | None) -> float:
    """Planar distance from ``start`` to ``goal`` (x y of each); 0 when either is unknown."""
    if start is None or goal is None or start.size < 2 or goal.size < 2:
        return 0.0
    return float(math.hypot(float(goal[0] - start[0]), float(goal[1] - start[1])))


def odometry_distance(samples: Iterable[tuple[float, float, float]]) -> float:
    """Distance driven, ``Σ (vL + vR) / 2 · Δt`` over samples ``(Δt, vL, vR)`` (s, m/s, m/s).

    Reversing counts as distance too (the absolute value of each step): a robot that drives
    out and back has worked for both legs.
    """
    rows = np.asarray(list(samples), dtype=np.float64)
    if rows.size == 0:
        return 0.0
    if rows.ndim != 2 or rows.shape[1] != 3:
        raise InvalidArgument("odometry samples are (dt vL vR) triples")
    if not np.all(np.isfinite(rows)) or np.any(rows[:, 0] < 0):
        raise InvalidArgument("odometry samples must be finite, with dt >= 0")
    return float(np.sum(np.abs((rows[:, 1] + rows[:, 2]) / 2.0) * rows[:, 0]))


def rank_scores(
    costs: Mapping[str, float],
    qos: Mapping[str, float],
    weight: float = DEFAULT_WEIGHT,
    scale: float | None = None,
) -> dict[str, float]:
    """Score of each provider, lower is better: ``weight · cost/scale + (1 − weight) · (1 − qos)``.

    ``scale`` is the largest cost of every provider that could serve (default: the largest in
    ``costs``; zero: cost does not count), so the two terms are on the same 0–1 scale whatever
    unit the cost is in, and a provider's score does not depend on which others are asked about;
    a provider without a QoS record counts as :data:`DEFAULT_QOS`.
    """
    top = max(costs.values(), default=0.0) if scale is None else scale
    scores = {}
    for name, cost in costs.items():
        relative = cost / top if top > 0 else 0.0
        scores[name] = weight * relative + (1.0 - weight) * (1.0 - qos.get(name, DEFAULT_QOS))
    return scores
