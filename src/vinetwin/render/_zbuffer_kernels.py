"""Compiled z-buffer work of the renderers: vinetwin's rasteriser (`raster`) and the conversion
of OpenGL reverse-Z buffers (`pyrender`, `mujoco`) and z-buffers to metric depth."""

from __future__ import annotations

import math

import numpy as np

from vinetwin._numba import nb


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
