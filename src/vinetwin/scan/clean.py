"""Cleaning a scan before its skeleton: stray points, the ground, ground clutter (grass, weeds),
trellis wires, posts.

Each step returns a mask of the points it removes, so the importer can count them, report them
and write them out to be looked at; each is switchable (`CleanConfig`)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy import sparse
from scipy.sparse import csgraph
from scipy.spatial import cKDTree

from vinetwin.frames import Array

Mask = npt.NDArray[np.bool_]


def statistical_strays(points: Array, neighbours: int, std: float) -> Mask:
    """(N,) True for points whose mean distance to their `neighbours` nearest is more than
    `std` deviations above the scan's mean (Open3D's statistical outlier removal)."""
    from vinetwin import _lazy

    o3d = _lazy.open3d()

    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    _, keep = pc.remove_statistical_outlier(nb_neighbors=neighbours, std_ratio=std)
    mask = np.ones(len(points), bool)
    mask[np.asarray(keep, dtype=np.int64)] = False
    return mask


@dataclass
class Ground:
    mask: Mask
    """(N,) True for the ground's points."""
    normal: Array
    """Unit normal, pointing to the plant's side."""
    offset: float
    """The plane is {p : normal . p = offset}."""


def find_ground(points: Array, spacing: float, rng: np.random.Generator) -> Ground | None:
    """A plane under the plant: at least 10% of the points within a threshold of it, spread
    over at least half the scan's width, and 97% of the other points on one side of it. A
    vertical canopy (a VSP vine's canes) has the plant on both sides and is not taken."""
    from vinetwin import _lazy

    o3d = _lazy.open3d()

    sample = points if len(points) <= 200_000 else points[rng.choice(len(points), 200_000, False)]
    thr = float(np.clip(3 * spacing, 0.01, 0.05))
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(sample))
    o3d.utility.random.seed(int(rng.integers(2**31)))
    (a, b, c, d), inl = pc.segment_plane(distance_threshold=thr, ransac_n=3, num_iterations=1000)
    n = np.array([a, b, c])
    nn = float(np.linalg.norm(n))
    if nn < 1e-9 or len(inl) < 0.1 * len(sample):
        return None
    n, off = n / nn, -d / nn
    dist = points @ n - off
    on = np.abs(dist) <= thr
    rest = dist[~on]
    if len(rest) < 100:
        return None
    above = float((rest > 0).mean())
    if max(above, 1 - above) < 0.97:
        return None
    if above < 0.5:
        n, off, dist = -n, -off, -dist
    flat = points[on]
    u = np.cross(n, [1.0, 0, 0] if abs(n[0]) < 0.9 else [0, 1.0, 0])
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    width = max(np.ptp(flat @ u), np.ptp(flat @ v))
    other = points[~on]
    scan_width = max(np.ptp(other @ u), np.ptp(other @ v), 1e-6)
    if width < 0.5 * scan_width:
        return None
    # everything at or below the plane (plus the band) is ground
    return Ground(dist <= thr, n, off)


#: Ground clutter (grass, weeds, prunings on the ground): every point below `CLUTTER_HEIGHT`
#: (m) above the ground but the columns of what reaches above it (a trunk, a post), each
#: followed down from its ring just above, in layers of `CLUTTER_LAYER` (m), within its
#: radius and `CLUTTER_MARGIN` (a trunk leans; grass touching it stays out). A vine's head
#: stands 0.4 m up or more, an orchard tree's first limb higher; a cane hanging lower than
#: this loses its end. Without it, 400 grass blades 6-20 cm tall around a generated vine's
#: foot became 230 trunks, the foot moved onto a blade and 13% of the skeleton lay on the vine.
CLUTTER_HEIGHT = 0.3
CLUTTER_LAYER = 0.02
#: A column holds what lies within its ring's radius and this (m) of its centre.
CLUTTER_MARGIN = 0.015
#: Points of one ring are joined within this many voxels.
CLUTTER_LINK = 2.5


def find_clutter(points: Array, up: Array, ground_offset: float, spacing: float) -> Mask:
    """(N,) True for ground clutter (see `CLUTTER_HEIGHT`); `up` the ground's normal, the ground
    {p : up . p = ground_offset}."""
    from vinetwin.scan.skeletonize import radius_graph, voxel_thin

    h = points @ up - ground_offset
    low = np.flatnonzero(h < CLUTTER_HEIGHT)
    mask = np.zeros(len(points), bool)
    slab = (h >= CLUTTER_HEIGHT) & (h < CLUTTER_HEIGHT + CLUTTER_LAYER)
    if not len(low) or not slab.any():
        return mask  # nothing stands above the band: no plant to tell the clutter from
    mask[low] = True
    flat = points[low] - np.outer(points[low] @ up, up)
    hl = h[low]
    voxel = max(spacing, 0.004)
    S, _ = voxel_thin(points[slab], voxel)
    _, lab = csgraph.connected_components(radius_graph(S, CLUTTER_LINK * voxel), directed=False)
    S = S - np.outer(S @ up, up)
    layer = np.floor((CLUTTER_HEIGHT - hl) / CLUTTER_LAYER).astype(np.int64)
    order = np.argsort(layer, kind="stable")
    starts = np.searchsorted(layer[order], np.arange(layer.max() + 2))
    for piece in range(lab.max() + 1):
        ring = S[lab == piece]
        centre = np.median(ring, 0)
        reach = float(np.median(np.linalg.norm(ring - centre, axis=1))) + CLUTTER_MARGIN
        for k in range(len(starts) - 1):
            idx = order[starts[k] : starts[k + 1]]
            idx = idx[np.linalg.norm(flat[idx] - centre, axis=1) < reach]
            if not len(idx):
                break
            mask[low[idx]] = False
            centre = np.median(flat[idx], 0)
    return mask


def find_wires(points: Array, up: Array, spacing: float, rng: np.random.Generator) -> Mask:
    """(N,) True for points of trellis wires: straight lines of points within 10 degrees of
    horizontal, thin (nothing but the wire within `WIRE_CLEAR` of it) along at least 1 m, half of
    its 5 cm slices at least, where the wire may pass through wood for up to
    `WIRE_THROUGH_WOOD` at a time (the trunk, a spur, the cordon lying on it: there the wood's
    points stay). A line that is no wire (a straight cane) is passed over and the search goes
    on, `WIRE_MISSES` times at most."""
    from vinetwin.scan.skeletonize import voxel_thin

    mask = np.zeros(len(points), bool)
    tol = float(np.clip(2 * spacing, 0.004, 0.01))
    P, _ = voxel_thin(points, max(spacing, 0.005))
    P = P[_horizontal_lines(P, up)]  # a wire is a few hundred of 100k points: look among these
    passed = np.zeros(len(P), bool)  # near lines tried that were no wire
    misses = 0
    for _ in range(8):  # lines tried at most
        live = ~passed & (~_near_any(P, points[mask], tol) if mask.any() else True)
        if live.sum() < 50:
            break
        line = _best_line(P[live], up, tol, rng)
        if line is None:
            break
        c, t = line
        along, off = _along_and_off(points, c, t)
        inl = off <= tol
        if inl.sum() < 30:
            break
        s0 = np.floor(along / WIRE_SLICE).astype(np.int64)
        wide = off <= WIRE_CLEAR
        lo = s0[wide].min()
        n_in = np.bincount(s0[inl] - lo, minlength=s0[wide].max() - lo + 1)
        n_wide = np.bincount(s0[wide] - lo, minlength=len(n_in))
        thin_slice = (n_in > 0) & (n_wide <= 1.3 * n_in + 2)
        if _longest_run(thin_slice, round(WIRE_THROUGH_WOOD / WIRE_SLICE)) * WIRE_SLICE < 1.0:
            passed |= _along_and_off(P, c, t)[1] <= tol
            misses += 1
            if misses > WIRE_MISSES:
                break
            continue
        mask |= inl & thin_slice[np.clip(s0 - lo, 0, len(thin_slice) - 1)] & wide
    return mask


#: Lines that are no wire passed over before the search ends (each costs a RANSAC: on the
#: 500k-point dense vine without a trellis, trying up to 8 made the stage 1.5 s slower).
WIRE_MISSES = 2
#: A wire is looked at in slices this long (m) along it.
WIRE_SLICE = 0.05
#: A slice of a line is thin (a wire's) when no more than its own points lie within this (m) of
#: it. A cordon often runs beside its wire, 2-3 cm above it, for a metre: at 3 cm the scans of
#: three generated vines no setting was chosen on (seeds 41-43, their wire at the trunk's top)
#: kept their wire, as a cane with cut candidates on it; at 1.5 cm all three were found.
WIRE_CLEAR = 0.015
#: A wire may pass through wood (the trunk, a spur, the cordon lying on it) for this long (m)
#: at a time and run on: on the dense generated vine's scan with a trellis, the cordon on the
#: wire broke its thin slices every 25-80 cm for 10 cm, and the wire was kept (precision
#: 90.6% against 99.9% without the trellis).
WIRE_THROUGH_WOOD = 0.15


def _along_and_off(X: Array, c: Array, t: Array) -> tuple[Array, Array]:
    """Each point's position along the line (c, unit t) and its distance from it."""
    d = X - c
    along = d @ t
    return along, np.linalg.norm(d - along[:, None] * t, axis=1)


def _longest_run(thin: Mask, gap: int) -> int:
    """The longest run (in slices, first thin slice to last) whose thin slices are broken by
    no more than `gap` slices that are not, and at least half of which are thin."""
    best = 0
    start = last = -1
    n = 0
    for k, x in enumerate(thin):
        if not x:
            continue
        if last < 0 or k - last - 1 > gap:
            start, n = k, 0
        last, n = k, n + 1
        span = last - start + 1
        if 2 * n >= span:
            best = max(best, span)
    return best


def _horizontal_lines(P: Array, up: Array, k: int = 12) -> Mask:
    """(N,) True where P's neighbourhood is a line (the largest of its spread's eigenvalues
    over 90% of their sum) within 15 degrees of horizontal: where a wire can be."""
    if len(P) < k + 1:
        return np.zeros(len(P), bool)
    _, idx = cKDTree(P).query(P, k=k)
    Q = P[idx] - P[idx].mean(1, keepdims=True)
    C = np.einsum("nki,nkj->nij", Q, Q)
    ev, evec = np.linalg.eigh(C)
    lin = ev[:, 2] / np.maximum(ev.sum(1), 1e-18)
    horiz = np.abs(evec[:, :, 2] @ up) < np.sin(np.radians(15))
    return (lin > 0.9) & horiz


def _near_any(P: Array, Q: Array, r: float) -> Mask:
    if len(Q) == 0:
        return np.zeros(len(P), bool)
    d, _ = cKDTree(Q).query(P, k=1, distance_upper_bound=r)
    return np.isfinite(d)


def _best_line(
    P: Array, up: Array, tol: float, rng: np.random.Generator
) -> tuple[Array, Array] | None:
    """The horizontal line through two of P's points with the most points within `tol`,
    spanning at least 1 m (RANSAC over 3000 pairs)."""
    i = rng.integers(len(P), size=6000)
    j = rng.integers(len(P), size=6000)
    d = P[j] - P[i]
    L = np.linalg.norm(d, axis=1)
    ok = (L > 0.5) & (np.abs(d @ up) < math.sin(math.radians(10)) * np.maximum(L, 1e-9))
    i, d, L = i[ok][:3000], d[ok][:3000], L[ok][:3000]
    if len(i) == 0:
        return None
    t = d / L[:, None]
    best, best_n = None, 0
    sub = P if len(P) <= 20_000 else P[rng.choice(len(P), 20_000, False)]
    for k0 in range(0, len(i), 200):
        c = P[i[k0 : k0 + 200]]
        tt = t[k0 : k0 + 200]
        q = sub[None, :, :] - c[:, None, :]
        a = np.einsum("mnk,mk->mn", q, tt)
        off2 = np.einsum("mnk,mnk->mn", q, q) - a * a
        inl = off2 <= tol * tol
        counts = inl.sum(1)
        m = int(np.argmax(counts))
        if counts[m] > best_n:
            span = np.ptp(a[m][inl[m]]) if counts[m] > 1 else 0.0
            if span >= 1.0:
                best, best_n = (c[m], tt[m]), int(counts[m])
    return best


def find_posts(points: Array, up: Array, voxel: float) -> Mask:
    """(N,) True for points of posts: pieces apart from the rest that are straight
    (linearity > 0.9), at least 1 m long and within 15 degrees of vertical. The largest piece
    that is not a post is the plant; when every large piece looks like a post, the largest
    stays."""
    from vinetwin.scan.skeletonize import voxel_thin

    P, inv = voxel_thin(points, voxel)
    pairs = cKDTree(P).query_pairs(2.5 * voxel, output_type="ndarray")
    n = len(P)
    g = sparse.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    ncomp, lab = csgraph.connected_components(g, directed=False)
    sizes = np.bincount(lab, minlength=ncomp)
    mask_v = np.zeros(n, bool)
    posts = []
    for c in np.flatnonzero(sizes >= 20):
        Q = P[lab == c]
        ev, evec = np.linalg.eigh(np.cov((Q - Q.mean(0)).T))
        axis = evec[:, -1]
        lin = (math.sqrt(max(ev[-1], 0)) - math.sqrt(max(ev[-2], 0))) / max(math.sqrt(ev[-1]), 1e-9)
        length = float(np.ptp(Q @ axis))
        if lin > 0.9 - 1e-9 and length >= 1.0 and abs(axis @ up) >= math.cos(math.radians(15)):
            posts.append(int(c))
    others = [c for c in np.flatnonzero(sizes >= 20) if c not in posts]
    if posts and not others:
        posts.remove(max(posts, key=lambda c: sizes[c]))
    mask_v[np.isin(lab, posts)] = True
    return mask_v[inv]
