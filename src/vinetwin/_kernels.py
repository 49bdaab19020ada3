"""Compiled inner loops (numba) of the perception chain: they run on every servo frame.

Each kernel is a plain loop over pixels or points with no Python objects; `cache=True` stores the
machine code beside the source so only the first run on a machine pays the compile (about 2 s).
Imported lazily by `vinetwin.cloud`.
"""

from __future__ import annotations

import numba as nb
import numpy as np


@nb.njit(cache=True, nogil=True)
def organised_points(
    depth: np.ndarray,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    dmin: float,
    dmax: float,
    edge_threshold: float,
    step: int,
    want_normals: bool,
) -> tuple[np.ndarray, np.ndarray]:
    """Depth image -> camera-frame points of valid pixels (range, flying-pixel filter) and their
    unnormalised normals from central differences `step` px apart (zero when undefined)."""
    H, W = depth.shape
    keep = np.zeros((H, W), np.bool_)
    n = 0
    for v in range(H):
        for u in range(W):
            z = depth[v, u]
            if not (z > dmin and z <= dmax):  # also rejects NaN
                continue
            ok = True
            if edge_threshold > 0:
                # drop the far side of a jump to any 4-neighbour
                for dv, du in ((-1, 0), (1, 0), (0, -1), (0, 1)):
                    vv, uu = v + dv, u + du
                    if 0 <= vv < H and 0 <= uu < W:
                        zn = depth[vv, uu]
                        if zn > dmin and zn <= dmax and z > zn and z - zn > edge_threshold * zn:
                            ok = False
                            break
            if ok:
                keep[v, u] = True
                n += 1
    pts = np.empty((n, 3))
    nrm = np.zeros((n, 3))
    i = 0
    for v in range(H):
        for u in range(W):
            if not keep[v, u]:
                continue
            z = depth[v, u]
            pts[i, 0] = (u - cx) / fx * z
            pts[i, 1] = (v - cy) / fy * z
            pts[i, 2] = z
            if want_normals and step <= u < W - step and step <= v < H - step:
                zl, zr = depth[v, u - step], depth[v, u + step]
                zu, zd = depth[v - step, u], depth[v + step, u]
                if (
                    keep[v, u - step]
                    and keep[v, u + step]
                    and keep[v - step, u]
                    and keep[v + step, u]
                ):
                    ax = (u + step - cx) / fx * zr - (u - step - cx) / fx * zl
                    ay = (v - cy) / fy * (zr - zl)
                    az = zr - zl
                    bx = (u - cx) / fx * (zd - zu)
                    by = (v + step - cy) / fy * zd - (v - step - cy) / fy * zu
                    bz = zd - zu
                    nrm[i, 0] = ay * bz - az * by
                    nrm[i, 1] = az * bx - ax * bz
                    nrm[i, 2] = ax * by - ay * bx
            i += 1
    return pts, nrm


@nb.njit(cache=True, nogil=True)
def voxel_grid(
    points: np.ndarray,
    normals: np.ndarray,
    voxel: float,
    ox: float,
    oy: float,
    oz: float,
    with_normals: bool,
) -> tuple[np.ndarray, np.ndarray]:
    """Centroid of the points in each occupied voxel (grid anchored at (ox, oy, oz)), and the
    sum of their normals; voxels in order of first occurrence. Open addressing hash table."""
    n = points.shape[0]
    cap = 16
    while cap < 2 * n:
        cap *= 2
    keys = np.empty((cap, 3), np.int64)
    slot_of = np.full(cap, -1, np.int64)
    acc = np.zeros((n, 3))
    nacc = np.zeros((n, 3))
    cnt = np.zeros(n, np.int64)
    m = 0
    inv = 1.0 / voxel
    for i in range(n):
        ix = np.int64(np.floor((points[i, 0] - ox) * inv))
        iy = np.int64(np.floor((points[i, 1] - oy) * inv))
        iz = np.int64(np.floor((points[i, 2] - oz) * inv))
        h = ((ix * 73856093) ^ (iy * 19349663) ^ (iz * 83492791)) & (cap - 1)
        while True:
            s = slot_of[h]
            if s == -1:
                slot_of[h] = m
                keys[h, 0], keys[h, 1], keys[h, 2] = ix, iy, iz
                s = m
                m += 1
                break
            if keys[h, 0] == ix and keys[h, 1] == iy and keys[h, 2] == iz:
                break
            h = (h + 1) & (cap - 1)
        cnt[s] += 1
        for k in range(3):
            acc[s, k] += points[i, k]
            if with_normals:
                nacc[s, k] += normals[i, k]
    out = np.empty((m, 3))
    nout = np.empty((m, 3))
    for s in range(m):
        for k in range(3):
            out[s, k] = acc[s, k] / cnt[s]
            nout[s, k] = nacc[s, k]
    return out, nout


@nb.njit(cache=True, nogil=True)
def window_extremes(depth: np.ndarray, w: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For each pixel, over the (2w+1)^2 window (clipped at the border): the nearest valid depth
    (inf if none), the farthest depth (0 if none) and whether the window holds an invalid pixel."""
    H, W = depth.shape
    near = np.full((H, W), np.inf, np.float32)
    far = np.zeros((H, W), np.float32)
    holes = np.zeros((H, W), np.bool_)
    # separable: rows first, then columns
    rnear = np.full((H, W), np.inf, np.float32)
    rfar = np.zeros((H, W), np.float32)
    rhole = np.zeros((H, W), np.bool_)
    for v in range(H):
        for u in range(W):
            lo, hi, hole = np.float32(np.inf), np.float32(0.0), False
            for uu in range(max(0, u - w), min(W, u + w + 1)):
                z = depth[v, uu]
                if z > 0:
                    if z < lo:
                        lo = z
                    if z > hi:
                        hi = z
                else:
                    hole = True
            rnear[v, u], rfar[v, u], rhole[v, u] = lo, hi, hole
    for v in range(H):
        for u in range(W):
            lo, hi, hole = np.float32(np.inf), np.float32(0.0), False
            for vv in range(max(0, v - w), min(H, v + w + 1)):
                if rnear[vv, u] < lo:
                    lo = rnear[vv, u]
                if rfar[vv, u] > hi:
                    hi = rfar[vv, u]
                hole = hole or rhole[vv, u]
            near[v, u], far[v, u], holes[v, u] = lo, hi, hole
    return near, far, holes
