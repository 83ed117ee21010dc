"""A robot's orientation as the tools that draw it want it: roll, pitch and yaw as a quaternion.

A ``location`` is ``x y z roll pitch yaw`` by the robots' convention; ROS messages and Foxglove's
schemas carry the rotation as a quaternion. Every front that shows a pose turns it here, so a
robot's pose is the same whichever tool draws it.
"""

from __future__ import annotations

import math

__all__ = ["quaternion"]


def quaternion(roll: float, pitch: float, yaw: float) -> list[float]:
    """Roll, pitch and yaw (radians, applied yaw, then pitch, then roll) as ``x y z w``."""
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return [
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
        cr * cp * cy + sr * sp * sy,
    ]
