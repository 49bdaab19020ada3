"""Compiled ICP (numba): the reference's search structures and one whole registration level.

The reference never changes during a servo, so its k-d tree (flat arrays, median splits, leaves
of 8 points) is built once; a query gives the exact closest reference point within the
correspondence distance. Within a registration the tree's answers are memoised: a point that
has moved less since its last search than the margin by which its partner was closest (the
second closest point's distance less the partner's) keeps its partner without a search, which
is still the exact answer; late iterations move points by hundredths of a millimetre. The
reference is also a view from a known camera: `ProjectiveIndex` bins its points by their pixel,
and projective association pairs a current point with the closest reference point in the cells
around its own projection (no tree, O(1) per point). A level runs entirely in compiled code:
association, the variant's linear system, the 6x6 solve (or the 3x3 SVD of point-to-point) and
the convergence test, so a frame costs one Python call per level.

Variant codes: 0 point-to-point, 1 Levenberg-Marquardt, 2 point-to-plane, 3 symmetric.
Status codes: 0 converged, 1 iteration limit, 2 too few correspondences, 3 singular system.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from vinetwin._numba import nb
from vinetwin.registration._search_kernels import _associate_range, _buffers

VARIANT_CODES = {"point_to_point": 0, "lm": 1, "point_to_plane": 2, "symmetric": 3}
CONVERGED, ITERATION_LIMIT, FEW_PAIRS, SINGULAR = 0, 1, 2, 3


@nb.njit(cache=True, nogil=True)
def _rodrigues(w: np.ndarray) -> np.ndarray:
    th = math.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
    R = np.eye(3)
    if th < 1e-15:
        R[0, 1] = -w[2]
        R[0, 2] = w[1]
        R[1, 0] = w[2]
        R[1, 2] = -w[0]
        R[2, 0] = -w[1]
        R[2, 1] = w[0]
        return R
    k = w / th
    K = np.zeros((3, 3))
    K[0, 1] = -k[2]
    K[0, 2] = k[1]
    K[1, 0] = k[2]
    K[1, 2] = -k[0]
    K[2, 0] = -k[1]
    K[2, 1] = k[0]
    return R + math.sin(th) * K + (1.0 - math.cos(th)) * (K @ K)


@nb.njit(cache=True, nogil=True)
def _pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


@nb.njit(cache=True, nogil=True)
def _kabsch_step(q: np.ndarray, y: np.ndarray, idx: np.ndarray, sel: np.ndarray) -> np.ndarray:
    """Closed-form rigid step (SVD of the cross-covariance) moving q[sel] onto y[idx[sel]]."""
    m = sel.shape[0]
    cq = np.zeros(3)
    cy = np.zeros(3)
    H = np.zeros((3, 3))
    for s in range(m):
        i = sel[s]
        j = idx[i]
        for a in range(3):
            cq[a] += q[i, a]
            cy[a] += y[j, a]
            for c in range(3):
                H[a, c] += q[i, a] * y[j, c]
    for a in range(3):
        cq[a] /= m
        cy[a] /= m
    for a in range(3):
        for c in range(3):
            H[a, c] -= m * cq[a] * cy[c]
    U, _, Vt = np.linalg.svd(H)
    D = np.eye(3)
    if np.linalg.det(Vt.T @ U.T) < 0:
        D[2, 2] = -1.0
    R = Vt.T @ D @ U.T
    return _pose(R, cy - R @ cq)


@nb.njit(cache=True, nogil=True)
def _normal_eq(
    q: np.ndarray,
    y: np.ndarray,
    ny: np.ndarray,
    nq: np.ndarray,
    idx: np.ndarray,
    sel: np.ndarray,
    symmetric: bool,
) -> tuple[np.ndarray, np.ndarray]:
    """J^T J and J^T r of the point-to-plane (or symmetric) residuals over the pairs `sel`
    (the 21 entries of J^T J's upper triangle and J^T r kept in scalars: in registers)."""
    a00 = a01 = a02 = a03 = a04 = a05 = 0.0
    a11 = a12 = a13 = a14 = a15 = 0.0
    a22 = a23 = a24 = a25 = 0.0
    a33 = a34 = a35 = 0.0
    a44 = a45 = 0.0
    a55 = 0.0
    b0 = b1 = b2 = b3 = b4 = b5 = 0.0
    for s in range(sel.shape[0]):
        i = sel[s]
        j = idx[i]
        if symmetric:
            n0 = nq[i, 0] + ny[j, 0]
            n1 = nq[i, 1] + ny[j, 1]
            n2 = nq[i, 2] + ny[j, 2]
            p0 = q[i, 0] + y[j, 0]
            p1 = q[i, 1] + y[j, 1]
            p2 = q[i, 2] + y[j, 2]
        else:
            n0 = ny[j, 0]
            n1 = ny[j, 1]
            n2 = ny[j, 2]
            p0 = q[i, 0]
            p1 = q[i, 1]
            p2 = q[i, 2]
        r = (q[i, 0] - y[j, 0]) * n0 + (q[i, 1] - y[j, 1]) * n1 + (q[i, 2] - y[j, 2]) * n2
        j3 = p1 * n2 - p2 * n1
        j4 = p2 * n0 - p0 * n2
        j5 = p0 * n1 - p1 * n0
        b0 += n0 * r
        b1 += n1 * r
        b2 += n2 * r
        b3 += j3 * r
        b4 += j4 * r
        b5 += j5 * r
        a00 += n0 * n0
        a01 += n0 * n1
        a02 += n0 * n2
        a03 += n0 * j3
        a04 += n0 * j4
        a05 += n0 * j5
        a11 += n1 * n1
        a12 += n1 * n2
        a13 += n1 * j3
        a14 += n1 * j4
        a15 += n1 * j5
        a22 += n2 * n2
        a23 += n2 * j3
        a24 += n2 * j4
        a25 += n2 * j5
        a33 += j3 * j3
        a34 += j3 * j4
        a35 += j3 * j5
        a44 += j4 * j4
        a45 += j4 * j5
        a55 += j5 * j5
    A = np.empty((6, 6))
    A[0, 0], A[0, 1], A[0, 2], A[0, 3], A[0, 4], A[0, 5] = a00, a01, a02, a03, a04, a05
    A[1, 1], A[1, 2], A[1, 3], A[1, 4], A[1, 5] = a11, a12, a13, a14, a15
    A[2, 2], A[2, 3], A[2, 4], A[2, 5] = a22, a23, a24, a25
    A[3, 3], A[3, 4], A[3, 5] = a33, a34, a35
    A[4, 4], A[4, 5] = a44, a45
    A[5, 5] = a55
    for a in range(6):
        for c in range(a):
            A[a, c] = A[c, a]
    b = np.array([b0, b1, b2, b3, b4, b5])
    return A, b


@nb.njit(cache=True, nogil=True)
def _lm_cost(
    q: np.ndarray, y: np.ndarray, idx: np.ndarray, sel: np.ndarray, dT: np.ndarray, huber: float
) -> float:
    cost = 0.0
    for s in range(sel.shape[0]):
        i = sel[s]
        j = idx[i]
        e2 = 0.0
        for a in range(3):
            v = dT[a, 0] * q[i, 0] + dT[a, 1] * q[i, 1] + dT[a, 2] * q[i, 2] + dT[a, 3] - y[j, a]
            e2 += v * v
        if huber > 0 and e2 > huber * huber:
            cost += 2.0 * huber * math.sqrt(e2) - huber * huber
        else:
            cost += e2
    return cost


@nb.njit(cache=True, nogil=True)
def _lm_step(
    q: np.ndarray, y: np.ndarray, idx: np.ndarray, sel: np.ndarray, mu: float, huber: float
) -> tuple[np.ndarray, float]:
    """One Levenberg-Marquardt step on the point-to-point residuals of fixed pairs (IRLS weights
    for the Huber kernel). Returns the accepted step (identity if none lowers the cost) and the
    new damping."""
    A = np.zeros((6, 6))
    g = np.zeros(6)
    for s in range(sel.shape[0]):
        i = sel[s]
        j = idx[i]
        r0 = q[i, 0] - y[j, 0]
        r1 = q[i, 1] - y[j, 1]
        r2 = q[i, 2] - y[j, 2]
        w = 1.0
        if huber > 0:
            nr = math.sqrt(r0 * r0 + r1 * r1 + r2 * r2)
            if nr > huber:
                w = huber / nr
        x0, x1, x2 = q[i, 0], q[i, 1], q[i, 2]
        # J = [I, -[x]x] for x' = x + w x x + t
        A[0, 0] += w
        A[1, 1] += w
        A[2, 2] += w
        A[0, 4] += w * x2
        A[0, 5] -= w * x1
        A[1, 3] -= w * x2
        A[1, 5] += w * x0
        A[2, 3] += w * x1
        A[2, 4] -= w * x0
        A[3, 3] += w * (x1 * x1 + x2 * x2)
        A[4, 4] += w * (x0 * x0 + x2 * x2)
        A[5, 5] += w * (x0 * x0 + x1 * x1)
        A[3, 4] -= w * x0 * x1
        A[3, 5] -= w * x0 * x2
        A[4, 5] -= w * x1 * x2
        g[0] += w * r0
        g[1] += w * r1
        g[2] += w * r2
        g[3] += w * (x1 * r2 - x2 * r1)
        g[4] += w * (x2 * r0 - x0 * r2)
        g[5] += w * (x0 * r1 - x1 * r0)
    for a in range(6):
        for c in range(a):
            A[a, c] = A[c, a]
    cost0 = _lm_cost(q, y, idx, sel, np.eye(4), huber)
    for _ in range(12):
        M = A.copy()
        for a in range(6):
            M[a, a] += mu * A[a, a]
        if not _well_posed(M):
            mu *= 10.0
            continue
        x = np.linalg.solve(M, -g)
        dT = _pose(_rodrigues(x[3:]), x[:3])
        if _lm_cost(q, y, idx, sel, dT, huber) < cost0:
            return dT, max(mu / 10.0, 1e-9)
        mu *= 10.0
    return np.eye(4), mu


@nb.njit(cache=True, nogil=True)
def disc_residual(
    x0: float, x1: float, x2: float, y: np.ndarray, nrm: np.ndarray, j: Any, radius: float
) -> tuple[float, float, float, float]:
    """The distance from point x to reference surfel j, a disc of `radius` about point j with
    normal j, and its gradient in x: over the disc the signed height above it (gradient: the
    normal), past its rim the distance to the rim (gradient: the unit vector from the rim)."""
    e0, e1, e2 = x0 - y[j, 0], x1 - y[j, 1], x2 - y[j, 2]
    n0, n1, n2 = nrm[j, 0], nrm[j, 1], nrm[j, 2]
    h = e0 * n0 + e1 * n1 + e2 * n2
    t0, t1, t2 = e0 - h * n0, e1 - h * n1, e2 - h * n2
    tt = t0 * t0 + t1 * t1 + t2 * t2
    if tt <= radius * radius:
        return h, n0, n1, n2
    tn = math.sqrt(tt)
    out = tn - radius
    d = math.sqrt(h * h + out * out)
    g0 = (h * n0 + out * t0 / tn) / d
    g1 = (h * n1 + out * t1 / tn) / d
    g2 = (h * n2 + out * t2 / tn) / d
    return d, g0, g1, g2


@nb.njit(cache=True, nogil=True)
def _rho(r: float, huber: float) -> float:
    """The Huber kernel of a residual (the square when huber is 0)."""
    a = abs(r)
    if huber > 0 and a > huber:
        return 2.0 * huber * a - huber * huber
    return r * r


@nb.njit(cache=True, nogil=True)
def _lm_surface_cost(
    q: np.ndarray,
    y: np.ndarray,
    nrm: np.ndarray,
    idx: np.ndarray,
    sel: np.ndarray,
    dT: np.ndarray,
    huber: float,
    radius: float,
) -> float:
    cost = 0.0
    for s in range(sel.shape[0]):
        i = sel[s]
        x0 = dT[0, 0] * q[i, 0] + dT[0, 1] * q[i, 1] + dT[0, 2] * q[i, 2] + dT[0, 3]
        x1 = dT[1, 0] * q[i, 0] + dT[1, 1] * q[i, 1] + dT[1, 2] * q[i, 2] + dT[1, 3]
        x2 = dT[2, 0] * q[i, 0] + dT[2, 1] * q[i, 1] + dT[2, 2] * q[i, 2] + dT[2, 3]
        cost += _rho(disc_residual(x0, x1, x2, y, nrm, idx[i], radius)[0], huber)
    return cost


@nb.njit(cache=True, nogil=True)
def _lm_surface_step(
    q: np.ndarray,
    y: np.ndarray,
    nrm: np.ndarray,
    idx: np.ndarray,
    sel: np.ndarray,
    mu: float,
    huber: float,
    radius: float,
    tol_t: float,
    tol_r: float,
) -> tuple[np.ndarray, float, bool]:
    """One Levenberg-Marquardt step on the distances of the paired current points to the
    reference surface, modelled as discs about its points (`disc_residual`): fixed pairs, IRLS
    weights for the Huber kernel, damping scaled by the Hessian's diagonal (Marquardt). Returns
    the accepted step (an update below the tolerances is returned untested: the level has
    converged; identity if no damping lowers the cost), the new damping, and whether the pairs
    leave a motion unconstrained (a plane, a straight cane: the step is then identity)."""
    A = np.zeros((6, 6))
    g = np.zeros(6)
    J = np.empty(6)
    cost0 = 0.0
    for s in range(sel.shape[0]):
        i = sel[s]
        x0, x1, x2 = q[i, 0], q[i, 1], q[i, 2]
        r, u0, u1, u2 = disc_residual(x0, x1, x2, y, nrm, idx[i], radius)
        cost0 += _rho(r, huber)
        w = 1.0
        a = abs(r)
        if huber > 0 and a > huber:
            w = huber / a
        # d r / d (t, w) for x' = x + w x x + t
        J[0], J[1], J[2] = u0, u1, u2
        J[3] = x1 * u2 - x2 * u1
        J[4] = x2 * u0 - x0 * u2
        J[5] = x0 * u1 - x1 * u0
        for k in range(6):
            g[k] += w * J[k] * r
            for c in range(k, 6):
                A[k, c] += w * J[k] * J[c]
    for k in range(6):
        for c in range(k):
            A[k, c] = A[c, k]
    if not _well_posed(A):
        return np.eye(4), mu, True
    for _ in range(12):
        M = A.copy()
        for k in range(6):
            M[k, k] += mu * A[k, k]
        x = np.linalg.solve(M, -g)
        dT = _pose(_rodrigues(x[3:]), x[:3])
        if _small(dT, tol_t, tol_r):
            return dT, mu, False
        if _lm_surface_cost(q, y, nrm, idx, sel, dT, huber, radius) < cost0:
            return dT, max(mu / 10.0, 1e-9), False
        mu *= 10.0
    return np.eye(4), mu, False


@nb.njit(cache=True, nogil=True)
def _symmetric_pose(x: np.ndarray) -> np.ndarray:
    """Rusinkiewicz's step: R_half * Trans(t cos(theta)) * R_half, theta = atan(|a|)."""
    a = x[3:]
    an = math.sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2])
    if an > 1e-15:
        th = math.atan(an)
        half = _rodrigues(a / an * th)
        c = math.cos(th)
    else:
        half = np.eye(3)
        c = 1.0
    H = _pose(half, np.zeros(3))
    return H @ _pose(np.eye(3), x[:3] * c) @ H


@nb.njit(cache=True, nogil=True)
def _well_posed(A: np.ndarray) -> bool:
    d = 0.0
    for a in range(6):
        d = max(d, A[a, a])
    if not d > 0:
        return False
    # relative determinant test on the scaled system
    s = np.empty(6)
    for a in range(6):
        s[a] = 1.0 / math.sqrt(A[a, a]) if A[a, a] > 0 else 0.0
    for a in range(6):
        if s[a] == 0.0:
            return False
    M = A * np.outer(s, s)
    return abs(np.linalg.det(M)) > 1e-14


@nb.njit(cache=True, nogil=True, parallel=True)
def register_level(
    src: np.ndarray,
    src_n: np.ndarray,
    tree: Any,
    nrm: np.ndarray,
    use: np.ndarray,
    T0: np.ndarray,
    dmax: float,
    variant: int,
    max_iter: int,
    tol_t: float,
    tol_r: float,
    min_pairs: int,
    huber: float,
    threads: int,
    accelerate: bool,
    proj: Any,
    lm_radius: float,
    memo: Any,
) -> tuple[np.ndarray, int, int, int, float]:
    """One level of ICP from T0. Returns (T, status, iterations, pairs, rmse of the last
    association). `tree` is `NNTree.arrays`; `nrm` and `use` are in its point order. `proj`:
    a `ProjectiveIndex`'s arrays over the same points for projective association, or
    `NO_PROJECTIVE` for the tree's exact closest points. `lm_radius` > 0: LM minimises the
    distances to the reference surface as discs of this radius about its points (`nrm` then
    holds their normals), else the distances to the points. `memo`: `new_memo(len(src))`, or the
    memo a previous level over the same `src` and tree left (its answers stay exact)."""
    pts = tree[0]
    T = T0.copy()
    n, q, idx, d2, chunks, size = _buffers(src, threads)
    hist = np.zeros((4, 4, 4))
    for k in range(4):
        hist[k] = T
    alpha = 1.0
    cooldown = 0
    extrapolated = False
    T_plain = T.copy()
    rmse_before = np.inf
    prev_step = np.zeros(6)
    mu = 1e-3
    it = 0
    npairs = 0
    rmse = np.nan
    for it in range(1, max_iter + 1):
        for c in nb.prange(chunks):
            _associate_range(
                src, T, tree, dmax, c * size, min(n, (c + 1) * size), q, idx, d2, proj, memo
            )
        for i in range(idx.shape[0]):
            if idx[i] >= 0 and not use[idx[i]]:
                idx[i] = -1
        sel = np.nonzero(idx >= 0)[0]
        npairs = sel.shape[0]
        if npairs < min_pairs:
            return T, FEW_PAIRS, it, npairs, rmse
        acc = 0.0
        for s in range(npairs):
            acc += d2[sel[s]]
        rmse = math.sqrt(acc / npairs)
        if extrapolated:
            extrapolated = False
            if rmse > rmse_before:  # the jump made things worse: back to the plain step
                T = T_plain
                alpha = 1.0
                cooldown = 3
                continue
        if variant == 0:
            dT = _kabsch_step(q, pts, idx, sel)
        elif variant == 1 and lm_radius > 0:
            dT, mu, singular = _lm_surface_step(
                q, pts, nrm, idx, sel, mu, huber, lm_radius, tol_t, tol_r
            )
            if singular:
                return T, SINGULAR, it, npairs, rmse
        elif variant == 1:
            dT, mu = _lm_step(q, pts, idx, sel, mu, huber)
        else:
            if variant == 3:
                nq = np.empty_like(src_n)
                for i in range(src_n.shape[0]):
                    for a in range(3):
                        nq[i, a] = (
                            T[a, 0] * src_n[i, 0] + T[a, 1] * src_n[i, 1] + T[a, 2] * src_n[i, 2]
                        )
            else:
                nq = src_n
            A, b = _normal_eq(q, pts, nrm, nq, idx, sel, variant == 3)
            if not _well_posed(A):
                return T, SINGULAR, it, npairs, rmse
            x = np.linalg.solve(A, -b)
            if variant == 2:
                dT = _pose(_rodrigues(x[3:]), x[:3])
            else:
                dT = _symmetric_pose(x)
        if _small(dT, tol_t, tol_r):
            return dT @ T, CONVERGED, it, npairs, rmse
        step = _step_vector(dT)
        if accelerate and (variant == 0 or (variant == 1 and lm_radius <= 0)):
            # Besl & McKay's acceleration, simplified: while successive updates point the same
            # way, take a growing multiple of the update; undo it if the energy rises
            if cooldown > 0:
                cooldown -= 1
                alpha = 1.0
            elif _cosine(step, prev_step) > 0.9:
                alpha = min(2.0 * alpha, 16.0)
            else:
                alpha = 1.0
            prev_step = step
            if alpha > 1.0:
                T_plain = dT @ T
                rmse_before = rmse
                extrapolated = True
                T = _pose(_rodrigues(alpha * _rotvec(dT)), alpha * dT[:3, 3]) @ T
            else:
                T = dT @ T
        else:
            T = dT @ T
        # a hard reach can make the pair set flip between two or three states: a limit cycle
        # whose poses agree within the tolerance is a fixed point too
        for back in range(2, 4):
            if it > back and _small(_between(hist[(it - back) % 4], T), tol_t, tol_r):
                return T, CONVERGED, it, npairs, rmse
        hist[it % 4] = T
    return T, ITERATION_LIMIT, it, npairs, rmse


@nb.njit(cache=True, nogil=True)
def plane_hessian(q: np.ndarray, nrm: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """J^T J of the point-to-plane residuals of the pairs (q[i], normal nrm[idx[i]]), about the
    centre of q, the rotation columns scaled by the cloud's RMS radius (so both halves are in
    metres): its eigenvalues say which motions the pairs constrain."""
    n = q.shape[0]
    c = np.zeros(3)
    for i in range(n):
        for a in range(3):
            c[a] += q[i, a]
    c /= max(n, 1)
    ss = 0.0
    for i in range(n):
        for a in range(3):
            ss += (q[i, a] - c[a]) ** 2
    scale = math.sqrt(ss / max(n, 1))
    if scale == 0.0:
        scale = 1.0
    A = np.zeros((6, 6))
    J = np.empty(6)
    for i in range(n):
        j = idx[i]
        n0, n1, n2 = nrm[j, 0], nrm[j, 1], nrm[j, 2]
        p0, p1, p2 = q[i, 0] - c[0], q[i, 1] - c[1], q[i, 2] - c[2]
        J[0], J[1], J[2] = n0, n1, n2
        J[3] = (p1 * n2 - p2 * n1) / scale
        J[4] = (p2 * n0 - p0 * n2) / scale
        J[5] = (p0 * n1 - p1 * n0) / scale
        for a in range(6):
            for b in range(a, 6):
                A[a, b] += J[a] * J[b]
    for a in range(6):
        for b in range(a):
            A[a, b] = A[b, a]
    return A


@nb.njit(cache=True, nogil=True)
def _between(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """inv(A) @ B for rigid transforms."""
    Ai = np.eye(4)
    for r in range(3):
        for c in range(3):
            Ai[r, c] = A[c, r]
        Ai[r, 3] = -(A[0, r] * A[0, 3] + A[1, r] * A[1, 3] + A[2, r] * A[2, 3])
    return Ai @ B


@nb.njit(cache=True, nogil=True)
def _rotvec(dT: np.ndarray) -> np.ndarray:
    """Rotation vector of a pose's rotation (angles below pi)."""
    c = min(1.0, max(-1.0, (dT[0, 0] + dT[1, 1] + dT[2, 2] - 1.0) / 2.0))
    th = math.acos(c)
    v = np.array([dT[2, 1] - dT[1, 2], dT[0, 2] - dT[2, 0], dT[1, 0] - dT[0, 1]])
    s = math.sin(th)
    return v * 0.5 if s < 1e-12 else v * (th / (2.0 * s))


@nb.njit(cache=True, nogil=True)
def _step_vector(dT: np.ndarray) -> np.ndarray:
    """An update as a 6-vector (translation, rotation vector times 0.1 m)."""
    out = np.empty(6)
    out[:3] = dT[:3, 3]
    out[3:] = 0.1 * _rotvec(dT)
    return out


@nb.njit(cache=True, nogil=True)
def _cosine(a: np.ndarray, b: np.ndarray) -> float:
    na = math.sqrt((a * a).sum())
    nb_ = math.sqrt((b * b).sum())
    if na == 0.0 or nb_ == 0.0:
        return 0.0
    return float((a * b).sum()) / (na * nb_)


@nb.njit(cache=True, nogil=True)
def _small(dT: np.ndarray, tol_t: float, tol_r: float) -> bool:
    st = math.sqrt(dT[0, 3] ** 2 + dT[1, 3] ** 2 + dT[2, 3] ** 2)
    c = (dT[0, 0] + dT[1, 1] + dT[2, 2] - 1.0) / 2.0
    sr = math.acos(min(1.0, max(-1.0, c)))
    return st < tol_t and sr < tol_r
