"""Compiled nearest-neighbour search of ICP (numba): the reference's k-d tree (`NNTree`, flat
arrays, median splits, leaves of 8 points), built once per reference, its exact closest-point
queries (memoised within a registration: a point that moved less than the margin by which its
partner was closest keeps its partner without a search), the projective index of a reference
seen from a known camera (`ProjectiveIndex`: a pair from the cells around a point's projection),
and `associate`, which pairs a whole cloud. The registration levels are in `_kernels`."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from vinetwin._numba import nb

LEAF_SIZE = 8


class NNTree:
    """The reference points in a k-d tree (flat arrays, built once), for exact closest-point
    queries within a distance. `points` are the input points reordered; `order` maps back."""

    def __init__(self, points: np.ndarray) -> None:
        pts = np.ascontiguousarray(points, dtype=np.float64)
        order, split_dim, split_val, child, lo, hi = _build_tree(pts, LEAF_SIZE)
        self.order = order
        self.points = np.ascontiguousarray(pts[order])
        self.split_dim = split_dim
        self.split_val = split_val
        self.child = child
        self.lo = lo
        self.hi = hi

    @property
    def arrays(self) -> tuple[np.ndarray, ...]:
        """What the kernels take: (points, split_dim, split_val, child, lo, hi)."""
        return (self.points, self.split_dim, self.split_val, self.child, self.lo, self.hi)


@nb.njit(cache=True)
def _build_tree(
    pts: np.ndarray, leaf: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Median split on the widest axis until a node holds at most `leaf` points. Node arrays:
    split dimension (-1 for a leaf), split value, first child (the second is child + 1), and
    the leaf's range [lo, hi) in `order`."""
    n = pts.shape[0]
    cap = 2 * (n // max(leaf // 2, 1) + 1) + 1
    order = np.arange(n)
    split_dim = np.full(cap, -1, np.int64)
    split_val = np.zeros(cap)
    child = np.full(cap, -1, np.int64)
    lo = np.zeros(cap, np.int64)
    hi = np.zeros(cap, np.int64)
    stack = np.empty(cap, np.int64)
    lo[0], hi[0] = 0, n
    count = 1
    top = 0
    stack[0] = 0
    while top >= 0:
        node = stack[top]
        top -= 1
        a, b = lo[node], hi[node]
        if b - a <= leaf:
            continue
        idx = order[a:b]
        sub = pts[idx]
        ext = np.empty(3)
        for d in range(3):
            ext[d] = sub[:, d].max() - sub[:, d].min()
        d = int(np.argmax(ext))
        srt = np.argsort(sub[:, d])
        order[a:b] = idx[srt]
        mid = a + (b - a) // 2
        split_dim[node] = d
        split_val[node] = pts[order[mid], d]
        child[node] = count
        lo[count], hi[count] = a, mid
        lo[count + 1], hi[count + 1] = mid, b
        top += 1
        stack[top] = count
        top += 1
        stack[top] = count + 1
        count += 2
    return (
        order,
        split_dim[:count].copy(),
        split_val[:count].copy(),
        child[:count].copy(),
        lo[:count].copy(),
        hi[:count].copy(),
    )


@nb.njit(cache=True, nogil=True, inline="always")
def _search(
    q: np.ndarray, tree: Any, dmax: float, stack: np.ndarray, bound: np.ndarray, two: bool
) -> tuple[int, float, float]:
    """Index (into the tree's points) and squared distance of the closest point within dmax,
    (-1, inf) when none; with `two`, also the squared distance of the second closest within
    dmax (dmax^2 when there is none: every other reference point is at least that far from
    q), else dmax^2. `tree` is `NNTree.arrays`."""
    pts, split_dim, split_val, child, lo, hi = tree
    best = -1
    best_d2 = dmax * dmax
    second_d2 = dmax * dmax
    limit = best_d2  # what a branch must beat: the closest so far, or with `two` the second
    top = 0
    stack[0] = 0
    bound[0] = 0.0
    while top >= 0:
        node = stack[top]
        if bound[top] > limit:
            top -= 1
            continue
        top -= 1
        d = split_dim[node]
        if d < 0:
            for m in range(lo[node], hi[node]):
                dx = pts[m, 0] - q[0]
                dy = pts[m, 1] - q[1]
                dz = pts[m, 2] - q[2]
                d2 = dx * dx + dy * dy + dz * dz
                if d2 <= best_d2:
                    if two and best >= 0:
                        second_d2 = best_d2
                    best_d2 = d2
                    best = m
                elif two and d2 < second_d2:
                    second_d2 = d2
            limit = second_d2 if two else best_d2
            continue
        diff = q[d] - split_val[node]
        near = child[node] if diff < 0 else child[node] + 1
        far = child[node] + 1 if diff < 0 else child[node]
        # push the far side first so the near side is searched first
        top += 1
        stack[top] = far
        bound[top] = diff * diff
        top += 1
        stack[top] = near
        bound[top] = 0.0
    if best < 0:
        return -1, np.inf, second_d2
    return best, best_d2, second_d2


@nb.njit(cache=True, nogil=True)
def _nearest(
    q: np.ndarray, tree: Any, dmax: float, stack: np.ndarray, bound: np.ndarray
) -> tuple[int, float]:
    """Index (into the tree's points) and squared distance of the closest point within dmax;
    (-1, inf) when none. `tree` is `NNTree.arrays`."""
    j, d2, _ = _search(q, tree, dmax, stack, bound, False)
    return j, d2


class ProjectiveIndex:
    """The reference points binned by where they project in the reference camera's image, for
    projective association: a current point, placed in the reference camera frame, is projected
    into that image and paired with the closest reference point in the cells around its pixel
    (`window` cells each side) within the correspondence distance. O(1) per point, no tree.

    Not the exact closest point: a partner farther sideways than the window reaches is not
    found (the window is sized by `cell`, the reference's point spacing, so at the final level,
    whose pairs are a few millimetres long, nearly all are); along the ray nothing is missed.
    `points` must be the tree's points (the indices are the tree's)."""

    def __init__(
        self,
        points: np.ndarray,
        fx: float,
        fy: float,
        cx: float,
        cy: float,
        width: int,
        height: int,
        spacing: float,
        window: int = 1,
    ) -> None:
        pts = np.ascontiguousarray(points, dtype=np.float64)
        z = pts[:, 2][pts[:, 2] > 0]
        zref = float(np.median(z)) if len(z) else 1.0
        # one cell: the point spacing at the reference's median depth, in pixels
        self.scale = max(1.0, spacing * fx / zref)
        wc = math.ceil(width / self.scale) + 1
        hc = math.ceil(height / self.scale) + 1
        self.params = np.array([fx, fy, cx, cy, 1.0 / self.scale, wc, hc, window], np.float64)
        self.start, self.items = _bin_points(pts, self.params)
        self.cell_points = np.ascontiguousarray(pts[self.items])

    @property
    def arrays(self) -> tuple[np.ndarray, ...]:
        """What the kernels take: (cell start, items, points in cell order, params)."""
        return (self.start, self.items, self.cell_points, self.params)


#: What the kernels take instead of a `ProjectiveIndex` for tree association.
NO_PROJECTIVE = (np.zeros(1, np.int64), np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0))


def new_memo(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """An empty memo of the tree's answers for n points (`_associate_range`)."""
    return (np.full(n, -1, np.int64), np.zeros((n, 3)), np.zeros(n))


#: No memo: every point searched (`_associate_range`).
NO_MEMO = new_memo(0)


@nb.njit(cache=True, nogil=True, inline="always")
def _cell_of(p: np.ndarray, prm: np.ndarray) -> tuple[int, int]:
    """The image cell (column, row) a camera-frame point projects to; (-1, -1) behind it."""
    if p[2] <= 0.0:
        return -1, -1
    u = (prm[0] * p[0] / p[2] + prm[2]) * prm[4]
    v = (prm[1] * p[1] / p[2] + prm[3]) * prm[4]
    return math.floor(u), math.floor(v)


@nb.njit(cache=True, nogil=True)
def _bin_points(pts: np.ndarray, prm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """CSR of the points per image cell (points outside the image go to its border cells)."""
    wc, hc = int(prm[5]), int(prm[6])
    n = pts.shape[0]
    cell = np.full(n, -1, np.int64)
    count = np.zeros(wc * hc + 1, np.int64)
    for i in range(n):
        if pts[i, 2] <= 0.0:
            continue
        cu, cv = _cell_of(pts[i], prm)
        cu = min(max(cu, 0), wc - 1)
        cv = min(max(cv, 0), hc - 1)
        cell[i] = cv * wc + cu
        count[cell[i] + 1] += 1
    for c in range(wc * hc):
        count[c + 1] += count[c]
    fill = count[:-1].copy()
    items = np.empty(count[wc * hc], np.int64)
    for i in range(n):
        if cell[i] >= 0:
            items[fill[cell[i]]] = i
            fill[cell[i]] += 1
    return count, items


@nb.njit(cache=True, nogil=True)
def _nearest_projective(
    q: np.ndarray, pts: np.ndarray, proj: Any, dmax: float
) -> tuple[int, float]:
    """The closest reference point within dmax among those binned in the window of cells
    around q's projection; (-1, inf) when none. The points are stored in cell order, so each
    row of the window is one contiguous run."""
    start, items, cpts, prm = proj
    wc, hc, w = int(prm[5]), int(prm[6]), int(prm[7])
    cu, cv = _cell_of(q, prm)
    if q[2] <= 0.0 or cu < -w or cv < -w or cu >= wc + w or cv >= hc + w:
        return -1, np.inf
    best = -1
    best_d2 = dmax * dmax
    c0, c1 = max(cu - w, 0), min(cu + w + 1, wc)
    for r in range(max(cv - w, 0), min(cv + w + 1, hc)):
        for j in range(start[r * wc + c0], start[r * wc + c1]):
            dx = cpts[j, 0] - q[0]
            dy = cpts[j, 1] - q[1]
            dz = cpts[j, 2] - q[2]
            d2 = dx * dx + dy * dy + dz * dz
            if d2 <= best_d2:
                best_d2 = d2
                best = j
    if best < 0:
        return -1, np.inf
    return items[best], best_d2


@nb.njit(cache=True, nogil=True)
def _associate_range(
    src: np.ndarray,
    T: np.ndarray,
    tree: Any,
    dmax: float,
    i0: int,
    i1: int,
    q: np.ndarray,
    idx: np.ndarray,
    d2: np.ndarray,
    proj: Any,
    memo: Any,
) -> None:
    """Points i0..i1: transformed by T, then paired by the tree, or by projection when `proj`
    is a `ProjectiveIndex`'s arrays (empty params: the tree). `memo`, (partner, where, gap)
    with a row per point (empty: none), keeps the tree's last answer for each point: its
    partner, where the point was then, and the distance of the second closest reference point
    then. A point that has moved less since than the margin by which its partner was closest
    keeps its partner without a search (the same, exact answer: every other reference point
    is still farther), else it is searched again; late iterations move points by hundredths
    of a millimetre, so most skip the tree."""
    stack = np.empty(128, np.int64)
    bound = np.empty(128)
    projective = proj[3].shape[0] > 0
    partner, where, gap = memo
    memoised = gap.shape[0] > 0
    pts = tree[0]
    for i in range(i0, i1):
        for a in range(3):
            q[i, a] = T[a, 0] * src[i, 0] + T[a, 1] * src[i, 1] + T[a, 2] * src[i, 2] + T[a, 3]
        if projective:
            idx[i], d2[i] = _nearest_projective(q[i], pts, proj, dmax)
        elif memoised:
            c = partner[i]
            if c >= 0:
                mx = q[i, 0] - where[i, 0]
                my = q[i, 1] - where[i, 1]
                mz = q[i, 2] - where[i, 2]
                margin = gap[i] - math.sqrt(mx * mx + my * my + mz * mz)
                dx = pts[c, 0] - q[i, 0]
                dy = pts[c, 1] - q[i, 1]
                dz = pts[c, 2] - q[i, 2]
                dd = dx * dx + dy * dy + dz * dz
                if margin > 0.0 and dd < margin * margin:  # still the closest
                    if dd <= dmax * dmax:
                        idx[i], d2[i] = c, dd
                    else:
                        idx[i], d2[i] = -1, np.inf
                    continue
            j, dj, second = _search(q[i], tree, dmax, stack, bound, True)
            idx[i], d2[i] = j, dj
            partner[i] = j
            gap[i] = math.sqrt(second)
            for a in range(3):
                where[i, a] = q[i, a]
        else:
            idx[i], d2[i] = _nearest(q[i], tree, dmax, stack, bound)


@nb.njit(cache=True, nogil=True)
def _buffers(
    src: np.ndarray, threads: int
) -> tuple[int, np.ndarray, np.ndarray, np.ndarray, int, int]:
    """Output arrays of an association and its split: (n, q, idx, d2, chunks, chunk size); one
    chunk per thread above 256 points."""
    n = src.shape[0]
    chunks = max(threads, 1) if n > 256 else 1
    return (
        n,
        np.empty((n, 3)),
        np.empty(n, np.int64),
        np.empty(n),
        chunks,
        (n + chunks - 1) // chunks,
    )


@nb.njit(cache=True, nogil=True, parallel=True)
def associate(
    src: np.ndarray, T: np.ndarray, tree: Any, dmax: float, threads: int, memo: Any
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Transforms src by T and finds each point's closest reference point within dmax.
    Returns (transformed points, tree-order reference index or -1, squared distance or inf).
    Split in one chunk per thread above 256 points. `memo`: `NO_MEMO`, or the memo a
    registration of the same `src` against the same tree left (`_associate_range`)."""
    n, q, idx, d2, chunks, size = _buffers(src, threads)
    proj = (np.zeros(1, np.int64), np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0))
    for c in nb.prange(chunks):
        _associate_range(
            src, T, tree, dmax, c * size, min(n, (c + 1) * size), q, idx, d2, proj, memo
        )
    return q, idx, d2
