"""How close a scan's skeleton and twin are to the truth (a twin of the same plant).

- **completeness**: the share of the true skeleton's length within `tol` (1 cm) of ours;
- **precision**: the share of ours within `tol` of the truth;
- **radius error**: the median |our radius - the true radius| where the two are within `tol`;
- **tips**: true tips (free ends of canes and branches) with one of ours within 3 cm, and ours
  with no true tip near (extra);
- **canes lost**: true tip paths at least `MIN_CANE` long that the scan saw (points along at
  least half of them) but our skeleton misses (less than half within `tol`); shorter stubs are
  under the skeleton's junction-noise threshold (`SkeletonConfig.min_branch` plus the parent's
  radius) and are not counted;
- **candidates**: the cut rule (`candidates.cut_candidates`) applied to both skeletons: the share
  of the truth's within `tol` of ours;
- **mesh**: Chamfer distance (mean of both directions) and F-score at 2 mm between the meshes.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy.spatial import cKDTree

from vinetwin.frames import Array
from vinetwin.scan.candidates import cut_candidates
from vinetwin.scan.config import PlantKind
from vinetwin.twin.skeleton import Skeleton, axis_samples, resample, tip_paths

#: Tip paths shorter than this (m) are stubs, not canes, for the "canes lost" count.
MIN_CANE = 0.06


def sample_skeleton(sk: Skeleton, step: float = 0.002) -> tuple[Array, Array]:
    """Points every `step` along every branch and their radii."""
    return axis_samples(sk, step=step)


@dataclass
class Accuracy:
    completeness: float
    precision: float
    radius_error_mm: float
    tips_true: int
    tips_found: int
    tips_extra: int
    canes_seen: int
    canes_lost: int
    candidates_true: int
    candidates_found: int
    candidates_ours: int
    chamfer_mm: float | None = None
    fscore_2mm: float | None = None

    def to_dict(self) -> dict[str, float | int | None]:
        return asdict(self)


def skeleton_accuracy(
    ours: Skeleton,
    truth: Skeleton,
    plant: PlantKind,
    internode: float,
    scan_points: Array | None = None,
    tol: float = 0.01,
) -> Accuracy:
    """The measures of the module's docstring; both skeletons in the same frame."""
    A, rA = sample_skeleton(truth)
    B, rB = sample_skeleton(ours)
    tA, tB = cKDTree(A), cKDTree(B)
    dA, iA = tB.query(A)
    dB, _ = tA.query(B)
    match = dA <= tol
    rad_err = (
        float(np.median(np.abs(rB[iA[match]] - rA[match]))) * 1000 if match.any() else float("nan")
    )
    tips_t = np.array([p[-1] for p, *_ in tip_paths(truth)])
    tips_o = np.array([p[-1] for p, *_ in tip_paths(ours)])
    found = int((cKDTree(tips_o).query(tips_t)[0] <= 0.03).sum()) if len(tips_o) else 0
    extra = int((cKDTree(tips_t).query(tips_o)[0] > 0.03).sum()) if len(tips_t) else len(tips_o)
    seen = lost = 0
    sp = cKDTree(scan_points) if scan_points is not None else None
    for P, R, _, _ in tip_paths(truth):
        if float(np.linalg.norm(np.diff(P, axis=0), axis=1).sum()) < MIN_CANE:
            continue
        Q, Rq = resample(P, R, 0.005)
        if sp is not None:
            d, _ = sp.query(Q)
            if (d <= Rq + 0.004).mean() < 0.5:
                continue
        seen += 1
        if (tB.query(Q)[0] <= tol).mean() < 0.5:
            lost += 1
    ct = cut_candidates(truth, plant, internode)
    co = cut_candidates(ours, plant, internode)
    cf = 0
    if ct and co:
        cf = int((cKDTree([c.point for c in co]).query([c.point for c in ct])[0] <= tol).sum())
    return Accuracy(
        completeness=float(match.mean()), precision=float((dB <= tol).mean()),
        radius_error_mm=rad_err, tips_true=len(tips_t), tips_found=found, tips_extra=extra,
        canes_seen=seen, canes_lost=lost, candidates_true=len(ct), candidates_found=cf,
        candidates_ours=len(co),
    )  # fmt: skip


def mesh_accuracy(
    V1: Array, F1: np.ndarray, V2: Array, F2: np.ndarray, tau: float = 0.002, n: int = 200_000
) -> tuple[float, float]:
    """Chamfer distance (mm, mean of both directions) and F-score at `tau` between two meshes,
    from `n` points sampled on each."""
    from vinetwin.scan.read import sample_mesh_surface

    rng = np.random.default_rng(0)

    def sample(V: Array, F: np.ndarray) -> Array:
        tri = V[F]
        area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
        return sample_mesh_surface(V, F, float(np.sqrt(area.sum() / n)), rng)

    a, b = sample(V1, F1), sample(V2, F2)
    dab = cKDTree(b).query(a)[0]
    dba = cKDTree(a).query(b)[0]
    p, r = float((dab <= tau).mean()), float((dba <= tau).mean())
    f = 2 * p * r / (p + r) if p + r > 0 else 0.0
    return 500.0 * float(dab.mean() + dba.mean()), f
