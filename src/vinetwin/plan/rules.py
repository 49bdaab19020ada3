"""Pruning rules on a skeleton: which canes are shortened, which are removed, and where each cut
sits, with the reason.

The rules are defined on the plant's shape, not on how its branches happen to be split into
polylines nor on how finely those are sampled (they run on `evenly_sampled`), so that they give
the same cuts on a scan's skeleton and on the true skeleton of the same vine:

- a **shoot** is a tip's path back to the permanent wood (trunk, cordons; for a tree, the tip's
  last fork), `twin.skeleton.tip_paths`;
- shoots leaving the permanent wood within `spur_radius` of each other form one **spur**;
- within a spur each shoot **parts** from the others where its surface is first `PART_GAP`
  (1 cm) clear of theirs; a shoot parting from a much thicker one (radius below
  `LATERAL_RATIO` of it), or farther out than `MAX_PARTING`, grows on that cane and goes with it;
- **buds**: the skeleton's nodes where it knows them (the generator's canes, hydroshoot's
  shoots), else every `internode` from the permanent wood's surface, the first `FIRST_NODE` out;
  a cane is shortened to N buds 30% of the way from bud N to bud N+1 (the generator's and the
  importers' candidates sit there for N = 2);
- a cane **removed** is cut where it parts from what stays (the kept cane, or the permanent
  wood when its whole spur goes): one cut removes a whole spur.

Spur pruning (`rule="spur"`): in each spur the best-placed cane (the most upright over its first
10 cm, then the thickest) is shortened to `buds` buds, the others are removed. Cane pruning
(`rule="cane"`): the `canes` best canes of the spurs nearest the head (the trunk's top) keep
`cane_buds` buds, the best cane of the next spur is a renewal spur of `buds` buds, everything
else is removed at the permanent wood.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from vinetwin.errors import InputError
from vinetwin.frames import Array
from vinetwin.plan.config import RuleConfig
from vinetwin.twin.skeleton import (
    FIRST_NODE,
    PERMANENT,
    Branch,
    Skeleton,
    arc_length,
    nearest_on_polyline,
    point_at,
    resample,
    standoff,
    tip_paths,
)

#: Two axes part where their surfaces are this far apart (m): room for the shears' jaw. Where
#: two canes touch, a scan's skeleton runs them as one axis and parts them late; 1 cm apart both
#: skeletons agree (on simulated scans: 44% of cuts within 1 cm against 33% at 5 mm).
PART_GAP = 0.01
#: A shoot parting from one more than 1 / this times thicker is its side shoot.
LATERAL_RATIO = 0.4
#: Canes of one spur part within this distance (m) of where they leave the permanent wood
#: (hydroshoot's longest spur and cane stub reach 17 cm); a shoot parting farther out grows on
#: a cane (a lateral, or a crossing a scan's skeleton could not separate) and goes with it.
MAX_PARTING = 0.18
#: A shoot shorter than this past the permanent wood (m) is noise at a junction.
MIN_SHOOT = 0.03
#: The cut sits this share of the way from the last kept bud to the next.
BETWEEN_BUDS = 0.3
#: A shoot's path is sampled this finely (m).
SHOOT_STEP = 0.002
#: A cane's axis at a cut is the chord over this much (m) either side of it.
AXIS_HALF = 0.01
#: Half the length of cane (m) around a cut whose visibility the pose search scores.
CANE_WINDOW = 0.05


@dataclass
class Shoot:
    """One-year wood: a tip's path from the permanent wood (or its last fork)."""

    points: Array
    radii: Array
    wood_radius: float
    """Radius of the permanent wood it leaves."""
    branch: int
    """The skeleton branch of its tip."""
    label: str
    arc: Array = field(init=False)
    standoff: Array | None = None
    """How far each point stands off the wood it grows from (`twin.skeleton.standoff`)."""
    reach: Array = field(init=False)
    """Distance from its first point (on the wood's axis), never decreasing: the standoff plus
    the wood's radius where given, else the straight-line distance."""
    spur: int = -1
    part: float = 0.0
    """Arc position where it parts from the other shoots of its spur (or the wood)."""
    side_of: int = -1
    """For a side shoot: the shoot it grows on."""
    buds: Array = field(default_factory=lambda: np.zeros(0))
    """Arc positions of its buds."""

    def __post_init__(self) -> None:
        self.arc = arc_length(self.points)
        if self.standoff is not None:
            reach = self.standoff + self.wood_radius
        else:
            reach = np.linalg.norm(self.points - self.points[0], axis=1)
        self.reach = np.maximum.accumulate(np.maximum(reach, 0.0))

    def at(self, s: float) -> tuple[Array, Array, float]:
        """Point, unit axis and radius at arc position s."""
        P, a = self.points, self.arc
        p = point_at(P, a, s)
        lo = int(np.clip(np.searchsorted(a, s - AXIS_HALF), 0, len(P) - 2))
        hi = int(np.clip(np.searchsorted(a, s + AXIS_HALF), lo + 1, len(P) - 1))
        axis = P[hi] - P[lo]
        axis /= max(float(np.linalg.norm(axis)), 1e-12)
        return p, axis, float(np.interp(s, a, self.radii))

    def window(self, s: float) -> Array:
        """The shoot's centre points within `CANE_WINDOW` of arc position s."""
        keep = np.abs(self.arc - s) <= CANE_WINDOW
        return self.points[keep] if keep.any() else self.at(s)[0][None]


@dataclass
class Proposal:
    """One proposed cut."""

    point: Array
    cane_axis: Array
    radius: float
    action: str
    """"shorten" or "remove"."""
    reason: str
    label: str
    cane: Array
    """The cut cane's centre points near the cut (what the camera should see)."""
    branch: int

    def to_json(self) -> dict[str, object]:
        return {"action": self.action, "reason": self.reason, "label": self.label,
                "radius": round(self.radius, 5)}  # fmt: skip


#: Kinds that only a vine's skeleton has: its cuts are counted from the permanent wood; on a tree
#: (branches only) from each tip's last fork.
_VINE_KINDS = {"cordon", "spur", "cane", "shoot"}


def _vine(sk: Skeleton) -> bool:
    return any(b.kind in _VINE_KINDS for b in sk.branches)


def evenly_sampled(sk: Skeleton) -> Skeleton:
    """The skeleton with each branch resampled every `SHOOT_STEP` (kinds, parents, labels and
    nodes kept): the rules see the plant's shape, however finely its source sampled it. On a
    hydroshoot vine's own skeleton (nodes 6-9 cm apart) a lateral's radius was otherwise
    ramped from its cane's over its first internode, and the same vine sampled every 2 mm
    got 3 of its 17 spur-rule cuts elsewhere."""

    def even(b: Branch) -> Branch:
        if len(b.points) < 2:
            return b
        P, R = resample(b.points, b.radii, SHOOT_STEP)
        return replace(b, points=P, radii=R)

    return replace(sk, branches=[even(b) for b in sk.branches])


def shoots(sk: Skeleton) -> list[Shoot]:
    """The skeleton's shoots (see the module's docstring), junction noise left out."""
    if not sk.branches:
        raise InputError("the skeleton has no branches")
    vine = _vine(sk)
    off = standoff(sk, "permanent" if vine else "rest")
    out = []
    for P, R, wood_r, b in tip_paths(sk, "permanent" if vine else "fork"):
        if sk.branches[b].parent < 0 or len(P) < 2:
            continue
        # every `SHOOT_STEP`: how far a path stands off the wood, and how far it is from its
        # neighbours, are not linear between a skeleton's points (hydroshoot's nodes are 6-9 cm
        # apart, a measured tree's cylinders up to 50 cm)
        P, R = resample(P, R, SHOOT_STEP)
        s = Shoot(P, R, wood_r, b, sk.branches[b].label or f"branch{b}", standoff=off(P))
        if s.reach[-1] - wood_r < MIN_SHOOT:
            continue
        out.append(s)
    return out


def _group(shoots_: list[Shoot], radius: float) -> list[list[int]]:
    """Spurs: single-linkage groups of shoots whose first points lie within `radius`."""
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    if not shoots_:
        return []
    starts = np.array([s.points[0] for s in shoots_])
    pairs = cKDTree(starts).query_pairs(radius, output_type="ndarray")
    from scipy.sparse import coo_matrix

    n = len(shoots_)
    g = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, labels = connected_components(g, directed=False)
    groups: dict[int, list[int]] = {}
    for i, lab in enumerate(labels):
        groups.setdefault(int(lab), []).append(i)
    # along the plant: by the first point's position along its principal horizontal axis
    order = sorted(groups.values(), key=lambda g: tuple(starts[g[0]]))
    return order


def _gap_reached(s: Shoot, gap: Array, level: float) -> float | None:
    """Arc position where `gap` first reaches `level` and stays there for 1 cm (interpolated)."""
    for i in np.nonzero(gap >= level)[0]:
        ahead = (s.arc >= s.arc[i]) & (s.arc <= s.arc[i] + 0.01)
        if np.all(gap[ahead] >= level):
            if i == 0:
                return 0.0
            f = (level - gap[i - 1]) / max(gap[i] - gap[i - 1], 1e-12)
            return float(s.arc[i - 1] + f * (s.arc[i] - s.arc[i - 1]))
    return None


def _first_clear(s: Shoot, others: list[tuple[Array, Array]]) -> tuple[float, float]:
    """Arc position on s where its surface first comes `PART_GAP` clear of every polyline in
    `others` (points, radii) and stays so for 1 cm, and the radius of the nearest other there;
    with no others, of the wood it starts on."""
    from scipy.spatial import cKDTree

    if not others:
        r = s.wood_radius + float(s.radii[0]) + PART_GAP
        return float(np.interp(r, s.reach, s.arc)), s.wood_radius
    pts = np.concatenate([o[0] for o in others])
    rad = np.concatenate([o[1] for o in others])
    d, k = cKDTree(pts).query(s.points)
    gap = d - rad[k] - s.radii
    at = _gap_reached(s, gap, PART_GAP)
    if at is None:
        return float(s.arc[-1]), float(rad[k[-1]])
    i = int(np.clip(np.searchsorted(s.arc, at), 0, len(s.arc) - 1))
    return at, float(rad[k[i]])


def _wood(sk: Skeleton) -> list[tuple[Array, Array]]:
    """A vine's permanent wood as polylines (resampled); none for a tree (its shoots start on
    their fork)."""
    if not _vine(sk):
        return []
    return [resample(b.points, b.radii) for b in sk.branches
            if (b.kind in PERMANENT or b.parent < 0) and len(b.points) > 1]  # fmt: skip


def _buds(sk: Skeleton, s: Shoot, cfg: RuleConfig) -> Array:
    """Arc positions of the shoot's buds."""
    b = sk.branches[s.branch]
    if cfg.internode == 0.0 and len(b.nodes):
        # the tip branch's nodes, moved onto the shoot's arc
        base = b.points[0]
        k, t, _ = nearest_on_polyline(base, s.points)
        a0 = s.arc[k] + t * (s.arc[min(k + 1, len(s.arc) - 1)] - s.arc[k])
        return a0 + b.nodes
    step = cfg.bud_spacing()
    reach = s.wood_radius + FIRST_NODE + step * np.arange(int(s.reach[-1] / step) + 2)
    reach = reach[reach <= s.reach[-1]]
    return np.interp(reach, s.reach, s.arc)


def _shorten_at(s: Shoot, n: int) -> float | None:
    """Arc position of the cut leaving n buds, or None when the shoot has no bud n + 1."""
    if len(s.buds) < n + 1:
        return None
    return float(s.buds[n - 1] + BETWEEN_BUDS * (s.buds[n] - s.buds[n - 1]))


def _placement(s: Shoot, up: Array) -> tuple[float, float]:
    """How well placed a cane is: how upright its first 10 cm past its parting, then its
    thickness there."""
    a0 = s.part
    p0 = s.at(a0)[0]
    p1 = s.at(min(a0 + 0.10, s.arc[-1]))[0]
    d = p1 - p0
    upright = float(d @ up / max(np.linalg.norm(d), 1e-9))
    return round(upright, 2), float(np.interp(s.part, s.arc, s.radii))


def analyse(sk: Skeleton, cfg: RuleConfig) -> tuple[list[Shoot], list[list[int]]]:
    """The skeleton's shoots with their spurs, partings and buds (on `evenly_sampled(sk)`:
    the shoots' branch indices are the skeleton's)."""
    sk = evenly_sampled(sk)
    ss = shoots(sk)
    groups = _group(ss, cfg.spur_radius)
    wood = _wood(sk)
    for g_i, g in enumerate(groups):
        order = sorted(g, key=lambda i: -ss[i].arc[-1])  # longest first
        for rank, i in enumerate(order):
            s = ss[i]
            s.spur = g_i
            longer = [resample(ss[j].points, ss[j].radii) for j in order[:rank]]
            if longer:
                s.part, r_other = _first_clear(s, longer)
                far = np.interp(s.part, s.arc, s.reach) > MAX_PARTING
                if far or np.interp(s.part, s.arc, s.radii) < LATERAL_RATIO * r_other:
                    # a side shoot: of the longer shoot it lies nearest where it parts
                    p = s.at(s.part)[0]
                    near = min(order[:rank],
                               key=lambda j: np.min(np.linalg.norm(ss[j].points - p, axis=1)))  # fmt: skip
                    s.side_of = near
            else:
                s.part, _ = _first_clear(s, wood)
        for i in g:
            ss[i].buds = _buds(sk, ss[i], cfg)
    return ss, groups


def _cut(s: Shoot, a: float, action: str, reason: str, label: str) -> Proposal:
    p, axis, r = s.at(a)
    return Proposal(p, axis, r, action, reason, label, s.window(a), s.branch)


def _spur_base(ss: list[Shoot], g: list[int], sk: Skeleton) -> tuple[Shoot, float]:
    """Where a whole spur is removed: on its longest shoot, where it leaves the permanent wood."""
    s = max((ss[i] for i in g), key=lambda s: s.arc[-1])
    return s, _first_clear(s, _wood(sk))[0]


def propose_cuts(sk: Skeleton, cfg: RuleConfig, up: Array | None = None) -> list[Proposal]:
    """The cuts the rule of `cfg` proposes on the skeleton (vine frame: +Z up)."""
    up = np.array([0.0, 0.0, 1.0]) if up is None else np.asarray(up, dtype=np.float64)
    if cfg.rule == "cane" and not _vine(sk):
        raise InputError(
            "the cane rule is for grapevines (a skeleton with cordons, spurs, canes or shoots); "
            "this skeleton is a tree's (branches only): use the spur rule"
        )
    sk = evenly_sampled(sk)  # for the spur bases and the head below; `analyse` samples again
    ss, groups = analyse(sk, cfg)
    if not ss:
        raise InputError("the skeleton has no canes or shoots to prune")
    out: list[Proposal] = []

    def canes_of(g: list[int]) -> list[int]:
        return [i for i in g if ss[i].side_of < 0]

    def best(g: list[int], need: int) -> int | None:
        """The best-placed cane of a spur with at least `need` buds (any cane when none has)."""
        cands = canes_of(g)
        long_ = [i for i in cands if len(ss[i].buds) >= need]
        pool = long_ or cands
        return max(pool, key=lambda i: _placement(ss[i], up)) if pool else None

    def shorten(i: int, n: int, what: str) -> None:
        s = ss[i]
        a = _shorten_at(s, n)
        if a is None:
            return  # it has no more than n buds: left as it is
        out.append(_cut(s, a, "shorten", f"{what}: {s.label} shortened to {n} buds", s.label))

    def remove_others(g: list[int], kept: int, spur_name: str) -> None:
        for i in canes_of(g):
            if i == kept:
                continue
            s = ss[i]
            # where it parts from the kept cane (never inside their shared wood: when it is
            # the longest of its spur, its own parting is from the permanent wood)
            k = ss[kept]
            a = max(s.part, _first_clear(s, [resample(k.points, k.radii)])[0])
            out.append(_cut(s, a, "remove",
                            f"{spur_name}: {s.label} removed at its base (kept: {ss[kept].label})",
                            s.label))  # fmt: skip

    if cfg.rule == "spur":
        for g_i, g in enumerate(groups):
            k = best(g, cfg.buds + 1)
            if k is None:
                continue
            name = f"spur {g_i + 1}"
            shorten(k, cfg.buds, name)
            remove_others(g, k, name)
        return out

    # cane pruning: spurs by their distance from the head
    head = _head(sk)
    dist = [float(np.min([np.linalg.norm(ss[i].points[0] - head) for i in g])) for g in groups]
    order = sorted(range(len(groups)), key=lambda j: dist[j])
    kept_canes: list[int] = []
    renewal: int | None = None
    for j in order:
        k = best(groups[j], cfg.cane_buds)
        if k is None or len(ss[k].buds) < min(cfg.cane_buds, 3):
            continue
        if len(kept_canes) < cfg.canes:
            kept_canes.append(j)
        elif renewal is None:
            renewal = j
            break
    for j, g in enumerate(groups):
        name = f"spur {j + 1}"
        if j in kept_canes or j == renewal:
            k = best(g, cfg.cane_buds if j in kept_canes else cfg.buds + 1)
            assert k is not None
            if j in kept_canes:
                shorten(k, cfg.cane_buds, f"{name} (cane {kept_canes.index(j) + 1} of the head)")
            else:
                shorten(k, cfg.buds, f"{name} (renewal spur)")
            remove_others(g, k, name)
            continue
        s, a = _spur_base(ss, g, sk)
        out.append(_cut(s, a, "remove", f"{name}: removed at the permanent wood ({dist[j]:.2f} m "
                                         "from the head)", s.label))  # fmt: skip
    return out


def _head(sk: Skeleton) -> Array:
    """The vine's head: the trunk's top (where its cordons or canes start)."""
    roots = [b for b in sk.branches if b.parent < 0]
    trunk = max(roots, key=lambda b: b.length)
    return trunk.points[-1]
