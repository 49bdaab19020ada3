"""Compiled inner loops (numba) of the perception chain (`vinetwin.cloud`), which runs on every
servo frame: depth counts to metres and back, organised points, the voxel grid and the fused
range-check + voxel pass. The outlier rules' neighbour counts are in `_outlier_kernels`.

Each kernel is a plain loop over pixels or points with no Python objects; `cache=True` stores the
machine code beside the source so only the first run on a machine pays the compile (about 2 s).
Imported lazily by `vinetwin.cloud`."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from vinetwin._numba import nb


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
    _keep_rows(depth, dmin, dmax, edge_threshold, keep, 0, H)
    n = 0
    for v in range(H):
        for u in range(W):
            n += keep[v, u]
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
def counts_to_metres(counts: np.ndarray, unit: np.float32, out: np.ndarray) -> None:
    """16-bit depth counts (flat) to float32 metres: count * unit in float32, as numpy's
    `counts.astype(np.float32) * np.float32(unit)` computes it, in one pass."""
    for i in range(counts.shape[0]):
        out[i] = np.float32(counts[i]) * unit


@nb.njit(cache=True, nogil=True)
def quantize_depth(d: np.ndarray, depth_unit: float, out: np.ndarray) -> None:
    """Metres (flat, any float type) to 16-bit counts, rounded half to even in float64: 0 for
    no data (0, negative, NaN, inf) and beyond 65535 counts."""
    for i in range(d.shape[0]):
        x = np.float64(d[i])
        c = np.rint(x / depth_unit) if math.isfinite(x) and x > 0 else 0.0
        out[i] = np.uint16(c) if c <= 65535.0 else np.uint16(0)


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


# ----------------------------------------------------------------------------- fused perception
@nb.njit(cache=True, nogil=True, inline="always")
def _nearer(zn: float, dmin: float, lim: float) -> bool:
    """A valid neighbour depth (above dmin) nearer than `lim` (NaN: False). Without
    branches, so the loops that call it vectorise."""
    return (zn > dmin) & (zn < lim)


@nb.njit(cache=True, nogil=True)
def _keep_pixel(
    depth: np.ndarray, dmin: float, dmax: float, inv: float, keep: np.ndarray, v: int, u: int
) -> None:
    """`_keep_rows` for one pixel, any pixel (its neighbours tested within the image)."""
    H, W = depth.shape
    z = np.float64(depth[v, u])
    if not (z > dmin and z <= dmax):  # also rejects NaN
        return
    lim = z * inv
    ok = True
    if v > 0 and _nearer(depth[v - 1, u], dmin, lim):
        ok = False
    if v < H - 1 and _nearer(depth[v + 1, u], dmin, lim):
        ok = False
    if u > 0 and _nearer(depth[v, u - 1], dmin, lim):
        ok = False
    if u < W - 1 and _nearer(depth[v, u + 1], dmin, lim):
        ok = False
    keep[v, u] = ok


@nb.njit(cache=True, nogil=True)
def _keep_rows(
    depth: np.ndarray,
    dmin: float,
    dmax: float,
    edge_threshold: float,
    keep: np.ndarray,
    v0: int,
    v1: int,
) -> None:
    """Rows v0..v1 of the keep mask into keep (zeros): valid pixels (range) that survive the
    flying-pixel filter. A pixel at depth z is the far side of a jump to a valid 4-neighbour at
    zn when z - zn > edge_threshold * zn, that is zn < z / (1 + edge_threshold) (zn is then
    also below dmax). Interior pixels test their four neighbours without branches (the loop
    vectorises: 0.6 against 0.9-1.4 ms per 848x480 image), the border ones one by one."""
    H, W = depth.shape
    if edge_threshold <= 0:
        for v in range(v0, v1):
            for u in range(W):
                z = np.float64(depth[v, u])
                keep[v, u] = (z > dmin) & (z <= dmax)  # NaN: False
        return
    inv = 1.0 / (1.0 + edge_threshold)
    for v in range(v0, v1):
        if not 0 < v < H - 1:
            for u in range(W):
                _keep_pixel(depth, dmin, dmax, inv, keep, v, u)
            continue
        up, row, dn, out = depth[v - 1], depth[v], depth[v + 1], keep[v]
        for u in range(1, W - 1):
            z = np.float64(row[u])
            lim = z * inv
            near = (
                _nearer(np.float64(up[u]), dmin, lim)
                | _nearer(np.float64(dn[u]), dmin, lim)
                | _nearer(np.float64(row[u - 1]), dmin, lim)
                | _nearer(np.float64(row[u + 1]), dmin, lim)
            )
            out[u] = (z > dmin) & (z <= dmax) & (not near)
        _keep_pixel(depth, dmin, dmax, inv, keep, v, 0)
        if W > 1:
            _keep_pixel(depth, dmin, dmax, inv, keep, v, W - 1)


@nb.njit(cache=True, nogil=True)
def _hash3(ix: np.int64, iy: np.int64, iz: np.int64, mask: np.int64) -> np.int64:
    """A table slot for a voxel: the spatial hash's xor of products, then a 64-bit finaliser
    (the xor alone keeps neighbouring voxels in neighbouring slots: long probe chains)."""
    x = (ix * np.int64(73856093)) ^ (iy * np.int64(19349663)) ^ (iz * np.int64(83492791))
    x = (x ^ (x >> np.int64(31))) * np.int64(-4658895280553007687)
    x = x ^ (x >> np.int64(29))
    return x & mask


@nb.njit(cache=True, nogil=True)
def _slot(
    skey: np.ndarray, slot_of: np.ndarray, mask: np.int64, ix: np.int64, iy: np.int64, iz: np.int64
) -> tuple[Any, Any]:
    """The table position of a voxel and its slot (-1 if absent: the position is then free).
    The table holds slots only; a slot's key is row `s` of `skey` (compact, in slot order)."""
    h = _hash3(ix, iy, iz, mask)
    while True:
        s = slot_of[h]
        if s == -1 or (skey[s, 0] == ix and skey[s, 1] == iy and skey[s, 2] == iz):
            return h, s
        h = (h + 1) & mask


@nb.njit(cache=True, nogil=True)
def _rehash(skey: np.ndarray, m: int, cap: int) -> tuple[np.ndarray, np.int64]:
    """A table of `cap` positions (a power of two) for the first m slots of skey."""
    mask = np.int64(cap - 1)
    slot_of = np.full(cap, -1, np.int32)
    for s in range(m):
        h = _hash3(skey[s, 0], skey[s, 1], skey[s, 2], mask)
        while slot_of[h] != -1:
            h = (h + 1) & mask
        slot_of[h] = s
    return slot_of, mask


@nb.njit(cache=True, nogil=True)
def _voxel_rows(
    depth: np.ndarray,
    keep: np.ndarray,
    xf: np.ndarray,
    yf: np.ndarray,
    v0: int,
    v1: int,
    step: int,
    inv: float,
    ox: float,
    oy: float,
    oz: float,
    skey: np.ndarray,
    acc: np.ndarray,
    nacc: np.ndarray,
    cnt: np.ndarray,
) -> int:
    """Rows v0..v1 of `depth_voxel_band` into the given arrays (room for one voxel per kept
    pixel): each voxel's key, sums of points and normals, pixel count, in order of first
    occurrence. Returns the number of voxels. The current voxel's sums ride in registers and go
    back to the arrays when the voxel changes (the same additions in the same order: 0.83-0.97x
    the time of adding into the arrays pixel by pixel)."""
    H, W = depth.shape
    # the table starts small and doubles at half full: sized for every kept pixel (the most
    # voxels there can be) it was megabytes of fresh pages per frame, most never used
    cap = 4096
    slot_of, mask = _rehash(skey, 0, cap)
    m = 0
    last_x, last_y, last_z, last_s = np.int64(0), np.int64(0), np.int64(0), -1
    c = np.int64(0)
    a0 = a1 = a2 = b0 = b1 = b2 = 0.0
    for v in range(v0, v1):
        inner_v = step <= v < H - step
        for u in range(W):
            if not keep[v, u]:
                continue
            z = np.float64(depth[v, u])
            px = xf[u] * z
            py = yf[v] * z
            n0 = n1 = n2 = 0.0
            if (
                inner_v
                and step <= u < W - step
                and keep[v, u - step]
                and keep[v, u + step]
                and keep[v - step, u]
                and keep[v + step, u]
            ):
                zl, zr = np.float64(depth[v, u - step]), np.float64(depth[v, u + step])
                zu, zd = np.float64(depth[v - step, u]), np.float64(depth[v + step, u])
                ax = xf[u + step] * zr - xf[u - step] * zl
                ay = yf[v] * (zr - zl)
                az = zr - zl
                bx = xf[u] * (zd - zu)
                by = yf[v + step] * zd - yf[v - step] * zu
                bz = zd - zu
                n0 = ay * bz - az * by
                n1 = az * bx - ax * bz
                n2 = ax * by - ay * bx
            ix = np.int64(np.floor((px - ox) * inv))
            iy = np.int64(np.floor((py - oy) * inv))
            iz = np.int64(np.floor((z - oz) * inv))
            if last_s >= 0 and ix == last_x and iy == last_y and iz == last_z:
                s = last_s
            else:  # neighbouring pixels mostly share a voxel: the table only on a change
                if last_s >= 0:
                    cnt[last_s] = c
                    acc[last_s, 0], acc[last_s, 1], acc[last_s, 2] = a0, a1, a2
                    nacc[last_s, 0], nacc[last_s, 1], nacc[last_s, 2] = b0, b1, b2
                h, s = _slot(skey, slot_of, mask, ix, iy, iz)
                if s == -1:
                    s = m
                    m += 1
                    skey[s, 0], skey[s, 1], skey[s, 2] = ix, iy, iz
                    if 2 * m > cap:
                        cap *= 2
                        slot_of, mask = _rehash(skey, m, cap)
                    else:
                        slot_of[h] = s
                    acc[s, 0] = acc[s, 1] = acc[s, 2] = 0.0
                    nacc[s, 0] = nacc[s, 1] = nacc[s, 2] = 0.0
                    cnt[s] = 0
                last_x, last_y, last_z, last_s = ix, iy, iz, s
                c = cnt[s]
                a0, a1, a2 = acc[s, 0], acc[s, 1], acc[s, 2]
                b0, b1, b2 = nacc[s, 0], nacc[s, 1], nacc[s, 2]
            c += 1
            a0 += px
            a1 += py
            a2 += z
            b0 += n0
            b1 += n1
            b2 += n2
    if last_s >= 0:
        cnt[last_s] = c
        acc[last_s, 0], acc[last_s, 1], acc[last_s, 2] = a0, a1, a2
        nacc[last_s, 0], nacc[last_s, 1], nacc[last_s, 2] = b0, b1, b2
    return m


@nb.njit(cache=True, nogil=True)
def depth_voxel_band(
    depth: np.ndarray,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    dmin: float,
    dmax: float,
    edge_threshold: float,
    step: int,
    voxel: float,
    ox: float,
    oy: float,
    oz: float,
    v0: int,
    v1: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """`organised_points` and `voxel_grid` in one pass over rows v0..v1, without the per-pixel
    arrays, before the centroids: each occupied voxel's key, the sums of its points and of its
    pixels' (unnormalised) normals and its pixel count, voxels in order of first occurrence, as
    the two kernels run one after the other give them. The flying-pixel filter runs on rows
    v0 - step .. v1 + step (the normals read their keep flags), so bands of rows are
    independent: `merge_voxel_bands` joins them (`vinetwin.cloud` runs bands on threads)."""
    H, W = depth.shape
    keep = np.zeros(depth.shape, np.bool_)
    _keep_rows(depth, dmin, dmax, edge_threshold, keep, max(0, v0 - step), min(H, v1 + step))
    xf = np.empty(W)  # ray factors: x = xf[u] z, y = yf[v] z
    for u in range(W):
        xf[u] = (u - cx) / fx
    yf = np.empty(H)
    for v in range(H):
        yf[v] = (v - cy) / fy
    total = 0
    for v in range(v0, v1):
        for u in range(W):
            total += keep[v, u]
    skey = np.empty((total, 3), np.int64)
    acc = np.empty((total, 3))
    nacc = np.empty((total, 3))
    cnt = np.empty(total, np.int64)
    m = _voxel_rows(
        depth, keep, xf, yf, v0, v1, step, 1.0 / voxel, ox, oy, oz, skey, acc, nacc, cnt
    )
    return skey[:m], acc[:m], nacc[:m], cnt[:m]


@nb.njit(cache=True, nogil=True)
def merge_voxel_bands(
    skey: np.ndarray, acc: np.ndarray, nacc: np.ndarray, cnt: np.ndarray, found: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The bands of `depth_voxel_band` (concatenated in row order, `found[b]` voxels each)
    joined: each voxel's centroid and normal sum, in order of first occurrence. A voxel that
    straddles two bands sums their partial sums (equal to one band's result to rounding)."""
    if found.shape[0] == 1:
        m = found[0]
        out = np.empty((m, 3))
        for s in range(m):
            for k in range(3):
                out[s, k] = acc[s, k] / cnt[s]
        return out, nacc[:m].copy()
    n = skey.shape[0]
    cap = 16
    while cap < 2 * n:
        cap *= 2
    mask = np.int64(cap - 1)
    mkey = np.empty((n, 3), np.int64)
    slot_of = np.full(cap, -1, np.int32)
    macc = np.empty((n, 3))
    mnacc = np.empty((n, 3))
    mcnt = np.empty(n, np.int64)
    m = 0
    for r in range(n):
        h, s = _slot(mkey, slot_of, mask, skey[r, 0], skey[r, 1], skey[r, 2])
        if s == -1:
            s = m
            m += 1
            slot_of[h] = s
            mkey[s, 0], mkey[s, 1], mkey[s, 2] = skey[r, 0], skey[r, 1], skey[r, 2]
            for k in range(3):
                macc[s, k] = acc[r, k]
                mnacc[s, k] = nacc[r, k]
            mcnt[s] = cnt[r]
        else:
            for k in range(3):
                macc[s, k] += acc[r, k]
                mnacc[s, k] += nacc[r, k]
            mcnt[s] += cnt[r]
    out = np.empty((m, 3))
    for s in range(m):
        for k in range(3):
            out[s, k] = macc[s, k] / mcnt[s]
    return out, mnacc[:m].copy()


@nb.njit(cache=True, nogil=True)
def unit_normals(
    points: np.ndarray, normals: np.ndarray, keep: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The points with keep set and a normal (norm above 1e-12), with their normals made unit
    and turned to face the origin (the camera): n . p <= 0."""
    n = points.shape[0]
    out = np.empty((n, 3))
    nout = np.empty((n, 3))
    m = 0
    for i in range(n):
        if not keep[i]:
            continue
        a, b, c = normals[i, 0], normals[i, 1], normals[i, 2]
        norm = math.sqrt(a * a + b * b + c * c)
        if not norm > 1e-12:
            continue
        a, b, c = a / norm, b / norm, c / norm
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        if a * px + b * py + c * pz > 0:
            a, b, c = -a, -b, -c
        out[m, 0], out[m, 1], out[m, 2] = px, py, pz
        nout[m, 0], nout[m, 1], nout[m, 2] = a, b, c
        m += 1
    return out[:m].copy(), nout[:m].copy()


@nb.njit(cache=True, nogil=True)
def valid_rows(depth: np.ndarray, dmin: float, dmax: float) -> np.ndarray:
    """Cumulative count of in-range pixels before each row (H + 1 entries): where to cut the
    image into bands of equal work."""
    H, W = depth.shape
    out = np.zeros(H + 1, np.int64)
    for v in range(H):
        c = 0
        for u in range(W):
            z = depth[v, u]
            c += z > dmin and z <= dmax
        out[v + 1] = out[v] + c
    return out
