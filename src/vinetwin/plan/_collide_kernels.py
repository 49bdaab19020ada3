"""Compiled collision queries of the arm's spheres against the vine's vertices (a spatial hash of
cells) and the platform's deck and the ground: the planner's validity check, a few microseconds
per configuration."""

from __future__ import annotations

import math

import numpy as np

from vinetwin._numba import nb
from vinetwin.arm import _frames
from vinetwin.frames import Array

#: Integer (or boolean) arrays: the hash's cells, the mesh's faces.
Ints = np.ndarray


def build_hash(V: Array, origin: Array, cell: float, shape: Ints) -> tuple[Ints, Ints]:
    """(starts, order): the vertices of flat cell c are order[starts[c]:starts[c + 1]]."""
    idx = np.floor((V - origin) / cell).astype(np.int64)
    flat = (idx[:, 0] * shape[1] + idx[:, 1]) * shape[2] + idx[:, 2]
    order = np.argsort(flat, kind="stable")
    starts = np.searchsorted(flat[order], np.arange(int(np.prod(shape)) + 1)).astype(np.int64)
    return starts, order.astype(np.int64)


@nb.njit(cache=True)
def nearest_vertex(
    p: Array, reach: float, V: Array, origin: Array, cell: float, shape: Ints,
    starts: Ints, order: Ints,
) -> float:  # pragma: no cover - compiled  # fmt: skip
    """Distance from p to the nearest vertex, if within `reach`; else `reach`. The cells are
    visited in rings around p's cell (ring r: Chebyshev distance r in cells), and the search
    ends once the next ring cannot hold a nearer vertex (every point of ring r lies at least
    (r - 1) cells from p)."""
    best = reach * reach
    c0 = np.empty(3, np.int64)
    lo = np.empty(3, np.int64)  # the cells within reach
    hi = np.empty(3, np.int64)
    for a in range(3):
        c0[a] = math.floor((p[a] - origin[a]) / cell)
        lo[a] = max(0, math.floor((p[a] - reach - origin[a]) / cell))
        hi[a] = min(shape[a] - 1, math.floor((p[a] + reach - origin[a]) / cell))
        if lo[a] > hi[a]:
            return reach
    rings = math.ceil(reach / cell) + 1
    for r in range(rings + 1):
        if r > 0 and ((r - 1) * cell) ** 2 >= best:
            break
        i0, i1 = max(lo[0], c0[0] - r), min(hi[0], c0[0] + r)
        j0, j1 = max(lo[1], c0[1] - r), min(hi[1], c0[1] + r)
        k0, k1 = max(lo[2], c0[2] - r), min(hi[2], c0[2] + r)
        for i in range(i0, i1 + 1):
            for j in range(j0, j1 + 1):
                base = (i * shape[1] + j) * shape[2]
                shell = abs(i - c0[0]) == r or abs(j - c0[1]) == r
                k = k0
                while k <= k1:
                    if not shell and abs(k - c0[2]) != r:
                        # inside the ring's cube: only its two faces in k belong to the ring
                        k = c0[2] + r if c0[2] + r <= k1 else k1 + 1
                        continue
                    c = base + k
                    for m in range(starts[c], starts[c + 1]):
                        v = order[m]
                        dx = V[v, 0] - p[0]
                        dy = V[v, 1] - p[1]
                        dz = V[v, 2] - p[2]
                        d2 = dx * dx + dy * dy + dz * dz
                        if d2 < best:
                            best = d2
                    k += 1
    return math.sqrt(best)


@nb.njit(cache=True)
def point_gaps(
    P: Array, radii: Array, reach: float, V: Array, origin: Array, cell: float, shape: Ints,
    starts: Ints, order: Ints, deck_lo: Array, deck_hi: Array, out: Array,
) -> None:  # pragma: no cover - compiled  # fmt: skip
    """out[k, 0]: sphere k's gap to the nearest vine vertex (at most `reach`), out[k, 1] to the
    deck (an axis-aligned box), out[k, 2] to the ground (z = 0); P in the vine frame."""
    for k in range(len(radii)):
        p = P[k]
        r = radii[k]
        out[k, 0] = nearest_vertex(p, reach + r, V, origin, cell, shape, starts, order) - r
        s = 0.0
        for a in range(3):
            e = max(deck_lo[a] - p[a], p[a] - deck_hi[a], 0.0)
            s += e * e
        out[k, 1] = math.sqrt(s) - r
        out[k, 2] = p[2] - r


@nb.njit(cache=True)
def arm_points(
    q: Array, T_vine_base: Array, frame: Ints, local: Array, points: Array
) -> None:  # pragma: no cover - compiled
    """points[k]: the centre of sphere k (on frame[k] at local[k]) in the vine frame."""
    F = np.empty((9, 4, 4))
    _frames(q, F)
    B = T_vine_base
    for k in range(len(frame)):
        M = F[frame[k]]
        x = M[0, 0] * local[k, 0] + M[0, 1] * local[k, 1] + M[0, 2] * local[k, 2] + M[0, 3]
        y = M[1, 0] * local[k, 0] + M[1, 1] * local[k, 1] + M[1, 2] * local[k, 2] + M[1, 3]
        z = M[2, 0] * local[k, 0] + M[2, 1] * local[k, 1] + M[2, 2] * local[k, 2] + M[2, 3]
        for a in range(3):  # into the vine frame (a product per point, not per frame)
            points[k, a] = B[a, 0] * x + B[a, 1] * y + B[a, 2] * z + B[a, 3]


def build_blocks(starts: Ints, shape: Ints, factor: int) -> Ints:
    """Which blocks of factor^3 cells hold a vertex."""
    counts = (starts[1:] - starts[:-1]).reshape(tuple(shape)) > 0
    bs = (np.asarray(shape) + factor - 1) // factor
    pad = bs * factor - np.asarray(shape)
    c = np.pad(counts, [(0, int(p)) for p in pad])
    return np.asarray(c.reshape(bs[0], factor, bs[1], factor, bs[2], factor).any(axis=(1, 3, 5)))


def build_free(V: Array, origin: Array, size: Array, cell: float) -> Array:
    """A grid of `cell` over the box from `origin` of `size` (m): per cell, a lower bound of the
    distance (m) from any point in it to any vertex. The Euclidean distance transform of the
    cells holding a vertex (centre to centre), less a cell's diagonal (each point lies within
    half of it of its cell's centre), at least 0; float32 (the bound is rounded down)."""
    from scipy.ndimage import distance_transform_edt

    shape = np.ceil(np.asarray(size, float) / cell).astype(np.int64)
    idx = np.clip(np.floor((V - origin) / cell).astype(np.int64), 0, shape - 1)
    occupied = np.zeros(tuple(shape), bool)
    occupied[idx[:, 0], idx[:, 1], idx[:, 2]] = True
    edt = np.asarray(distance_transform_edt(~occupied), float)
    free = np.maximum(edt - math.sqrt(3.0), 0.0) * cell
    return np.ascontiguousarray(np.nextafter(free.astype(np.float32), np.float32(0)))


@nb.njit(cache=True, inline="always")
def _any_vertex_within(
    p: Array, R0: float, bound: float, vbound: Array, V: Array, origin: Array, cell: float,
    shape: Ints, starts: Ints, order: Ints, blocks: Ints, factor: int, free: Array,
    fcell: float,
) -> bool:  # pragma: no cover - compiled  # fmt: skip
    """Whether a vertex v lies within R0 + vbound[v] of p (vbound <= bound: how much closer
    than v the surface of v's triangles can come). A point whose cell of `free` (`fcell`
    across, from `origin`; `build_free`) is at least R0 + bound from every vertex is answered
    at once, without visiting one."""
    R = R0 + bound
    # scalars, not arrays: this runs for every sphere of every check (an allocation each
    # would cost more than the test)
    x, y, z = p[0] - origin[0], p[1] - origin[1], p[2] - origin[2]
    ci, cj, ck = math.floor(x / fcell), math.floor(y / fcell), math.floor(z / fcell)
    if (
        0 <= ci < free.shape[0] and 0 <= cj < free.shape[1] and 0 <= ck < free.shape[2]
        and free[ci, cj, ck] >= R
    ):  # fmt: skip
        return False
    i0, i1 = max(0, math.floor((x - R) / cell)), min(shape[0] - 1, math.floor((x + R) / cell))
    j0, j1 = max(0, math.floor((y - R) / cell)), min(shape[1] - 1, math.floor((y + R) / cell))
    k0, k1 = max(0, math.floor((z - R) / cell)), min(shape[2] - 1, math.floor((z + R) / cell))
    if i0 > i1 or j0 > j1 or k0 > k1:
        return False
    occupied = False  # the coarse blocks first
    for bi in range(i0 // factor, i1 // factor + 1):
        for bj in range(j0 // factor, j1 // factor + 1):
            for bk in range(k0 // factor, k1 // factor + 1):
                if blocks[bi, bj, bk]:
                    occupied = True
    if not occupied:
        return False
    for i in range(i0, i1 + 1):
        for j in range(j0, j1 + 1):
            base = (i * shape[1] + j) * shape[2]
            for k in range(k0, k1 + 1):
                c = base + k
                for m in range(starts[c], starts[c + 1]):
                    v = order[m]
                    dx = V[v, 0] - p[0]
                    dy = V[v, 1] - p[1]
                    dz = V[v, 2] - p[2]
                    Rv = R0 + vbound[v]
                    if dx * dx + dy * dy + dz * dz < Rv * Rv:
                        return True
    return False


@nb.njit(cache=True)
def arm_valid(
    q: Array, T_vine_base: Array, frame: Ints, local: Array, radii: Array, clearance: Array,
    bound: float, vbound: Array, V: Array, origin: Array, cell: float, shape: Ints,
    starts: Ints, order: Ints, blocks: Ints, factor: int, free: Array, fcell: float,
    deck_lo: Array, deck_hi: Array,
) -> bool:  # pragma: no cover - compiled  # fmt: skip
    """Whether every sphere k at joints q keeps clearance[k] from the vine (no vertex v within
    radius + clearance + vbound[v]), the deck and the ground."""
    P = np.empty((len(radii), 3))
    arm_points(q, T_vine_base, frame, local, P)
    for k in range(len(radii)):
        p = P[k]
        need = radii[k] + clearance[k]
        if p[2] < need:
            return False
        s = 0.0
        for a in range(3):
            e = max(deck_lo[a] - p[a], p[a] - deck_hi[a], 0.0)
            s += e * e
        if s < need * need:
            return False
    for k in range(len(radii)):  # the vine last: the dearest
        if _any_vertex_within(P[k], radii[k] + clearance[k], bound, vbound, V, origin, cell,
                              shape, starts, order, blocks, factor, free, fcell):  # fmt: skip
            return False
    return True


def vertex_triangles(V: Array, F: Ints) -> tuple[Ints, Ints, Array]:
    """CSR of the triangles around each vertex (vertex v's are tris[starts[v]:starts[v + 1]])
    and each vertex's longest incident edge."""
    flat = F.ravel()
    order = np.argsort(flat, kind="stable")
    starts = np.searchsorted(flat[order], np.arange(len(V) + 1)).astype(np.int64)
    edges = np.linalg.norm(V[F[:, [1, 2, 0]]] - V[F], axis=2).max(axis=1)
    vedge = np.zeros(len(V))
    np.maximum.at(vedge, F.ravel(), np.repeat(edges, 3))
    return starts, (order // 3).astype(np.int64), vedge


@nb.njit(cache=True)
def _closest_on_triangle(p: Array, a: Array, b: Array, c: Array) -> Array:  # pragma: no cover
    """The point of triangle abc nearest p (Ericson, Real-Time Collision Detection, 5.1.5)."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = ab @ ap, ac @ ap
    if d1 <= 0.0 and d2 <= 0.0:
        return a
    bp = p - b
    d3, d4 = ab @ bp, ac @ bp
    if d3 >= 0.0 and d4 <= d3:
        return b
    vc = d1 * d4 - d3 * d2
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        return a + ab * (d1 / (d1 - d3))
    cp = p - c
    d5, d6 = ab @ cp, ac @ cp
    if d6 >= 0.0 and d5 <= d6:
        return c
    vb = d5 * d2 - d1 * d6
    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
        return a + ac * (d2 / (d2 - d6))
    va = d3 * d6 - d5 * d4
    if va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
        return b + (c - b) * ((d4 - d3) / ((d4 - d3) + (d5 - d6)))
    den = 1.0 / (va + vb + vc)
    return a + ab * (vb * den) + ac * (vc * den)


@nb.njit(cache=True)
def closest_points(
    P: Array, near: Array, cand_starts: Ints, cand: Ints, V: Array, F: Ints,
    vt_starts: Ints, vt_tris: Ints, vedge: Array, reach: float, dist: Array, closest: Array,
) -> None:  # pragma: no cover - compiled  # fmt: skip
    """For each point: its exact distance to the mesh and the nearest surface point, when that
    is within `reach` (else dist = inf, closest NaN). near[n]: the distance to its nearest
    vertex (a point of the surface: a first bound); cand[cand_starts[n]:cand_starts[n + 1]]:
    the vertices within near[n] + the mesh's longest edge (the nearest triangle has a corner
    there), whose triangles are tried."""
    for n in range(len(P)):
        p = P[n]
        best = near[n] * near[n] + 1e-15
        cx, cy, cz = np.nan, np.nan, np.nan
        for m in range(cand_starts[n], cand_starts[n + 1]):
            v = cand[m]
            d = V[v] - p
            dd = d @ d
            lim = math.sqrt(best) + vedge[v]  # its triangles lie within its longest edge of it
            if dd > lim * lim:
                continue
            for t in vt_tris[vt_starts[v] : vt_starts[v + 1]]:
                q = _closest_on_triangle(p, V[F[t, 0]], V[F[t, 1]], V[F[t, 2]])
                e = q - p
                d2 = e @ e
                if d2 <= best:  # ties too: the nearest vertex may be it
                    best = d2
                    cx, cy, cz = q[0], q[1], q[2]
        if best <= reach * reach and not math.isnan(cx):
            dist[n] = math.sqrt(best)
            closest[n, 0], closest[n, 1], closest[n, 2] = cx, cy, cz
        else:
            dist[n] = np.inf
            closest[n, 0] = closest[n, 1] = closest[n, 2] = np.nan
