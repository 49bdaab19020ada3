"""Position-based visual servoing (paper eqs. 6-8) and the kinematic initial guess (eq. 11).

Notation: `c*` is the reference (desired) camera, `c` the current one. ICP gives `T_ref_cur`
(= c*H_c, the current camera in the reference camera frame). The PBVS error is
`e = (c*t_c, theta*u)` with `(theta, u)` the angle-axis of `c*R_c`; its goal is 0.

- Control law (eq. 8): `v_c = -lambda * (c*R_c)^T @ c*t_c`, `omega_c = -lambda * theta*u`,
  a twist of the current camera expressed in the current camera frame.
- Interaction matrix (eq. 7): `de/dt = L @ (v_c, omega_c)` with
  `L = [[c*R_c, 0], [0, L_thetau]]`,
  `L_thetau = I + theta/2 [u]x + (1 - sinc(theta) / sinc^2(theta/2)) [u]x^2`.
  The paper (and DESIGN.md) print `- theta/2 [u]x`; finite differences of this error under
  camera twists expressed in the current camera frame (tests/test_pbvs.py) give `+`, the
  inverse right Jacobian of SO(3). The sign does not change the control law: `[u]x theta*u = 0`,
  so `L_thetau @ theta*u = theta*u` either way, and with the law above `de/dt = -lambda e`
  exactly: the error decays exponentially.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from vinetwin.frames import Array, compose, invert, skew, so3_log
from vinetwin.servo.config import Limits


def pbvs_error(T_ref_cur: Any) -> Array:
    """The PBVS error (c*t_c, theta*u) (6,) of the current camera pose in the reference frame."""
    T = np.asarray(T_ref_cur, dtype=np.float64)
    return np.concatenate([T[:3, 3], so3_log(T[:3, :3])])


def _sinc(x: float) -> float:
    return 1.0 if abs(x) < 1e-12 else math.sin(x) / x


def interaction_matrix(T_ref_cur: Any) -> Array:
    """The 6x6 interaction matrix L of eq. 7 at the current pose."""
    T = np.asarray(T_ref_cur, dtype=np.float64)
    w = so3_log(T[:3, :3])
    theta = float(np.linalg.norm(w))
    L = np.zeros((6, 6))
    L[:3, :3] = T[:3, :3]
    if theta < 1e-12:
        L[3:, 3:] = np.eye(3)
        return L
    u = w / theta
    U = skew(u)
    L[3:, 3:] = np.eye(3) + theta / 2 * U + (1 - _sinc(theta) / _sinc(theta / 2) ** 2) * U @ U
    return L


@dataclass(frozen=True, kw_only=True)
class Gain:
    """Constant or adaptive gain. Adaptive (ViSP's `vpAdaptiveGain`):
    `lambda(x) = (l0 - l_inf) * exp(-l0_slope / (l0 - l_inf) * x) + l_inf`, x = ||e||: `l0` near
    the goal, `l_inf` far from it, `l0_slope` the slope at x = 0."""

    l0: float = 0.8
    """Gain at the goal (1/s); the constant gain when adaptive is False."""
    l_inf: float = 0.3
    """Gain far from the goal (1/s)."""
    l0_slope: float = 8.0
    """Slope of the gain at zero error."""
    adaptive: bool = False
    """Use the adaptive law instead of the constant l0."""

    def __call__(self, error_norm: float) -> float:
        if not self.adaptive or self.l0 == self.l_inf:
            return self.l0
        a = self.l0 - self.l_inf
        return a * math.exp(-self.l0_slope / a * error_norm) + self.l_inf


def saturate(twist: Any, limits: Limits) -> Array:
    """Scales a twist (v, omega) down, as a whole, until both parts are within the limits."""
    t = np.asarray(twist, dtype=np.float64).reshape(6)
    scale = 1.0
    nv, nw = float(np.linalg.norm(t[:3])), float(np.linalg.norm(t[3:]))
    if nv > limits.max_linear:
        scale = min(scale, limits.max_linear / nv)
    if nw > limits.max_angular:
        scale = min(scale, limits.max_angular / nw)
    return t * scale


def pbvs_twist(T_ref_cur: Any, gain: Gain | float = 0.8, limits: Limits | None = None) -> Array:
    """Camera twist (v, omega) (6,) in the current camera frame from the control law (eq. 8)."""
    T = np.asarray(T_ref_cur, dtype=np.float64)
    e = pbvs_error(T)
    g = gain if isinstance(gain, Gain) else Gain(l0=float(gain))
    lam = g(float(np.linalg.norm(e)))
    twist = np.concatenate([-lam * T[:3, :3].T @ e[:3], -lam * e[3:]])
    return saturate(twist, limits) if limits is not None else twist


def target_twist(
    T_ref_cur: Any, target: Any, gain: Gain | float = 0.8, limits: Limits | None = None
) -> Array:
    """The view-keeping law: PBVS on s = (c_t_o, theta*u) (Chaumette & Hutchinson 2006, IEEE
    RAM 13(4), sec. "Position-based visual servo control", second choice of s), with `target`
    the point o (the cut) in the reference camera frame, c*_t_o.

    With p = c_t_o = (c*R_c)^T (c*_t_o - c*t_c), the target in the current camera frame, and
    dp/dt = -v + [p]x omega under a camera twist, the law
    `omega = -lambda theta*u`, `v = lambda ((p - c*_t_o) - [p]x theta*u)`
    gives dp/dt = -lambda (p - c*_t_o): the target moves on a straight line in the camera frame,
    so its image moves on a straight line too, and stays in view when it starts in view (eq. 8
    moves the camera's centre on a straight line instead, and the target can leave the image on
    large rotations). Both errors decay as exp(-lambda t); at the goal p = c*_t_o and the
    rotation is the identity, so the camera is at the reference pose."""
    T = np.asarray(T_ref_cur, dtype=np.float64)
    o = np.asarray(target, dtype=np.float64).reshape(3)
    R, t = T[:3, :3], T[:3, 3]
    p = R.T @ (o - t)
    w = so3_log(R)
    g = gain if isinstance(gain, Gain) else Gain(l0=float(gain))
    lam = g(float(np.linalg.norm(np.concatenate([p - o, w]))))
    twist = np.concatenate([lam * ((p - o) - np.cross(p, w)), -lam * w])
    return saturate(twist, limits) if limits is not None else twist


def kinematic_guess(T_ref_prev: Any, T_base_camera_prev: Any, T_base_camera_now: Any) -> Array:
    """ICP initial guess from robot kinematics (eq. 11):
    c*H_ck = c*H_ck-1 @ inv(B_H_ck-1) @ B_H_ck."""
    return compose(T_ref_prev, invert(T_base_camera_prev), T_base_camera_now)
