"""Forks moved back to where two touching branches really part ("unzipping").

A level-set skeleton parts two branches only where their slices stop touching: canes of one
spur that run side by side for centimetres are followed as one axis, between the two, and the
child starts where they are a graph link apart (measured on simulated scans of the dense vine:
canes touching for 3-20 cm parted 1-15 cm late, their shared axis 5-6 mm off each). Cut rules
that remove a cane where it parts from the kept one then cut in the wrong place.

From each fork where the child leaves its parent at a small angle (`MAX_ANGLE`), the two
branches are followed back along the parent's axis in slices across it: in each slice, two
circles of the radii the two branches have past the fork are fitted to the scan's points (each
point to the circle it lies nearer; a few Gauss-Newton steps per centre, started where the
previous slice left them and, again, either side of the slice's points; the fit holding more
points is kept). The child is still there while enough points lie on its circle and off the
parent's (`MIN_SUPPORT`), the two circles hold clearly more points than one circle of any
radius (`TWO`: one branch's ring is not two canes) and the two centres stay apart (`MIN_APART`
of the radii's sum); slices where it is not made out are passed over up to an occlusion gap
(`MAX_MISSES`), and where it ends the branches have merged: the fork moves there. Both axes
then run through their own fitted centres over that stretch (the parent's shared, too-thick
stretch gets its own radius back).

Only a vine's skeleton is unzipped (`scan.skeletonize`): on the Tree-Models-Library's Y-trellis
apple the slices of the thick trunk below its arms, which neither one circle nor two explain,
were taken for two limbs (skeleton precision 95.8% to 92.3%), and a tree's laterals do not run
along their parent.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

from vinetwin.frames import Array
from vinetwin.twin.skeleton import (
    Branch,
    Skeleton,
    arc_length,
    arc_of_nearest,
    axis_samples,
    nearest_on_polyline,
    point_at,
)

#: Degrees: only a child leaving its parent within this of the parent's heading can have run
#: along it (a cane leaving a cordon across it is not followed back).
MAX_ANGLE = 60.0
#: Metres: no fork is unzipped when the scan's points lie farther than this (median absolute
#: deviation) off the skeleton's surfaces: two circles of a cane's radius cannot be told from
#: one there. Measured: 1.0-1.3 mm on simulated LiDAR scans of the vines at the realistic
#: quality, 1.7 at the coarse, 1.9-2.1 on a D405 rig's fused frames of the dense and VSP vines
#: (unzipped: better), 3.0 on the GDC vine's (its trunk's and cordons' smeared slices taken for
#: two branches: precision 89.1% to 72.1%).
MAX_SPREAD = 0.0025
#: Furthest (m) a fork is moved back.
MAX_BACK = 0.25
#: Points on the child's circle and off the parent's, at least (and at least this share of the
#: parent's own).
MIN_SUPPORT = 5
MIN_SHARE = 0.2
#: The two centres stay at least this share of the sum of the radii apart while both are there.
MIN_APART = 0.5
#: Two circles must hold this many times the points one circle (of any radius) holds (one
#: branch's ring: about as many; two touching canes: 1.5-2.2 times, on simulated scans).
TWO = 1.25
#: Slices in a row where the child is not made out that are passed over (an occlusion gap of
#: up to 2 cm at 4 mm steps).
MAX_MISSES = 5
#: How far back from the skeleton's fork (m) the first slice showing both may lie (the fork's
#: own slices are a junction's, neither branch's circle).
MAX_START = 0.03
#: Half a slice's thickness, in steps (the slices overlap: enough points on a thin cane).
SLAB = 2.0


def _unit(v: Array) -> Array:
    return v / max(float(np.linalg.norm(v)), 1e-12)


def _fit(q: Array, c: Array, r: float, steps: int = 4) -> Array:
    """Centre of a circle of radius r through the 2D points q (Gauss-Newton from c)."""
    for _ in range(steps):
        d = q - c
        n = np.maximum(np.linalg.norm(d, axis=1), 1e-9)
        res = n - r
        J = -d / n[:, None]
        try:
            dc = np.linalg.lstsq(J, -res, rcond=None)[0]
        except np.linalg.LinAlgError:
            break
        step = float(np.linalg.norm(dc))
        if step > r:  # damped: a few points on a short arc can pull the centre far
            dc *= r / step
        c = c + dc
        if step < 1e-5:
            break
    return c


def unzip_forks(sk: Skeleton, points: Array, tol: float) -> int:
    """Moves each fork of `sk` back to where its two branches part in `points` (see the
    module's docstring); in place. `tol`: how far (m) a point may lie off a branch's surface
    and count as on it (the scan's noise). Nothing is unzipped when the points lie more than
    `MAX_SPREAD` off the skeleton's surfaces. Returns the number of forks moved."""
    if len(points) < 50 or len(sk.branches) < 2:
        return 0
    if surface_spread(sk, points) > MAX_SPREAD:
        return 0
    tree = cKDTree(points)
    moved = 0
    # parents' children from the farthest along first, so that a fork moved back does not
    # pass over a sibling not yet looked at
    order = []
    for c, b in enumerate(sk.branches):
        if b.parent >= 0:
            P = sk.branches[b.parent].points
            order.append((b.parent, -arc_of_nearest(b.points[0], P, arc_length(P)), c))
    for _, _, c in sorted(order):
        if _unzip_one(sk, c, points, tree, tol):
            moved += 1
    return moved


def surface_spread(sk: Skeleton, points: Array, n: int = 3000) -> float:
    """Median absolute deviation (m) of how far the points (a sample of n) lie off the
    skeleton's surfaces (their distance from the nearest axis less its radius; points over
    2 cm off, strays and unskeletonised pieces, left out)."""
    A, R = axis_samples(sk)
    rng = np.random.default_rng(0)
    Q = points[rng.choice(len(points), min(n, len(points)), replace=False)]
    d, k = cKDTree(A).query(Q)
    e = d - R[k]
    e = e[np.abs(e) < 0.02]
    return float(np.median(np.abs(e - np.median(e)))) if len(e) else 0.0


def _two_circles(
    q: Array, cb: Array, cc: Array, rB: float, rC: float, tol: float
) -> tuple[Array, Array, int, int]:
    """Two circles of radii rB and rC fitted to the 2D points q from centres cb and cc; their
    centres and how many points lie on each and off the other."""
    for _ in range(3):
        eB = np.abs(np.linalg.norm(q - cb, axis=1) - rB)
        eC = np.abs(np.linalg.norm(q - cc, axis=1) - rC)
        near = np.minimum(eB, eC) < 3 * tol
        aB, aC = near & (eB <= eC), near & (eC < eB)
        if aB.sum() < 3 or aC.sum() < 3:
            break
        cb, cc = _fit(q[aB], cb, rB), _fit(q[aC], cc, rC)
    eB = np.abs(np.linalg.norm(q - cb, axis=1) - rB)
    eC = np.abs(np.linalg.norm(q - cc, axis=1) - rC)
    return cb, cc, int(np.sum((eB < tol) & (eC > tol))), int(np.sum((eC < tol) & (eB > tol)))


def _one_circle(q: Array, tol: float) -> int:
    """How many of the 2D points q lie on one circle (of any radius) fitted to them."""
    A = np.column_stack([2 * q, np.ones(len(q))])
    try:
        a, b, k = np.linalg.lstsq(A, (q * q).sum(1), rcond=None)[0]
    except np.linalg.LinAlgError:
        return 0
    c = np.array([a, b])
    r = math.sqrt(max(float(k + a * a + b * b), 1e-12))
    for _ in range(3):  # geometric refinement: centre and radius
        d = q - c
        n = np.maximum(np.linalg.norm(d, axis=1), 1e-9)
        J = np.column_stack([-d / n[:, None], -np.ones(len(q))])
        dx = np.linalg.lstsq(J, -(n - r), rcond=None)[0]
        c, r = c + dx[:2], r + float(dx[2])
    e = np.abs(np.linalg.norm(q - c, axis=1) - r)
    return int(np.sum(e < tol))


def _unzip_one(sk: Skeleton, c: int, points: Array, tree: cKDTree, tol: float) -> bool:
    C = sk.branches[c]
    B = sk.branches[C.parent]
    if len(C.points) < 3 or len(B.points) < 3:
        return False
    arcB, arcC = arc_length(B.points), arc_length(C.points)
    sB = arc_of_nearest(C.points[0], B.points, arcB)
    after = (arcB > sB + 1e-6) & (arcB <= sB + 0.04)
    if not after.any() or sB < 0.02 or arcC[-1] < 0.03:
        return False
    rB = float(np.median(B.radii[after]))
    first = (arcC > 0) & (arcC <= 0.04)
    rC = float(np.median(C.radii[first])) if first.any() else float(C.radii[1])
    tB = _unit(point_at(B.points, arcB, sB) - point_at(B.points, arcB, max(sB - 0.03, 0.0)))
    dC = _unit(point_at(C.points, arcC, min(arcC[1] + 0.03, arcC[-1])) - C.points[1])
    if math.degrees(math.acos(float(np.clip(dC @ tB, -1, 1)))) > MAX_ANGLE:
        return False
    step = max(2.0 * tol, 0.004)
    reach = 2.0 * (rB + rC) + 2 * tol + 0.005
    # which side the child lies on: from the parent's axis past the fork towards the child's
    side = C.points[1] - point_at(B.points, arcB, min(sB + 0.01, arcB[-1]))
    found: list[tuple[float, Array, Array]] = []
    cB3 = cC3 = np.zeros(3)
    misses = 0
    s = sB
    while s > 0.01 and sB - s <= MAX_BACK:
        o = point_at(B.points, arcB, s)
        t = _unit(point_at(B.points, arcB, min(s + 0.01, arcB[-1]))
                  - point_at(B.points, arcB, max(s - 0.01, 0.0)))  # fmt: skip
        u = _unit(np.cross(t, [1.0, 0.0, 0.0] if abs(t[0]) < 0.9 else [0.0, 1.0, 0.0]))
        v = np.cross(t, u)
        mid = (cB3 + cC3) / 2 if found else o
        idx = tree.query_ball_point(mid, reach)
        Q = points[idx] if idx else np.zeros((0, 3))
        Q = Q[np.abs((Q - o) @ t) <= SLAB * step]
        if len(Q) < 2 * MIN_SUPPORT:
            break
        q = np.column_stack([(Q - o) @ u, (Q - o) @ v])
        n1 = _one_circle(q, tol)
        m = q.mean(0)
        inits = []
        if found:  # where the last slice left them; else either side of the slice's points
            cb = np.array([(cB3 - o) @ u, (cB3 - o) @ v])
            cc = np.array([(cC3 - o) @ u, (cC3 - o) @ v])
            inits.append((cb, cc, step + 2 * tol))
            w = _unit(cc - cb)
        else:
            w = _unit(np.array([side @ u, side @ v]))
        inits.append((m - w * (rB + rC) / 2, m + w * (rB + rC) / 2, rB + rC))
        best: tuple[int, Array, Array] | None = None  # of the fits that pass, the fullest
        for cb, cc, max_jump in inits:
            cb, cc, nB, nC = _two_circles(q, cb, cc, rB, rC, tol)
            eB = np.abs(np.linalg.norm(q - cb, axis=1) - rB)
            eC = np.abs(np.linalg.norm(q - cc, axis=1) - rC)
            n2 = int(np.sum(np.minimum(eB, eC) < tol))
            apart = float(np.linalg.norm(cb - cc))
            at_b = o + cb[0] * u + cb[1] * v
            at_c = o + cc[0] * u + cc[1] * v
            jump = (max(float(np.linalg.norm(at_b - cB3)), float(np.linalg.norm(at_c - cC3)))
                    if found else 0.0)  # fmt: skip
            ok = (nC >= max(MIN_SUPPORT, MIN_SHARE * nB) and nB >= MIN_SUPPORT
                  and n2 >= TWO * n1 and jump <= max_jump
                  and MIN_APART * (rB + rC) <= apart <= 2 * (rB + rC) + 5 * tol)  # fmt: skip
            if ok and (best is None or n2 > best[0]):
                best = (n2, at_b, at_c)
        if best is not None:
            _, at_b, at_c = best
            found.append((s, at_b, at_c))
            misses = 0
            cB3, cC3 = at_b - step * t, at_c - step * t
        else:  # slices where the scan saw too little of one (a gap) are passed over; the
            misses += 1  # first found within `MAX_START` of the skeleton's fork
            if (misses > MAX_MISSES and found) or (not found and sB - s > MAX_START):
                break
            if found:
                cB3, cC3 = cB3 - step * t, cC3 - step * t
        s -= step
    if len(found) < 2:
        return False
    return _apply(sk, c, found, rB, rC, step)


def _apply(sk: Skeleton, c: int, found: list[tuple[float, Array, Array]], rB: float,
           rC: float, step: float) -> bool:  # fmt: skip
    """The parent's axis through its own centres over the unzipped stretch, the child's
    through its centres back to the new fork; the parent's other children re-attached. The
    child keeps its path from where it passes the last centre along the parent's heading
    there (the centres' own heading, over a few slices, can point anywhere); when none of it
    does, nothing is changed (False)."""
    C = sk.branches[c]
    p = C.parent
    B = sk.branches[p]
    arcB = arc_length(B.points)
    s_hi = found[0][0]
    head = found[0][2]
    d = _unit(point_at(B.points, arcB, min(s_hi + 0.01, arcB[-1]))
              - point_at(B.points, arcB, max(s_hi - 0.01, 0.0)))  # fmt: skip
    past = [i for i in range(1, len(C.points)) if (C.points[i] - head) @ d > 1e-4]
    if not past:
        return False
    s_fork = max(found[-1][0] - step, 0.0)
    fork = point_at(B.points, arcB, s_fork)
    keep_lo = arcB < s_fork - 1e-6
    keep_hi = arcB > s_hi + 1e-6
    fb = [f[1] for f in reversed(found)]
    fc = [f[2] for f in reversed(found)]
    Bp = np.vstack([B.points[keep_lo], fork[None], fb, B.points[keep_hi]])
    Br = np.concatenate([B.radii[keep_lo], [float(np.interp(s_fork, arcB, B.radii))],
                         np.full(len(fb), rB), B.radii[keep_hi]])  # fmt: skip
    sk.branches[p] = Branch(Bp, Br, kind=B.kind, parent=B.parent, label=B.label, nodes=B.nodes)
    rest = list(range(past[0], len(C.points)))  # from where it passes the head
    Cp = np.vstack([fork[None], fc, C.points[rest]])
    Cr = np.concatenate([[min(rC, float(Br[len(B.points[keep_lo])]))], np.full(len(fc), rC),
                         C.radii[rest]])  # fmt: skip
    sk.branches[c] = Branch(Cp, Cr, kind=C.kind, parent=p, label=C.label, nodes=C.nodes)
    for o in sk.branches:  # the parent's other children and the child's start on the axes
        if o.parent in (p, c) and o is not sk.branches[c]:
            _, _, q = nearest_on_polyline(o.points[0], Bp if o.parent == p else Cp)
            o.points[0] = q
    return True
