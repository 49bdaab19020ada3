"""Where the arm can prune from: the obstacles (`Collider`: the vine's mesh with exact distances,
the platform's deck, the ground), which platform stops reach each cut's pruning pose and its
straight approach (`reach_cut`), the fewest stops that cover the reachable cuts (`choose_stops`)
and the cut order at a stop (`order_cuts`).

A cut is reachable from a stop when the arm's inverse kinematics puts the camera at the pruning
pose within the joint limits (less `ReachConfig.limit_margin`) and above the manipulability
floor, the straight approach that brings the blade onto the cut point stays reachable step by
step without a jump in the joints, and no collision sphere of the arm, camera or tool comes
closer than the body margin to the vine, the deck or the ground there (the tool's spheres may
touch the cane within the jaw zone of the cut point: that is the cut)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from vinetwin.arm import HOME, STOW, ArmModel, base_pose
from vinetwin.errors import InputError
from vinetwin.frames import Array, invert, make_pose, transform_points
from vinetwin.plan._collide_kernels import (
    arm_valid,
    build_blocks,
    build_free,
    build_hash,
    closest_points,
    point_gaps,
    vertex_triangles,
)
from vinetwin.plan.job_config import JobConfig, PlatformConfig

#: The largest joint jump (rad) between neighbouring steps of a straight approach.
MAX_JOINT_JUMP = 0.3
#: The spatial hash's cell (m), and its blocks (cells per side) that skip empty space.
GRID_CELL = 0.02
BLOCK = 4
#: The free-space grid's cell (m): a sphere that far from every vertex needs no search.
FREE_CELL = 0.01
#: Spheres nearer the vine than this (m) get the exact distance.
NEAR = 0.02


class Collider:
    """The obstacles in the vine frame: the vine's mesh, the ground (z = 0) and the platform's
    deck under the base at each stop.

    Two queries, compiled, on a spatial hash of the mesh's vertices: a conservative one for the
    planner (`arm_clear`: no vertex within a sphere's radius, its clearance and what the surface
    between vertices can come closer: microseconds), and an exact one for judging contacts
    (`clearance`: point-to-triangle distances, for the spheres the first finds near; checked
    against Open3D's in tests/test_prune.py)."""

    def __init__(self, vertices: Any, faces: Any, platform: PlatformConfig) -> None:
        V = np.ascontiguousarray(vertices, dtype=float)
        F = np.asarray(faces, np.int64)
        if len(V) == 0 or len(F) == 0:
            raise InputError("the vine mesh is empty: nothing to plan around")
        edges = np.linalg.norm(V[F[:, [1, 2, 0]]] - V[F], axis=2)
        self.bound = float(edges.max()) / math.sqrt(3.0)
        """The surface may come this much closer than its nearest vertex (a triangle's points
        lie within its circumradius, at most its longest edge / sqrt(3), of a corner)."""
        self.V = V
        self.origin = V.min(0) - GRID_CELL
        self.shape = np.ceil((V.max(0) - self.origin) / GRID_CELL).astype(np.int64) + 2
        self.starts, self.order = build_hash(V, self.origin, GRID_CELL, self.shape)
        self.blocks = build_blocks(self.starts, self.shape, BLOCK)
        self.free = build_free(V, self.origin, self.shape * GRID_CELL, FREE_CELL)
        self.F = np.ascontiguousarray(F)
        self.edge = float(edges.max())
        self.vt_starts, self.vt_tris, self.vedge = vertex_triangles(V, self.F)
        self.vbound = self.vedge / math.sqrt(3.0)
        """Per vertex, how much closer than it the surface of its triangles can come (their
        longest edge / sqrt(3)): a few long triangles (a digitised trunk's) then widen the
        check only around themselves."""
        self.platform = platform
        self._clearances: dict[tuple[int, float, float], Array] = {}
        self._tree: Any = None
        self.at_stop(np.eye(4))

    def at_stop(self, T_vine_base: Array) -> None:
        self.T_vine_base = np.ascontiguousarray(T_vine_base, dtype=float)
        b = self.T_vine_base[:3, 3]
        L, W = self.platform.deck
        self.deck_lo = np.array([b[0] - L / 2, b[1] - W / 2, -1e9])
        self.deck_hi = np.array([b[0] + L / 2, b[1] + W / 2, b[2]])

    def gaps(self, points_vine: Array, radii: Array, reach: float = NEAR) -> Array:
        """(N, 3) gaps of spheres (centres in the vine frame) to the vine (a lower bound, at
        most `reach`), the deck and the ground."""
        P = np.ascontiguousarray(points_vine, dtype=float).reshape(-1, 3)
        out = np.empty((len(P), 3))
        point_gaps(P, np.asarray(radii, float), reach + self.bound, self.V, self.origin,
                   GRID_CELL, self.shape, self.starts, self.order, self.deck_lo, self.deck_hi,
                   out)  # fmt: skip
        out[:, 0] -= self.bound
        return out

    def arm_clear(self, arm: ArmModel, q: Array, links: float, hand: float) -> bool:
        """Every sphere of the arm at joints q clear of every obstacle: the links' by `links`,
        the hand's (mount, camera, tool) by `hand` (conservative: no vine vertex within the
        sphere's radius, its clearance and what the surface between vertices can come
        closer)."""
        s = arm.spheres
        key = (id(arm), links, hand)
        clearance = self._clearances.get(key)
        if clearance is None:
            clearance = self._clearances[key] = np.where(s.frame == 8, hand, links)
        return bool(arm_valid(np.asarray(q, float), self.T_vine_base, s.frame, s.centre,
                              s.radius, clearance, self.bound, self.vbound, self.V, self.origin,
                              GRID_CELL, self.shape, self.starts, self.order, self.blocks, BLOCK, self.free, FREE_CELL,
                              self.deck_lo, self.deck_hi))  # fmt: skip

    def closest(self, P: Array, reach: float) -> tuple[Array, Array]:
        """Each point's exact distance to the mesh and its nearest surface point, where that is
        within `reach` (else inf and NaN): the nearest vertex and the vertices within it plus
        the longest edge from a KD-tree (scipy's, built on first use), their triangles'
        closest points compiled."""
        from scipy.spatial import cKDTree

        if self._tree is None:
            self._tree = cKDTree(self.V)
        P = np.ascontiguousarray(P, dtype=float).reshape(-1, 3)
        dist, closest = np.full(len(P), np.inf), np.full((len(P), 3), np.nan)
        dv, _ = self._tree.query(P, distance_upper_bound=reach + self.edge)
        ok = np.isfinite(dv)
        if not ok.any():
            return dist, closest
        lists = self._tree.query_ball_point(P[ok], dv[ok] + self.edge)
        starts = np.zeros(int(ok.sum()) + 1, np.int64)
        starts[1:] = np.cumsum([len(c) for c in lists])
        cand = np.fromiter((v for c in lists for v in c), np.int64, count=int(starts[-1]))
        d, c = np.empty(len(starts) - 1), np.empty((len(starts) - 1, 3))
        closest_points(P[ok], np.asarray(dv[ok], float), starts, cand, self.V, self.F,
                       self.vt_starts, self.vt_tris, self.vedge, reach, d, c)  # fmt: skip
        dist[ok], closest[ok] = d, c
        return dist, closest

    def clearance(
        self,
        centres_base: Array,
        radii: Array,
        exempt: tuple[Array, float, Array] | None = None,
        need: float = NEAR,
    ) -> tuple[float, int, str]:
        """The smallest gap (m) between the spheres (centres in the base) and any obstacle,
        with the sphere that has it and the obstacle ("vine", "deck", "ground"). A sphere's gap
        to the vine is exact where its lower bound is under `need` (else that bound: what is
        asked is whether the gap reaches `need`). `exempt` = (cut point, jaw zone, mask): the
        masked spheres' contacts with the vine within the jaw zone of the cut point do not
        count."""
        P = transform_points(self.T_vine_base, centres_base)
        radii = np.asarray(radii, float)
        g = self.gaps(P, radii, max(need, 0.0) + 1e-3)
        near = g[:, 0] < need
        if near.any():
            Pn = np.ascontiguousarray(P[near])
            dist, closest = self.closest(Pn, float(radii[near].max()) + max(need, 0.0) + 1e-3)
            exact = dist - radii[near]
            if exempt is not None:
                cut, zone, mask = exempt
                inside = np.linalg.norm(closest - cut, axis=1) < zone
                exact = np.where(mask[near] & inside, np.inf, exact)
            g[near, 0] = exact
        k = np.unravel_index(int(np.argmin(g)), g.shape)
        return float(g[k]), int(k[0]), ("vine", "deck", "ground")[int(k[1])]


@dataclass
class CutReach:
    """How the arm reaches one cut from one stop."""

    cut: str
    pose: str
    stop: float
    """The platform's position along the row (m)."""
    q_pose: Array
    """Joints at the pruning pose."""
    q_cut: Array
    """Joints with the blade on the cut point (the approach's end)."""
    manipulability: float
    clearance: float
    """Smallest gap (m) to the vine, deck or ground at the pose and along the approach."""


@dataclass
class VinePlan:
    """A vine's plan: the stops, the cuts done at each in order, and the cuts no stop reaches,
    with the reason."""

    stops: list[float] = field(default_factory=list)
    order: dict[float, list[CutReach]] = field(default_factory=dict)
    unreachable: dict[str, str] = field(default_factory=dict)
    """pose id -> why no stop reaches it."""
    planning_s: float = 0.0
    platform: dict[str, Any] = field(default_factory=dict)
    """The platform as placed (its offset and height set from the poses when automatic)."""
    tried: int = 0
    """(pose, stop) pairs tried."""

    def to_dict(self) -> dict[str, Any]:
        return {
            "stops": self.stops,
            "order": [
                {"stop": s, "poses": [r.pose for r in self.order.get(s, [])]} for s in self.stops
            ],
            "unreachable": self.unreachable,
            "platform": self.platform,
            "planning_s": self.planning_s,
        }


def stop_pose(x: float, platform: PlatformConfig) -> Array:
    """T_vine_base at the stop x: on the -Y side, facing the row (+Y)."""
    return base_pose(x, -platform.offset, platform.height, math.pi / 2)


def reach_cut(
    arm: ArmModel,
    collider: Collider,
    T_vine_camera: Array,
    cut: Array,
    T_vine_base: Array,
    cfg: JobConfig,
    margin: float,
    jaw_zone: float,
    warm: list[Array],
    rng: np.random.Generator,
    prefer: Array | None = None,
    approach: bool = True,
) -> tuple[Array, Array, float, float] | str:
    """(q at the pose, q with the blade on the cut, manipulability, clearance) from the base at
    T_vine_base, or the reason it cannot. Of the inverse kinematics solutions the `warm` seeds
    reach, then (if none of those serves) those `HOME` and random seeds reach, the one nearest
    `prefer` (default: the first warm seed, else `STOW`) in joint time whose approach is clear
    is taken. Without `approach` only the pose is checked (the joints at the cut are then those
    at the pose; `plan_vine` checks the approach where it uses the stop)."""
    rc = cfg.reach
    T_base_vine = invert(T_vine_base)
    T_pose = T_base_vine @ np.asarray(T_vine_camera, float)
    cut_base = transform_points(T_base_vine, np.asarray(cut, float)[None])[0]
    ref = prefer if prefer is not None else (warm[0] if warm else STOW)
    why, tried = "", 0
    # the warm seeds first (their solutions are the near ones), then the others
    for batch in (
        list(warm),
        [HOME] + [rng.uniform(arm.lower, arm.upper) for _ in range(rc.seeds)],
    ):
        found = arm.solutions(T_pose, batch, min_manipulability=rc.min_manipulability,
                              limit_margin=rc.limit_margin)  # fmt: skip
        found.sort(key=lambda q: joint_time(ref, q, arm.vmax))
        for q in found:
            tried += 1
            got = _approach(arm, collider, T_pose, cut, cut_base, q, cfg, margin, jaw_zone,
                            approach)  # fmt: skip
            if not isinstance(got, str):
                return got
            why = why or got
    if not tried:
        return "no inverse kinematics solution within the joint limits, away from singularities"
    return why


def _approach(
    arm: ArmModel, collider: Collider, T_pose: Array, cut: Array, cut_base: Array, q: Array,
    cfg: JobConfig, margin: float, jaw_zone: float, along: bool = True,
) -> tuple[Array, Array, float, float] | str:  # fmt: skip
    """The straight approach from joints q at the pose: clear at the pose (the cheap checks
    first), then (`along`) reachable step by step, and clear along the way (its steps'
    spheres queried at once)."""
    rc = cfg.reach
    s = arm.spheres
    if not collider.arm_clear(arm, q, rc.clearance, margin):
        return (
            f"the arm's links come within {1000 * rc.clearance:.0f} mm of an obstacle at the pose"
        )
    worst, i, what = collider.clearance(arm.sphere_centres(q), s.radius, None, need=margin)
    if worst < margin:
        return (
            f"the {s.part[i]} comes within {1000 * max(worst, 0):.0f} mm of the {what} at the pose"
        )
    if not along:
        return q, q, arm.manipulability(q), worst
    travel = cut_base - arm.blade(q)
    qs = [q]
    for k in range(1, rc.approach_steps + 1):
        T_k = make_pose(T_pose[:3, :3], T_pose[:3, 3] + travel * k / rc.approach_steps)
        qk = arm.solve(T_k, [qs[-1]], limit_margin=rc.limit_margin)
        if qk is None or np.max(np.abs(qk - qs[-1])) > MAX_JOINT_JUMP:
            return f"the straight approach leaves the arm's reach {k}/{rc.approach_steps} of the way in"
        qs.append(qk)
    n = len(s.radius)
    tool = np.tile(np.array([p == "tool" for p in s.part]), len(qs) - 1)
    centres = np.concatenate([arm.sphere_centres(qk) for qk in qs[1:]])
    gap, j, what = collider.clearance(centres, np.tile(s.radius, len(qs) - 1),
                                      (np.asarray(cut, float), jaw_zone, tool), need=margin)  # fmt: skip
    if gap < margin:
        k, i = j // n + 1, j % n
        return (f"the {s.part[i]} comes within {1000 * max(gap, 0):.0f} mm of the {what} "
                f"{k}/{rc.approach_steps} of the way in")  # fmt: skip
    return q, qs[-1], arm.manipulability(q), min(worst, gap)


def candidate_stops(cut_xs: list[float], cfg: JobConfig) -> list[float]:
    """Stops every `platform.spacing` along the row, within `reach.max_reach` of the cuts."""
    if not cut_xs:
        return []
    sp = cfg.platform.spacing
    lo = math.floor((min(cut_xs) - cfg.reach.max_reach) / sp)
    hi = math.ceil((max(cut_xs) + cfg.reach.max_reach) / sp)
    return [round(k * sp, 6) for k in range(lo, hi + 1)]


def choose_stops(reach: dict[str, dict[float, Any]]) -> list[float]:
    """The fewest stops covering every reachable pose: greedy set cover (each step the stop that
    reaches most of the poses left; ties to the one with the better-conditioned poses), sorted
    along the row."""
    left = {p for p, by_stop in reach.items() if by_stop}
    chosen: list[float] = []
    while left:
        counts: dict[float, tuple[int, float]] = {}
        for p in left:
            for s, r in reach[p].items():
                n, m = counts.get(s, (0, 0.0))
                counts[s] = (n + 1, m + r.manipulability)
        best = max(counts, key=lambda s: (counts[s], -abs(s)))
        chosen.append(best)
        left -= {p for p in left if best in reach[p]}
    return sorted(chosen)


def joint_time(a: Array, b: Array, vmax: Array) -> float:
    """A transit's time at full speed, ignoring acceleration: the slowest joint's."""
    return float(np.max(np.abs(np.asarray(b) - np.asarray(a)) / vmax))


def order_cuts(start: Array, items: list[CutReach], vmax: Array) -> list[CutReach]:
    """A short joint-space tour from `start` through the cuts and back: nearest neighbour, then
    2-opt."""
    if len(items) < 2:
        return list(items)
    nodes = [np.asarray(start, float)] + [r.q_pose for r in items]
    n = len(nodes)
    D = np.array([[joint_time(a, b, vmax) for b in nodes] for a in nodes])
    tour, left = [0], set(range(1, n))
    while left:
        nxt = min(left, key=lambda j: D[tour[-1], j])
        tour.append(nxt)
        left.remove(nxt)
    tour.append(0)
    improved = True
    while improved:
        improved = False
        for i in range(1, n - 1):
            for j in range(i + 1, n):
                a, b, c, d = tour[i - 1], tour[i], tour[j], tour[j + 1]
                if D[a, c] + D[b, d] < D[a, b] + D[c, d] - 1e-9:
                    tour[i : j + 1] = tour[i : j + 1][::-1]
                    improved = True
    return [items[k - 1] for k in tour[1:-1]]
