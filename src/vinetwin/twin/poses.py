"""Pruning poses: where the eye-in-hand camera stands to see a cut point.

A pruning pose is `T_vine_camera` (OpenCV camera) with its optical axis through the cut point at
`standoff` metres (0.15 m in the paper). Its orientation is described by three angles a person can
adjust: the approach direction (the optical axis, from camera to cut point) by `azimuth` (about
+Z of the vine frame, from +X; 90 deg looks along +Y) and `elevation` (positive looks down), and a
`roll` about the optical axis measured from the reference roll in which the cane runs across the
image, left to right from its base to its tip. The default approach is perpendicular to the cane,
from the robot's side of the row (-Y, looking along +Y).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from vinetwin.errors import InputError
from vinetwin.frames import Array, make_pose, unit_vector

#: The distance (m) from the camera to its cut point along the optical axis: the paper's 0.15 m
#: by default, and the range a person may set (a D405 sees from 7 cm; beyond 0.6 m a cane is a
#: few pixels wide). The web app and `Twin.add_pose` read these.
DEFAULT_STANDOFF = 0.15
STANDOFF_RANGE = (0.05, 0.6)
#: Direction the camera looks along by default: from the robot's side (-Y) towards the row.
DEFAULT_TOWARD: Array = np.array([0.0, 1.0, 0.0])


@dataclass(frozen=True)
class Approach:
    """The adjustable description of a pruning pose around its cut point."""

    standoff: float = DEFAULT_STANDOFF
    azimuth: float = math.pi / 2
    elevation: float = 0.0
    roll: float = 0.0


def _unit(v: Any, name: str) -> Array:
    return unit_vector(v, name)


def direction_from_angles(azimuth: float, elevation: float) -> Array:
    """Unit optical-axis direction for an azimuth and elevation (radians)."""
    ce = math.cos(elevation)
    return np.array([ce * math.cos(azimuth), ce * math.sin(azimuth), -math.sin(elevation)])


def angles_from_direction(direction: Any) -> tuple[float, float]:
    """(azimuth, elevation) of a unit optical-axis direction."""
    d = _unit(direction, "direction")
    return math.atan2(d[1], d[0]), math.asin(float(np.clip(-d[2], -1.0, 1.0)))


def default_approach_direction(cane_axis: Any, toward: Any = DEFAULT_TOWARD) -> Array:
    """Optical-axis direction perpendicular to the cane, as close as possible to `toward`."""
    a = _unit(cane_axis, "cane_axis")
    t = _unit(toward, "toward")
    d = t - (t @ a) * a
    if np.linalg.norm(d) < 1e-6:  # cane along the preferred direction: look horizontally across it
        d = np.cross(a, [0.0, 0.0, 1.0])
        if np.linalg.norm(d) < 1e-6:
            d = np.array([0.0, 1.0, 0.0])
    return d / np.linalg.norm(d)


def _reference_x(z: Array, cane_axis: Array) -> Array:
    """Image x axis at zero roll: the cane's direction projected on the image plane."""
    x = cane_axis - (cane_axis @ z) * z
    if np.linalg.norm(x) < 1e-6:  # looking along the cane: fall back to a horizontal image x
        x = np.cross(z, [0.0, 0.0, 1.0])
        if np.linalg.norm(x) < 1e-6:
            x = np.array([1.0, 0.0, 0.0])
    return x / np.linalg.norm(x)


def pruning_pose(
    cut_point: Any,
    cane_axis: Any,
    approach: Approach | None = None,
) -> Array:
    """T_vine_camera looking at `cut_point` from `approach.standoff` metres.

    Args:
        cut_point: (3,) point on the cane, vine frame, metres.
        cane_axis: (3,) direction of the cane there (base to tip), vine frame.
        approach: standoff and angles; None gives the default: perpendicular to the cane from
            the -Y side at 0.15 m, cane across the image.
    """
    p = np.asarray(cut_point, dtype=np.float64).reshape(3)
    if not np.all(np.isfinite(p)):
        raise InputError(f"cut_point must be finite, got {p.tolist()}")
    a = _unit(cane_axis, "cane_axis")
    ap = approach or default_approach(a)
    if not (np.isfinite(ap.standoff) and ap.standoff > 0):
        raise InputError(f"standoff must be a positive distance in metres, got {ap.standoff}")
    z = direction_from_angles(ap.azimuth, ap.elevation)
    x0 = _reference_x(z, a)
    y0 = np.cross(z, x0)
    c, s = math.cos(ap.roll), math.sin(ap.roll)
    x = c * x0 + s * y0
    y = np.cross(z, x)
    return make_pose(np.column_stack([x, y, z]), p - ap.standoff * z)


#: A pose whose optical axis points this much towards -Y looks at the row from its far side (the
#: aisle beyond the row, +Y; the robot's side is -Y).
FAR_SIDE = 0.1


#: The half turn about the vine frame's vertical axis (x -> -x, y -> -y): the row seen from its
#: far aisle, which is then the robot's side (its own inverse).
HALF_TURN: Array = np.diag([-1.0, -1.0, 1.0, 1.0])


def from_far_side(T_vine_camera: Any) -> bool:
    """Whether a camera pose looks at the row from its far side (`FAR_SIDE`)."""
    return float(np.asarray(T_vine_camera, dtype=np.float64)[1, 2]) <= -FAR_SIDE


def default_approach(
    cane_axis: Any, standoff: float = DEFAULT_STANDOFF, toward: Any = DEFAULT_TOWARD
) -> Approach:
    """The default approach (perpendicular to the cane, from -Y; looking `toward`) as angles."""
    az, el = angles_from_direction(default_approach_direction(cane_axis, toward))
    return Approach(standoff=standoff, azimuth=az, elevation=el, roll=0.0)


def approach_of(T_vine_camera: Any, cut_point: Any, cane_axis: Any) -> Approach:
    """Recovers the approach angles of a camera pose looking at a cut point.

    The optical axis is taken from the pose; standoff is the distance along it to the point's
    foot on the axis. Use `snap_to_cut_point` first if the axis may miss the point.
    """
    T = np.asarray(T_vine_camera, dtype=np.float64)
    p = np.asarray(cut_point, dtype=np.float64).reshape(3)
    a = _unit(cane_axis, "cane_axis")
    z = T[:3, 2] / np.linalg.norm(T[:3, 2])
    az, el = angles_from_direction(z)
    x0 = _reference_x(z, a)
    y0 = np.cross(z, x0)
    roll = math.atan2(float(T[:3, 0] @ y0), float(T[:3, 0] @ x0))
    standoff = float((p - T[:3, 3]) @ z)
    return Approach(standoff=standoff, azimuth=az, elevation=el, roll=roll)


def snap_to_cut_point(T_vine_camera: Any, cut_point: Any, cane_axis: Any) -> Array:
    """Keeps the camera position, turns the optical axis back through the cut point, keeps the
    roll as close as possible, and returns the new T_vine_camera."""
    T = np.asarray(T_vine_camera, dtype=np.float64)
    p = np.asarray(cut_point, dtype=np.float64).reshape(3)
    d = p - T[:3, 3]
    dist = float(np.linalg.norm(d))
    if dist < 1e-6:
        raise InputError("the camera sits on the cut point; move it away before snapping")
    az, el = angles_from_direction(d)
    old = approach_of(T, p, cane_axis)
    return pruning_pose(p, cane_axis, Approach(dist, az, el, old.roll))


def axis_miss_distance(T_vine_camera: Any, cut_point: Any) -> float:
    """Distance (m) between the cut point and the camera's optical axis."""
    T = np.asarray(T_vine_camera, dtype=np.float64)
    d = np.asarray(cut_point, dtype=np.float64).reshape(3) - T[:3, 3]
    z = T[:3, 2]
    return float(np.linalg.norm(d - (d @ z) * z))


def estimate_cane_axis(vertices: Any, point: Any, radius: float = 0.015) -> Array:
    """Cane direction near `point` from the mesh vertices within `radius`: the principal axis of
    that tube patch. Raises InputError when fewer than 10 vertices are that close."""
    V = np.asarray(vertices, dtype=np.float64)
    p = np.asarray(point, dtype=np.float64).reshape(3)
    near = V[np.linalg.norm(V - p, axis=1) < radius]
    if len(near) < 10:
        raise InputError(f"fewer than 10 mesh vertices within {radius} m of the point")
    c = near - near.mean(0)
    _, _, vt = np.linalg.svd(c, full_matrices=False)
    axis = vt[0]
    return axis if axis[2] >= 0 else -axis
