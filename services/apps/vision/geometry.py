"""Where things are as a camera sees them: poses, the camera frame, field of view, confidence.

The geometry is 2-D on the ground plane: a camera looks level along its yaw;
its roll and pitch are kept in its pose but do not tilt the view. A target is
in view when its ground distance is within the range and its bearing within
half the horizontal field of view on either side (both limits included).

The camera frame is the usual body frame: x forward along the camera's
heading, y to its left, z up, the origin at the camera.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from services.kernel.values import Vector

__all__ = ["confidence", "in_view", "mounted_pose", "to_camera_frame"]

#: Closer than this (m) a target is on the lens, not in view: it has no bearing.
MIN_DISTANCE = 1e-6
#: Slack for a target exactly on an edge of the view, which float rounding may push out by a hair.
_EDGE_SLACK = 1e-9
#: Confidence at the far end of the range, straight ahead; and the factor at the edge of the view.
FAR_CONFIDENCE = 0.5
EDGE_CONFIDENCE = 0.5


def mounted_pose(robot: Vector, offset: Vector) -> Vector:
    """The world pose of a camera mounted at ``offset`` (x y z roll pitch yaw in the robot's frame).

    The offset's x y turn with the robot's yaw; z adds to the robot's height; the
    angles add to the robot's (the yaw wrapped to -pi..pi).
    """
    pose = np.zeros(6)
    yaw = float(robot[5])
    c, s = math.cos(yaw), math.sin(yaw)
    pose[0] = robot[0] + c * offset[0] - s * offset[1]
    pose[1] = robot[1] + s * offset[0] + c * offset[1]
    pose[2] = robot[2] + offset[2]
    pose[3:5] = robot[3:5] + offset[3:5]
    pose[5] = math.remainder(yaw + float(offset[5]), math.tau)
    return pose


def to_camera_frame(camera: Vector, points: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """World points (N x 3: x y z) in the frame of a camera at pose ``camera`` (N x 3: forward, left, up)."""
    yaw = float(camera[5])
    c, s = math.cos(yaw), math.sin(yaw)
    dx = points[:, 0] - camera[0]
    dy = points[:, 1] - camera[1]
    out = np.empty_like(points, dtype=np.float64)
    out[:, 0] = c * dx + s * dy
    out[:, 1] = -s * dx + c * dy
    out[:, 2] = points[:, 2] - camera[2]
    return out


def in_view(
    local: npt.NDArray[np.float64], range_m: float, fov_rad: float
) -> tuple[npt.NDArray[np.bool_], npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """Which camera-frame points are in view, with their ground distances and bearings (rad, + left)."""
    distance = np.hypot(local[:, 0], local[:, 1])
    bearing = np.arctan2(local[:, 1], local[:, 0])
    seen = (
        (distance > MIN_DISTANCE)
        & (distance <= range_m + _EDGE_SLACK)
        & (np.abs(bearing) <= fov_rad / 2 + _EDGE_SLACK)
    )
    return seen, distance, bearing


def confidence(
    distance: npt.NDArray[np.float64], bearing: npt.NDArray[np.float64], range_m: float, fov_rad: float
) -> npt.NDArray[np.float64]:
    """How sure the camera is of each sighting: 1 close and straight ahead, falling linearly
    with distance (to FAR_CONFIDENCE at the range) and toward the edge of the view (times
    EDGE_CONFIDENCE at the edge): 0.25 in the far corner."""
    far = 1.0 - (1.0 - FAR_CONFIDENCE) * np.clip(distance / range_m, 0.0, 1.0)
    edge = 1.0 - (1.0 - EDGE_CONFIDENCE) * np.clip(np.abs(bearing) / (fov_rad / 2), 0.0, 1.0)
    return np.asarray(far * edge, dtype=np.float64)
