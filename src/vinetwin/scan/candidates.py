"""Cut candidates on a skeleton whose buds are not known (a scan), and the plant's kinds.

The rule follows the generator and the importers (a cane shortened to a two-bud spur), with the
buds where an internode length puts them, and is defined on the plant's shape alone, not on how
its branches happen to be split into polylines, so that it gives the same cuts on a scan's
skeleton and on the true skeleton of the same plant:

- **vine**: every tip (the free end of a cane or shoot) is followed back to the permanent wood
  (the trunk or a cordon); the cut sits where that path first stands `FIRST_NODE + 1.3 *
  internode` off the permanent wood's surface (its distance from the trunk's and cordons' axes
  less their radius): 30% of the way from the second bud to the third, as the generator's and
  hydroshoot's candidates, with the buds counted from the cordon. Counting from the cordon,
  not from the cane's own base on its spur, is what a scan allows: two canes of one spur touch
  for their first centimetres and a scan cannot tell where they part. On a vine with 2-5 cm
  spurs the cut sits that much nearer the cordon than counting from the spur. Measuring off the
  wood's surface, not from where the path meets the wood's axis, keeps the cut where it is
  when a skeleton forks a few centimetres early or late. Canes sharing their base give one
  cut; paths ending less than `PAST_VINE` past the cut get none;
- **tree**: each tip is followed back to its **last fork** (where the plant branches), and the cut
  sits where the path first stands `CANDIDATE_OFFSET` (3 cm, the cylinder importer's) off the
  surface of the rest of the plant (the branch it grows from, its siblings), heading back each
  shoot; shoots ending less than `PAST_TREE` past the cut get none.
"""

from __future__ import annotations

import numpy as np

from vinetwin.frames import Array
from vinetwin.scan.config import PlantKind
from vinetwin.twin.importers import CANDIDATE_OFFSET
from vinetwin.twin.skeleton import (
    FIRST_NODE,
    Branch,
    BranchKind,
    CutCandidate,
    Skeleton,
    arc_length,
    children,
    resample,
    standoff,
    tip_paths,
)

REACH_STEP = 0.002
"""How finely (m) a tip's path is sampled to find where it stands the rule's offset off the wood."""

PAST_TREE = 0.02
"""A tree's shoot gets a cut when it reaches at least this (m) past where the cut sits."""

PAST_VINE = 0.005
"""A vine's cane gets a cut when its path reaches at least this (m) past where the cut sits (the
shears' jaw). No true cane ends within 2 cm past its two-bud cut (the true skeletons of the
generated and hydroshoot vines measured give the same candidates at 5 mm as at 2 cm), while a
scan's skeleton ends a cane where it touches another one and hangs the rest on that one: its
path then stops a few millimetres past the cut. At 2 cm those canes got no cut (the first
scans of the 12 tuned vines and `dense@6-21`: 8 more of 799 true cuts found at 5 mm, 2 more of
ours not matching)."""


def cut_candidates(sk: Skeleton, plant: PlantKind, internode: float) -> list[CutCandidate]:
    """The rule of the module's docstring on `sk`; ordered along the plant as its tips are.
    Candidates within 1 cm of an earlier one (canes sharing their base) are one."""
    vine = plant == "vine"
    offset = FIRST_NODE + 1.3 * internode if vine else CANDIDATE_OFFSET
    wood = standoff(sk, "permanent" if vine else "rest")
    out: list[CutCandidate] = []
    for P, R, _, branch in tip_paths(sk, "permanent" if vine else "fork"):
        if sk.branches[branch].parent < 0:
            continue  # the trunk's own top
        s = arc_length(P)
        # how far it stands off the wood it grows from, every `REACH_STEP` along it: that
        # distance is not linear between a skeleton's points (a digitised cane's nodes are
        # 7 cm apart, a measured tree's cylinders up to 25 cm)
        Pd = resample(P, R, REACH_STEP)[0]
        sd = arc_length(Pd)
        reach = np.maximum.accumulate(wood(Pd))
        want = offset
        if reach[-1] < want + (PAST_VINE if vine else PAST_TREE):
            continue
        k = int(np.clip(np.searchsorted(reach, want), 1, len(Pd) - 1))
        f = (want - reach[k - 1]) / max(reach[k] - reach[k - 1], 1e-12)
        point = Pd[k - 1] + f * (Pd[k] - Pd[k - 1])
        want = sd[k - 1] + f * (sd[k] - sd[k - 1])
        if any(np.linalg.norm(c.point - point) < 0.01 for c in out):
            continue
        k = int(np.clip(np.searchsorted(s, want), 1, len(P) - 1))
        lo, hi = max(k - 2, 0), min(k + 2, len(P) - 1)
        axis = P[hi] - P[lo]
        axis /= max(float(np.linalg.norm(axis)), 1e-12)
        out.append(CutCandidate(point, axis, branch=branch, radius=float(np.interp(want, s, R)),
                                label=f"{sk.branches[branch].label or branch}/cut"))  # fmt: skip
    return out


CORDON_RADIUS = 0.5
"""A cordon's median radius is at least this share of the trunk's, so a long level shoot or cane
on a cordon is not taken for permanent wood (the hydroshoot vines' cordons are 0.61-0.82 of
their trunk, their canes and shoots at most 0.41; over 60 generated vines of each kind cordons
run 0.43-0.9 and canes up to 0.52, so a bilateral vine's thinner cordon is judged against its
other one: `SISTER`)."""


ARM_MIN = 0.05
"""A head-trained vine's arm (m): a branch from the trunk whose first `ARM_MIN` or more is as
thick as a cordon (`CORDON_RADIUS`) and level, then thins, is split there (`frame.split_cordons`)
and its thick start is permanent wood, a cordon however short, when it leaves the trunk's
head (starts within `HEAD` of the trunk's top)."""

HEAD = 0.06
"""How near the trunk's top (m) an arm starts."""

ARM_RISE = 0.64
"""An arm is level: it rises by at most this share of its length (sin 40 degrees)."""

CONTINUE_WITHIN = 0.10
"""How near a cordon's end (m) a branch must start to be taken for its continuation."""

CONTINUE_RADIUS = 0.6
"""A cordon tapers: its continuation is thick enough at this share of the cordon's own median
radius, when that is under the trunk's rule (`candidates.CORDON_RADIUS`). Measured on the GDC
vine's scans: its right cordon (17 mm in the scan) curls on for 16 cm at 10-12.5 mm, under half
the trunk's 26 mm, while the shoots hanging there are 4-5 mm."""


SISTER = 0.6
"""A bilateral vine's second cordon is at least this share of the first one's median radius
(the generator draws each 18-30 mm thick), when the trunk's rule (`CORDON_RADIUS`) misses it: on
generated vines cordons run down to 0.43 of the trunk's radius while canes reach 0.52, yet
within one vine every cordon is thicker than every cane."""


def level_and_thick(b: Branch, up: Array, r_ref: float = 0.0) -> bool:
    """At least 15 cm long, its median radius at least `r_ref`, and level (its principal axis
    within 30 degrees of horizontal): a cordon's shape."""
    if b.length < 0.15 or float(np.median(b.radii)) < r_ref:
        return False
    Q = b.points - b.points.mean(0)
    return abs(float(np.linalg.eigh(Q.T @ Q)[1][:, -1] @ up)) < 0.5


def arm_shape(b: Branch, up: Array, heads: list[Array]) -> bool:
    """A head-trained vine's arm, or a cordon cut short at the head: `ARM_MIN` or more long,
    leaving the trunk's head (within `HEAD` of one of `heads`), its chord within 40 degrees of
    level (`ARM_RISE`)."""
    if b.length < ARM_MIN:
        return False
    if min((float(np.linalg.norm(b.points[0] - h)) for h in heads), default=1.0) > HEAD:
        return False
    return abs(float((b.points[-1] - b.points[0]) @ up)) < ARM_RISE * b.length


def _heading(c: Branch, last: float = 0.1) -> Array:
    """The unit direction of a branch's last `last` metres."""
    s = arc_length(c.points)
    e = c.points[-1] - c.points[min(int(np.searchsorted(s, s[-1] - last)), len(s) - 2)]
    return e / max(float(np.linalg.norm(e)), 1e-12)


def carries_on(b: Branch, c: Branch, up: Array, r_c: float) -> bool:
    """A piece of `ARM_MIN` or more carrying cordon `c` on from its end: starting within
    `CONTINUE_WITHIN` of it, level, as thick as `r_c`, heading within 35 degrees of the way
    `c`'s last 10 cm head (a cordon's last centimetres past the fork of its last spur)."""
    if b.length < ARM_MIN or float(np.median(b.radii)) < r_c:
        return False
    if float(np.linalg.norm(b.points[0] - c.points[-1])) > CONTINUE_WITHIN:
        return False
    d = b.points[-1] - b.points[0]
    if abs(float(d @ up)) > ARM_RISE * b.length:
        return False
    return float(d @ _heading(c)) >= 0.82 * float(np.linalg.norm(d))


def sister_cordons(sk: Skeleton, up: Array, r_ref: float) -> set[int]:
    """Branches leaving the trunk's head (within `HEAD` of its top), level and 15 cm or longer,
    thinner than `r_ref` but at least `SISTER` of a cordon's median radius (a branch from the
    head as thick as `r_ref`) and heading the other way along the row from it: a bilateral
    vine's thinner cordon."""
    roots = [i for i, b in enumerate(sk.branches) if b.parent < 0]
    if not roots:
        return set()
    head = sk.branches[roots[0]].points[-1]
    kids = [i for i, b in enumerate(sk.branches)
            if b.parent in roots and float(np.linalg.norm(b.points[0] - head)) <= HEAD
            and level_and_thick(b, up)]  # fmt: skip
    med = {i: float(np.median(sk.branches[i].radii)) for i in kids}

    def way(i: int) -> Array:
        d = sk.branches[i].points[-1] - sk.branches[i].points[0]
        d = d - (d @ up) * up
        return d / max(float(np.linalg.norm(d)), 1e-9)

    firsts = [i for i in kids if med[i] >= r_ref]
    return {i for i in kids if med[i] < r_ref
            and any(med[i] >= SISTER * med[f] and float(way(i) @ way(f)) < -0.5 for f in firsts)}  # fmt: skip


def label_kinds(sk: Skeleton, up: Array, plant: PlantKind) -> None:
    """Names each branch's kind from its shape (in place): for a vine the root is the trunk,
    long near-horizontal thick branches from the trunk are cordons (and so is a head-trained
    vine's arm: thick, level, carrying others, leaving the trunk's head from whichever branch
    the skeleton's chain gave it), short branches carrying others are spurs, the rest canes; for
    a tree the root is the trunk, the rest branches."""
    kids = children(sk)
    order = [i for i, b in enumerate(sk.branches) if b.parent < 0]
    for i in order:  # parents before children, however the list is ordered
        order.extend(kids[i])
    r_trunk = float(np.median(sk.branches[order[0]].radii)) if order else 0.0
    head = sk.branches[order[0]].points[-1] if order else np.zeros(3)
    sisters = sister_cordons(sk, up, CORDON_RADIUS * r_trunk) if plant == "vine" else set()
    for i in order:
        b = sk.branches[i]
        kind: BranchKind
        if b.parent < 0:
            kind = "trunk"
        elif plant == "tree":
            kind = "branch"
        else:
            parent_kind = sk.branches[b.parent].kind
            thick = float(np.median(b.radii)) >= CORDON_RADIUS * r_trunk or i in sisters
            arm = bool(kids[i]) and arm_shape(b, up, [head])
            cordon = parent_kind in ("trunk", "cordon") and level_and_thick(b, up)
            pb = sk.branches[b.parent]  # a cordon's continuation from its end, tapering
            tapers = (parent_kind == "cordon" and float(np.linalg.norm(b.points[0] - pb.points[-1])) <= CONTINUE_WITHIN
                      and float(np.median(b.radii)) >= CONTINUE_RADIUS * float(np.median(pb.radii)))  # fmt: skip
            r_on = min(CORDON_RADIUS * r_trunk, CONTINUE_RADIUS * float(np.median(pb.radii)))
            onward = parent_kind == "cordon" and carries_on(b, pb, up, r_on)
            # an arm: wherever hung
            if ((cordon or arm) and thick) or (cordon and tapers) or onward:
                kind = "cordon"
            elif kids[i] and b.length < 0.12:
                kind = "spur"
            else:
                kind = "cane"
        b.kind = kind
