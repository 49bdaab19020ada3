"""Vine skeletons (branches as centre polylines with radii) and their tube meshes.

A skeleton is what the importers read from digitised plants and what the sample generator grows;
`tube_mesh` sweeps it into a closed triangle mesh whose triangles are kept close to equilateral
(ray casting slows down by an order of magnitude on long thin triangles along canes).
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from vinetwin.errors import InputError
from vinetwin.frames import Array

BranchKind = Literal["trunk", "cordon", "spur", "cane", "shoot", "branch"]
CapStyle = Literal["round", "flat"]


@dataclass
class Branch:
    """One woody axis: a centre polyline (N, 3) in metres with a radius (N,) at each point."""

    points: Array
    radii: Array
    kind: BranchKind = "branch"
    parent: int = -1
    """Index of the branch this one grows from (-1 for a root)."""
    label: str = ""
    """Free text, e.g. the source's key for imported axes."""
    nodes: Array = field(default_factory=lambda: np.zeros(0))
    """Arc positions (m, from the first point) of the nodes (buds) where the source knows them
    (the generator's canes, hydroshoot's shoots); empty when unknown (a scan)."""

    def __post_init__(self) -> None:
        self.points = np.asarray(self.points, dtype=np.float64).reshape(-1, 3)
        self.radii = np.asarray(self.radii, dtype=np.float64).reshape(-1)
        self.nodes = np.sort(np.asarray(self.nodes, dtype=np.float64).reshape(-1))
        if not np.all(np.isfinite(self.nodes)):
            raise InputError(f"branch '{self.label}': non-finite node position")
        if self.points.shape[0] != self.radii.shape[0]:
            raise InputError(
                f"branch '{self.label}': {self.points.shape[0]} points but {self.radii.shape[0]} radii"
            )
        if not (np.all(np.isfinite(self.points)) and np.all(np.isfinite(self.radii))):
            raise InputError(f"branch '{self.label}': non-finite point or radius")
        if np.any(self.radii <= 0):
            raise InputError(f"branch '{self.label}': radii must be positive")

    @property
    def length(self) -> float:
        return float(np.linalg.norm(np.diff(self.points, axis=0), axis=1).sum())


@dataclass
class CutCandidate:
    """A place where a pruner could cut: a point on a cane's axis and the cane direction there."""

    point: Array
    cane_axis: Array
    branch: int
    radius: float
    label: str = ""


@dataclass
class Skeleton:
    """Branches plus the cut-point candidates found on them."""

    branches: list[Branch] = field(default_factory=list)
    candidates: list[CutCandidate] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)
    """What an importer could not use, each with its line number (not saved with the twin)."""

    def bounds(self, inflate_by_radius: bool = True) -> Array:
        """(2, 3) min/max corner of all centre points, optionally grown by each point's radius."""
        pts = np.concatenate([b.points for b in self.branches])
        if not inflate_by_radius:
            return np.stack([pts.min(0), pts.max(0)])
        r = np.concatenate([b.radii for b in self.branches])[:, None]
        return np.stack([(pts - r).min(0), (pts + r).max(0)])

    def to_json(self) -> dict[str, Any]:
        return {
            "branches": [
                {
                    "kind": b.kind,
                    "parent": b.parent,
                    "label": b.label,
                    "points": np.round(b.points, 6).tolist(),
                    "radii": np.round(b.radii, 6).tolist(),
                    **({"nodes": np.round(b.nodes, 6).tolist()} if len(b.nodes) else {}),
                }
                for b in self.branches
            ],
            "candidates": [
                {
                    "point": np.round(c.point, 6).tolist(),
                    "cane_axis": np.round(c.cane_axis, 6).tolist(),
                    "branch": c.branch,
                    "radius": round(float(c.radius), 6),
                    "label": c.label,
                }
                for c in self.candidates
            ],
        }

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> Skeleton:
        branches = [
            Branch(
                points=np.asarray(b["points"]),
                radii=np.asarray(b["radii"]),
                kind=b.get("kind", "branch"),
                parent=int(b.get("parent", -1)),
                label=str(b.get("label", "")),
                nodes=np.asarray(b.get("nodes", []), dtype=np.float64),
            )
            for b in data.get("branches", [])
        ]
        cands = [
            CutCandidate(
                point=np.asarray(c["point"], dtype=np.float64),
                cane_axis=np.asarray(c["cane_axis"], dtype=np.float64),
                branch=int(c["branch"]),
                radius=float(c["radius"]),
                label=str(c.get("label", "")),
            )
            for c in data.get("candidates", [])
        ]
        return cls(branches, cands)

    def save(self, path: str | Path) -> None:
        Path(path).write_text(json.dumps(self.to_json(), separators=(",", ":")))

    @classmethod
    def load(cls, path: str | Path) -> Skeleton:
        return cls.from_json(json.loads(Path(path).read_text()))


# ---------------------------------------------------------------------------- polylines
def arc_length(points: Array) -> Array:
    """(N,) distance along a polyline (N, 3) from its first point."""
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])


def point_at(P: Array, arc: Array, s: Array | float) -> Array:
    """The points of the polyline `P` (arc lengths `arc`) at arc positions `s`: (3,) for one,
    (N, 3) for N."""
    return np.stack([np.interp(s, arc, P[:, d]) for d in range(3)], -1)


def resample(P: Array, R: Array, step: float = 0.002) -> tuple[Array, Array]:
    """A polyline and its radii at evenly spaced points at most `step` apart (ends kept)."""
    a = arc_length(P)
    n = max(2, int(np.ceil(a[-1] / step)) + 1)
    t = np.linspace(0.0, a[-1], n)
    return point_at(P, a, t), np.interp(t, a, R)


def nearest_on_polyline(p: Array, pts: Array) -> tuple[int, float, Array]:
    """The point of the polyline `pts` nearest p: its segment k, the fraction t along it, and
    the point (a one-point polyline: segment 0, t 0)."""
    if len(pts) == 1:
        return 0, 0.0, pts[0]
    a, ab = pts[:-1], np.diff(pts, axis=0)
    t = np.clip(np.einsum("ij,ij->i", p - a, ab) / np.maximum((ab * ab).sum(1), 1e-18), 0, 1)
    q = a + t[:, None] * ab
    k = int(np.argmin(np.linalg.norm(q - p, axis=1)))
    return k, float(t[k]), q[k]


#: Distance (m) between nodes (buds) of a dormant cane when the skeleton does not know them
#: (a scan): 5-9 cm on the generator's canes, 6-10 cm on the hydroshoot vines of
#: `../shared/data` (median 7.3 cm over their shoots).
DEFAULT_INTERNODE = 0.07
#: Where the first node sits on a cane, from its base (m): the generator's 1-2.5 cm.
FIRST_NODE = 0.0175


# ---------------------------------------------------------------------------- tips and paths
_EPS = 1e-3  # m: a child starting this close to its parent's end continues it


def children(sk: Skeleton) -> list[list[int]]:
    """For each branch, the indices of the branches hanging from it, in list order."""
    out: list[list[int]] = [[] for _ in sk.branches]
    for i, b in enumerate(sk.branches):
        if b.parent >= 0:
            out[b.parent].append(i)
    return out


def ancestors(sk: Skeleton, k: int) -> set[int]:
    """Branch `k` and the branches it hangs from."""
    out: set[int] = set()
    while k >= 0 and k not in out:
        out.add(k)
        k = sk.branches[k].parent
    return out


def children_on_axes(sk: Skeleton, parents: set[int] | None = None) -> None:
    """Each child (of `parents` only, when given) starts on its parent's axis, at the point
    nearest its second point: after the parent's axis moved (in place)."""
    for b in sk.branches:
        if b.parent >= 0 and len(b.points) >= 2 and (parents is None or b.parent in parents):
            b.points[0] = nearest_on_polyline(b.points[1], sk.branches[b.parent].points)[2]


def arc_of_nearest(p: Array, pts: Array, arc: Array) -> float:
    """Arc position of the point of the polyline `pts` nearest p."""
    k, t, _ = nearest_on_polyline(p, pts)
    return float(arc[k] + t * (arc[min(k + 1, len(arc) - 1)] - arc[k]))


def _attachments(sk: Skeleton) -> tuple[list[list[float]], list[float]]:
    """For each branch, the arc positions on it where children start; and each branch's
    position on its parent."""
    on: list[list[float]] = [[] for _ in sk.branches]
    at: list[float] = [0.0] * len(sk.branches)
    arcs = [arc_length(b.points) for b in sk.branches]
    for i, b in enumerate(sk.branches):
        p = b.parent
        if p < 0:
            continue
        at[i] = arc_of_nearest(b.points[0], sk.branches[p].points, arcs[p])
        on[p].append(at[i])
    return on, at


PERMANENT: tuple[BranchKind, ...] = ("trunk", "cordon")
"""A vine's permanent wood: cuts are never proposed on it, and a cane's path is followed back
to it."""


def tip_paths(sk: Skeleton, back_to: str = "fork") -> list[tuple[Array, Array, float, int]]:
    """Each tip's path back to its last fork (`back_to="fork"`) or to the permanent wood
    (`"permanent"`: the trunk or a cordon): (points from there to the tip, starting on the
    parent's axis; their radii; the radius of the wood it leaves; the tip's branch)."""
    on, at = _attachments(sk)
    arcs = [arc_length(b.points) for b in sk.branches]
    out = []
    for i, b in enumerate(sk.branches):
        L = arcs[i][-1]
        if any(s >= L - _EPS for s in on[i]):
            continue  # something grows from its end: not a tip
        if back_to == "permanent" and (b.kind in PERMANENT or b.parent < 0):
            continue
        pieces_p, pieces_r = [], []
        cur, pos = i, L
        fork_r = 0.0
        while True:
            s = arcs[cur]
            forks = [x for x in on[cur] if x < pos - _EPS] if back_to == "fork" else []
            lo = max(forks) if forks else 0.0
            keep = (s > lo) & (s <= pos + 1e-12)
            pts = sk.branches[cur].points
            rad = sk.branches[cur].radii
            p_lo = point_at(pts, s, lo)
            pieces_p.insert(0, np.vstack([p_lo, pts[keep]]))
            pieces_r.insert(0, np.concatenate([[np.interp(lo, s, rad)], rad[keep]]))
            if forks:
                fork_r = float(np.interp(lo, s, rad))
                break
            par = sk.branches[cur].parent
            if par < 0:
                break
            ppos = at[cur]
            if back_to == "fork":
                stop = not (ppos >= arcs[par][-1] - _EPS
                            and sum(1 for x in on[par] if x >= arcs[par][-1] - _EPS) == 1)  # fmt: skip
            else:
                stop = sk.branches[par].kind in PERMANENT or sk.branches[par].parent < 0
            if stop:  # the path starts where it leaves its parent, on the parent's axis
                pp = sk.branches[par].points
                fork_r = float(np.interp(ppos, arcs[par], sk.branches[par].radii))
                axis_pt = point_at(pp, arcs[par], ppos)
                pieces_p.insert(0, axis_pt[None, :])
                pieces_r.insert(0, np.array([fork_r]))
                break
            cur, pos = par, ppos
        P = np.vstack(pieces_p)
        R = np.concatenate(pieces_r)
        keep = np.ones(len(P), bool)
        keep[1:] = np.linalg.norm(np.diff(P, axis=0), axis=1) > 1e-9
        out.append((P[keep], R[keep], fork_r, i))
    return out


def axis_samples(
    sk: Skeleton, keep: Callable[[int], bool] | None = None, step: float = 0.002
) -> tuple[Array, Array]:
    """Points every `step` along the axes of the branches `keep` accepts (all by default), and
    their radii."""
    got = [resample(b.points, b.radii, step) for i, b in enumerate(sk.branches)
           if keep is None or keep(i)]  # fmt: skip
    if not got:
        return np.zeros((0, 3)), np.zeros(0)
    return np.vstack([p for p, _ in got]), np.concatenate([r for _, r in got])


def _surface_distance(pts: Array, rad: Array, P: Array, tree: Any = None) -> Array:
    """The distance of `P` from the surface of the wood whose axis samples are `pts` (the
    distance from an axis less its radius there; `tree`: their k-d tree, when built already);
    infinite without wood."""
    from scipy.spatial import cKDTree

    if not len(pts):
        return np.full(len(P), np.inf)
    d, i = (tree or cKDTree(pts)).query(P, k=min(8, len(pts)))
    d, i = d.reshape(len(P), -1), i.reshape(len(P), -1)
    return (d - rad[i]).min(axis=1)


def _permanent_standoff(sk: Skeleton) -> Callable[[Array], Array]:
    """How far points stand off the surface of the plant's permanent wood (trunk and cordons)."""
    from scipy.spatial import cKDTree

    pts, rad = axis_samples(
        sk, lambda i: sk.branches[i].kind in PERMANENT or sk.branches[i].parent < 0
    )
    tree = cKDTree(pts) if len(pts) else None  # one tree for every path
    return lambda P: _surface_distance(pts, rad, P, tree)


def _rest_standoff(sk: Skeleton) -> Callable[[Array], Array]:
    """How far a tip's path stands off the surface of the rest of the plant (all wood but the
    path itself: the branch it forks from, on both sides of the fork, and its siblings)."""
    pts, rad = axis_samples(sk)

    def surface(P: Array) -> Array:
        from scipy.spatial import cKDTree

        near = np.all((pts > P.min(0) - 0.15) & (pts < P.max(0) + 0.15), axis=1)
        own = cKDTree(resample(P, np.zeros(len(P)), 0.001)[0]).query(pts[near])[0] < 6e-4
        idx = np.nonzero(near)[0][~own]
        return _surface_distance(pts[idx], rad[idx], P)

    return surface


def standoff(sk: Skeleton, of: str) -> Callable[[Array], Array]:
    """How far points stand off the surface of the plant's wood: `of="permanent"`, the trunk and
    cordons (a vine's shoots are counted from there); `of="rest"`, all wood but the points' own
    path (a tip's path from its last fork: the branch it grows from and its siblings). Both are
    shape alone: they do not depend on where a skeleton happens to fork."""
    return _permanent_standoff(sk) if of == "permanent" else _rest_standoff(sk)


# ---------------------------------------------------------------------------- tube meshes
def _rotation_minimizing_frames(points: Array, tangents: Array) -> Array:
    """Normals (N, 3) of a rotation-minimising frame along a curve (double reflection)."""
    n = points.shape[0]
    t0 = tangents[0]
    helper = np.array([0.0, 0.0, 1.0]) if abs(t0[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    r = np.cross(t0, helper)
    r /= np.linalg.norm(r)
    normals = np.empty((n, 3))
    normals[0] = r
    for i in range(n - 1):
        v1 = points[i + 1] - points[i]
        c1 = v1 @ v1
        if c1 < 1e-24:
            normals[i + 1] = r
            continue
        rL = r - (2.0 / c1) * (v1 @ r) * v1
        tL = tangents[i] - (2.0 / c1) * (v1 @ tangents[i]) * v1
        v2 = tangents[i + 1] - tL
        c2 = v2 @ v2
        r = rL if c2 < 1e-24 else rL - (2.0 / c2) * (v2 @ rL) * v2
        r = r - (r @ tangents[i + 1]) * tangents[i + 1]
        r /= np.linalg.norm(r)
        normals[i + 1] = r
    return normals


def _segments_for(radius: float, edge: float, max_sagitta: float) -> int:
    m = math.ceil(2 * math.pi * radius / edge)
    # enough sides that the polygon stays within max_sagitta of the true circle
    if radius > max_sagitta:
        m = max(m, math.ceil(math.pi / math.acos(1.0 - max_sagitta / radius)))
    return int(min(max(m, 8), 96))


def _rings(
    points: Array, radii: Array, edge: float, max_sagitta: float
) -> tuple[int, Array, Array, int]:
    """A tube's vertices per ring, its points' arc lengths, their ring coordinate and its
    number of rings: ring spacing ~ the local circumferential edge * sqrt(3)/2 (equilateral)."""
    m = _segments_for(float(radii.max()), edge, max_sagitta)
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    r_mid = 0.5 * (radii[1:] + radii[:-1])
    h = np.maximum(2 * math.pi * r_mid / m * math.sqrt(3) / 2, 1e-4)
    u = np.concatenate([[0.0], np.cumsum(seg / h)])
    return m, s, u, max(2, math.ceil(u[-1]) + 1)


def _tube(
    points: Array,
    radii: Array,
    edge: float,
    caps: tuple[CapStyle, CapStyle],
    max_sagitta: float,
) -> tuple[Array, np.ndarray]:
    """Vertices and faces of one capped tube along a polyline."""
    # drop repeated points
    keep = np.ones(len(points), dtype=bool)
    keep[1:] = np.linalg.norm(np.diff(points, axis=0), axis=1) > 1e-9
    points, radii = points[keep], radii[keep]
    if len(points) < 2:
        raise InputError("a branch needs at least two distinct points")
    m, s, u, n_rings = _rings(points, radii, edge, max_sagitta)
    s_k = np.interp(np.linspace(0.0, u[-1], n_rings), u, s)
    P = np.column_stack([np.interp(s_k, s, points[:, i]) for i in range(3)])
    R = np.interp(s_k, s, radii)
    T = np.gradient(P, axis=0)
    T /= np.linalg.norm(T, axis=1, keepdims=True)
    N = _rotation_minimizing_frames(P, T)
    B = np.cross(T, N)
    k = np.arange(n_rings)[:, None]
    ang = 2 * math.pi * (np.arange(m)[None, :] + 0.5 * (k % 2)) / m
    ring = P[:, None, :] + R[:, None, None] * (
        np.cos(ang)[..., None] * N[:, None, :] + np.sin(ang)[..., None] * B[:, None, :]
    )
    verts = [ring.reshape(-1, 3)]
    faces = []
    j = np.arange(m)
    j1 = (j + 1) % m
    for kk in range(n_rings - 1):
        a, b = kk * m, (kk + 1) * m
        if kk % 2 == 0:  # next ring is shifted by +half a step
            faces.append(np.column_stack([a + j, a + j1, b + j]))
            faces.append(np.column_stack([b + j, a + j1, b + j1]))
        else:  # this ring is shifted; next is not
            faces.append(np.column_stack([a + j, a + j1, b + j1]))
            faces.append(np.column_stack([a + j, b + j1, b + j]))
    nv = n_rings * m
    extra_v: list[Array] = []

    def add_cap(end: int, style: CapStyle) -> None:
        nonlocal nv
        ring_start = 0 if end == 0 else (n_rings - 1) * m
        centre, radius = P[0 if end == 0 else -1], R[0 if end == 0 else -1]
        tangent = -T[0] if end == 0 else T[-1]
        ring_idx = ring_start + j
        base_ang = ang[0 if end == 0 else -1]
        if style == "round":
            n_lat = max(2, m // 4)
            prev = ring_idx
            for i in range(1, n_lat):
                phi = (math.pi / 2) * i / n_lat
                nrm = N[0 if end == 0 else -1]
                bin_ = B[0 if end == 0 else -1]
                pts = (
                    centre
                    + radius * math.sin(phi) * tangent
                    + radius
                    * math.cos(phi)
                    * (np.cos(base_ang)[:, None] * nrm + np.sin(base_ang)[:, None] * bin_)
                )
                idx = nv + j
                extra_v.append(pts)
                nv += m
                faces.append(_band(prev, idx, end))
                prev = idx
            apex = nv
            extra_v.append((centre + radius * tangent)[None, :])
            nv += 1
            faces.append(_fan(prev, apex, end))
        else:
            apex = nv
            extra_v.append(centre[None, :])
            nv += 1
            faces.append(_fan(ring_idx, apex, end))

    add_cap(0, caps[0])
    add_cap(1, caps[1])
    V = np.concatenate(verts + extra_v)
    F = np.concatenate(faces).astype(np.int64)
    return V, F


def _band(inner: np.ndarray, outer: np.ndarray, end: int) -> np.ndarray:
    """Quad strip between two aligned rings, wound outward for the given end."""
    m = len(inner)
    j1 = np.roll(np.arange(m), -1)
    a, b, c, d = inner, inner[j1], outer, outer[j1]
    if end == 1:
        return np.concatenate([np.column_stack([a, b, c]), np.column_stack([c, b, d])])
    return np.concatenate([np.column_stack([a, c, b]), np.column_stack([c, d, b])])


def _fan(ring: np.ndarray, apex: int, end: int) -> np.ndarray:
    j1 = np.roll(ring, -1)
    ap = np.full(len(ring), apex)
    if end == 1:
        return np.column_stack([ring, j1, ap])
    return np.column_stack([ring, ap, j1])


#: Tube mesh edge lengths accepted (m): finer runs out of memory on a whole vine, coarser loses
#: the canes' shape.
MIN_EDGE, MAX_EDGE = 0.0005, 0.05
#: Most vertices a tube mesh is made with (a measured nectarine's 351 branches at 3 mm: 1.1
#: million; a wrong skeleton of a whole row of Y-trellis apples ran past 22 GB unbounded).
MAX_TUBE_VERTICES = 30_000_000


def tube_mesh(
    skeleton: Skeleton | list[Branch],
    edge: float = 0.002,
    caps: CapStyle = "round",
    max_sagitta: float = 2e-4,
) -> tuple[Array, np.ndarray]:
    """Sweeps every branch into a closed tube; returns vertices (V, 3) and faces (F, 3).

    Args:
        skeleton: the branches (metres).
        edge: target triangle edge length, metres; rings hold about 2*pi*r/edge vertices.
        caps: "round" (hemispheres, a swept-sphere body) or "flat" ends.
        max_sagitta: the polygonal cross-section stays within this distance (m) of the circle.
    """
    if not (math.isfinite(edge) and MIN_EDGE <= edge <= MAX_EDGE):
        raise InputError(
            f"the mesh edge length must be between {MIN_EDGE} and {MAX_EDGE} m, got {edge}"
        )
    branches = skeleton.branches if isinstance(skeleton, Skeleton) else skeleton
    if not branches:
        raise InputError("the skeleton has no branches")
    n = 0  # vertices, counted before any is made: a wrong skeleton must not exhaust memory
    for b in branches:
        if len(b.points) >= 2:
            m, _, _, rings = _rings(b.points, np.maximum(b.radii, 0.0), edge, max_sagitta)
            n += m * rings
    if n > MAX_TUBE_VERTICES:
        r = np.concatenate([b.radii for b in branches])
        raise InputError(
            f"the tube mesh would have {n / 1e6:.0f} million vertices (at most "
            f"{MAX_TUBE_VERTICES / 1e6:.0f} million, a few GB): {len(branches)} branches, "
            f"radii {1000 * r.min():.2g}-{1000 * r.max():.3g} mm at a {1000 * edge:g} mm edge; "
            "look at the skeleton (a thin branch carrying a thick radius is meshed in fine rings) "
            "or choose a coarser edge"
        )
    vs, fs, off = [], [], 0
    for b in branches:
        V, F = _tube(b.points, b.radii, edge, (caps, caps), max_sagitta)
        vs.append(V)
        fs.append(F + off)
        off += len(V)
    return np.concatenate(vs), np.concatenate(fs)


def transform_skeleton(sk: Skeleton, T: Array) -> Skeleton:
    """The skeleton with its points mapped by the 4x4 `T` (rigid), in place; returned."""
    R, t = T[:3, :3], T[:3, 3]
    for b in sk.branches:
        b.points = b.points @ R.T + t
    for c in sk.candidates:
        c.point = R @ c.point + t
        c.cane_axis = R @ c.cane_axis
    return sk
