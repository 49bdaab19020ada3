"""SE(3) and SO(3) helpers on plain numpy arrays.

A pose is a 4x4 float64 array `T_a_b` with `p_a = T_a_b @ p_b` (homogeneous). Rotation vectors
are `theta * u` (angle-axis), in radians. Twists are `(v, omega)` stacked as a 6-vector, linear
part first (the order of the paper's PBVS error `e = (t, theta*u)`). Only numpy here.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import numpy.typing as npt

from vinetwin.errors import InputError, PoseError

Array = npt.NDArray[np.float64]

_EPS = 1e-12


def as_points(points: Any, name: str = "points") -> Array:
    """Returns `points` as a float64 (N, 3) array, or raises InputError naming `name`."""
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim == 1 and arr.shape[0] == 3:
        arr = arr[None, :]
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InputError(f"{name} must have shape (N, 3), got {arr.shape}")
    return arr


def unit_vector(v: Any, name: str = "direction") -> Array:
    """`v` (3 numbers) scaled to length 1; InputError when it is not finite or is zero. Scaled
    by its largest component first, so that a huge direction ([1e308, 1e308, 0], whose plain
    norm overflows to infinity) is still a direction."""
    a = np.asarray(v, dtype=np.float64).reshape(3)
    big = float(np.max(np.abs(a))) if np.all(np.isfinite(a)) else math.nan
    if not (math.isfinite(big) and big > 0.0):
        raise InputError(f"{name} must be a finite non-zero 3-vector, got {a.tolist()}")
    a = a / big
    n = float(np.linalg.norm(a))
    if n < 1e-9:
        raise InputError(f"{name} must be a finite non-zero 3-vector, got {a.tolist()}")
    return a / n


def check_pose(T: Any, name: str = "pose", atol: float = 1e-6) -> Array:
    """Validates a 4x4 rigid transform and returns it as float64.

    Raises PoseError naming `name` when the shape is wrong, a value is not finite, the last row
    is not (0, 0, 0, 1) or the rotation block is not orthonormal with determinant +1.
    """
    arr = np.asarray(T, dtype=np.float64)
    if arr.shape != (4, 4):
        raise PoseError(f"{name} must be a 4x4 matrix, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise PoseError(f"{name} holds a non-finite value (NaN or inf)")
    if not np.allclose(arr[3], [0.0, 0.0, 0.0, 1.0], atol=atol):
        raise PoseError(f"{name} last row must be [0, 0, 0, 1], got {arr[3].tolist()}")
    R = arr[:3, :3]
    if np.max(np.abs(R)) > 2.0:  # no rotation has such an entry (and R^T R would overflow)
        raise PoseError(f"{name} rotation block is not a proper rotation (an entry above 1)")
    if not np.allclose(R.T @ R, np.eye(3), atol=max(atol, 1e-5)) or np.linalg.det(R) < 0:
        raise PoseError(f"{name} rotation block is not a proper rotation (R^T R != I or det < 0)")
    return arr


def make_pose(R: Any = None, t: Any = None) -> Array:
    """Builds a 4x4 pose from a 3x3 rotation and a translation (either may be omitted)."""
    T = np.eye(4)
    if R is not None:
        T[:3, :3] = np.asarray(R, dtype=np.float64)
    if t is not None:
        T[:3, 3] = np.asarray(t, dtype=np.float64).reshape(3)
    return T


def invert(T: Any) -> Array:
    """Inverse of a rigid transform (uses R^T, exact for rotations)."""
    T = np.asarray(T, dtype=np.float64)
    R = T[:3, :3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ T[:3, 3]
    return out


def compose(*poses: Any) -> Array:
    """Product of poses left to right: compose(T_a_b, T_b_c) = T_a_c."""
    out = np.eye(4)
    for T in poses:
        out = out @ np.asarray(T, dtype=np.float64)
    return out


def transform_points(T_a_b: Any, points_b: Any) -> Array:
    """Applies T_a_b to (N, 3) points expressed in frame b; returns points in frame a."""
    T = np.asarray(T_a_b, dtype=np.float64)
    pts = as_points(points_b)
    return pts @ T[:3, :3].T + T[:3, 3]


def skew(v: Any) -> Array:
    """The 3x3 cross-product matrix [v]x, with [v]x @ w = v x w."""
    x, y, z = np.asarray(v, dtype=np.float64).reshape(3)
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def so3_exp(rotvec: Any) -> Array:
    """Rodrigues: rotation matrix of the rotation vector theta*u."""
    w = np.asarray(rotvec, dtype=np.float64).reshape(3)
    theta = float(np.linalg.norm(w))
    K = skew(w)
    if theta < 1e-8:
        return np.eye(3) + K + 0.5 * K @ K
    a = np.sin(theta) / theta
    b = (1.0 - np.cos(theta)) / theta**2
    return np.eye(3) + a * K + b * K @ K


def so3_log(R: Any) -> Array:
    """Rotation vector theta*u of a rotation matrix, theta in [0, pi]; stable near 0 and pi."""
    R = np.asarray(R, dtype=np.float64)
    cos_theta = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    vee = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    # atan2 of (sin, cos) keeps full precision at small angles, where arccos loses half the digits
    theta = float(np.arctan2(0.5 * np.linalg.norm(vee), cos_theta))
    if theta < 1e-6:
        return 0.5 * vee
    if np.pi - theta > 1e-4:
        return theta / (2.0 * np.sin(theta)) * vee
    # Near pi the antisymmetric part vanishes; the symmetric part gives u u^T exactly:
    # (R + R^T) / 2 = cos(theta) I + (1 - cos(theta)) u u^T. Its sign comes from vee.
    S = 0.5 * (R + R.T)
    B = (S - cos_theta * np.eye(3)) / (1.0 - cos_theta)
    i = int(np.argmax(np.diag(B)))
    u = B[:, i] / np.sqrt(max(B[i, i], _EPS))
    u /= np.linalg.norm(u)
    if np.dot(u, vee) < 0:
        u = -u
    return theta * u


def angle_axis(R: Any) -> tuple[float, Array]:
    """(theta, u) of a rotation; u is (1, 0, 0) when theta is 0."""
    w = so3_log(R)
    theta = float(np.linalg.norm(w))
    if theta < _EPS:
        return 0.0, np.array([1.0, 0.0, 0.0])
    return theta, w / theta


def theta_u(R: Any) -> Array:
    """The theta*u vector of a rotation: the rotational half of the PBVS error."""
    return so3_log(R)


def rotation_angle(R: Any) -> float:
    """Geodesic angle of a rotation in radians, in [0, pi]."""
    R = np.asarray(R, dtype=np.float64)
    return float(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)))


def _so3_left_jacobian(w: Array) -> Array:
    theta = float(np.linalg.norm(w))
    K = skew(w)
    if theta < 1e-6:
        return np.eye(3) + 0.5 * K + K @ K / 6.0
    return (
        np.eye(3)
        + (1.0 - np.cos(theta)) / theta**2 * K
        + (theta - np.sin(theta)) / theta**3 * K @ K
    )


def se3_exp(xi: Any) -> Array:
    """Exponential map of a twist xi = (v, omega) (6,) to a 4x4 pose."""
    xi = np.asarray(xi, dtype=np.float64).reshape(6)
    v, w = xi[:3], xi[3:]
    T = np.eye(4)
    T[:3, :3] = so3_exp(w)
    T[:3, 3] = _so3_left_jacobian(w) @ v
    return T


def se3_log(T: Any) -> Array:
    """Logarithm of a 4x4 pose as a twist (v, omega) (6,); inverse of se3_exp."""
    T = np.asarray(T, dtype=np.float64)
    w = so3_log(T[:3, :3])
    v = np.linalg.solve(_so3_left_jacobian(w), T[:3, 3])
    return np.concatenate([v, w])


def interpolate(T_a: Any, T_b: Any, alpha: float) -> Array:
    """Pose between T_a (alpha=0) and T_b (alpha=1): geodesic rotation, straight translation.

    This decoupled interpolation moves the frame origin on a straight line, which is what a
    camera path between two viewpoints should do.
    """
    T_a = np.asarray(T_a, dtype=np.float64)
    T_b = np.asarray(T_b, dtype=np.float64)
    R_ab = T_a[:3, :3].T @ T_b[:3, :3]
    R = T_a[:3, :3] @ so3_exp(alpha * so3_log(R_ab))
    t = (1.0 - alpha) * T_a[:3, 3] + alpha * T_b[:3, 3]
    return make_pose(R, t)


def pose_error(T_a: Any, T_b: Any) -> tuple[float, float]:
    """(translation distance in m, rotation angle in rad) between two poses of the same frame."""
    T_a = np.asarray(T_a, dtype=np.float64)
    T_b = np.asarray(T_b, dtype=np.float64)
    dt = float(np.linalg.norm(T_a[:3, 3] - T_b[:3, 3]))
    dr = rotation_angle(T_a[:3, :3].T @ T_b[:3, :3])
    return dt, dr


def look_at(eye: Any, target: Any, up_hint: Any = (0.0, 0.0, 1.0)) -> Array:
    """T_world_camera of an OpenCV camera at `eye` whose optical axis (+Z) points at `target`.

    The image's down direction (+Y) is chosen as close as possible to -up_hint. Raises
    InputError when eye equals target or the axis is parallel to up_hint.
    """
    eye = np.asarray(eye, dtype=np.float64).reshape(3)
    target = np.asarray(target, dtype=np.float64).reshape(3)
    up = np.asarray(up_hint, dtype=np.float64).reshape(3)
    z = target - eye
    n = np.linalg.norm(z)
    if n < 1e-12:
        raise InputError("look_at: eye and target coincide")
    z /= n
    x = np.cross(z, up)  # right = forward x up  (OpenCV: x right, y down, z forward)
    nx = np.linalg.norm(x)
    if nx < 1e-9:
        raise InputError("look_at: viewing direction is parallel to up_hint")
    x /= nx
    y = np.cross(z, x)
    return make_pose(np.column_stack([x, y, z]), eye)


def random_pose(rng: np.random.Generator, translation: float, rotation: float) -> Array:
    """A pose with translation of norm `translation` (m) and rotation angle `rotation` (rad),
    both in random directions."""
    d = rng.normal(size=3)
    d /= np.linalg.norm(d)
    a = rng.normal(size=3)
    a /= np.linalg.norm(a)
    return make_pose(so3_exp(rotation * a), translation * d)
