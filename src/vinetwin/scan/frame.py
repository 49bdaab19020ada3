"""The vine frame of a scan (`docs/conventions.md`): origin at the trunk's foot, +Z up, +X along
the row (the cordon's principal axis), +Y across it; `T_vine_scan` maps the scan's points (in
metres) into it and is kept in the twin's provenance, so poses can be given back in the
scanner's frame."""

from __future__ import annotations

import heapq

import numpy as np

from vinetwin.errors import InputError
from vinetwin.frames import Array
from vinetwin.scan.candidates import (
    ARM_MIN,
    ARM_RISE,
    CONTINUE_RADIUS,
    CONTINUE_WITHIN,
    CORDON_RADIUS,
    HEAD,
    arm_shape,
    carries_on,
    level_and_thick,
    sister_cordons,
)
from vinetwin.twin.skeleton import (
    Branch,
    Skeleton,
    ancestors,
    arc_length,
    children,
    point_at,
)

AXES = {"x": 0, "y": 1, "z": 2}


def axis_vector(name: str) -> Array:
    """The unit vector of an axis name: x, y, z, -x, -y, -z."""
    sign = -1.0 if name.startswith("-") else 1.0
    key = name.lstrip("-+").lower()
    if key not in AXES:
        raise InputError(f"up axis must be one of x y z -x -y -z, got {name!r}")
    v = np.zeros(3)
    v[AXES[key]] = sign
    return v


#: A trunk's direction within this angle (degrees) of an axis of the file is taken as that
#: axis: scanners and photogrammetry tools write z or y up, and a trunk leans a few degrees.
SNAP_DEGREES = 30.0


def guess_up(found: Array, what: str = "the trunk's direction") -> tuple[Array, str]:
    """The up direction of a scan without ground or `--up`: the direction the skeleton found
    (`what`: the trunk's, or the plant's mass over its foot), snapped to the file's nearest axis
    when within `SNAP_DEGREES`."""
    best = max(("x", "y", "z", "-x", "-y", "-z"), key=lambda n: float(axis_vector(n) @ found))
    v = axis_vector(best)
    angle = float(np.degrees(np.arccos(np.clip(v @ found, -1, 1))))
    if angle <= SNAP_DEGREES:
        return v, f"{what} ({angle:.0f} degrees from {best}: {best} taken)"
    return found, f"{what} ({angle:.0f} degrees from the nearest axis, {best})"


def row_axis(sk: Skeleton, up: Array) -> Array:
    """The row's direction: the principal axis of the skeleton's centre lines (length-weighted,
    thick wood counted more) in the horizontal plane; its largest component made positive."""
    pts, w = [], []
    for b in sk.branches:
        seg = np.linalg.norm(np.diff(b.points, axis=0), axis=1)
        pts.append(0.5 * (b.points[1:] + b.points[:-1]))
        w.append(seg * 0.5 * (b.radii[1:] + b.radii[:-1]))
    P = np.concatenate(pts)
    W = np.concatenate(w)
    P = P - (P @ up)[:, None] * up
    m = (W[:, None] * P).sum(0) / W.sum()
    Q = P - m
    C = (W[:, None] * Q).T @ Q
    C -= np.outer(up, up) * np.trace(C)  # keep the search horizontal
    x = np.linalg.eigh(C)[1][:, -1]
    x = x - (x @ up) * up
    x /= np.linalg.norm(x)
    return x if x[np.argmax(np.abs(x))] > 0 else -x


def vine_from_scan(up: Array, x: Array, origin: Array) -> Array:
    """T_vine_scan for a unit up vector, a horizontal row direction and the trunk's foot (all
    in the scan's frame, metres)."""
    z = up / np.linalg.norm(up)
    x = x - (x @ z) * z
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z])
    T[:3, 3] = -T[:3, :3] @ origin
    return T


def split_trunk(sk: Skeleton, up: Array) -> None:
    """Splits the root branch where it bends from vertical to horizontal (a cordon leaving the
    trunk's head, which the skeleton followed as one chain); in place. Children past the bend
    move to the new cordon. Branch order stays parents-first."""
    if not sk.branches or sk.branches[0].parent >= 0:
        return
    b = sk.branches[0]
    P = b.points
    if len(P) < 6:
        return
    s = arc_length(P)
    h = (P - P[0]) @ up
    for k in range(2, len(P) - 2):
        t = P[min(k + 3, len(P) - 1)] - P[max(k - 3, 0)]
        t /= max(np.linalg.norm(t), 1e-9)
        if abs(t @ up) < 0.64 and h[k] > 0.2 and s[-1] - s[k] >= 0.15:
            break
    else:
        return
    from vinetwin.twin.skeleton import Branch

    cordon = Branch(P[k:], b.radii[k:], kind="cordon", parent=0, label="cordon")
    sk.branches[0] = Branch(P[: k + 1], b.radii[: k + 1], kind="trunk", parent=-1, label="trunk")
    sk.branches.insert(1, cordon)
    for c in sk.branches[2:]:
        if c.parent >= 1:
            c.parent += 1
        elif c.parent == 0:
            j = int(np.argmin(np.linalg.norm(P - c.points[0], axis=1)))
            c.parent = 1 if j > k else 0
    for c in sk.candidates:
        if c.branch >= 1:
            c.branch += 1


def split_cordons(sk: Skeleton, up: Array) -> None:
    """Splits each branch growing from the trunk that runs level for at least 15 cm (a cordon)
    where it turns up or down by more than 40 degrees, or where it thins for good below
    `candidates.CORDON_RADIUS` of the trunk's radius (where the skeleton followed the cordon on
    into the cane or shoot of its last spur), or, first of all, where an arm's thick start ends
    (`_arm_end`, from 5 cm); in place. The rest becomes a branch of its own,
    hanging from the cordon's end, appended; at the end the branches are put parents first."""
    roots = {i for i, b in enumerate(sk.branches) if b.parent < 0}
    r_ref = CORDON_RADIUS * float(np.median(sk.branches[min(roots)].radii)) if roots else 0.0
    heads = [sk.branches[j].points[-1] for j in roots]
    for i in range(len(sk.branches)):
        b = sk.branches[i]
        if b.parent not in roots:
            # an arm may leave the head from another arm's start (the skeleton's chain)
            at_head = min((float(np.linalg.norm(b.points[0] - h)) for h in heads), default=1.0)
            if at_head <= HEAD and (k := _arm_end(b.points, arc_length(b.points), b.radii, up,
                                                   r_ref)) is not None:  # fmt: skip
                _split_at(sk, i, k)
            continue
        P = b.points
        s = arc_length(P)
        k_split = _turn_at(P, s, up, ARM_MIN)
        k_thin = _thin_from(s, b.radii, r_ref)
        if k_thin is not None and (k_split is None or k_thin < k_split):
            k_split = k_thin
        # a head-trained arm thins before 15 cm: the first of the three ends (on the VSP
        # vine the skeleton's arm ran on level into a cane until it turned up 5 cm later)
        k_arm = _arm_end(P, s, b.radii, up, r_ref)
        if k_arm is not None and (k_split is None or k_arm < k_split):
            k_split = k_arm
        if k_split is None:
            continue
        _split_at(sk, i, k_split)
    _continue_cordons(sk, up, roots, r_ref)
    _parents_first(sk)  # a split appends a branch its children may come before


#: A branch's first metres (m) leave its parent's axis, down or up through the parent's wood:
#: a steep step there is no turn when the branch runs level past it (a cane lying along a
#: generated vine's cordon for 20 cm and then rising, taken for the cordon's continuation,
#: dropped 1 cm from the cordon's axis in its first 2 cm, and that step was taken for its turn).
JUNCTION = 0.03
#: Level past the junction: the chord over the next `JUNCTION_RUN` (m) within 20 degrees of
#: horizontal (sine `JUNCTION_LEVEL`). A cane rising from its start through a curved base (a
#: 2.5 cm step up, 5 cm flat, then steep; a generated vine of seed 21) is not level there.
JUNCTION_LEVEL = 0.34
JUNCTION_RUN = 0.10


def _turn_at(P: Array, s: Array, up: Array, before: float) -> int | None:
    """The index where a branch first turns up or down by more than 40 degrees (its direction
    over 3 points either side), when that is at least `before` (m) from its start and 5 cm
    before its end; else None. (Turning sideways is no end: the GDC vine's right cordon curls.)
    A turn within `JUNCTION` of its start is its junction's step when it runs level past it."""
    for k in range(1, len(P) - 1):
        t = P[min(k + 3, len(P) - 1)] - P[max(k - 3, 0)]
        t /= max(np.linalg.norm(t), 1e-9)
        if abs(t @ up) <= ARM_RISE:
            continue
        if s[k] < JUNCTION:
            a, b = point_at(P, s, JUNCTION), point_at(P, s, min(JUNCTION + JUNCTION_RUN, s[-1]))
            d = b - a
            if abs(float(d @ up)) <= JUNCTION_LEVEL * float(np.linalg.norm(d)) + 1e-12:
                continue  # the step off its parent's axis
        return k if s[k] >= before and s[-1] - s[k] >= 0.05 else None
    return None


def _window_median(s: Array, r: Array, window: float) -> Array:
    """Each point's radius as the median over `window` (m of arc) either side."""
    lo = np.searchsorted(s, s - window)
    hi = np.searchsorted(s, s + window, side="right")
    return np.array([np.median(r[a:b]) for a, b in zip(lo, hi, strict=True)])


def _arm_end(P: Array, s: Array, r: Array, up: Array, r_ref: float,
             window: float = 0.03) -> int | None:  # fmt: skip
    """The index where a branch's thick, level start ends (its radius, a median over
    `window` either side, below `r_ref` from there on for `ARM_MIN`), when that start is at
    least `ARM_MIN` long,
    level (`ARM_RISE`: within 40 degrees of horizontal) and followed by at least 5 cm more; else None.
    Measured on the head-trained `vsp_ww` vine's scans: its 22 cm arm (12.5 mm in radius, the
    trunk 20 mm) came out 12-15 mm thick for 7-20 cm and then 4-6 mm along the shoot the
    skeleton's chain ran on into, with dips to 9 mm (under `r_ref`) for 4 cm within the arm."""
    if r_ref <= 0 or s[-1] < ARM_MIN + 0.05:
        return None
    w = _window_median(s, r, window)
    # the first point from which it stays thin for `ARM_MIN` on (a dip of the scan's radius
    # within the arm, as where a shoot leaves it, is not its end)
    thick = np.r_[0, np.cumsum(w >= r_ref)]
    ahead = np.searchsorted(s, s + ARM_MIN, side="right")
    stays = np.flatnonzero((w < r_ref) & (thick[ahead] == thick[np.arange(len(s))]))
    k = int(stays[0]) if len(stays) else len(s)
    if k >= len(s) or s[k] < ARM_MIN or s[-1] - s[k] < 0.05:
        return None
    if abs(float((P[k] - P[0]) @ up)) > ARM_RISE * s[k]:  # rises by over 40 degrees along it
        return None
    return k


def _split_at(sk: Skeleton, i: int, k: int) -> None:
    """Branch i keeps its points up to k; the rest becomes a cane hanging from its end,
    appended, with the children past k."""
    b = sk.branches[i]
    P = b.points
    rest = Branch(P[k:], b.radii[k:], kind="cane", parent=i, label=f"{b.label}+")
    sk.branches[i] = Branch(P[: k + 1], b.radii[: k + 1], kind=b.kind, parent=b.parent,
                            label=b.label)  # fmt: skip
    new = len(sk.branches)
    sk.branches.append(rest)
    for c in sk.branches[:new]:
        if c.parent == i:
            j = int(np.argmin(np.linalg.norm(P - c.points[0], axis=1)))
            if j > k:
                c.parent = new


def _continue_cordons(sk: Skeleton, up: Array, roots: set[int], r_ref: float) -> None:
    """Where a cordon forks at its end, the skeleton's chain may run on into a shoot hanging
    from it while the cordon itself goes on as a branch of that shoot (measured on the GDC
    vine: its right cordon's last 30 cm). A branch starting within `CONTINUE_WITHIN` of a
    cordon's end whose thick part is a cordon's shape continues it: it hangs from the cordon,
    split where it thins for good (a cordon tapers: thick by `candidates.CONTINUE_RADIUS` of
    the cordon's own radius where that is under `r_ref`) or where it turns up or down 5 cm or
    more on (the cordon's last centimetres and the cane of its last spur make one chain:
    generated vines of seeds 6-21), and a level piece of `ARM_MIN` or more carrying the cordon
    on in its own direction (`candidates.carries_on`) is one too. The cordons it starts from
    include short ones at the head (`candidates.arm_shape`) and a bilateral vine's thinner one
    (`candidates.sister_cordons`). Repeated from each new piece; in place."""
    heads = [sk.branches[j].points[-1] for j in roots]
    queue = [i for i, b in enumerate(sk.branches) if b.parent in roots and (
        level_and_thick(b, up, r_ref)
        or (arm_shape(b, up, heads) and float(np.median(b.radii)) >= r_ref))]  # fmt: skip
    queue += sorted(sister_cordons(sk, up, r_ref))
    done = set(queue) | roots
    while queue:
        c = queue.pop()
        end = sk.branches[c].points[-1]
        r_c = min(r_ref, CONTINUE_RADIUS * float(np.median(sk.branches[c].radii)))
        above = ancestors(sk, c)
        # any branch, not only those after it: a split appends the cordon's new piece after
        # the shoot that carries its tail on (a generated vine of seed 8: the cordon's last
        # 9 cm hung from the cane its chain ran into)
        for j in range(len(sk.branches)):
            b = sk.branches[j]
            if (
                j in done
                or j in above
                or float(np.linalg.norm(b.points[0] - end)) > CONTINUE_WITHIN
            ):
                continue
            if b.parent in roots:
                # it leaves the trunk beside the cordon, not the cordon's end (on a D405 rig's
                # scan of the VSP vine a cane from the head was carried on from its 6 cm arm)
                continue
            s = arc_length(b.points)
            ks = [k for k in (_thin_from(s, b.radii, r_c), _turn_at(b.points, s, up, ARM_MIN))
                  if k is not None]  # fmt: skip
            if ks:
                _split_at(sk, j, min(ks))
            b = sk.branches[j]
            if not (level_and_thick(b, up, r_c) or carries_on(b, sk.branches[c], up, r_c)):
                continue
            sk.branches[j].parent = c
            done.add(j)
            queue.append(j)


def _parents_first(sk: Skeleton) -> None:
    """Orders the branches so that each comes after its parent, keeping the order they have
    where it already does (the smallest index whose parent is placed goes next), in place;
    parents and candidates renumbered."""
    n = len(sk.branches)
    if all(b.parent < i for i, b in enumerate(sk.branches)):
        return
    kids = children(sk)
    ready = [i for i, b in enumerate(sk.branches) if b.parent < 0]
    heapq.heapify(ready)
    order: list[int] = []
    while ready:
        i = heapq.heappop(ready)
        order.append(i)
        for c in kids[i]:
            heapq.heappush(ready, c)
    if len(order) != n:
        return  # not a tree (a branch its own ancestor): left as it is
    new = {old: k for k, old in enumerate(order)}
    branches = [sk.branches[i] for i in order]
    for b in branches:
        if b.parent >= 0:
            b.parent = new[b.parent]
    sk.branches = branches
    for cand in sk.candidates:
        if cand.branch >= 0:
            cand.branch = new[cand.branch]


def _thin_from(s: Array, r: Array, r_ref: float, window: float = 0.03) -> int | None:
    """The index from which a branch thick at its start (its first 15 cm's median radius at
    least `r_ref`) stays thin: its radius (a median over `window` either side) below `r_ref`
    from there on, at least 15 cm from its start and 5 cm before its end; None if it does not."""
    if r_ref <= 0 or s[-1] < 0.2 or float(np.median(r[s <= 0.15])) < r_ref:
        return None
    w = _window_median(s, r, window)
    thick = np.flatnonzero(w >= r_ref)
    k = int(thick[-1]) + 1 if len(thick) else 0
    if k >= len(s) or s[k] < 0.15 or s[-1] - s[k] < 0.05:
        return None
    return k
