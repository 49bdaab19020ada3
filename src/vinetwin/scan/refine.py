"""Each branch's centres and radii re-fitted to its own points, once the skeleton's shape is known.

A level-set skeleton fits each node to the points of one geodesic slice. Near a fork a slice
holds both branches: the parent's centre leans towards the child and its radius swells, and the
child's first centimetres lean back towards the parent. Measured on simulated scans of the
Y-trellis apple at the realistic quality: the axis lay 4 mm (median; 8.5 mm at the 90th
percentile) off the true axis 1-3 cm from a fork, against 1.7 mm elsewhere. A cut rule that
places a cut where a shoot stands 3 cm off the rest of the plant then places it 1-2 cm off.

Here every scan point goes to the branch whose surface (axis distance less radius) is nearest,
and each node of a branch is re-fitted (`circle_fit`, the skeleton's own fit) to that branch's points in the
slab across it between its neighbours' midpoints: a child's points no longer pull the parent.
A node keeps its place when its slab holds fewer than `MIN_POINTS` points or the fit would move
it farther than its radius (a slab that is mostly another branch's). Children then start on
their parent's new axis, and the radii get the skeleton's 5-node median again. Two passes
(`SkeletonConfig.refine`): the second assigns the points by the first's better surfaces.

Measured at the realistic quality, seeds 0-2 (`benchmarks/scan_accuracy.py`, two passes against
none; `docs/scans.md` has the tables): skeleton completeness up 1-2 points on the vines and the
Y-trellis apple, and the cut candidates found within 1 cm up on the GDC vine and the Y-trellis
apple. It costs about 3 s per pass on a 355k-point tree scan.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

from vinetwin.frames import Array
from vinetwin.twin.skeleton import (
    Skeleton,
    arc_length,
    children,
    children_on_axes,
    point_at,
    resample,
)

#: Fewest points in a node's slab for it to be re-fitted.
MIN_POINTS = 10
#: A point farther than this many of the nearest branch's radii (plus `REACH_PAD`) from its axis
#: belongs to no branch (a stray the cleaning kept).
REACH_RADII = 2.0
REACH_PAD = 0.003
#: Nearest axis samples compared per point (the nearest surface is among them).
NEIGHBOURS = 8


def median5(x: Array) -> Array:
    """Each row's median with its two neighbours either side (the ends padded with their own
    value): the skeleton's smoothing of centres and radii along a branch."""
    pad = np.pad(x, [(2, 2)] + [(0, 0)] * (x.ndim - 1), mode="edge")
    return np.median(np.lib.stride_tricks.sliding_window_view(pad, 5, axis=0), axis=-1)


def circle_fit(points: Array, centre: Array, t: Array) -> tuple[Array, float]:
    """Centre and radius of a branch's cross-section from its points: a circle fitted in the
    plane across `t`, when sound; else the centroid and the median distance from it."""
    u = np.cross(t, [1.0, 0.0, 0.0] if abs(t[0]) < 0.9 else [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(t, u)
    q = points - centre
    x, y = q @ u, q @ v
    r0 = float(np.median(np.hypot(x, y)))
    if len(points) >= 10:
        # the algebraic circle fit's least squares by its 3 x 3 normal equations (an SVD per
        # slice was most of a large tree's skeleton time)
        A = np.column_stack([2 * x, 2 * y, np.ones_like(x)])
        try:
            sol = np.linalg.solve(A.T @ A, A.T @ (x * x + y * y))
        except np.linalg.LinAlgError:
            sol = np.zeros(3)
        a, b, c = (float(v) for v in sol)
        rr = c + a * a + b * b
        if rr > 0 and np.all(np.isfinite(sol)):
            r = math.sqrt(rr)
            ang = np.sort(np.arctan2(y - b, x - a))
            steps = np.diff(np.concatenate([ang, [ang[0] + 2 * math.pi]])).astype(np.float64)
            cover = 2 * math.pi - float(steps.max())
            if 0.5 * r0 <= r <= 2.0 * max(r0, 1e-4) and math.hypot(a, b) < 2 * r and cover > 2.0:
                return centre + a * u + b * v, r
    return centre, max(r0, 1e-4)


def _assign(sk: Skeleton, points: Array) -> tuple[Array, Array, Array]:
    """Each point's branch (by the nearest surface) and its arc position there, for the points
    that lie on one: (points, branch, arc)."""
    S, R, B, A = [], [], [], []
    for i, b in enumerate(sk.branches):
        if len(b.points) < 2:
            continue
        P, r = resample(b.points, b.radii, 0.002)
        S.append(P)
        R.append(r)
        B.append(np.full(len(P), i))
        A.append(arc_length(P))
    S_, R_, B_, A_ = (np.concatenate(x) for x in (S, R, B, A))
    k = min(NEIGHBOURS, len(S_))
    d, j = cKDTree(S_).query(points, k=k)
    d, j = d.reshape(len(points), k), j.reshape(len(points), k)
    pick = np.argmin(np.abs(d - R_[j]), axis=1)
    rows = np.arange(len(points))
    jj, dd = j[rows, pick], d[rows, pick]
    ok = dd < REACH_RADII * R_[jj] + REACH_PAD
    return points[ok], B_[jj[ok]], A_[jj[ok]]


def refine_axes(sk: Skeleton, points: Array, passes: int = 2) -> None:
    """Re-fits the skeleton's centres and radii to the points (see the module's docstring);
    in place."""
    for _ in range(passes):
        if not sk.branches or len(points) < MIN_POINTS:
            return
        pts, bid, arc = _assign(sk, points)
        order = np.argsort(bid, kind="stable")
        pts, bid, arc = pts[order], bid[order], arc[order]
        bounds = np.searchsorted(bid, np.arange(len(sk.branches) + 1))
        for i, b in enumerate(sk.branches):
            Q, s = pts[bounds[i] : bounds[i + 1]], arc[bounds[i] : bounds[i + 1]]
            n = len(b.points)
            if n < 3 or len(Q) < MIN_POINTS:
                continue
            a = arc_length(b.points)
            node = np.searchsorted((a[:-1] + a[1:]) / 2, s)
            P, R = b.points.copy(), b.radii.copy()
            for v in range(1 if b.parent >= 0 else 0, n):  # a child's first point is on its parent
                q = Q[node == v]
                if len(q) < MIN_POINTS:
                    continue
                t = b.points[min(v + 1, n - 1)] - b.points[max(v - 1, 0)]
                t = t / max(float(np.linalg.norm(t)), 1e-12)
                c, r = circle_fit(q, b.points[v], t)
                if np.linalg.norm(c - b.points[v]) <= b.radii[v] + 0.001:
                    P[v], R[v] = c, r
            b.points, b.radii = P, np.maximum(median5(R) if n >= 5 else R, 5e-4)
        children_on_axes(sk)


BUMP_SPAN = 0.03
"""Half the span (m of arc) over which permanent wood is taken for straight (`straighten_bumps`)."""


BUMP_HEADING = 0.9
"""A detour returns to its line: the axis's heading over the `BUMP_SPAN` before it and the one
after it are within 25 degrees (cosine at least this)."""

BUMP_PASSES = 3
"""Passes of `straighten_bumps` over a branch, until one moves nothing."""

BUMP_OFF = 0.5
"""A node standing more than this share of its branch's median radius off the chord is a
detour (5 mm on a 10 mm cordon: a 20 cm bend is 2.3 mm off a 6 cm chord; the node's own radius,
inflated where a spur's base joins the slice, hid 6-8 mm detours on generated vines of seeds 7,
12 and 21)."""


def _straighten(P: Array, r: Array) -> tuple[Array, Array, int]:
    """One pass of `straighten_bumps` over a polyline with radii `r`: the new points, the new
    radii and how many moved."""
    s = arc_length(P)
    inner = np.flatnonzero((s >= BUMP_SPAN) & (s <= s[-1] - BUMP_SPAN))
    if not len(inner):
        return P, r, 0
    a, c = point_at(P, s, s[inner] - BUMP_SPAN), point_at(P, s, s[inner] + BUMP_SPAN)
    ac = c - a
    t = np.einsum("ij,ij->i", P[inner] - a, ac) / np.maximum((ac * ac).sum(1), 1e-12)
    off = np.linalg.norm(P[inner] - (a + np.clip(t, 0, 1)[:, None] * ac), axis=1)
    # out and back onto one line, not a corner: the axis heads the same way before and after
    # (the VSP vine's arm turns 60 degrees at a digitised node, 15 mm off such a chord)
    s_lo = np.maximum(s[inner] - 2 * BUMP_SPAN, 0.0)
    s_hi = np.minimum(s[inner] + 2 * BUMP_SPAN, s[-1])
    before = s[inner] - BUMP_SPAN - s_lo >= 0.01
    after = s_hi - s[inner] - BUMP_SPAN >= 0.01
    u, v = a - point_at(P, s, s_lo), point_at(P, s, s_hi) - c
    cos = np.einsum("ij,ij->i", u, v) / np.maximum(
        np.linalg.norm(u, axis=1) * np.linalg.norm(v, axis=1), 1e-12
    )
    bad = inner[(off > BUMP_OFF * float(np.median(r))) & before & after & (cos >= BUMP_HEADING)]
    if not len(bad):
        return P, r, 0
    new, new_r = P.copy(), r.copy()
    moved = 0
    spans: list[list[float]] = []  # each run of detour nodes widened, overlapping ones joined
    for run in np.split(bad, np.flatnonzero(np.diff(bad) > 1) + 1):
        lo = max(float(s[run[0]]) - 2 * BUMP_SPAN / 3, 0.0)
        hi = min(float(s[run[-1]]) + 2 * BUMP_SPAN / 3, float(s[-1]))
        if spans and lo <= spans[-1][1]:
            spans[-1][1] = hi
        else:
            spans.append([lo, hi])
    for lo, hi in spans:
        pa, pc = point_at(P, s, lo), point_at(P, s, hi)
        k = np.flatnonzero((s > lo) & (s < hi))
        f = (s[k] - lo) / max(hi - lo, 1e-12)
        new[k] = pa + f[:, None] * (pc - pa)
        # the detour's slices held the spur's base too: their radius with it
        ra, rc = np.interp(lo, s, r), np.interp(hi, s, r)
        new_r[k] = ra + f * (rc - ra)
        moved += len(k)
    return new, new_r, moved


def straighten_bumps(sk: Skeleton) -> int:
    """Takes the detours out of the axes of a vine's cordons (in place), each cordon taken as
    the chain of its pieces (`_cordon_chains`: a detour at a joint is seen whole): a node
    standing more than `BUMP_OFF` of the branch's radius off the chord between its points
    `BUMP_SPAN` before and after it, where the axis heads the same way before and after
    (`BUMP_HEADING`: a detour, not a corner), is a detour, and the run of such nodes, with
    `2/3 BUMP_SPAN` more either side (runs overlapping so joined), is put on the straight line
    between the ends of that stretch, its radii on the line between theirs. Children starting
    there start on the new axis. Returns the nodes moved. (The trunk is left alone:
    straightening it too moved the head-trained VSP vine's arm and lost a cane on a generated
    vine.)

    Where a spur stands up from a cordon, a level set of the geodesic distance holds the spur's
    base with the cordon's points: its centre rises into the spur, and `refine_axes` keeps it
    there when the fit would move it farther than the radius. Measured on the realistic scans
    of generated dense vines (seeds 6-11): such detours ran 9-20 mm off the true cordon over
    2-4 cm, and cuts placed 10.85 cm off the wood's surface came 1-2.6 cm nearer the cordon
    for every cane whose path passed by. Thick wood does not bend that sharply (a 20 cm bend
    radius is 2.3 mm off a 6 cm chord), so the chord is the better axis there; a corner is
    left, for arms do turn sharply (the VSP vine's turns 60 degrees at a digitised node)."""
    moved = 0
    changed = set()
    for chain in _cordon_chains(sk):
        P = np.vstack([sk.branches[i].points for i in chain])
        R = np.concatenate([sk.branches[i].radii for i in chain])
        if len(P) < 5:
            continue
        n_chain = 0
        for _ in range(BUMP_PASSES):  # a wide detour leans the chords of its first pass
            P, R, n = _straighten(P, R)
            if not n:
                break
            n_chain += n
        if not n_chain:
            continue
        moved += n_chain
        at = 0
        for i in chain:  # back into its pieces
            b = sk.branches[i]
            k = len(b.points)
            if not (
                np.array_equal(b.points, P[at : at + k]) and np.array_equal(b.radii, R[at : at + k])
            ):
                b.points, b.radii = P[at : at + k].copy(), R[at : at + k].copy()
                changed.add(i)
            at += k
    children_on_axes(sk, changed)
    return moved


#: Metres: a cordon piece starting this near another's end carries it on (one chain).
CHAIN_JOIN = 0.02


def _cordon_chains(sk: Skeleton) -> list[list[int]]:
    """The cordons as chains of pieces, each piece carrying the one before on from its end
    (the skeleton splits a cordon where canes leave it, and `scan.frame` hangs its pieces one
    from another), so that a detour at a joint is seen whole."""

    def carries(c: int, j: int) -> bool:
        b, p = sk.branches[j], sk.branches[c]
        return (b.kind == "cordon" and b.parent == c
                and float(np.linalg.norm(b.points[0] - p.points[-1])) <= CHAIN_JOIN)  # fmt: skip

    kids = children(sk)
    cordons = [i for i, b in enumerate(sk.branches) if b.kind == "cordon"]
    nxt = {c: on[0] for c in cordons if (on := [j for j in kids[c] if carries(c, j)])}
    followed = set(nxt.values())  # a second piece from one end starts a chain of its own
    chains = []
    for i in cordons:
        if i in followed:
            continue
        chain = [i]
        while chain[-1] in nxt:
            chain.append(nxt[chain[-1]])
        chains.append(chain)
    return chains
