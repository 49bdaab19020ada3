"""Compiled outlier rules of the perception chain (`vinetwin.cloud`): the mean distance to the
k nearest neighbours (statistical rule) and the neighbour counts within a radius (radius rule),
over a hash grid of cells."""

from __future__ import annotations

import math

import numpy as np

from vinetwin._cloud_kernels import _hash3
from vinetwin._numba import nb


@nb.njit(cache=True, nogil=True)
def _cell_key(ix: np.int64, iy: np.int64, iz: np.int64) -> np.int64:
    off = np.int64(1) << 20
    return ((ix + off) << 42) | ((iy + off) << 21) | (iz + off)


@nb.njit(cache=True, nogil=True, inline="always")
def _run_of(
    ix: np.int64, iy: np.int64, iz: np.int64, table: np.ndarray, runkey: np.ndarray, mask: np.int64
) -> int:
    """The run (of points sorted by cell) of grid cell (ix, iy, iz); -1 when it is empty."""
    key = _cell_key(ix, iy, iz)
    h = _hash3(ix, iy, iz, mask)
    while table[h] != -1:
        if runkey[table[h]] == key:
            return int(table[h])
        h = (h + 1) & mask
    return -1


@nb.njit(cache=True, nogil=True, inline="always")
def _gap(d: int, lo: float, hi: float, cell: float) -> float:
    """Distance along one axis from a point to the cell `d` cells away (0: its own), given
    the point's distances `lo` and `hi` to its own cell's faces."""
    if d == 0:
        return 0.0
    return (-d - 1) * cell + lo if d < 0 else (d - 1) * cell + hi


@nb.njit(cache=True, nogil=True)
def _cell_runs(
    points: np.ndarray, cell: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.int64, np.ndarray, int]:
    """The points binned in grid cells of side `cell`: each point's cell (ci), the points
    grouped by cell (order, sorted_pts; cells in order of first occurrence, a cell's points in
    input order), the runs of one cell each (starts, runkey) and a hash table from a cell to its
    run (`_run_of`). Returns (ci, order, starts, runkey, table, mask, sorted_pts, number of
    runs). A counting sort through the table: an argsort of the cell keys took 0.8-1.2 ms for
    12k points, most of the radius rule's time."""
    n = points.shape[0]
    inv = 1.0 / cell
    ci = np.empty((n, 3), np.int64)
    run = np.empty(n, np.int64)
    cap = 16
    while cap < 2 * n:
        cap *= 2
    mask = np.int64(cap - 1)
    table = np.full(cap, -1, np.int64)
    runkey = np.empty(n, np.int64)
    starts = np.zeros(n + 1, np.int64)
    nr = 0
    for i in range(n):
        ix = np.int64(np.floor(points[i, 0] * inv))
        iy = np.int64(np.floor(points[i, 1] * inv))
        iz = np.int64(np.floor(points[i, 2] * inv))
        ci[i, 0], ci[i, 1], ci[i, 2] = ix, iy, iz
        key = _cell_key(ix, iy, iz)
        h = _hash3(ix, iy, iz, mask)
        while True:
            r = table[h]
            if r == -1:
                r = nr
                nr += 1
                table[h] = r
                runkey[r] = key
                break
            if runkey[r] == key:
                break
            h = (h + 1) & mask
        run[i] = r
        starts[r + 1] += 1
    for r in range(nr):
        starts[r + 1] += starts[r]
    fill = starts[:nr].copy()
    order = np.empty(n, np.int64)
    sorted_pts = np.empty((n, 3))
    for i in range(n):
        j = fill[run[i]]
        fill[run[i]] += 1
        order[j] = i
        sorted_pts[j, 0], sorted_pts[j, 1], sorted_pts[j, 2] = (
            points[i, 0],
            points[i, 1],
            points[i, 2],
        )
    return ci, order, starts, runkey, table, mask, sorted_pts, nr


@nb.njit(cache=True, nogil=True)
def knn_mean_distance(
    points: np.ndarray, k: int, cell: float, rings: int, threads: int
) -> np.ndarray:
    """Mean distance from each point to its k nearest points (itself included, at 0), exact,
    by a search of grid cells of side `cell`: cell by cell, the points of the 27 cells around it
    are gathered once and each of its points selects its k nearest among them (`_knn_cell`); a
    point whose k-th distance might reach past them is searched alone in growing rings (after
    ring r every point closer than r * cell has been seen). NaN where `rings` rings were not
    enough (the caller finishes those with a k-d tree).
    `threads`: numba's thread count (passed in: a kernel that asks numba cannot be cached)."""
    n = points.shape[0]
    ci, order, starts, runkey, table, mask, sorted_pts, nr = _cell_runs(points, cell)
    out = np.empty(n)
    chunks = max(1, min(threads * 4, nr // 64))
    size = (nr + chunks - 1) // chunks
    for chunk in nb.prange(chunks):
        best = np.empty(k)  # ascending squared distances, one buffer per chunk
        cand = np.empty((256, 3))
        dist = np.empty(256)
        for r in range(chunk * size, min(nr, (chunk + 1) * size)):
            cand, dist = _knn_cell(
                points, r, k, cell, rings, ci, order, starts, runkey, table, mask, sorted_pts,
                best, cand, dist, out,
            )  # fmt: skip
    return out


@nb.njit(cache=True, nogil=True)
def _knn_cell(
    points: np.ndarray,
    r: int,
    k: int,
    cell: float,
    rings: int,
    ci: np.ndarray,
    order: np.ndarray,
    starts: np.ndarray,
    runkey: np.ndarray,
    table: np.ndarray,
    mask: np.int64,
    sorted_pts: np.ndarray,
    best: np.ndarray,
    cand: np.ndarray,
    dist: np.ndarray,
    out: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """`knn_mean_distance` for the points of one cell (run r): the points of the 27 cells
    around it are gathered once into `cand` (grown as needed, returned) and each point of the
    cell scans them; a point whose k-th neighbour might lie beyond those cells (farther than
    one cell plus its distance to its own cell's faces) is searched alone in growing rings
    (`_knn_one`). Exact either way."""
    j0 = order[starts[r]]
    cx_, cy_, cz_ = ci[j0, 0], ci[j0, 1], ci[j0, 2]
    m = 0
    for dx in range(-1, 2):
        for dy in range(-1, 2):
            for dz in range(-1, 2):
                rr = _run_of(cx_ + dx, cy_ + dy, cz_ + dz, table, runkey, mask)
                if rr < 0:
                    continue
                add = starts[rr + 1] - starts[rr]
                if m + add > cand.shape[0]:
                    grown = np.empty((2 * (m + add), 3))
                    grown[:m] = cand[:m]
                    cand = grown
                for j in range(starts[rr], starts[rr + 1]):
                    cand[m, 0] = sorted_pts[j, 0]
                    cand[m, 1] = sorted_pts[j, 1]
                    cand[m, 2] = sorted_pts[j, 2]
                    m += 1
    if dist.shape[0] < m:
        dist = np.empty(2 * m)
    tau = np.inf  # squared distance below which a point's k nearest are expected
    for jj in range(starts[r], starts[r + 1]):
        i = order[jj]
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        # keep (branch-free) the candidates within tau: when k of them are, the k nearest of
        # all are among them; otherwise select among all
        kept = 0
        for c in range(m):
            ex = cand[c, 0] - px
            ey = cand[c, 1] - py
            ez = cand[c, 2] - pz
            d2 = ex * ex + ey * ey + ez * ez
            dist[kept] = d2
            kept += d2 <= tau
        if kept < k:
            for c in range(m):
                ex = cand[c, 0] - px
                ey = cand[c, 1] - py
                ez = cand[c, 2] - pz
                dist[c] = ex * ex + ey * ey + ez * ez
            kept = m
        kth = np.inf
        if kept >= k:
            _select(dist, kept, k - 1)  # the k smallest first, the k-th at k - 1
            kth = dist[k - 1]
            tau = 1.5 * kth  # the next point of the cell: about as dense around
        inner = min(
            px - cx_ * cell, (cx_ + 1) * cell - px,
            py - cy_ * cell, (cy_ + 1) * cell - py,
            pz - cz_ * cell, (cz_ + 1) * cell - pz,
        )  # fmt: skip
        reach = cell + inner  # every point not gathered lies farther than this
        if kth <= reach * reach:
            acc = 0.0
            for a in range(k):
                acc += math.sqrt(dist[a])
            out[i] = acc / k
        else:
            _knn_one(
                points, i, k, cell, rings, ci, starts, runkey, table, mask, sorted_pts, best, out
            )
    return cand, dist


@nb.njit(cache=True, nogil=True)
def _select(a: np.ndarray, m: int, nth: int) -> None:
    """Reorders a[:m] in place so that a[nth] is the value a sort would put there, with no
    larger value before it and no smaller one after it (quickselect, median of three)."""
    lo, hi = 0, m - 1
    while hi > lo:
        mid = (lo + hi) // 2
        if a[mid] < a[lo]:
            a[mid], a[lo] = a[lo], a[mid]
        if a[hi] < a[lo]:
            a[hi], a[lo] = a[lo], a[hi]
        if a[hi] < a[mid]:
            a[hi], a[mid] = a[mid], a[hi]
        pivot = a[mid]
        i, j = lo, hi
        while i <= j:
            while a[i] < pivot:
                i += 1
            while a[j] > pivot:
                j -= 1
            if i <= j:
                a[i], a[j] = a[j], a[i]
                i += 1
                j -= 1
        if nth <= j:
            hi = j
        elif nth >= i:
            lo = i
        else:
            return


@nb.njit(cache=True, nogil=True)
def _knn_one(
    points: np.ndarray,
    i: int,
    k: int,
    cell: float,
    rings: int,
    ci: np.ndarray,
    starts: np.ndarray,
    runkey: np.ndarray,
    table: np.ndarray,
    mask: np.int64,
    sorted_pts: np.ndarray,
    best: np.ndarray,
    out: np.ndarray,
) -> None:
    """`knn_mean_distance` for point i into out[i]."""
    best[:] = np.inf
    px, py, pz = points[i, 0], points[i, 1], points[i, 2]
    cx_, cy_, cz_ = ci[i, 0], ci[i, 1], ci[i, 2]
    # distance from the point to its own cell's faces, low and high side per axis
    lx, hx = px - cx_ * cell, (cx_ + 1) * cell - px
    ly, hy = py - cy_ * cell, (cy_ + 1) * cell - py
    lz, hz = pz - cz_ * cell, (cz_ + 1) * cell - pz
    inner = min(lx, hx, ly, hy, lz, hz)
    done = False
    for ring in range(rings + 1):
        for dx in range(-ring, ring + 1):
            gx = _gap(dx, lx, hx, cell)
            for dy in range(-ring, ring + 1):
                gy = _gap(dy, ly, hy, cell)
                for dz in range(-ring, ring + 1):
                    if max(abs(dx), abs(dy), abs(dz)) != ring:
                        continue
                    gz = _gap(dz, lz, hz, cell)
                    if gx * gx + gy * gy + gz * gz > best[k - 1]:
                        continue  # the whole cell is farther than the k-th so far
                    r = _run_of(cx_ + dx, cy_ + dy, cz_ + dz, table, runkey, mask)
                    if r < 0:
                        continue
                    for j in range(starts[r], starts[r + 1]):
                        ex = sorted_pts[j, 0] - px
                        ey = sorted_pts[j, 1] - py
                        ez = sorted_pts[j, 2] - pz
                        d2 = ex * ex + ey * ey + ez * ez
                        if d2 < best[k - 1]:
                            a = k - 1
                            while a > 0 and best[a - 1] > d2:
                                best[a] = best[a - 1]
                                a -= 1
                            best[a] = d2
        # every point not yet seen lies beyond the rings searched
        reach = ring * cell + inner
        if best[k - 1] <= reach * reach:
            done = True
            break
    if done:
        acc = 0.0
        for a in range(k):
            acc += math.sqrt(best[a])
        out[i] = acc / k
    else:
        out[i] = np.nan


@nb.njit(cache=True, nogil=True)
def radius_counts(points: np.ndarray, radius: float, enough: int) -> np.ndarray:
    """For each point, how many other points lie within `radius` (inclusive), counted up to
    `enough` (a point with that many is not counted further): the radius-outlier rule of PCL
    and Open3D (`remove_radius_outlier`), by a search of grid cells of side `radius` (the 27
    cells around a point's cell hold every point within the radius)."""
    n = points.shape[0]
    out = np.zeros(n, np.int64)
    if n == 0:
        return out
    ci, order, starts, runkey, table, mask, sorted_pts, nr = _cell_runs(points, radius)
    r2 = radius * radius
    for r in range(nr):
        j0 = order[starts[r]]
        cx_, cy_, cz_ = ci[j0, 0], ci[j0, 1], ci[j0, 2]
        for jj in range(starts[r], starts[r + 1]):
            px, py, pz = sorted_pts[jj, 0], sorted_pts[jj, 1], sorted_pts[jj, 2]
            c = 0  # the point itself included; the cells nearest first stop it early
            for dx in (0, -1, 1):
                for dy in (0, -1, 1):
                    for dz in (0, -1, 1):
                        rr = _run_of(cx_ + dx, cy_ + dy, cz_ + dz, table, runkey, mask)
                        if rr < 0:
                            continue
                        for j in range(starts[rr], starts[rr + 1]):
                            ex = sorted_pts[j, 0] - px
                            ey = sorted_pts[j, 1] - py
                            ez = sorted_pts[j, 2] - pz
                            c += ex * ex + ey * ey + ez * ez <= r2
                        if c > enough:
                            break
                    if c > enough:
                        break
                if c > enough:
                    break
            out[order[jj]] = min(c - 1, enough)
    return out
