"""Compiled inner loops (numba) of the perception chain: they run on every servo frame.

Each kernel is a plain loop over pixels or points with no Python objects; `cache=True` stores the
machine code beside the source so only the first run on a machine pays the compile (about 2 s).
Imported lazily by `vinetwin.cloud`.
"""

from __future__ import annotations

import math
from typing import Any

import numba as nb
import numpy as np
from numba.core import config as _nb_config

from vinetwin import NUMBA_THREADING_LAYERS

# the order `import vinetwin` set in the environment, also where numba was imported before it;
# set here, on the import of the kernels every band pass (`_bands`) runs, not on each pass
_nb_config.THREADING_LAYER_PRIORITY = list(NUMBA_THREADING_LAYERS)  # type: ignore[attr-defined]


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
def gl_reverse_z_depth(
    buf: np.ndarray,
    c_coef: float,
    d_coef: float,
    far_cut: float,
    out: np.ndarray,
    v0: int = 0,
    v1: int = -1,
) -> None:
    """An OpenGL reverse-Z depth buffer (bottom row first) to metric z-depth, top row first:
    `d_coef / (b + c_coef)` in float64 (as `mujoco.Renderer` computes it), 0 at or beyond
    `far_cut` (nothing hit); one pass instead of the renderer's float64 copy, flip and our mask.
    The buffer's cleared value (0, the far plane: most of a view of a vine) is converted once
    (0.5-0.6 against 0.8-0.95 ms per 848x480 view of the sample, the same numbers). Output rows
    v0..v1 (v1 -1: to the last), so that bands of rows can run on threads."""
    H, W = buf.shape
    if v1 < 0:
        v1 = H
    z0 = np.float32(d_coef / (0.0 + c_coef))
    out0 = z0 if np.float64(z0) < far_cut else np.float32(0.0)
    for v in range(v0, v1):
        row = buf[H - 1 - v]
        for u in range(W):
            x = row[u]
            if x == 0:
                out[v, u] = out0
            else:
                z = np.float32(d_coef / (np.float64(x) + c_coef))
                out[v, u] = z if np.float64(z) < far_cut else np.float32(0.0)


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


# ----------------------------------------------------------------------------- D405 model
@nb.njit(cache=True, nogil=True, fastmath=True)
def _min3_rows(src: np.ndarray, dst: np.ndarray, sign: np.float32) -> None:
    """dst = the minimum of sign * src over each pixel's row neighbours u-1..u+1 (clipped at
    the border). Reads one array and writes another, so the loop vectorises (the inputs hold
    no NaN: the D405 model zeroes them first)."""
    H, W = src.shape
    for v in range(H):
        a, o = src[v], dst[v]
        if W == 1:
            o[0] = a[0] * sign
            continue
        o[0] = min(a[0] * sign, a[1] * sign)
        for u in range(1, W - 1):
            o[u] = min(min(a[u - 1] * sign, a[u] * sign), a[u + 1] * sign)
        o[W - 1] = min(a[W - 2] * sign, a[W - 1] * sign)


@nb.njit(cache=True, nogil=True, fastmath=True)
def _min3_cols(src: np.ndarray, dst: np.ndarray) -> None:
    """dst = the minimum of src over each pixel's column neighbours v-1..v+1 (clipped)."""
    H, W = src.shape
    for v in range(H):
        a, b, c, o = src[max(v - 1, 0)], src[v], src[min(v + 1, H - 1)], dst[v]
        for u in range(W):
            o[u] = min(min(a[u], b[u]), c[u])


@nb.njit(cache=True, nogil=True)
def _window_min(a: np.ndarray, w: int, sign: np.float32) -> np.ndarray:
    """The minimum of sign * a over each pixel's (2w+1)^2 window clipped at the border: w
    passes of the 3-wide minimum along rows, then w along columns (a clipped window's minimum
    is the 3-wide one's applied w times)."""
    x, y = np.empty_like(a), np.empty_like(a)
    _min3_rows(a, x, sign)
    for _ in range(w - 1):
        _min3_rows(x, y, np.float32(1.0))
        x, y = y, x
    for _ in range(w):
        _min3_cols(x, y)
        x, y = y, x
    return x


@nb.njit(cache=True, nogil=True, fastmath=True)
def _edge_mask(lo: np.ndarray, neg_hi: np.ndarray, jump: np.float32, out: np.ndarray) -> None:
    """Silhouette pixels from the window's minimum depth `lo` (0: a hole in it) and its
    negated maximum: a surface in the window, and a hole or a relative range above `jump`."""
    H, W = lo.shape
    for v in range(H):
        a, b, o = lo[v], neg_hi[v], out[v]
        for u in range(W):
            z, hi = a[u], -b[u]
            o[u] = (hi > 0) & ((z <= 0) | (np.float32(hi - z) > np.float32(jump * z)))


@nb.njit(cache=True, nogil=True)
def d405_edges(
    depth: np.ndarray, w: int, jump: np.float32
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The silhouette pixels of the D405 model, in row-major order: those whose (2w+1)^2
    window (clipped at the border) holds a surface and either an invalid pixel or a depth
    range above `jump` times its nearest depth. Returns their rows, columns, and the window's
    nearest and farthest depths (float32). `depth` holds no NaN (0: invalid).

    Separable window minimum and maximum over the whole image (branch-free, vectorised), then
    the nearest valid depth searched again only for the silhouette pixels whose window holds a
    hole: 3.3x faster than one branching pass per pixel (benchmarks in docs/results/speed.md)."""
    H, W = depth.shape
    lo = _window_min(depth, w, np.float32(1.0))
    neg_hi = _window_min(depth, w, np.float32(-1.0))
    mask = np.empty((H, W), np.bool_)
    _edge_mask(lo, neg_hi, jump, mask)
    n = np.count_nonzero(mask)
    ev = np.empty(n, np.int64)
    eu = np.empty(n, np.int64)
    nv = np.empty(n, np.float32)
    fv = np.empty(n, np.float32)
    n = 0
    for v in range(H):
        row = mask[v]
        for u in range(W):
            if not row[u]:
                continue
            near = lo[v, u]
            if not near > 0:  # a hole in the window: its nearest valid depth
                near = np.float32(np.inf)
                for vv in range(max(0, v - w), min(H, v + w + 1)):
                    for uu in range(max(0, u - w), min(W, u + w + 1)):
                        z = depth[vv, uu]
                        if z > 0 and z < near:
                            near = z
            ev[n], eu[n], nv[n], fv[n] = v, u, near, -neg_hi[v, u]
            n += 1
    return ev, eu, nv, fv


@nb.njit(cache=True, nogil=True)
def d405_edges_rows(
    depth: np.ndarray, w: int, jump: np.float32, v0: int, v1: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """`d405_edges` for rows v0..v1 only: run on those rows and w more on each side (every
    window of the band's rows, clipped at the image's border as in the whole image)."""
    H = depth.shape[0]
    a0, a1 = max(0, v0 - w), min(H, v1 + w)
    ev, eu, nv, fv = d405_edges(depth[a0:a1], w, jump)
    n = 0
    for k in range(ev.shape[0]):
        if v0 <= ev[k] + a0 < v1:
            ev[n], eu[n], nv[n], fv[n] = ev[k] + a0, eu[k], nv[k], fv[k]
            n += 1
    return ev[:n], eu[:n], nv[:n], fv[:n]


@nb.njit(cache=True, nogil=True)
def d405_silhouettes(
    depth: np.ndarray,
    ev: np.ndarray,
    eu: np.ndarray,
    nv: np.ndarray,
    fv: np.ndarray,
    u1: np.ndarray,
    u2: np.ndarray,
    u3: np.ndarray,
    fatten_above: np.float32,
    p_fatten: np.float32,
    p_invalid: np.float32,
    p_smear: np.float32,
) -> None:
    """Step 1 of the D405 model on the silhouette pixels of `d405_edges`, in place, with one
    uniform draw of each of u1, u2, u3 per pixel: foreground fattening (a background or empty
    pixel beside a near surface takes its depth, u1 < p_fatten), else invalid (u2 < p_invalid),
    else a smear between the near and the far side (u2 < p_smear, a cumulative threshold)."""
    for k in range(ev.shape[0]):
        v, u = ev[k], eu[k]
        dv, near, far = depth[v, u], nv[k], fv[k]
        on = dv > 0
        if ((not on) or dv > near * fatten_above) and u1[k] < p_fatten:
            depth[v, u] = near
        elif u2[k] < p_invalid:
            depth[v, u] = np.float32(0.0)
        elif on and u2[k] < p_smear:
            hi = far if far > 0 else near
            depth[v, u] = near + u3[k] * (hi - near)


@nb.njit(cache=True, nogil=True)
def standard_normals(rng: np.random.Generator, n: int) -> np.ndarray:
    """n standard normal draws from `rng`, the numbers and the generator's state after them
    exactly as `rng.standard_normal(n)` gives (numba's Generator follows numpy's ziggurat;
    tests/test_render.py), 3.5x faster: 0.34 against 1.19 ms for 140k draws."""
    return rng.standard_normal(n)


@nb.njit(cache=True, nogil=True)
def d405_axial(
    depth: np.ndarray,
    normal: np.ndarray,
    drop: np.ndarray,
    scale: float,
    sub: float,
    fxb: float,
    p_drop: float,
    zmin: float,
    zmax: float,
    unit: float,
    before: np.ndarray,
    v0: int,
    v1: int,
) -> None:
    """Steps 2-5 of the D405 model on the valid pixels of rows v0..v1 in row-major order, in
    place: depth times `scale`; plus normal[i] * z^2 * sub / fxb (when `normal` is not empty);
    invalid when drop[i] < p_drop (when `drop` is not empty); invalid outside [zmin, zmax];
    rounded to `unit` (when unit > 0). Computed in float64 and stored in the image's float32.
    `before[v]`: the valid pixels before row v (the draws are indexed over the whole image)."""
    i = before[v0]
    noise = normal.shape[0] > 0
    dropping = drop.shape[0] > 0
    for v in range(v0, v1):
        for u in range(depth.shape[1]):
            if not depth[v, u] > 0:
                continue
            z = np.float64(depth[v, u])
            if scale != 1.0:
                z *= scale
            if noise:
                z += normal[i] * (z * z * sub / fxb)
            if dropping and drop[i] < p_drop:
                z = 0.0
            if z < zmin or z > zmax:
                z = 0.0
            if unit > 0:
                z = np.rint(z / unit) * unit
            depth[v, u] = z
            i += 1


@nb.njit(cache=True, nogil=True)
def clean_depth(src: np.ndarray, out: np.ndarray) -> tuple[int, int, int, int]:
    """`src` (any float type) into float32 `out`, 0 where it is not finite or negative; returns
    the bounding box of the valid (positive) pixels as rows r0..r1 and columns c0..c1
    (inclusive; r1 = -1 when there is none). Branch-free copy, then per row a test for any
    valid pixel and a search from each end only up to the box so far (numpy's copy, mask and
    box took 0.4-0.5 ms of an 848x480 image)."""
    H, W = src.shape
    r0, r1, c0, c1 = H, -1, W, -1
    for v in range(H):
        row = out[v]
        srow = src[v]
        for u in range(W):
            x = np.float32(srow[u])
            row[u] = x if (x >= 0 and x < np.inf) else np.float32(0.0)  # NaN, inf, negative
        hit = False
        for u in range(W):
            hit |= row[u] > 0
        if not hit:
            continue
        if r0 == H:
            r0 = v
        r1 = v
        for u in range(min(c0, W)):
            if row[u] > 0:
                c0 = u
                break
        for u in range(W - 1, c1, -1):
            if row[u] > 0:
                c1 = u
                break
    return r0, r1, c0, c1


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


# ----------------------------------------------------------------------------- z-buffer rendering
@nb.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _raster_triangle(
    u0: float,
    v0: float,
    w0: float,
    u1: float,
    v1: float,
    w1: float,
    u2: float,
    v2: float,
    w2: float,
    zbuf: np.ndarray,
) -> None:
    """One projected triangle (pixel coordinates u, v; w = 1/z) into `zbuf` (z-depth, +inf where
    empty): every pixel centre (integer u, v) inside it or on its edges takes the depth of the
    triangle's plane along its ray (1/z interpolated linearly in the image), where nearer. A back
    face (clockwise in the image, y down: its outward normal faces away) is skipped: the caller
    draws a two-sided face in both windings. (A branch on a flag here cost 20% of the view.)
    The pixel loop has no branch: every pixel of the box gets its depth computed and the nearer
    one stored, as the boxes are small (9 pixels on average in the dense vine's views) and a
    test per pixel mispredicted (the dense vine's view 4.75 -> 3.5 ms, the same image to the
    bit); so `error_model="numpy"`: a division by zero outside the triangle gives inf, not an
    exception."""
    H, W = zbuf.shape
    area = (u1 - u0) * (v2 - v0) - (u2 - u0) * (v1 - v0)
    if not area < 0.0:  # degenerate (or NaN)
        return
    # the pixel centres of its bounding box, clamped to the image before rounding
    umin = math.ceil(max(min(u0, min(u1, u2)), 0.0))
    umax = math.floor(min(max(u0, max(u1, u2)), W - 1.0))
    if umin > umax:
        return
    vmin = math.ceil(max(min(v0, min(v1, v2)), 0.0))
    vmax = math.floor(min(max(v0, max(v1, v2)), H - 1.0))
    if vmin > vmax:
        return
    inv = 1.0 / area
    du0 = v1 - v2  # the edge functions' steps along a row
    du1 = v2 - v0
    for v in range(vmin, vmax + 1):
        # edge functions opposite vertices 0 and 1 (<= 0 inside, since the area is negative)
        e0 = (u1 - umin) * (v2 - v) - (u2 - umin) * (v1 - v)
        e1 = (u2 - umin) * (v0 - v) - (u0 - umin) * (v2 - v)
        for u in range(umin, umax + 1):
            b0 = e0 * inv
            b1 = e1 * inv
            b2 = 1.0 - b0 - b1
            z = 1.0 / (b0 * w0 + b1 * w1 + b2 * w2)
            inside = (e0 <= 0.0) & (e1 <= 0.0) & (b2 >= 0.0)
            cur = np.float64(zbuf[v, u])
            zbuf[v, u] = z if inside and z < cur else cur  # no branch: small boxes mispredict
            e0 += du0
            e1 += du1


@nb.njit(cache=True, nogil=True)
def _raster_clipped(
    V: np.ndarray,
    a: int,
    b: int,
    c: int,
    R: np.ndarray,
    t: np.ndarray,
    k: np.ndarray,
    two_sided: bool,
    zbuf: np.ndarray,
) -> None:
    """A triangle crossing the near plane (camera frame): its part in front, clipped
    (Sutherland-Hodgman against the one plane: 3 or 4 corners), drawn as a fan. R, t, k: as for
    `raster_pieces`."""
    fx, fy, cx, cy, znear = k[0], k[1], k[2], k[3], k[4]
    cam = np.empty((3, 3))
    idx = (a, b, c)
    for j in range(3):
        i = idx[j]
        d0, d1, d2 = V[i, 0] - t[0], V[i, 1] - t[1], V[i, 2] - t[2]
        for r in range(3):
            cam[j, r] = R[0, r] * d0 + R[1, r] * d1 + R[2, r] * d2
    poly = np.empty((4, 3))
    n = 0
    for j in range(3):
        p, q = cam[j], cam[(j + 1) % 3]
        p_in, q_in = p[2] >= znear, q[2] >= znear
        if p_in:
            poly[n] = p
            n += 1
        if p_in != q_in:
            s = (znear - p[2]) / (q[2] - p[2])
            poly[n] = p + s * (q - p)
            poly[n, 2] = znear
            n += 1
    uvw = np.empty((4, 3))
    for j in range(n):
        w = 1.0 / poly[j, 2]
        uvw[j, 0] = fx * poly[j, 0] * w + cx
        uvw[j, 1] = fy * poly[j, 1] * w + cy
        uvw[j, 2] = w
    for j in range(1, n - 1):
        _raster_triangle(
            uvw[0, 0], uvw[0, 1], uvw[0, 2], uvw[j, 0], uvw[j, 1], uvw[j, 2],
            uvw[j + 1, 0], uvw[j + 1, 1], uvw[j + 1, 2], zbuf,
        )  # fmt: skip
        if two_sided:
            _raster_triangle(
                uvw[0, 0], uvw[0, 1], uvw[0, 2], uvw[j + 1, 0], uvw[j + 1, 1], uvw[j + 1, 2],
                uvw[j, 0], uvw[j, 1], uvw[j, 2], zbuf,
            )  # fmt: skip


@nb.njit(cache=True, nogil=True)
def raster_pieces(
    V: np.ndarray,
    F: np.ndarray,
    pieces: np.ndarray,
    vstart: np.ndarray,
    fstart: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    k: np.ndarray,
    two_sided: bool,
    zbuf: np.ndarray,
    P: np.ndarray,
) -> None:
    """Z-buffer rendering of the mesh pieces `pieces` (ids) into `zbuf` (H, W, float32, +inf
    where empty), the camera at rotation `R`, position `t` in the mesh's frame (OpenCV axes),
    `k` = (fx, fy, cx, cy, znear): the intrinsics and the near plane.
    Piece p owns vertices `V[vstart[p]:vstart[p+1]]` and faces `F[fstart[p]:fstart[p+1]]`
    (indices into V, within its own vertices), so each vertex is projected once per view into
    the scratch `P` (n, 4: u, v, 1/z, z). Triangles wholly behind `znear` are dropped, those
    crossing it clipped."""
    r00, r01, r02 = R[0, 0], R[0, 1], R[0, 2]
    r10, r11, r12 = R[1, 0], R[1, 1], R[1, 2]
    r20, r21, r22 = R[2, 0], R[2, 1], R[2, 2]
    tx, ty, tz = t[0], t[1], t[2]
    fx, fy, cx, cy, znear = k[0], k[1], k[2], k[3], k[4]
    for piece in pieces:
        for i in range(vstart[piece], vstart[piece + 1]):
            dx, dy, dz = V[i, 0] - tx, V[i, 1] - ty, V[i, 2] - tz
            x = r00 * dx + r10 * dy + r20 * dz  # R^T (v - t)
            y = r01 * dx + r11 * dy + r21 * dz
            z = r02 * dx + r12 * dy + r22 * dz
            P[i, 3] = z
            if z >= znear:
                w = 1.0 / z
                P[i, 0] = fx * x * w + cx
                P[i, 1] = fy * y * w + cy
                P[i, 2] = w
        for f in range(fstart[piece], fstart[piece + 1]):
            a, b, c = F[f, 0], F[f, 1], F[f, 2]
            a_in, b_in, c_in = P[a, 3] >= znear, P[b, 3] >= znear, P[c, 3] >= znear
            if a_in and b_in and c_in:
                _raster_triangle(
                    P[a, 0], P[a, 1], P[a, 2], P[b, 0], P[b, 1], P[b, 2],
                    P[c, 0], P[c, 1], P[c, 2], zbuf,
                )  # fmt: skip
                if two_sided:  # the face seen from behind: the other winding
                    _raster_triangle(
                        P[a, 0], P[a, 1], P[a, 2], P[c, 0], P[c, 1], P[c, 2],
                        P[b, 0], P[b, 1], P[b, 2], zbuf,
                    )  # fmt: skip
            elif a_in or b_in or c_in:
                _raster_clipped(V, a, b, c, R, t, k, two_sided, zbuf)


@nb.njit(cache=True, nogil=True)
def zbuffer_depth(zbuf: np.ndarray, out: np.ndarray) -> None:
    """`out` = the z-buffer with 0 where empty (+inf); the z-buffer reset to +inf for the next
    view."""
    H, W = out.shape
    for v in range(H):
        for u in range(W):
            z = zbuf[v, u]
            out[v, u] = z if z < np.inf else np.float32(0.0)
            zbuf[v, u] = np.inf


@nb.njit(cache=True, nogil=True)
def closed_consistent(F: np.ndarray, n_vertices: int) -> bool:
    """Whether the triangles `F` (m, 3) close a surface consistently wound: every directed edge
    (a, b) occurs once, and its reverse (b, a) once (each edge shared by two faces that agree on
    its orientation). Outgoing edges are bucketed by their first vertex, so each check scans a
    vertex's few neighbours: linear in the faces (the dense vine's 897k in tens of ms)."""
    m = F.shape[0]
    start = np.zeros(n_vertices + 1, np.int64)
    for f in range(m):
        for j in range(3):
            start[F[f, j] + 1] += 1
    for i in range(n_vertices):
        start[i + 1] += start[i]
    fill = start[:-1].copy()
    target = np.empty(3 * m, np.int64)
    for f in range(m):
        for j in range(3):
            a, b = F[f, j], F[f, (j + 1) % 3]
            target[fill[a]] = b
            fill[a] += 1
    for a in range(n_vertices):
        for k in range(start[a], start[a + 1]):
            b = target[k]
            if b == a:
                return False
            for k2 in range(k + 1, start[a + 1]):
                if target[k2] == b:  # (a, b) twice: inconsistent winding or non-manifold
                    return False
            back = 0
            for k3 in range(start[b], start[b + 1]):
                back += target[k3] == a
            if back != 1:  # an open edge, or a non-manifold one
                return False
    return True


@nb.njit(cache=True, nogil=True)
def signed_volume(V: np.ndarray, F: np.ndarray) -> float:
    """The volume the triangles enclose, positive where they are wound counter-clockwise seen
    from outside (outward normals); meaningful for a closed surface (`closed_consistent`)."""
    total = 0.0
    for f in range(F.shape[0]):
        a, b, c = V[F[f, 0]], V[F[f, 1]], V[F[f, 2]]
        total += (
            a[0] * (b[1] * c[2] - b[2] * c[1])
            - a[1] * (b[0] * c[2] - b[2] * c[0])
            + a[2] * (b[0] * c[1] - b[1] * c[0])
        )
    return total / 6.0
