"""Several plants in one scan (a row of vines or trees): their trunks are found at their feet,
and each point goes to the plant the scan joins it to by the shortest path (a geodesic Voronoi
split over the thinned points), so that one plant can be imported on its own.

A scan of a row holds several vines whose canes touch and cross between neighbours. Without
this split the skeleton of such a scan starts from one trunk and takes the others for canes
(measured: three bundled-sample vines 0.8 m apart became one trunk, one cordon and 42 canes,
with no error), or, where the plants do not touch, the largest is kept and the others dropped
as stray pieces.

Feet: the points within `FOOT_BAND` of the ground (or of the lowest point when no ground was
scanned) joined within `FOOT_LINK`, each piece a trunk's column (`FOOT_HEIGHT`, `FOOT_LOW`,
`FOOT_LEAN`: not a cane or a limb hanging low); pieces closer than `PLANT_SPACING` are one plant (a double
trunk, a stake beside its vine); a post touching the canes, found the same way, is told by its
shape, and a weed or a stump by its size (`plants_of_row`). Rows on a slope are served
through the ground plane (heights are taken above it); a row scanned without ground on a slope
steeper than `FOOT_BAND` over the row may miss the higher feet.
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import csgraph
from scipy.spatial import cKDTree

from vinetwin.frames import Array

#: Metres above the ground (or the lowest point) that only trunks reach down to.
FOOT_BAND = 0.25
#: Points of one foot are joined within this (m).
FOOT_LINK = 0.04
#: A foot stands at least this tall (m) in the band, from within `FOOT_LOW` (m) of the ground,
#: its principal axis within `FOOT_LEAN` degrees of up: a trunk's column (the hydroshoot GDC
#: vine's trunk leans 13-24 degrees), not a limb hanging into the band (on the
#: Tree-Models-Library's nectarine two of them end 9 and 12 cm above its foot, leaning 37 and
#: 44 degrees).
FOOT_HEIGHT = 0.10
FOOT_LOW = 0.10
FOOT_LEAN = 30.0
#: Feet closer than this (m, horizontally) are one plant: vines and trees are planted 0.5 m or
#: more apart; a double trunk or a stake stands within a few centimetres.
PLANT_SPACING = 0.3
#: A plant of the row holding `POST_SHARE` of its points within `POST_WIDTH` (m, horizontally)
#: of their median is a post or a bare stem, nothing to prune: a vine's own trunk holds a third
#: of its points or less (34-40% on the bundled sample's and the VSP vine's), the simulated
#: trellis's posts 100% (88% on one the split gave a cordon's end and a cane).
POST_WIDTH = 0.10
POST_SHARE = 0.75
#: A "plant" with fewer points than this share of the largest one's is none (a weed or a heap of
#: strays standing in the foot band); its points go to the plants.
MIN_PLANT = 0.2
#: The split works on the points thinned to this voxel (m) at least.
SPLIT_VOXEL = 0.01


def find_feet(points: Array, up: Array, ground_offset: float | None = None) -> Array:
    """(K, 3) the plants' feet (the lowest point of each trunk, metres, the scan's frame),
    ordered along the row (the feet's principal horizontal direction, sign: its largest
    component positive); one row when the scan holds one plant. `ground_offset`: the ground
    plane is {p : up . p = offset} (else the lowest point is the ground)."""
    from vinetwin.scan.skeletonize import radius_graph, voxel_thin

    h = points @ up
    lowest = points[[int(np.argmin(h))]]  # one plant, wherever its foot
    base = float(h.min()) if ground_offset is None else ground_offset
    band = points[h - base <= FOOT_BAND]
    if len(band) < 10:
        return lowest
    P, _ = voxel_thin(band, 0.01)
    _, lab = csgraph.connected_components(radius_graph(P, FOOT_LINK), directed=False)
    hp = P @ up - base
    feet = []
    for c in np.unique(lab):
        m = lab == c
        if m.sum() < 5 or np.ptp(hp[m]) < FOOT_HEIGHT or hp[m].min() > FOOT_LOW:
            continue
        Q = P[m]
        axis = np.linalg.eigh(np.cov((Q - Q.mean(0)).T))[1][:, -1]
        if abs(float(axis @ up)) >= np.cos(np.radians(FOOT_LEAN)):
            feet.append(Q[np.argmin(hp[m])])
    if not feet:
        return lowest
    F = np.array(feet)
    flat = F - np.outer(F @ up, up)  # horizontal positions
    # feet nearer than PLANT_SPACING are one plant: single linkage, the lowest foot kept
    _, lab = csgraph.connected_components(radius_graph(flat, PLANT_SPACING), directed=False)
    F = np.array([F[lab == c][np.argmin(F[lab == c] @ up)] for c in np.unique(lab)])
    if len(F) == 1:
        return F
    flat = F - np.outer(F @ up, up)
    _, _, vt = np.linalg.svd(flat - flat.mean(0), full_matrices=False)
    axis = vt[0] * np.sign(vt[0][np.argmax(np.abs(vt[0]))])
    return F[np.argsort(flat @ axis)]


def split_plants(points: Array, feet: Array, spacing: float) -> np.ndarray:
    """(N,) the index into `feet` of the plant each point belongs to: the foot nearest along
    the scan (shortest paths over the points thinned to `SPLIT_VOXEL` or the spacing, joined
    within 2.5 voxels); points of pieces no path reaches go with the nearest point that one
    reaches."""
    from vinetwin.scan.skeletonize import radius_graph, voxel_thin

    voxel = max(SPLIT_VOXEL, spacing)
    P, inv = voxel_thin(points, voxel)
    g = radius_graph(P, 2.5 * voxel)
    n = len(P)
    tree = cKDTree(P)
    # each foot's sources: the thinned points within a trunk's width of it
    src, owner = [], []
    for k, f in enumerate(feet):
        near = tree.query_ball_point(f, 0.05) or [int(tree.query(f)[1])]
        src.extend(near)
        owner.extend([k] * len(near))
    src_a, owner_a = np.array(src), np.array(owner)
    order = np.unique(src_a, return_index=True)[1]  # a point near two feet: the first
    src_a, owner_a = src_a[order], owner_a[order]
    dist, _, from_src = csgraph.dijkstra(
        g, directed=False, indices=src_a, min_only=True, return_predecessors=True
    )
    lab = np.full(n, -1)
    reached = np.isfinite(dist)
    lab[reached] = owner_a[np.searchsorted(src_a, from_src[reached])]
    if (~reached).any():
        j = cKDTree(P[reached]).query(P[~reached])[1]
        lab[~reached] = lab[reached][j]
    return lab[inv]


def _post_column(points: Array, foot: Array, up: Array) -> np.ndarray | None:
    """When a plant of the row (its points, its foot) is a post or a bare stem: the mask of its
    column's points (within `POST_WIDTH` of their median's vertical), else None. Such a column
    holds `POST_SHARE` or more of the points the split gave it (the rest: ends of canes it
    touches, given back to the plants)."""
    d = points - foot
    flat = d - np.outer(d @ up, up)
    near = np.linalg.norm(flat - np.median(flat, axis=0), axis=1) <= POST_WIDTH
    return near if float(near.mean()) >= POST_SHARE else None


def plants_of_row(
    points: Array, feet: Array, up: Array, spacing: float
) -> tuple[Array, np.ndarray, np.ndarray]:
    """The feet that are plants' (a post or a bare stem is none, `_post_column`; nor is a piece
    holding under `MIN_PLANT` of the largest plant's points: a weed, a stump, a stray heap),
    the mask of the posts' points, and each point's plant (`split_plants`) among the feet
    given. When none is left, the largest stays."""
    lab = split_plants(points, feet, spacing)
    sizes = np.bincount(lab, minlength=len(feet))
    keep = sizes >= MIN_PLANT * sizes.max()
    post = np.zeros(len(points), bool)
    for k in np.flatnonzero(keep):
        idx = np.flatnonzero(lab == k)
        col = _post_column(points[idx], feet[k], up)
        if col is not None:
            post[idx[col]], keep[k] = True, False
    if not keep.any():
        return feet[[int(np.argmax(sizes))]], np.zeros(len(points), bool), lab
    return feet[keep], post, lab
