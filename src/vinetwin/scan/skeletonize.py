"""A plant's skeleton from its scan: level sets of the geodesic distance from the trunk's foot.

Method (the level-set skeleton of Verroust and Lazarus 2000, as TreeQSM-like and plant
phenotyping tools use it), chosen over Laplacian contraction (pc-skeletor, which needs
robust_laplacian and a mesh-like density, minutes on 500k points, and collapses crossing canes)
and over a 3D thinning of a voxel grid (breaks at 1-3 cm gaps and doubled surfaces):

1. The points are thinned to one per voxel (`SkeletonConfig.voxel`) and joined to their
   neighbours within 2.5 voxels (a graph; a doubled surface a few millimetres apart joins into
   one).
2. Pieces are joined across gaps up to `SkeletonConfig.gap` (a minimum spanning tree of the
   pieces, scipy); what stays apart is reported as stray.
3. Dijkstra's geodesic distance from the trunk's foot (the lowest 2 cm of the plant when the up
   axis is known; else the end of the plant whose branch is thickest); the points are sliced by
   that distance (`bin`), each slice's connected clusters become nodes, each node's parent is
   the node its first point's shortest path comes from: a tree, by construction.
4. Side branches shorter than `min_branch` plus the parent's radius are junction noise and are
   dropped; chains become branches, a side branch starting on its parent's axis.
5. Each node's centre and radius: a circle fitted to its points (all points, not the thinned
   ones) in the plane across the branch, when the fit is sound; else the centroid and the
   median distance.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt
from scipy import sparse
from scipy.sparse import csgraph
from scipy.spatial import cKDTree

from vinetwin.errors import ScanError
from vinetwin.frames import Array
from vinetwin.scan.config import PlantKind, SkeletonConfig
from vinetwin.scan.refine import circle_fit, median5, refine_axes
from vinetwin.scan.unzip import unzip_forks
from vinetwin.twin.skeleton import Branch, Skeleton, children, nearest_on_polyline


@dataclass
class SkeletonResult:
    skeleton: Skeleton
    voxel: float
    bin: float
    stray_points: int
    """Points in pieces that no gap up to `gap` joins to the plant (left out of the skeleton)."""
    bridges: int
    """Gaps bridged between pieces of the plant."""
    stray_mask: npt.NDArray[np.bool_] = field(default_factory=lambda: np.zeros(0, bool))
    """(N,) True for the input points left out as stray."""
    up: Array | None = None
    """The plant's up direction found from its shape (when the up axis was not given)."""
    up_from: str = ""
    up_trusted: bool = True
    """False when the trunk's direction did not confirm `up` (found or not)."""
    """What `up` was found from."""


def voxel_thin(points: Array, voxel: float) -> tuple[Array, np.ndarray]:
    """One point per occupied voxel (the mean of its points), and each input point's voxel."""
    key = np.floor((points - points.min(0)) / voxel).astype(np.int64)
    span = key.max(0) + 1
    flat = (key[:, 0] * span[1] + key[:, 1]) * span[2] + key[:, 2]
    _, inv, counts = np.unique(flat, return_inverse=True, return_counts=True)
    inv = inv.reshape(-1)
    sums = np.zeros((len(counts), 3))
    np.add.at(sums, inv, points)
    return sums / counts[:, None], inv


def radius_graph(P: Array, radius: float) -> sparse.csr_matrix:
    """The symmetric graph joining points within `radius`, weighted by their distance."""
    pairs = cKDTree(P).query_pairs(radius, output_type="ndarray")
    w = np.linalg.norm(P[pairs[:, 0]] - P[pairs[:, 1]], axis=1) + 1e-9
    n = len(P)
    g = sparse.coo_matrix((w, (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    return (g + g.T).tocsr()


def _bridge(
    P: Array, g: sparse.csr_matrix, gap: float, min_piece: int = 1
) -> tuple[sparse.csr_matrix, int, npt.NDArray[np.bool_]]:
    """Joins pieces closer than `gap` (minimum spanning tree over the pieces; only pieces of at
    least `min_piece` points); returns the graph, the number of bridges and the mask of points
    in the plant's piece."""
    ncomp, lab = csgraph.connected_components(g, directed=False)
    if ncomp == 1:
        return g, 0, np.ones(len(P), bool)
    sizes = np.bincount(lab, minlength=ncomp)
    # representatives: one point per (gap/3) cell and piece, so the search stays small
    cell = np.floor((P - P.min(0)) / (gap / 3)).astype(np.int64)
    key = np.column_stack([cell, lab])
    _, first = np.unique(key, axis=0, return_index=True)
    reps = np.sort(first)
    reps = reps[sizes[lab[reps]] >= min_piece]
    pairs = cKDTree(P[reps]).query_pairs(gap, output_type="ndarray")
    a, b = reps[pairs[:, 0]], reps[pairs[:, 1]]
    other = lab[a] != lab[b]
    a, b = a[other], b[other]
    bridges = 0
    if len(a):
        d = np.linalg.norm(P[a] - P[b], axis=1)
        la, lb = np.minimum(lab[a], lab[b]), np.maximum(lab[a], lab[b])
        order = np.lexsort((d, lb, la))
        a, b, d, la, lb = a[order], b[order], d[order], la[order], lb[order]
        keep = np.ones(len(a), bool)
        keep[1:] = (la[1:] != la[:-1]) | (lb[1:] != lb[:-1])
        a, b, d, la, lb = a[keep], b[keep], d[keep], la[keep], lb[keep]
        cg = sparse.coo_matrix((d + 1e-9, (la, lb)), shape=(ncomp, ncomp))
        mst = csgraph.minimum_spanning_tree(cg).tocoo()
        chosen = {(int(i), int(j)) for i, j in zip(mst.row, mst.col, strict=True)}
        sel = np.array([(int(x), int(y)) in chosen for x, y in zip(la, lb, strict=True)], bool)
        a, b, d = a[sel], b[sel], d[sel]
        bridges = len(a)
        n = len(P)
        extra = sparse.coo_matrix((d + 1e-9, (a, b)), shape=(n, n))
        g = (g + extra + extra.T).tocsr()
    _, lab = csgraph.connected_components(g, directed=False)
    main = np.bincount(lab).argmax()
    return g, bridges, lab == main


TRUST_TRUNK = 30.0
"""Degrees: the trunk's direction is the plant's up when within this of the foot-to-mass
direction (measured: 0.2-2 degrees from the truth on the generated, hydroshoot and apple
plants, where the mass lay 2-9 degrees off; the hydroshoot GDC vine's trunk leans 13-24)."""

REVERSED = 120.0
"""Degrees: the up found from the foot (its trunk's direction, or the plant's mass over it) is
taken for reversed when it lies farther than this from the axis of the plant's thickest
stretch (`thickest_stretch`), a cue that does not depend on which end was taken for the foot;
the stretch's axis is then taken when the plant's mass lies within `TO_MASS` of it (on a
Tree-Models-Library apple the thickest end was a crown tip's, and its scan stood upside down).
Nearer than this, the stretch does not overrule the foot: it can run into a Y-trellis' arm and
point down it (measured on 26 scans of 13 trees and 6 of the vines without ground: the
stretch's axis within 1-38 degrees of the truth, but 138 degrees from it on a Y-trellis)."""

TO_MASS = 45.0
"""Degrees: the thickest stretch's axis is taken for up when the direction from its middle to
the plant's mass lies within this of it."""

THICK_SHARE = 0.6
"""The thickest stretch: the nodes along the thickest node's chain at least this share of its
radius."""

BIN_VOXELS: dict[PlantKind, float] = {"vine": 4.0, "tree": 3.0}
"""The slice width in voxels when `SkeletonConfig.bin` is 0. A tree's laterals are short and
leave thick limbs close together: thinner slices part them nearer their fork (measured on five
Tree-Models-Library trees at the realistic quality: completeness +0.4 to +2.7 points at 3
voxels, precision within 0.3 points). On the vines 3 voxels also gives a slightly more complete
skeleton, but moves where the short arms and cordons are told from the trunk, and the cut
candidates with them (`docs/scans.md`)."""


def skeletonize(
    points: Array,
    cfg: SkeletonConfig,
    spacing: float,
    up: Array | None = None,
    plant: PlantKind = "vine",
) -> SkeletonResult:
    """The skeleton of a cleaned plant scan in metres (see the module's docstring); `up` is
    the unit up vector when known. Raises ScanError when the points make no tree."""
    voxel = cfg.voxel or float(np.clip(spacing, 0.003, 0.03))
    binw = cfg.bin or BIN_VOXELS[plant] * voxel
    P, inv = voxel_thin(points, voxel)
    if len(P) < 20:
        raise ScanError(f"only {len(P)} voxels of {voxel * 1000:.3g} mm: too little for a plant")
    g = radius_graph(P, 2.5 * voxel)
    g, bridges, on_plant = _bridge(P, g, max(cfg.gap, 6 * voxel))
    if not on_plant.all():  # pieces of some size (a twig, not a stray) across wider gaps
        g, more, on_plant = _bridge(P, g, max(2 * cfg.gap, 12 * voxel), min_piece=10)
        bridges += more
    idx = np.flatnonzero(on_plant)
    P, g = P[idx], g[idx][:, idx]
    remap = np.full(len(on_plant), -1)
    remap[idx] = np.arange(len(idx))
    inv = remap[inv]
    stray_mask = inv < 0
    found_up, up_from, up_trusted = None, "", True
    if up is not None:
        h = P @ up
        sources = np.flatnonzero(h <= h.min() + 0.02)
        tree = _level_tree(P, g, sources, binw, points, inv, cfg, voxel)
    else:
        # first from one end of the plant, then from the end whose branch is thickest
        d0 = csgraph.dijkstra(g, indices=0)
        far = int(np.argmax(np.where(np.isfinite(d0), d0, -1)))
        tree = _level_tree(P, g, np.array([far]), binw, points, inv, cfg, voxel)
        root_pts = tree.thickest_end_points()
        tree = _level_tree(P, g, root_pts, binw, points, inv, cfg, voxel)
        found_up, up_from, up_trusted = tree.up_direction()
    sk = tree.skeleton()
    if plant == "vine":  # canes of one spur running side by side (see `scan.unzip`)
        unzip_forks(sk, points[~stray_mask], float(np.clip(0.5 * voxel, 0.0015, 0.004)))
    refine_axes(sk, points[~stray_mask], cfg.refine)  # forks' leaning centres (`scan.refine`)
    if not sk.branches:
        raise ScanError("no skeleton could be found: the scan holds no branching plant")
    return SkeletonResult(sk, voxel, binw, int(stray_mask.sum()), bridges, stray_mask, found_up,
                          up_from, up_trusted)  # fmt: skip


class _LevelTree:
    """Nodes (clusters of a geodesic slice) with their parent, centre, radius and points."""

    def __init__(self, parent: np.ndarray, centre: Array, radius: Array, reach: Array,
                 geo_min: Array, members: list[np.ndarray], P: Array) -> None:  # fmt: skip
        self.parent, self.centre, self.radius = parent, centre, radius
        self.reach, self.geo_min, self.members, self.P = reach, geo_min, members, P
        n = len(parent)
        self.children: list[list[int]] = [[] for _ in range(n)]
        for c in range(n):
            if parent[c] >= 0:
                self.children[parent[c]].append(c)
        self.roots = [c for c in range(n) if parent[c] < 0]
        self.end_window = 0.1
        """How far from an end its thickness is measured (m)."""
        self._chains: list[tuple[list[int], int]] | None = None

    def _ahead(self, k: int, steps: int = 3) -> Array:
        """The centre a few nodes down k's farthest-reaching path."""
        for _ in range(steps):
            if not self.children[k]:
                break
            k = max(self.children[k], key=lambda j: self.reach[j])
        return self.centre[k]

    def _start_radius(self, k: int) -> float:
        """The median radius of nodes 2-4 down k's farthest-reaching path (the first node,
        still part of the junction, left out)."""
        rs = []
        for _ in range(4):
            rs.append(self.radius[k])
            if not self.children[k]:
                break
            k = max(self.children[k], key=lambda j: self.reach[j])
        return float(np.median(rs[1:] if len(rs) > 1 else rs))

    def chains(self) -> list[tuple[list[int], int]]:
        """Branches as node chains: (nodes, index of the parent chain or -1). At a fork the
        thickest child heading on most nearly in the chain's direction continues it (the score
        radius * (1 + cos angle) / 2: a cordon continues a trunk rather than a cane rising from
        its head, and runs on to its own end past its last spur's cane); the others start new
        chains. Found once: the foot, the up axis and the skeleton all ask (the tree does not
        change after it is built)."""
        if self._chains is not None:
            return self._chains
        out: list[tuple[list[int], int]] = []
        stack = [(r, -1) for r in self.roots]
        while stack:
            start, pchain = stack.pop()
            chain, c = [start], start
            me = len(out)
            while self.children[c]:
                kids = self.children[c]
                nxt = kids[0]
                if len(kids) > 1:
                    back = self.centre[chain[max(0, len(chain) - 4)]]
                    d_in = self.centre[c] - back
                    n_in = float(np.linalg.norm(d_in))
                    best_score = -1.0
                    for k in kids:
                        d = self._ahead(k) - self.centre[c]
                        cos = (
                            float(d @ d_in / max(np.linalg.norm(d) * n_in, 1e-12))
                            if n_in > 1e-9
                            else 1.0
                        )
                        score = self._start_radius(k) * (1.0 + cos) / 2
                        if score > best_score:
                            nxt, best_score = k, score
                    for k in kids:
                        if k != nxt:
                            stack.append((k, me))
                c = nxt
                chain.append(c)
            out.append((chain, pchain))
        self._chains = out
        return out

    def thickest_end_points(self) -> np.ndarray:
        """Points of the end node whose chain's first 10 cm is thickest (the trunk's foot)."""
        best, best_r = None, -1.0
        for chain, _ in self.chains():
            for end in (chain[-1],) + ((chain[0],) if self.parent[chain[0]] < 0 else ()):
                nodes = chain[::-1] if end == chain[-1] else chain
                c0 = self.centre[end]
                near = [k for k in nodes if np.linalg.norm(self.centre[k] - c0) < self.end_window]
                r = float(np.median(self.radius[near]))
                if r > best_r:
                    best, best_r = end, r
        assert best is not None
        return self.members[best]

    def _root_chain(self) -> list[int]:
        return next(c for c, p in self.chains() if p < 0)

    def root_direction(self, chain: list[int] | None = None) -> Array:
        """The trunk's direction: the principal axis of the root chain's centres from 2 cm above
        its foot up to where its heading over 10 cm turns by 30 degrees from its first 10 cm's
        (at most 0.6 m; a Y-trellis' arms leave at 45), pointing away from the foot. Positions
        along it are the slices' geodesic distances, not the centres' own path, which zigzags
        where a thick trunk's thin slices are seen from two sides."""
        chain = chain or self._root_chain()
        C = self.centre[chain]
        g = self.geo_min[chain] - self.geo_min[chain[0]]

        def at(x: float) -> Array:
            return C[min(len(C) - 1, int(np.searchsorted(g, x)))]

        first = at(0.12) - at(0.02)
        keep = []
        for i in range(len(C)):
            if g[i] > 0.6:
                break
            d = C[i] - at(g[i] - 0.1)
            if g[i] > 0.15 and d @ first < 0.85 * np.linalg.norm(d) * np.linalg.norm(first):
                break
            if g[i] >= 0.02:
                keep.append(i)
        Q = C[keep]
        if len(Q) < 2:
            raise ScanError("the trunk's direction could not be found; name --up")
        ax = np.linalg.eigh(np.cov((Q - Q.mean(0)).T))[1][:, -1]
        return ax if ax @ (Q[-1] - Q[0]) > 0 else -ax

    def up_direction(self) -> tuple[Array, str, bool]:
        """The plant's up direction, what it was found from, and whether the trunk confirmed
        it: the trunk's direction
        (`root_direction`) when it lies within `TRUST_TRUNK` degrees of the direction from the
        foot to the plant's mass (the mean of its voxels: a plant stands over its foot); else
        that direction (a short, thick trunk's slices zigzag and its own direction is not
        trusted: on the Tree-Models-Library's nectarine the trunk gave 46-64 degrees off, the
        mass 13-15); either checked against the axis of the plant's thickest stretch, which does
        not depend on the foot (`REVERSED`)."""
        chain = self._root_chain()
        mass = self.P.mean(0) - self.centre[chain[0]]
        mass /= max(float(np.linalg.norm(mass)), 1e-12)
        try:
            trunk = self.root_direction(chain)
        except ScanError:
            return self._checked(mass, "the plant's mass over its foot (the trunk's direction "
                                       "not found)", False)  # fmt: skip
        off = float(np.degrees(np.arccos(np.clip(trunk @ mass, -1.0, 1.0))))
        if off <= TRUST_TRUNK:
            return self._checked(trunk, "the trunk's direction", True)
        return self._checked(mass, (f"the plant's mass over its foot (the trunk's direction, "
                                    f"{off:.0f} degrees from it, not trusted)"), False)  # fmt: skip

    def _checked(self, up: Array, what: str, trusted: bool) -> tuple[Array, str, bool]:
        """`up` found from the foot, unless the thickest stretch says it is reversed
        (`REVERSED`)."""
        stretch = self.thickest_stretch()
        if stretch is None:
            return up, what, trusted
        axis, to_mass = stretch
        off = float(np.degrees(np.arccos(np.clip(up @ axis, -1.0, 1.0))))
        if off <= REVERSED or to_mass > TO_MASS:
            return up, what, trusted
        return axis, (f"the axis of the plant's thickest stretch, towards its mass ({what}: "
                      f"{off:.0f} degrees from it, the foot in doubt)"), False  # fmt: skip

    def thickest_stretch(self) -> tuple[Array, float] | None:
        """The principal axis of the plant's thickest stretch (on a plant, its trunk): the run
        of nodes along the thickest node's chain at least `THICK_SHARE` of its radius (each a
        median of 5 along the chain, `median5`), pointing from its middle towards the plant's mass, and
        the angle (degrees) between the two; None when the run has fewer than 3 nodes."""
        best: tuple[float, list[int]] | None = None
        for chain, _ in self.chains():
            med = median5(self.radius[chain])
            i = int(np.argmax(med))
            if best is None or med[i] > best[0]:
                lo, hi = i, i
                while lo > 0 and med[lo - 1] >= THICK_SHARE * med[i]:
                    lo -= 1
                while hi < len(chain) - 1 and med[hi + 1] >= THICK_SHARE * med[i]:
                    hi += 1
                best = (float(med[i]), chain[lo : hi + 1])
        if best is None or len(best[1]) < 3:
            return None
        Q = self.centre[best[1]]
        axis = np.linalg.eigh(np.cov((Q - Q.mean(0)).T))[1][:, -1]
        to_mass = self.P.mean(0) - Q.mean(0)
        if axis @ to_mass < 0:
            axis = -axis
        cos = float(axis @ to_mass / max(float(np.linalg.norm(to_mass)), 1e-12))
        return axis, float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))

    def skeleton(self) -> Skeleton:
        sk = Skeleton()
        chains = self.chains()
        index: dict[int, int] = {}
        for ci, (chain, pchain) in enumerate(chains):
            pts = self.centre[chain]
            rad = self.radius[chain]
            if len(pts) >= 5:  # a junction's node leans towards the side branch: median of 5
                med = median5(pts)
                med[0], med[-1] = pts[0], pts[-1]
                pts = med
            if len(pts) >= 3:  # smooth the centre line, ends kept
                sm = pts.copy()
                sm[1:-1] = (pts[:-2] + 2 * pts[1:-1] + pts[2:]) / 4
                pts = sm
            if len(rad) >= 5:
                rad = median5(rad)
            # extend the tip to the farthest point of the last node
            tip_pts = self.P[self.members[chain[-1]]]
            if len(pts) >= 2:
                t = pts[-1] - pts[-2]
                t /= max(np.linalg.norm(t), 1e-9)
                ext = float(np.max((tip_pts - pts[-1]) @ t)) - float(rad[-1])
                if ext > 1e-3:
                    pts = np.vstack([pts, pts[-1] + ext * t])
                    rad = np.append(rad, rad[-1])
            parent = -1
            if pchain >= 0 and pchain in index:
                parent = index[pchain]
                ppts = sk.branches[parent].points
                pprad = sk.branches[parent].radii
                k, t, start = nearest_on_polyline(pts[0], ppts)
                r_at = float(pprad[k] + t * (pprad[min(k + 1, len(pprad) - 1)] - pprad[k]))
                if np.linalg.norm(start - pts[0]) > 1e-6:
                    pts = np.vstack([start, pts])
                    rad = np.concatenate([[min(rad[0], r_at)], rad])
            if len(pts) < 2:
                continue
            index[ci] = len(sk.branches)
            sk.branches.append(
                Branch(pts, np.maximum(rad, 5e-4), kind="branch", parent=parent, label=f"b{ci}")
            )
        return merge_slivers(sk)


def _dist_to_polyline(Q: Array, P: Array) -> Array:
    """Distance of each point of Q to the polyline P."""
    if len(P) == 1:
        return np.linalg.norm(Q - P[0], axis=1)
    a, b = P[:-1], P[1:]
    ab = b - a
    den = np.maximum((ab * ab).sum(1), 1e-18)
    t = np.clip(np.einsum("qsk,sk->qs", Q[:, None, :] - a[None], ab) / den, 0, 1)
    proj = a[None] + t[..., None] * ab[None]
    return np.linalg.norm(proj - Q[:, None, :], axis=2).min(1)


def merge_slivers(sk: Skeleton) -> Skeleton:
    """Where an occluded branch's slices split in two for a while (its front and back seen,
    not its top), the skeleton holds two parallel pieces: one continues the branch and one
    hangs from it. A piece lying within 1.5 radii (at least 5 mm) of another is a sliver:
    a branch's tail that runs along one of its children is replaced by that child (the child
    continues the branch); a childless side piece running along its parent is dropped."""
    # pairs already found not to be slivers, by identity (held, so that an id is not reused):
    # each change restarts the scan, which then skips them (quadratic otherwise on large trees)
    kept: set[tuple[object, ...]] = set()
    held: list[Branch] = []
    changed = True
    while changed:
        changed = False
        kids = children(sk)
        for i, b in enumerate(sk.branches):
            for c in kids[i]:
                child = sk.branches[c]
                # what the test below depends on: the two, whether c has children, c's siblings
                key = (id(b), id(child), bool(kids[c]), tuple(id(sk.branches[o]) for o in kids[i]))
                if key in kept:
                    continue
                tol = max(1.5 * float(np.median(b.radii)), 0.005)
                k = int(np.argmin(np.linalg.norm(b.points - child.points[0], axis=1)))
                tail = b.points[k:]
                if len(tail) < 2 or len(child.points) < 2:
                    continue
                if not kids[c] and np.all(_dist_to_polyline(child.points[1:], b.points) <= tol):
                    _drop(sk, c)  # a side sliver
                    changed = True
                    break
                others = [o for o in kids[i] if o != c and
                          np.linalg.norm(b.points[k:] - sk.branches[o].points[0], axis=1).min() < 1e-9]  # fmt: skip
                if (not others and child.length > _length(tail)
                        and np.all(_dist_to_polyline(tail[1:], child.points) <= tol)):  # fmt: skip
                    _continue_with(sk, i, k, c)
                    changed = True
                    break
                kept.add(key)
                held += [b, child]
            if changed:
                break
    return sk


def _length(P: Array) -> float:
    return float(np.linalg.norm(np.diff(P, axis=0), axis=1).sum())


def _drop(sk: Skeleton, c: int) -> None:
    del sk.branches[c]
    for b in sk.branches:
        if b.parent > c:
            b.parent -= 1


def _continue_with(sk: Skeleton, i: int, k: int, c: int) -> None:
    """Branch i keeps its points up to k and continues along child c; c's children move to i."""
    b, child = sk.branches[i], sk.branches[c]
    pts = np.vstack([b.points[: k + 1], child.points[1:]])
    rad = np.concatenate([b.radii[: k + 1], child.radii[1:]])
    sk.branches[i] = Branch(pts, rad, kind=b.kind, parent=b.parent, label=b.label)
    for o in sk.branches:
        if o.parent == c:
            o.parent = i
    _drop(sk, c)


def _level_tree(
    P: Array,
    g: sparse.csr_matrix,
    sources: np.ndarray,
    binw: float,
    points: Array,
    inv: np.ndarray,
    cfg: SkeletonConfig,
    voxel: float,
) -> _LevelTree:
    geo, pred, _ = csgraph.dijkstra(g, indices=sources, min_only=True, return_predecessors=True)
    ok = np.isfinite(geo)
    geo = np.where(ok, geo, np.inf)
    b = np.floor(np.where(ok, geo, 0) / binw).astype(np.int64)
    coo = sparse.triu(g, k=1).tocoo()
    same = (b[coo.row] == b[coo.col]) & ok[coo.row] & ok[coo.col]
    n = len(P)
    sg = sparse.coo_matrix((np.ones(same.sum()), (coo.row[same], coo.col[same])), shape=(n, n))
    ncl, lab = csgraph.connected_components(sg, directed=False)
    lab = np.where(ok, lab, -1)
    # each cluster's first point (least geodesic distance) and where its path comes from
    order = np.lexsort((geo, lab))
    order = order[lab[order] >= 0]
    first = np.ones(len(order), bool)
    first[1:] = lab[order][1:] != lab[order][:-1]
    firsts = order[first]
    cl_ids = lab[firsts]
    parent = np.full(ncl, -1)
    pp = pred[firsts]
    has = pp >= 0
    parent[cl_ids[has]] = lab[pp[has]]
    geo_min = np.full(ncl, np.inf)
    geo_min[cl_ids] = geo[firsts]
    geo_max = np.full(ncl, -np.inf)
    np.maximum.at(geo_max, lab[ok], geo[ok])
    # reach: the farthest geodesic distance below each cluster
    reach = geo_max.copy()
    for c in np.argsort(-geo_min):
        p = parent[c]
        if p >= 0 and reach[c] > reach[p]:
            reach[p] = reach[c]
    # members (thinned points) and their centroid
    members = [np.empty(0, np.int64)] * ncl
    srt = np.argsort(lab, kind="stable")
    srt = srt[lab[srt] >= 0]
    bounds = np.searchsorted(lab[srt], np.arange(ncl + 1))
    for c in range(ncl):
        members[c] = srt[bounds[c] : bounds[c + 1]]
    centroid = np.array([P[m].mean(0) if len(m) else np.zeros(3) for m in members])
    # junction noise: a side branch reaching less than min_branch + the parent's radius past
    # the fork's slice. The radius is the smaller of the fork's slice and the slice below it:
    # the fork's slice also holds the side branches' bases and is wider than the parent (three
    # 1 cm stubs leaving a 1 cm limb together: 2.0-2.2 cm against 1.6 cm below)
    rough_r = np.array([
        float(np.median(np.linalg.norm(P[m] - centroid[c], axis=1))) if len(m) else 0.0
        for c, m in enumerate(members)
    ])  # fmt: skip
    alive = np.ones(ncl, bool)
    kids: list[list[int]] = [[] for _ in range(ncl)]
    for c in range(ncl):
        if parent[c] >= 0:
            kids[parent[c]].append(c)
    for c in range(ncl):
        if len(kids[c]) > 1:
            main = max(kids[c], key=lambda k: reach[k])
            r_c = min(rough_r[c], rough_r[parent[c]]) if parent[c] >= 0 else rough_r[c]
            for k in kids[c]:
                if k != main and reach[k] - geo_max[c] < cfg.min_branch + r_c:
                    alive[k] = False
    # a dropped cluster drops its subtree
    for c in np.argsort(geo_min):
        if parent[c] >= 0 and not alive[parent[c]]:
            alive[c] = False
    keep = np.flatnonzero(alive)
    new = np.full(ncl, -1)
    new[keep] = np.arange(len(keep))
    parent_k = np.where(parent[keep] >= 0, new[np.maximum(parent[keep], 0)], -1)
    # centres and radii from the original points of each node
    lab_orig = np.where(inv >= 0, lab[np.maximum(inv, 0)], -1)
    srt_o = np.argsort(lab_orig, kind="stable")
    lo = lab_orig[srt_o]
    bo = np.searchsorted(lo, np.arange(ncl + 1))
    rng = np.random.default_rng(0)
    centre = np.empty((len(keep), 3))
    radius = np.empty(len(keep))
    kids_k: list[list[int]] = [[] for _ in range(len(keep))]
    for i in range(len(keep)):
        if parent_k[i] >= 0:
            kids_k[parent_k[i]].append(i)
    for i, c in enumerate(keep):
        pts = points[srt_o[bo[c] : bo[c + 1]]]
        if len(pts) > 400:
            pts = pts[rng.choice(len(pts), 400, replace=False)]
        if len(pts) == 0:
            pts = P[members[c]]
        a = centroid[parent[c]] if parent_k[i] >= 0 else centroid[c]
        nxt = [keep[k] for k in kids_k[i]]
        z = centroid[max(nxt, key=lambda k: reach[k])] if nxt else centroid[c]
        t = z - a
        if np.linalg.norm(t) < 1e-6:
            t = centroid[c] - a
        if np.linalg.norm(t) < 1e-6:
            t = np.array([0.0, 0.0, 1.0])
        centre[i], radius[i] = circle_fit(pts, centroid[c], t / np.linalg.norm(t))
    tree = _LevelTree(parent_k, centre, radius, reach[keep], geo_min[keep],
                      [members[c] for c in keep], P)  # fmt: skip
    tree.end_window = max(0.1, 3 * binw)
    return tree
