"""A pruning pose for each cut, searched, not defaulted.

For a cut point and its cane, approach directions are tried over a grid of azimuth and elevation
(`SearchConfig`), each at the standoff with the cane across the image (roll 0; then, for a cut
no direction serves, the image turned over, which puts the wrist on the cane's other side), and
kept only when:

- **clear**: every part of the body (`BodyConfig`: the camera swept along its straight approach,
  the tool's capsule from the camera to the cut) stays `margin` away from the vine, the cane
  being cut excepted within the jaw zone; with the twin's hand-eye transform (`Wrist`), so do
  the arm's parts fixed to the camera (the tool mount, the camera's housing as the planner models
  it, and link 7, which keeps the arm links' clearance, `ReachConfig.clearance`), swept along the
  same approach: a pose whose wrist meets a cane is one no arm carrying this tool can take. The
  vine is the mesh's vertices and the centres of its triangles (on a tube mesh of 2 mm edges a
  clearance is exact to about 1 mm);
- **seen**: the camera sees the cut point and at least `min_visible` of its cane within 5 cm
  (Open3D ray casting towards the cane's centre points);
- **rich**: the camera sees at least `min_points` vine points in its depth range (every 16th
  pixel cast, times 256).

Of those the best by `score`: clearance (counted up to 3 cm), the cane's visible share, the
points seen (up to 4x `min_points`) and closeness to the default approach (perpendicular to the
cane from the robot's side), which the servo's validations know best. A cut with no acceptable
direction gets no pose, with the reason.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from vinetwin import _lazy
from vinetwin.arm import wrist_parts
from vinetwin.camera import CameraModel
from vinetwin.frames import Array
from vinetwin.plan.config import BodyConfig, SearchConfig
from vinetwin.plan.job_config import ReachConfig
from vinetwin.twin.poses import (
    DEFAULT_TOWARD,
    Approach,
    default_approach,
    direction_from_angles,
    pruning_pose,
)

#: Clearance beyond this (m) scores no better (and is not measured further).
CLEARANCE_CAP = 0.03
#: Pixels between the rays cast to count what the camera sees.
RAY_STEP = 16


@dataclass
class Candidate:
    """One approach direction, scored."""

    approach: Approach
    clearance: float
    """Smallest distance (m) from the body to the vine (negative: inside); for link 7, its
    distance less what it keeps beyond the margin (`Wrist`)."""
    visible: float = 0.0
    """Share of the cane within 5 cm of the cut the camera sees."""
    cut_seen: bool = False
    points: int = 0
    """Vine points the camera sees (full-resolution estimate)."""
    score: float = -math.inf

    def summary(self) -> dict[str, Any]:
        return {"azimuth_deg": round(math.degrees(self.approach.azimuth), 1),
                "elevation_deg": round(math.degrees(self.approach.elevation), 1),
                "roll_deg": round(math.degrees(self.approach.roll), 1),
                "clearance_m": round(self.clearance, 4), "visible": round(self.visible, 3),
                "cut_seen": self.cut_seen, "points": self.points}  # fmt: skip


@dataclass
class Found:
    """The search's answer for one cut: the best candidate (None when no direction passes),
    the reason when none does, and the default approach's scores for comparison."""

    best: Candidate | None
    reason: str
    default: Candidate
    tried: int
    ranked: list[Candidate] = field(default_factory=list)
    """Every direction that passes, best score first (the first is `best`)."""


class VineObstacles:
    """The vine as the search sees it: points for clearances, a ray-casting scene for sight."""

    def __init__(self, vertices: Array, faces: np.ndarray, camera: CameraModel) -> None:
        from scipy.spatial import cKDTree

        V = np.asarray(vertices, dtype=np.float64)
        F = np.asarray(faces, dtype=np.int64)
        # the vertices, and the centres of triangles with an edge over 3 mm (of a tube mesh of
        # 2 mm edges, no surface point is more than about 1.2 mm from a vertex)
        E = V[F]
        edge = np.linalg.norm(E - np.roll(E, 1, axis=1), axis=2).max(axis=1)
        self.points = np.concatenate([V, E[edge > 0.003].mean(axis=1)])
        self.tree = cKDTree(self.points)
        self.camera = camera
        o3d = _lazy.open3d()
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(
            o3d.core.Tensor(V.astype(np.float32)), o3d.core.Tensor(F.astype(np.uint32))
        )
        cam = camera
        u, v = np.meshgrid(np.arange(RAY_STEP / 2, cam.width, RAY_STEP),
                           np.arange(RAY_STEP / 2, cam.height, RAY_STEP))  # fmt: skip
        rays = np.column_stack([(u.ravel() - cam.cx) / cam.fx, (v.ravel() - cam.cy) / cam.fy,
                                np.ones(u.size)])  # fmt: skip
        self._pixel_rays = rays  # camera frame, z = 1

    def cast(self, origins: Array, directions: Array) -> Array:
        """Distance along each (unit) ray to the first hit (inf: none)."""
        o3d = _lazy.open3d()
        r = np.concatenate([origins, directions], axis=1).astype(np.float32)
        return self.scene.cast_rays(o3d.core.Tensor(r))["t_hit"].numpy().astype(np.float64)


#: Spacing (m) of the points that stand for the wrist's swept parts: each part's capsule is
#: sampled along its axis and along the approach, and a vine point's distance to the nearest
#: sample is its distance to the swept part to within 0.3 mm.
WRIST_STEP = 0.005


@dataclass(frozen=True)
class Wrist:
    """The arm's parts fixed to the camera, as the planner models them (`arm.wrist_parts`:
    link 7, the tool mount, the camera's housing), swept along the approach: points on their
    axes in the camera frame at the pruning pose (`WRIST_STEP` apart), each with the distance
    (m) the vine must keep from it, its part's radius plus what the part keeps beyond the body's
    margin (link 7: the arm links' clearance, `ReachConfig.clearance`, less the margin; the
    hand's parts nothing more)."""

    points: Array
    need: Array
    links: float
    """The clearance (m) link 7 keeps from the vine."""

    @classmethod
    def for_arm(cls, T_flange_camera: Array, cfg: SearchConfig,
                links_clearance: float | None = None) -> Wrist:  # fmt: skip
        """From the hand-eye transform and the search's standoff and body; `links_clearance`
        defaults to `ReachConfig`'s."""
        keep = ReachConfig().clearance if links_clearance is None else links_clearance
        T_cf = np.linalg.inv(np.asarray(T_flange_camera, float))
        travel = cfg.standoff - cfg.body.tool_reach
        sweep = np.linspace(0.0, travel, max(2, math.ceil(travel / WRIST_STEP) + 1))
        pts, need = [], []
        for part, p0, p1, r in wrist_parts(T_flange_camera):
            a, b = (T_cf @ np.append(p0, 1.0))[:3], (T_cf @ np.append(p1, 1.0))[:3]
            # along the axis at the sweep's own step: an axis along the approach then repeats
            length, step = float(np.linalg.norm(b - a)), float(sweep[1])
            u = (b - a) / length if length > 0 else np.zeros(3)
            along = np.minimum(np.arange(math.ceil(length / step) + 1) * step, length)
            axis = a + along[:, None] * u
            grid = (axis[:, None, :] + sweep[None, :, None] * np.array([0.0, 0.0, 1.0])).reshape(
                -1, 3
            )
            grid = np.unique(np.round(grid, 6), axis=0)
            extra = max(keep - cfg.body.margin, 0.0) if part == "link7" else 0.0
            pts.append(grid)
            need.append(np.full(len(grid), r + extra))
        return cls(np.concatenate(pts), np.concatenate(need), keep)


def wrist_clearances(obs: VineObstacles, Ts: Array, wrist: Wrist) -> Array:
    """Each pose's (Ts: (D, 4, 4), camera in the vine frame) wrist clearance (m), capped at
    `CLEARANCE_CAP`: the nearest vine point to each of the wrist's points (a KD-tree query)
    less the distance that point needs."""
    P = np.einsum("dij,kj->dki", Ts[:, :3, :3], wrist.points) + Ts[:, None, :3, 3]
    bound = float(wrist.need.max()) + CLEARANCE_CAP
    dist, _ = obs.tree.query(P.reshape(-1, 3), distance_upper_bound=bound, workers=-1)
    gap = dist.reshape(P.shape[:2]) - wrist.need[None, :]
    return np.minimum(gap.min(axis=1), CLEARANCE_CAP)


def body_distance(Q: Array, standoff: float, body: BodyConfig, exempt: Array) -> Array:
    """Distance (m) from points Q (..., N, 3) in the camera frame at the pruning pose to the body
    (the swept camera and the tool's capsule; `exempt` points (N,) ignored by the tool); negative
    inside."""
    w, h, d = body.camera_size
    travel = standoff - body.tool_reach
    lo = np.array([-w / 2, -h / 2, -d])
    hi = np.array([w / 2, h / 2, travel])
    c, half = (lo + hi) / 2, (hi - lo) / 2
    q = np.abs(Q - c) - half
    box = np.linalg.norm(np.maximum(q, 0.0), axis=-1) + np.minimum(q.max(axis=-1), 0.0)
    t = np.clip(Q[..., 2], 0.0, standoff)
    tool = np.sqrt(Q[..., 0] ** 2 + Q[..., 1] ** 2 + (Q[..., 2] - t) ** 2) - body.tool_radius
    tool = np.where(exempt, np.inf, tool)
    return np.minimum(box, tool)


def approaches(
    cane_axis: Array, cfg: SearchConfig, fine: int = 1, roll: float = 0.0, far: bool = False
) -> list[Approach]:
    """The grid of approach directions across the cane (at least `min_cross` from it), at image
    roll `roll` (rad); `fine` > 1 divides each step of the grid that many times; `far`: from the
    row's far side."""
    a0, a1 = np.radians(cfg.azimuths_for(far))
    e0, e1 = np.radians(cfg.elevation_range)
    out = []
    for az in np.linspace(a0, a1, (cfg.azimuths - 1) * fine + 1):
        for el in np.linspace(e0, e1, (cfg.elevations - 1) * fine + 1):
            d = direction_from_angles(float(az), float(el))
            if abs(float(d @ cane_axis)) <= math.cos(math.radians(cfg.min_cross)) + 1e-9:
                out.append(Approach(cfg.standoff, float(az), float(el), roll))
    return out


def _dot3(A: Array, B: Array) -> Array:
    """`A @ B.T` for (N, 3) and (D, 3) arrays, as three broadcast products."""
    return A[:, :1] * B[:, 0] + A[:, 1:2] * B[:, 1] + A[:, 2:3] * B[:, 2]


def _clearances(
    obs: VineObstacles,
    cut: Array,
    axis: Array,
    aps: list[Approach],
    cfg: SearchConfig,
    wrist: Wrist | None = None,
) -> Array:
    """Each approach's clearance (m), exact up to `CLEARANCE_CAP` (reported as the cap beyond):
    only the vine points in a corridor around the body's axis are measured. With `wrist`, the
    wrist is measured first, and a direction it already rules out (under the margin) keeps the
    wrist's clearance without the camera's and tool's."""
    body = cfg.body
    w, h, d = body.camera_size
    corridor = max(math.hypot(w, h) / 2, body.tool_radius) + CLEARANCE_CAP
    idx = obs.tree.query_ball_point(cut, cfg.standoff + d + corridor)
    T_all = np.stack([pruning_pose(cut, axis, ap) for ap in aps])
    out = np.full(len(aps), CLEARANCE_CAP)
    if wrist is not None:
        out = wrist_clearances(obs, T_all, wrist)
    todo = np.nonzero(out >= body.margin)[0]
    if not idx or not len(todo):
        return out
    Q = obs.points[np.asarray(idx)]
    exempt = np.linalg.norm(Q - cut, axis=1) < body.jaw_zone
    Q2 = (Q * Q).sum(1)[:, None]
    for j0 in range(0, len(todo), 64):
        js = todo[j0 : j0 + 64]
        Ts = T_all[js]
        Z, O = Ts[:, :3, 2], Ts[:, :3, 3]
        # (N, D) products over 3 coordinates, written out: no BLAS call, whose worker threads
        # spin against a busy second core (a web-app propose once ran for minutes beside Chromium)
        t = _dot3(Q, Z) - np.einsum("dj,dj->d", O, Z)  # along each optical axis
        perp2 = Q2 - 2 * _dot3(Q, O) + (O * O).sum(1)[None] - t * t
        near = (t > -d - corridor) & (t < cfg.standoff + corridor) & (perp2 < corridor**2)
        for i in np.nonzero(near.any(axis=0))[0]:
            k = near[:, i]
            Qc = (Q[k] - O[i]) @ Ts[i, :3, :3]
            dist = float(body_distance(Qc, cfg.standoff, body, exempt[k]).min())
            out[js[i]] = min(out[js[i]], dist)
    return out


def _sight(obs: VineObstacles, c: Candidate, cut: Array, axis: Array, cane: Array,
           radius: float) -> None:  # fmt: skip
    """Fills what the camera sees at the candidate's pose."""
    T = pruning_pose(cut, axis, c.approach)
    R, o = T[:3, :3], T[:3, 3]
    cam = obs.camera
    # the cane near the cut (and the cut itself): each centre point seen when the first hit
    # towards it is on its own surface
    targets = np.vstack([cut[None], cane])
    vec = targets - o
    dist = np.linalg.norm(vec, axis=1)
    dirs = vec / dist[:, None]
    pc = (targets - o) @ R
    in_view = (
        (pc[:, 2] > cam.min_depth)
        & (pc[:, 2] < cam.max_depth)
        & (np.abs(pc[:, 0] / pc[:, 2] * cam.fx + cam.cx - cam.width / 2) < cam.width / 2)
        & (np.abs(pc[:, 1] / pc[:, 2] * cam.fy + cam.cy - cam.height / 2) < cam.height / 2)
    )
    t = obs.cast(np.repeat(o[None], len(targets), 0), dirs)
    seen = in_view & (t >= dist - radius - 0.004)
    c.cut_seen = bool(seen[0])
    c.visible = float(seen[1:].mean()) if len(seen) > 1 else float(seen[0])
    rays = obs._pixel_rays
    dirs = rays / np.linalg.norm(rays, axis=1, keepdims=True)
    t = obs.cast(np.repeat(o[None], len(dirs), 0), dirs @ R.T)
    z = t * dirs[:, 2]
    hit = np.isfinite(z) & (z > cam.min_depth) & (z < cam.max_depth)
    c.points = int(hit.sum()) * RAY_STEP * RAY_STEP


def search_pose(
    obs: VineObstacles,
    cut: Array,
    cane_axis: Array,
    cane: Array,
    radius: float,
    cfg: SearchConfig,
    wrist: Wrist | None = None,
    far: bool = False,
) -> Found:
    """The best pruning pose for one cut (see the module's docstring): the grid at each of the
    search's rolls in turn, then, when no direction of them passes, a grid three times as fine
    at each roll. `wrist`: the arm's parts fixed to the camera, checked too (`Wrist.for_arm`
    with the twin's hand-eye transform). `far`: from the row's far side (+Y), the grid and the
    default approach half a turn about the vertical."""
    cut = np.asarray(cut, dtype=np.float64)
    axis = np.asarray(cane_axis, dtype=np.float64)
    axis = axis / np.linalg.norm(axis)
    dflt = default_approach(axis, cfg.standoff, -DEFAULT_TOWARD if far else DEFAULT_TOWARD)
    default = Candidate(dflt, float(_clearances(obs, cut, axis, [dflt], cfg, wrist)[0]))
    _sight(obs, default, cut, axis, cane, radius)
    found = Found(None, "", default, 0)
    for fine in (1, 3):
        for roll in cfg.rolls:
            aps = approaches(axis, cfg, fine, math.radians(roll), far)
            clear = _clearances(obs, cut, axis, aps, cfg, wrist)
            tried = [Candidate(ap, float(cl)) for ap, cl in zip(aps, clear, strict=True)]
            found = _choose(obs, tried, default, cut, axis, cane, radius, cfg, wrist)
            if found.best is not None:
                return found
    return found


def _choose(obs: VineObstacles, tried: list[Candidate], default: Candidate, cut: Array,
            axis: Array, cane: Array, radius: float, cfg: SearchConfig,
            wrist: Wrist | None = None) -> Found:  # fmt: skip
    """The best of the directions tried, or why none passes."""
    m = cfg.body.margin
    ok = [c for c in tried if c.clearance >= m]
    if not ok:
        b = max(tried, key=lambda c: c.clearance) if tried else default
        if wrist is None:
            why = f"no approach keeps {m * 1000:.0f} mm from the vine (best {b.clearance * 1000:.1f} mm"
        else:  # a clearance counts link 7's beyond the margin: say what is short
            why = (f"no approach keeps the camera and tool {m * 1000:.0f} mm and the arm's link 7 "
                   f"{wrist.links * 1000:.0f} mm from the vine (the best {(m - b.clearance) * 1000:.1f} "
                   "mm short,")  # fmt: skip
        return Found(None, f"{why} of {len(tried)} tried)", default, len(tried))
    d0 = direction_from_angles(default.approach.azimuth, default.approach.elevation)
    for c in ok:
        _sight(obs, c, cut, axis, cane, radius)
        d = direction_from_angles(c.approach.azimuth, c.approach.elevation)
        c.score = (
            min(c.clearance, CLEARANCE_CAP) / CLEARANCE_CAP
            + c.visible
            + 0.5 * min(c.points / max(4 * cfg.min_points, 1), 1.0)
            + 0.5 * float(d @ d0)
        )
    good = [c for c in ok if c.cut_seen and c.visible >= cfg.min_visible
            and c.points >= cfg.min_points]  # fmt: skip
    if not good:
        seen = [c for c in ok if c.cut_seen]
        why = (
            "the cut point is hidden from every clear approach"
            if not seen
            else f"no clear approach sees {cfg.min_visible:.0%} of the cane near the cut and "
            f"{cfg.min_points} vine points (best: {max(c.visible for c in seen):.0%} seen)"
        )
        return Found(None, why, default, len(tried))
    ranked = sorted(good, key=lambda c: -c.score)
    return Found(ranked[0], "", default, len(tried), ranked)
