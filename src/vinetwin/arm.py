"""The arm a plan is made for: a Franka Emika Panda's kinematics, limits and collision model, in
plain numpy and numba, so the planner (`vinetwin.plan`), the simulator (`vinetwin.sim.panda`)
and a hardware session read one definition.

- Kinematics: Franka's published modified (Craig) Denavit-Hartenberg parameters, the same chain
  as `sim/assets/panda/panda.xml` (tests/test_prune.py checks the two agree), the flange 0.107 m
  along link 7's z axis.
- Limits: joint position, velocity, acceleration and jerk limits from Franka's datasheet
  (frankaemika.github.io/docs/control_parameters.html).
- Collision model: spheres that cover panda.xml's collision capsules link by link, the tool's mount,
  the D405's housing (42 x 42 x 23 mm) and the tool's capsule from the camera to the blade. A
  sphere of radius r every r/2 along a capsule of radius r covers it to within 3.2% of r. The
  pruning end effector replaces Franka's hand: a mount on the flange (5 cm across, 4 cm long),
  the D405 and the shears.
- Inverse kinematics (`ArmModel.solve`): damped least squares on the camera frame from several
  seeds, compiled; a solution must lie within the joint limits and keep the arm's
  manipulability above a floor (away from singularities).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from vinetwin._numba import nb
from vinetwin.frames import Array, make_pose

#: Modified DH parameters per joint: a_{i-1} (m), d_i (m), alpha_{i-1} (rad).
DH = np.array(
    [
        [0.0, 0.333, 0.0],
        [0.0, 0.0, -math.pi / 2],
        [0.0, 0.316, math.pi / 2],
        [0.0825, 0.0, math.pi / 2],
        [-0.0825, 0.384, -math.pi / 2],
        [0.0, 0.0, math.pi / 2],
        [0.088, 0.0, math.pi / 2],
    ]
)
#: Link 7 to the flange (m, along z).
FLANGE_OFFSET = 0.107
LOWER = np.array([-2.8973, -1.7628, -2.8973, -3.0718, -2.8973, -0.0175, -2.8973])
UPPER = np.array([2.8973, 1.7628, 2.8973, -0.0698, 2.8973, 3.7525, 2.8973])
#: Franka's joint velocity (rad/s), acceleration (rad/s^2) and jerk (rad/s^3) limits.
VELOCITY_LIMITS = (2.175, 2.175, 2.175, 2.175, 2.61, 2.61, 2.61)
ACCELERATION_LIMITS = (15.0, 7.5, 10.0, 12.5, 15.0, 20.0, 20.0)
JERK_LIMITS = (7500.0, 3750.0, 5000.0, 6250.0, 7500.0, 10000.0, 10000.0)
#: panda.xml's `home` keyframe.
HOME = np.array([0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785])
#: The arm folded over its base (nothing more than 0.22 m ahead of it): where it rides while
#: the platform drives, and where a vine's job starts and ends.
STOW = np.array([0.0, -1.76, 0.0, -3.0, 0.0, 1.6, 0.785])

#: panda.xml's collision capsules: (frame, start, end, radius); frame 0 is the base (link 0),
#: 1-7 the links, 8 the flange. A sphere is a capsule of zero length.
_CAPSULES = (
    (1, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 0.065),
    (2, (0.0, 0.0, 0.0), (0.0, -0.316, 0.0), 0.055),
    (3, (0.0, 0.0, 0.0), (0.0825, 0.0, 0.0), 0.055),
    (4, (0.0, 0.0, 0.0), (-0.0825, 0.384, 0.0), 0.055),
    (5, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 0.065),
    (6, (0.0, 0.0, 0.0), (0.088, 0.0, 0.0), 0.055),
    (7, (0.0, 0.0, 0.0), (0.0, 0.0, 0.107), 0.055),
)
#: The pruning end effector replaces Franka's hand: a mount on the flange (radius, length along
#: its z, m) that carries the shears and the D405.
_MOUNT = (0.025, 0.04)


@nb.njit(cache=True)
def _frames(q: Array, out: Array) -> None:  # pragma: no cover - compiled
    """out[0] the base, out[1..7] the links, out[8] the flange, as 4x4 poses in the base. Each
    link's transform (modified DH: Rx(alpha) Tx(a) Rz(theta) Tz(d)) is multiplied in by hand,
    in place: a small matrix product through BLAS, and an array per link, would cost more than
    the arithmetic (the planner's check runs this for every configuration)."""
    out[0] = 0.0
    for k in range(4):
        out[0, k, k] = 1.0
    for i in range(7):
        a, d, al = DH[i, 0], DH[i, 1], DH[i, 2]
        ca, sa = math.cos(al), math.sin(al)
        ct, st = math.cos(q[i]), math.sin(q[i])
        P = out[i]
        N = out[i + 1]
        for r in range(3):
            x, y, z = P[r, 0], P[r, 1], P[r, 2]
            # the columns of A: (ct, st ca, st sa), (-st, ct ca, ct sa), (0, -sa, ca), (a, -d sa, d ca)
            N[r, 0] = x * ct + y * st * ca + z * st * sa
            N[r, 1] = -x * st + y * ct * ca + z * ct * sa
            N[r, 2] = -y * sa + z * ca
            N[r, 3] = x * a - y * d * sa + z * d * ca + P[r, 3]
        N[3, 0] = 0.0
        N[3, 1] = 0.0
        N[3, 2] = 0.0
        N[3, 3] = 1.0
    T = out[7]
    F = out[8]
    for r in range(4):
        for c in range(3):
            F[r, c] = T[r, c]
        F[r, 3] = T[r, 2] * FLANGE_OFFSET + T[r, 3]


@nb.njit(cache=True)
def _jacobian(frames: Array, p: Array) -> Array:  # pragma: no cover - compiled
    """The 6x7 geometric Jacobian (linear; angular) of a point p fixed to the flange."""
    J = np.zeros((6, 7))
    for i in range(7):
        z = frames[i + 1, :3, 2]
        o = frames[i + 1, :3, 3]
        r = p - o
        J[0, i] = z[1] * r[2] - z[2] * r[1]
        J[1, i] = z[2] * r[0] - z[0] * r[2]
        J[2, i] = z[0] * r[1] - z[1] * r[0]
        J[3:, i] = z
    return J


@nb.njit(cache=True)
def _rot_error(R: Array, Rt: Array) -> Array:  # pragma: no cover - compiled
    """The rotation vector taking R to Rt, in the base frame (log of Rt R^T)."""
    E = Rt @ R.T
    c = min(1.0, max(-1.0, (E[0, 0] + E[1, 1] + E[2, 2] - 1.0) / 2.0))
    th = math.acos(c)
    w = np.array([E[2, 1] - E[1, 2], E[0, 2] - E[2, 0], E[1, 0] - E[0, 1]])
    if th < 1e-9:
        return 0.5 * w
    if th > math.pi - 1e-6:  # near pi: from the symmetric part
        k = np.argmax(np.array([E[0, 0], E[1, 1], E[2, 2]]))
        v = (E[:, k] + np.eye(3)[:, k]) / math.sqrt(max(2.0 * (1.0 + E[k, k]), 1e-12))
        return th * v
    return th / (2.0 * math.sin(th)) * w


@nb.njit(cache=True)
def _solve(
    target: Array,
    T_flange_x: Array,
    q0: Array,
    lower: Array,
    upper: Array,
    iterations: int,
    tol_t: float,
    tol_r: float,
    damping: float,
) -> tuple[Array, float, float]:  # pragma: no cover - compiled
    """Damped least squares from q0 for the frame T_flange_x to reach `target` (in the base);
    joints clamped to their limits after each step. Returns (q, translation error, rotation
    error)."""
    q = q0.copy()
    frames = np.empty((9, 4, 4))
    et, er = 1e9, 1e9
    best, since = 1e18, 0
    for _ in range(iterations):
        _frames(q, frames)
        X = frames[8] @ T_flange_x
        e = np.empty(6)
        e[:3] = target[:3, 3] - X[:3, 3]
        e[3:] = _rot_error(X[:3, :3].copy(), target[:3, :3].copy())
        et = math.sqrt(e[0] ** 2 + e[1] ** 2 + e[2] ** 2)
        er = math.sqrt(e[3] ** 2 + e[4] ** 2 + e[5] ** 2)
        if et < tol_t and er < tol_r:
            break
        score = et + 0.1 * er
        if score < best * 0.999:
            best, since = score, 0
        else:
            since += 1
            if since >= 10:  # stalled: at a joint limit or a local minimum
                break
        s = min(1.0, 0.1 / max(et, 1e-12), 0.3 / max(er, 1e-12))  # bounded steps
        J = _jacobian(frames, X[:3, 3])
        dq = J.T @ np.linalg.solve(J @ J.T + damping**2 * np.eye(6), s * e)
        q = np.minimum(np.maximum(q + dq, lower), upper)
    return q, et, er


@dataclass(frozen=True)
class Spheres:
    """The collision model: sphere centres (local, in their frame) and radii, with the frame
    each rides on (0 base .. 8 flange) and the part it belongs to."""

    frame: np.ndarray
    centre: Array
    radius: Array
    part: tuple[str, ...]

    def __len__(self) -> int:
        return len(self.radius)


def _capsule_spheres(p0: Any, p1: Any, r: float) -> list[Array]:
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    n = max(1, math.ceil(float(np.linalg.norm(p1 - p0)) / (r / 2))) + 1
    return [p0 + (p1 - p0) * k / (n - 1) for k in range(n)] if n > 1 else [p0]


def wrist_parts(T_flange_camera: Any) -> list[tuple[str, Array, Array, float]]:
    """The parts fixed to the flange as capsules in the flange frame (part, end, end, radius):
    link 7, the tool mount and the D405's housing (a sphere around its 42 x 42 x 23 mm body,
    1 mm to spare). `sphere_model` covers them with spheres."""
    T_fc = np.asarray(T_flange_camera, float)
    _, a, b, r7 = _CAPSULES[6]
    down = np.array([0.0, 0.0, FLANGE_OFFSET])
    housing = (T_fc @ np.array([0.0, 0.0, -0.0115, 1.0]))[:3]
    return [
        ("link7", np.asarray(a, float) - down, np.asarray(b, float) - down, r7),
        ("mount", np.zeros(3), np.array([0.0, 0.0, _MOUNT[1]]), _MOUNT[0]),
        ("camera", housing, housing, math.sqrt(0.021**2 * 2 + 0.0115**2) + 0.001),
    ]


def sphere_model(T_flange_camera: Any, blade: Any, tool_radius: float) -> Spheres:
    """The Panda's spheres (links 1-7, the tool mount), the D405's and the tool's (a capsule of
    `tool_radius` from the camera's optical centre to the blade point, both in the flange
    frame)."""
    frames, centres, radii, parts = [], [], [], []

    def add(frame: int, pts: list[Array], r: float, part: str) -> None:
        for p in pts:
            frames.append(frame)
            centres.append(p)
            radii.append(r)
            parts.append(part)

    for f, p0, p1, r in _CAPSULES:
        add(f, _capsule_spheres(p0, p1, r), r, f"link{f}")
    hand = {part: (p0, p1, r) for part, p0, p1, r in wrist_parts(T_flange_camera)}
    p0, p1, r = hand["mount"]
    for p in _capsule_spheres(p0, p1, r):
        add(8, [p], r, "mount")
    p0, _, r = hand["camera"]
    add(8, [p0], r, "camera")
    T_fc = np.asarray(T_flange_camera, float)
    add(8, _capsule_spheres(T_fc[:3, 3], np.asarray(blade, float), tool_radius), tool_radius,
        "tool")  # fmt: skip
    return Spheres(np.asarray(frames), np.asarray(centres), np.asarray(radii), tuple(parts))


def camera_fixed_spheres(T_flange_camera: Any) -> tuple[Array, Array, tuple[str, ...]]:
    """The planner's spheres (`sphere_model`) on the parts fixed to the camera, the tool
    excepted: link 7, the tool mount and the housing; their centres in the camera frame, their
    radii and parts."""
    T_fc = np.asarray(T_flange_camera, float)
    s = sphere_model(T_fc, T_fc[:3, 3], 0.01)  # its tool spheres are not used
    use = np.isin(s.frame, (7, 8)) & (np.asarray(s.part) != "tool")
    c = s.centre[use].copy()
    c[s.frame[use] == 7, 2] -= FLANGE_OFFSET  # link 7's frame: the flange's, less its offset
    cam = (c - T_fc[:3, 3]) @ T_fc[:3, :3]
    return cam, s.radius[use].copy(), tuple(np.asarray(s.part)[use].tolist())


class ArmModel:
    """The Panda with its camera and tool, on a base pose: forward kinematics, its collision
    spheres and inverse kinematics for the camera (or any flange-fixed frame)."""

    def __init__(
        self,
        T_flange_camera: Any,
        T_flange_tool: Any,
        blade: Any = (0.0, 0.0, 0.0),
        tool_radius: float = 0.01,
    ) -> None:
        """`blade`: the blade point in the tool frame."""
        self.T_flange_camera = np.asarray(T_flange_camera, float)
        self.T_flange_tool = np.asarray(T_flange_tool, float)
        self.blade_flange = (self.T_flange_tool @ np.append(np.asarray(blade, float), 1.0))[:3]
        self.spheres = sphere_model(self.T_flange_camera, self.blade_flange, tool_radius)
        self.lower, self.upper = LOWER.copy(), UPPER.copy()
        self.vmax = np.asarray(VELOCITY_LIMITS)
        self.amax = np.asarray(ACCELERATION_LIMITS)
        self.jmax = np.asarray(JERK_LIMITS)
        self._buf = np.empty((9, 4, 4))

    @property
    def camera_reach(self) -> float:
        """An upper bound (m) on the camera's distance from the shoulder (joint 2's axis, on
        the base's z axis `DH[0, 1]` above it), whatever the joints: the straight lengths from
        each joint's origin to the next, the flange's and the camera's offsets, end to end."""
        links = float(np.sum(np.hypot(DH[2:, 0], DH[2:, 1])))
        return links + FLANGE_OFFSET + float(np.linalg.norm(self.T_flange_camera[:3, 3]))

    def frames(self, q: Any) -> Array:
        out = np.empty((9, 4, 4))
        _frames(np.asarray(q, float), out)
        return out

    def flange(self, q: Any) -> Array:
        """T_base_flange."""
        return self.frames(q)[8]

    def camera(self, q: Any) -> Array:
        """T_base_camera."""
        return self.flange(q) @ self.T_flange_camera

    def blade(self, q: Any) -> Array:
        """The blade point in the base."""
        return (self.flange(q) @ np.append(self.blade_flange, 1.0))[:3]

    def sphere_centres(self, q: Any) -> Array:
        """(N, 3) sphere centres in the base at joints q."""
        F = self.frames(q)
        s = self.spheres
        R = F[s.frame, :3, :3]
        return np.einsum("nij,nj->ni", R, s.centre) + F[s.frame, :3, 3]

    def manipulability(self, q: Any) -> float:
        """Yoshikawa's measure sqrt(det(J J^T)) of the camera frame's Jacobian."""
        F = self.frames(q)
        J = _jacobian(F, (F[8] @ self.T_flange_camera)[:3, 3])
        return float(math.sqrt(max(np.linalg.det(J @ J.T), 0.0)))

    def solve(
        self,
        T_base_x: Any,
        seeds: list[Array],
        *,
        T_flange_x: Any = None,
        tol: tuple[float, float] = (5e-4, 5e-3),
        iterations: int = 150,
        min_manipulability: float = 0.0,
        limit_margin: float = 0.0,
    ) -> Array | None:
        """Joints that put the frame T_flange_x (default: the camera) at T_base_x, from the
        first seed that converges within `tol` (m, rad) with every joint `limit_margin` inside
        its limits and the manipulability above `min_manipulability`; None when no seed does."""
        for q in self._solutions(T_base_x, seeds, T_flange_x, tol, iterations,
                                 min_manipulability, limit_margin):  # fmt: skip
            return q
        return None

    def solutions(
        self,
        T_base_x: Any,
        seeds: list[Array],
        *,
        T_flange_x: Any = None,
        tol: tuple[float, float] = (5e-4, 5e-3),
        iterations: int = 150,
        min_manipulability: float = 0.0,
        limit_margin: float = 0.0,
    ) -> list[Array]:
        """Every distinct solution (joints 0.05 rad apart) the seeds converge to, as `solve`
        accepts them."""
        out: list[Array] = []
        for q in self._solutions(T_base_x, seeds, T_flange_x, tol, iterations,
                                 min_manipulability, limit_margin):  # fmt: skip
            if all(np.max(np.abs(q - o)) > 0.05 for o in out):
                out.append(q)
        return out

    def _solutions(
        self, T_base_x: Any, seeds: list[Array], T_flange_x: Any, tol: tuple[float, float],
        iterations: int, min_manipulability: float, limit_margin: float,
    ) -> Any:  # fmt: skip
        target = np.asarray(T_base_x, float)
        T_fx = self.T_flange_camera if T_flange_x is None else np.asarray(T_flange_x, float)
        lo, hi = self.lower + limit_margin, self.upper - limit_margin
        for q0 in seeds:
            q, et, er = _solve(
                target, T_fx, np.clip(np.asarray(q0, float), lo, hi), lo, hi, iterations,
                tol[0], tol[1], 0.01,
            )  # fmt: skip
            if et < tol[0] and er < tol[1] and self.manipulability(q) >= min_manipulability:
                yield q


def seeds(rng: np.random.Generator, n: int, first: list[Array] | None = None) -> list[Array]:
    """IK seeds: the given ones, `HOME`, then random joints within the limits."""
    out = list(first or []) + [HOME.copy()]
    out += [rng.uniform(LOWER, UPPER) for _ in range(n)]
    return out


def base_pose(x: float, y: float, z: float, yaw: float) -> Array:
    """T_vine_base: the robot base at (x, y, z) in the vine frame, turned `yaw` about +Z."""
    c, s = math.cos(yaw), math.sin(yaw)
    return make_pose(np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]), [x, y, z])
