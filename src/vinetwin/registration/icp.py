"""ICP: the pose of the current camera in the reference camera frame, four variants.

- `point_to_point`: closed-form SVD step on closest-point pairs (Besl & McKay 1992);
- `lm`: Levenberg-Marquardt ICP (Fitzgibbon 2003): the Huber-robust distance of each current
  point to the reference, minimised by Levenberg-Marquardt. By default the distance to the
  reference surface, modelled as a disc about each reference point (`ICPConfig.lm_model`
  "surface"); "points": the distance to the closest reference point, point-to-point's
  residuals (what PCL's IterativeClosestPointNonLinear minimises);
- `point_to_plane`: linearised 6x6 solve of `sum ((R p + t - q) . n_q)^2` (Chen & Medioni 1992);
- `symmetric`: `sum ((n_p + n_q) . (R p - R^-1 q + t))^2`, linearised with half rotations
  (Rusinkiewicz 2019).

The reference never changes during a servo: `ICP(reference_cloud, config)` builds its
k-d trees (one per voxel size of its levels; their searches memoised within a registration,
the same exact answers) and, for projective association, the reference points binned by their
pixel in the reference camera's image, once (`_search_kernels`); `align(current_cloud,
T_init)` runs per frame, each level in one compiled call (`vinetwin.registration._kernels`). A
registration runs through levels, coarse to fine: each level is (voxel size, maximum
correspondence distance). The default (`SCHEDULES`) shrinks the distance: 3 cm (on 4 mm copies
of the clouds for point-to-plane and symmetric), 1 cm, then `max_correspondence_distance` on the
clouds as given: a wide first reach pulls a warm start in, a tight last one keeps the partial
overlap of two views (canes entering or leaving the image) from biasing the result. The levels
of 1 cm reach or less pair points by projection into the reference view
(`ICPConfig.association`), the wider one by the exact tree. `ICPConfig.coarse_to_fine()` adds
downsampled levels for starts far from the goal.

Failures come back as a result with `converged=False` and a `reason`, never as an exception from
inside numpy: an empty or non-finite cloud, too few points or correspondences, or a geometry that
constrains fewer than six degrees of freedom (a single straight cane: sliding along it and
rolling about it are unobservable).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from vinetwin.camera import CameraModel
from vinetwin.cloud import ICP_VARIANTS, Cloud, voxel_downsample
from vinetwin.errors import InputError
from vinetwin.frames import Array, invert, pose_error
from vinetwin.registration import _kernels as K
from vinetwin.registration import _search_kernels as S
from vinetwin.registration._search_kernels import NNTree

NDF = npt.NDArray[np.float64]

#: Default edge-of-view rejection reach per variant (m); absent: none. LM with
#: `lm_model="points"` takes point-to-point's defaults (reach, schedule, final-level edges).
EDGE_REACH = {"point_to_plane": 0.003, "point_to_point": 0.01, "lm": 0.003}
#: Default levels before the final one per variant (`ICPConfig.schedule`).
SCHEDULES: dict[str, tuple[tuple[float, float], ...]] = {
    "point_to_plane": ((0.004, 0.03), (0.0, 0.01)),
    "symmetric": ((0.004, 0.03), (0.0, 0.01)),
    "point_to_point": ((0.0, 0.03), (0.0, 0.01)),
    "lm": ((0.004, 0.03), (0.0, 0.01)),
}
#: What LM measures a current point's distance to (`ICPConfig.lm_model`).
LM_MODELS = ("surface", "points")
#: How ICP levels pair points (`ICPConfig.association`).
ASSOCIATIONS = ("tree", "projective")
#: Default association per variant (`ICPConfig.association` None). Point-to-point and LM pair
#: by the exact tree: under the field profile (a reconstructed twin, every error source;
#: `vinetwin campaign --profile field`, Table 1's starts, seed 0) projective association left
#: them twice as far off in rotation on the sample (0.010-0.012 against 0.0044-0.0062 rad; a
#: second seed alike for point-to-point) and no closer on the hydroshoot and dense vines; at the
#: cut point the two were within about 0.2 mm either way. Point-to-plane and symmetric did as
#: well with projection (docs/results/speed.md, "Projective association in the field").
ASSOCIATION_DEFAULTS = {
    "point_to_point": "tree", "lm": "tree",
    "point_to_plane": "projective", "symmetric": "projective",
}  # fmt: skip
#: Variants whose edge rejection also applies at the final level (the others: coarse levels only).
EDGE_FINAL = frozenset({"point_to_plane", "lm"})
#: Default `ICPConfig.coarse_tolerance` per variant; absent: 0. Symmetric and LM on the
#: surface hand a level's answer on once it moves less than 1% of the level's reach: on four
#: vines' views (benchmarks/icp.py's cases, 2 and 4 mm, 2 cm and 5 cm starts) they took 25-50%
#: fewer iterations for the same share within 1 mm / 0.1 degree in all 16 cells each, since the
#: final level settles the answer. Point-to-plane did too in 14 of 16 but lost a case of 12-15
#: in two (2 mm from 5 cm, the sample and the dense vine), so it keeps 0; point-to-point and LM
#: on points creep along the canes, where stopping early costs accuracy (docs/results/speed.md).
COARSE_TOLERANCE = {"symmetric": 0.01, "lm": 0.01}


@dataclass(frozen=True, kw_only=True)
class ICPConfig:
    """Settings of one registration."""

    variant: str = "point_to_plane"
    """One of point_to_point, lm, point_to_plane, symmetric."""
    max_correspondence_distance: float = 0.005
    """Pairs farther apart than this (m) are rejected at the final level."""
    max_iterations: int = 60
    """Iterations per level."""
    tolerance_translation: float = 1e-5
    """Convergence when an update moves less than this (m)..."""
    tolerance_rotation: float = 1e-5
    """...and turns less than this (rad)."""
    schedule: tuple[tuple[float, float], ...] | None = None
    """Levels run before the final one, coarse to fine: (voxel size m, correspondence distance
    m). Voxel 0 uses the clouds as given. The final level is (0, max_correspondence_distance).
    None: the variant's default, `SCHEDULES` (a 3 cm reach then 1 cm; the 3 cm level on 4 mm
    copies of the clouds for point-to-plane, symmetric and LM on the surface, whose answer the
    finer levels then settle: on 2 mm clouds it halves their time at equal accuracy,
    benchmarks/icp.py; point-to-point and LM on points, which creep along the canes, keep the
    clouds as given)."""
    accelerate: bool = True
    """Point-to-point and LM on points: while successive updates point the same way, take up to
    16 times the update, undone if the energy rises (after Besl & McKay's accelerated ICP)."""
    coarse_tolerance: float | None = None
    """Levels before the final one also stop when an update moves less than this fraction of
    their reach (and turns less than that distance at a 10 cm lever arm); 0: the tolerances
    above everywhere. None: the variant's default, `COARSE_TOLERANCE` (0.01 for symmetric and
    LM on the surface; 0 for point-to-plane, and for point-to-point and LM on points, which
    creep along canes, so that stopping them early costs accuracy)."""
    edge_reach: float | None = None
    """With the reference's camera given to ICP: pairs whose reference point lies within
    min(this, the level's reach) of the edge of the reference view are rejected (m). None: the
    variant's default, `EDGE_REACH` (measured on the sample's views, benchmarks/icp.py: it
    helps point-to-plane and LM on the surface, and costs symmetric accuracy; point-to-point
    and LM on points use it at their coarse levels only, see `edge_final`)."""
    edge_final: bool | None = None
    """Also reject edge pairs at the final level (False: only at the coarse levels, where a
    current view reaching past the reference's drags the estimate along the canes; at the
    final level the pairs are already short). None: the variant's default, `EDGE_FINAL`.
    Measured on the sample's views from Table 1's starts (benchmarks/icp_basin.py):
    point-to-point without the coarse rejection slid 215-343 mm away from a 5 mm / 0.02 rad
    guess in some views, with it at most 8 mm."""
    cycle_translation: float = 0.0005
    """At the iteration limit of the final level, an estimate still alternating between pair
    sets (a limit cycle) whose states lie within this (m)..."""
    cycle_rotation: float = 0.005
    """...and this (rad) of each other is accepted as converged, with the cycle's size in
    `ICPResult.reason`; 0: never."""
    min_points: int = 30
    """Fewer points than this in a cloud is a failure."""
    min_correspondences: int = 20
    """Fewer accepted pairs than this is a failure."""
    crop_margin: float = 0.03
    """With the reference's camera given to ICP: current points that, placed by the initial
    guess, fall farther than this (m) outside the reference's view (image border, far depth
    limit) are left out before registering: a camera far from its goal sees three to five
    times the reference's points, which cost time and pull the estimate along canes the
    reference never saw (Table 1's start 4, 32 cm away: 4000 points against 700). The fitness
    and overlap still count every point. 0: keep all."""
    min_overlap: float = 0.2
    """A result pairing less than this share of the smaller cloud, or covering less than this
    share of the reference (`ICPResult.coverage`), at the final level is a failure
    ("diverged"), whatever its update size said: an estimate that wandered off along the canes
    can stop moving with a tenth of its points paired (a held-out vine's 2 mm view,
    point-to-plane from 2 cm / 3 deg: 184 mm off, fitness 0.11). 0: no check."""
    max_rotation_correction: float = 0.785
    """A result that turned more than this (rad; 45 deg) from its initial guess is a failure
    ("turned ... from its initial guess"), whatever its overlap: a local registration that far
    from its start has left any basin it can be trusted in. Measured on the sample's views from
    5 cm / 10 deg (symmetric, coarse to fine, D405 noise streams 1-4): right answers turned
    9.9-10.1 deg; the two false convergences among them, which `min_overlap` let through (60%
    of the smaller cloud paired, 31-33% of the reference covered, 78-88 mm / 75-78 deg from the
    truth), turned 68.5 and 72 deg. The paper's largest start (Tables 1 and 2) is 0.568 rad (32.5 deg) from
    the goal. 0: no check."""
    huber_delta: float = 0.0
    """LM only: Huber kernel width (m); 0 disables the robust kernel."""
    lm_model: str = "surface"
    """LM only: what a current point's distance is measured to. "surface": the reference
    surface, a disc about each reference point (its normal, radius `lm_disc_radius`): the
    height above the disc, or past its rim the distance to the rim (Fitzgibbon's distance to
    the model, for a sampled surface; needs reference normals). "points": the closest
    reference point, point-to-point's residuals (the form PCL minimises). Measured on three
    vines' 2 and 4 mm views from 2 cm / 3 deg starts (benchmarks/icp.py,
    docs/results/speed.md): "points" settles 0.22-2.45 mm (median) from the truth, held by the
    voxel lattice (the closest sample is not the correspondent), in 30-46 iterations; "surface"
    0.07-0.20 mm in 14-24.
    "points" takes point-to-point's defaults for `schedule` and edge rejection, "surface"
    point-to-plane's."""
    lm_disc_radius: float = 1.0
    """LM "surface": a reference point's disc radius, in the level's point spacing (its voxel,
    or for the clouds as given the median distance between neighbouring reference points): 1
    reaches the neighbouring points, so only where the surface ends (a cane's tip, the edge
    of what the reference saw) does a point's distance grow along it."""
    association: str | None = None
    """How a level pairs points (None: the variant's default, `ASSOCIATION_DEFAULTS`: the tree
    for point-to-point and LM, projective for point-to-plane and symmetric): "tree", the exact
    closest reference point (k-d tree), or
    "projective", the closest among the reference points that project within
    `projective_window` cells of the current point's pixel in the reference camera's image
    (`_search_kernels.ProjectiveIndex`; a cell is the reference's point spacing). Projective
    association needs the reference's camera given to ICP (without it: the tree) and applies to
    the levels whose reach is at most `projective_reach`; wider levels use the tree (their
    partners lie far sideways: projective association there lost 1-3 of 8-10 warm starts that
    the tree brought in, on three vines). Against the tree, whose searches are memoised
    within a registration (`_search_kernels`), point-to-plane and symmetric took 0.66-1.64x its time
    on three vines' 2 and 4 mm views, at an equal or smaller median error at 2 mm (dense vine,
    point-to-plane from 2 cm: 0.10 against 0.15 mm); the fitness, overlap and coverage of a
    result are always counted with the tree (exact)."""
    projective_reach: float = 0.01
    """The widest level (correspondence distance, m) that projective association serves."""
    projective_window: int = 1
    """Projective association: cells searched on each side of the projected pixel."""
    degeneracy_ratio: float = 1e-3
    """A cloud whose weakest constrained motion is this much weaker than its strongest fails as
    degenerate (smallest / largest eigenvalue of the scaled point-to-plane Hessian)."""

    def __post_init__(self) -> None:
        if self.variant not in ICP_VARIANTS:
            raise InputError(
                f"unknown ICP variant '{self.variant}'; choose one of: {', '.join(ICP_VARIANTS)}"
            )
        if self.lm_model not in LM_MODELS:
            raise InputError(
                f"unknown lm_model '{self.lm_model}'; choose one of: {', '.join(LM_MODELS)}"
            )
        if not self.lm_disc_radius > 0:
            raise InputError("lm_disc_radius must be positive")
        if self.association is not None and self.association not in ASSOCIATIONS:
            raise InputError(
                f"unknown association '{self.association}'; choose one of: "
                f"{', '.join(ASSOCIATIONS)}"
            )
        if self.max_correspondence_distance <= 0 or self.max_iterations <= 0:
            raise InputError("max_correspondence_distance and max_iterations must be positive")
        if not 0 <= self.max_rotation_correction <= np.pi:
            raise InputError(
                f"max_rotation_correction must lie in [0, pi] rad, not {self.max_rotation_correction!r}"
            )
        if self.coarse_tolerance is not None and not 0 <= self.coarse_tolerance < 1:
            raise InputError(f"coarse_tolerance must lie in [0, 1), not {self.coarse_tolerance!r}")
        for level in self.levels()[:-1]:
            if len(level) != 2 or level[0] < 0 or level[1] <= 0:
                raise InputError(
                    f"schedule level {level!r} is not (voxel >= 0, correspondence distance > 0)"
                )

    @property
    def association_in_use(self) -> str:
        """The association in use: `association`, or the variant's default."""
        return self.association or ASSOCIATION_DEFAULTS[self.variant]

    @property
    def lm_surface(self) -> bool:
        """LM on the distances to the reference surface (`lm_model` "surface")."""
        return self.variant == "lm" and self.lm_model == "surface"

    @property
    def needs_reference_normals(self) -> bool:
        """Whether the objective reads the reference's normals."""
        return self.variant in ("point_to_plane", "symmetric") or self.lm_surface

    def _defaults_of(self) -> str:
        """The variant whose defaults (schedule, edge rejection) apply."""
        return "point_to_point" if self.variant == "lm" and not self.lm_surface else self.variant

    def edge_reach_m(self) -> float:
        """The edge-of-view reach in use (m)."""
        if self.edge_reach is not None:
            return self.edge_reach
        return EDGE_REACH.get(self._defaults_of(), 0.0)

    def coarse_tolerance_in_use(self) -> float:
        """The coarse levels' tolerance in use (a fraction of their reach)."""
        if self.coarse_tolerance is not None:
            return self.coarse_tolerance
        return COARSE_TOLERANCE.get(self._defaults_of(), 0.0)

    def edge_at_final(self) -> bool:
        """Whether the final level rejects edge pairs too."""
        return self._defaults_of() in EDGE_FINAL if self.edge_final is None else self.edge_final

    def levels(self) -> list[tuple[float, float]]:
        """All levels, the final one included: (voxel size, correspondence distance)."""
        schedule = SCHEDULES[self._defaults_of()] if self.schedule is None else self.schedule
        return [*schedule, (0.0, self.max_correspondence_distance)]

    @classmethod
    def coarse_to_fine(cls, variant: str = "point_to_plane", **overrides: Any) -> ICPConfig:
        """A schedule for starts far from the goal (about 5 cm / 10 deg): 16 mm and 8 mm voxels
        with a reach of three voxels, then the clouds as given at 1.2 cm and 5 mm."""
        schedule = ((0.016, 0.048), (0.008, 0.024), (0.0, 0.012))
        return cls(variant=variant, schedule=schedule, **overrides)


@dataclass
class ICPResult:
    """Outcome of `ICP.align`."""

    T_ref_cur: Array
    """Current camera in the reference camera frame (the last estimate, even on failure)."""
    converged: bool
    fitness: float = 0.0
    """Fraction of current points with an accepted correspondence (Open3D's definition)."""
    overlap: float = 0.0
    """Accepted pairs over the size of the smaller cloud: near 1 when one view holds the other
    (a camera far from its goal sees more than the reference, and its fitness is low)."""
    coverage: float = 0.0
    """Share of the reference's points (final level) that the current camera, placed by the
    estimate, has in view (image and depth range; all of them without a camera) paired with
    some current point."""
    inlier_rmse: float = float("nan")
    """RMS point-to-point distance of the accepted pairs (m)."""
    correspondences: int = 0
    iterations: int = 0
    reason: str = ""
    """Why it failed (empty when converged)."""


def _check_cloud(cloud: Cloud, name: str, min_points: int, need_normals: bool) -> str:
    p = cloud.points
    if p.ndim != 2 or p.shape[1] != 3:
        return f"{name} cloud has shape {p.shape}, expected (N, 3)"
    if len(p) == 0:
        return f"{name} cloud is empty"
    if not np.all(np.isfinite(p)):
        return f"{name} cloud holds {int((~np.isfinite(p)).any(1).sum())} non-finite points"
    if len(p) < min_points:
        return f"{name} cloud has {len(p)} points, fewer than the minimum {min_points}"
    if need_normals:
        if cloud.normals is None or cloud.normals.shape != p.shape:
            return f"{name} cloud has no normals (this variant needs them)"
        if not np.all(np.isfinite(cloud.normals)):
            return f"{name} cloud holds non-finite normals"
    return ""


@dataclass
class _Level:
    voxel: float
    dmax: float
    tree: NNTree
    normals: NDF
    """Reference normals in the tree's point order ((0, 3) when the reference has none)."""
    use: npt.NDArray[np.bool_]
    """False for reference points at the edge of the reference view (tree order)."""
    proj: tuple[np.ndarray, ...] = S.NO_PROJECTIVE
    """The level's `ProjectiveIndex` arrays when it pairs by projection."""
    lm_radius: float = 0.0
    """LM "surface": the reference points' disc radius at this level (m); 0: LM on points."""

    @property
    def memo_key(self) -> tuple[int, float]:
        """Levels over the same tree and the same current copy share the tree's memo."""
        return (id(self.tree), self.voxel)


def view_edge_mask(
    points: NDF, camera: CameraModel, reach: float, max_depth: float = np.inf
) -> npt.NDArray[np.bool_]:
    """True for points within `reach` (m) of the edge of the camera's view: the image border or
    the far depth limit. A current point beyond the reference's view would pair with these
    (Turk & Levoy's boundary rule), dragging the estimate along the cane it lies on."""
    z = np.maximum(points[:, 2], 1e-9)
    u = camera.fx * points[:, 0] / z + camera.cx
    v = camera.fy * points[:, 1] / z + camera.cy
    mu = reach * camera.fx / z
    mv = reach * camera.fy / z
    return (
        (u < mu - 0.5)
        | (u > camera.width - 0.5 - mu)
        | (v < mv - 0.5)
        | (v > camera.height - 0.5 - mv)
        | (points[:, 2] > max_depth - reach)
    )


def _threads() -> int:
    import numba

    return int(numba.get_num_threads())


def _spacing(points: NDF, voxel: float) -> float:
    """A level's point spacing: its voxel, or for the clouds as given the median distance
    between neighbouring reference points; at least 0.1 mm."""
    if voxel > 0 or len(points) < 2:
        return max(voxel, 1e-4)
    from scipy.spatial import KDTree

    d, _ = KDTree(points).query(points, k=2)
    return max(float(np.median(d[:, 1])), 1e-4)


def _projective_index(
    points: NDF, camera: CameraModel, spacing: float, cfg: ICPConfig
) -> tuple[np.ndarray, ...]:
    """A level's `ProjectiveIndex`, its cells the level's point spacing (`_spacing`)."""
    idx = S.ProjectiveIndex(
        points, camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height,
        spacing, cfg.projective_window,
    )  # fmt: skip
    return idx.arrays


def _downsample(points: NDF, normals: NDF | None, voxel: float) -> tuple[NDF, NDF | None]:
    """A level's copy of a cloud, contiguous float64 as the kernels take it."""
    pts, nrm = voxel_downsample(points, voxel, normals)
    return np.ascontiguousarray(pts, dtype=np.float64), (
        None if nrm is None else np.ascontiguousarray(nrm, dtype=np.float64)
    )


class ICP:
    """Registration of current clouds to one reference cloud (both in camera frames).

    Built once per reference (its per-level downsampled copies and k-d trees);
    `align` then runs per frame, each level in one compiled call."""

    def __init__(
        self,
        reference: Cloud,
        config: ICPConfig | None = None,
        *,
        camera: CameraModel | None = None,
        max_depth: float = np.inf,
        final_reference: Cloud | None = None,
    ) -> None:
        """`camera` and `max_depth` describe the reference's view (the twin's camera and its
        perception's max_depth); with them, pairs that land within a level's reach of the edge
        of that view are rejected. `final_reference`: the same view sampled more densely (the
        reference depth at a finer voxel, `render.reference.dense_cloud`), which the final
        level pairs against instead: point-to-point and LM on points then land between the
        points of the voxel lattice (the overlap and coverage rules still count the reference's
        own points)."""
        self.config = config or ICPConfig()
        self.reference = reference
        self._camera = camera
        self._max_depth = max_depth
        self._coverage_tree: NNTree | None = None
        need_n = self.config.needs_reference_normals
        self.problem = _check_cloud(reference, "reference", self.config.min_points, need_n)
        self._levels: list[_Level] = []
        if self.problem:
            return
        if final_reference is not None:
            problem = _check_cloud(final_reference, "final reference", 1, need_n)
            if problem:
                self.problem = problem
                return
        cache: dict[tuple[bool, float], tuple[NNTree, NDF]] = {}
        spacings: dict[tuple[bool, float], float] = {}
        levels = self.config.levels()
        for i, (voxel, dmax) in enumerate(levels):
            final = i == len(levels) - 1
            src = final_reference if final and final_reference is not None else reference
            key = (src is not reference, voxel)
            if key not in cache:
                pts, nrm = _downsample(src.points, src.normals, voxel)
                tree = NNTree(pts)
                nrm = np.ascontiguousarray(nrm[tree.order]) if nrm is not None else np.zeros((0, 3))
                cache[key] = (tree, nrm)
            tree, nrm = cache[key]
            if final and src is not reference:
                own = cache.get((False, voxel))
                self._coverage_tree = (
                    own[0]
                    if own is not None
                    else NNTree(_downsample(reference.points, None, voxel)[0])
                )
            use = np.ones(len(tree.points), dtype=bool)
            if (
                camera is not None
                and self.config.edge_reach_m() > 0
                and (self.config.edge_at_final() or not final)
            ):
                use = ~view_edge_mask(
                    tree.points, camera, min(dmax, self.config.edge_reach_m()), max_depth
                )
            proj = S.NO_PROJECTIVE
            projective = (
                camera is not None
                and self.config.association_in_use == "projective"
                and dmax <= self.config.projective_reach + 1e-12
            )
            lm_surface = self.config.lm_surface
            if (projective or lm_surface) and key not in spacings:  # once per point set
                spacings[key] = _spacing(tree.points, voxel)
            spacing = spacings.get(key, 0.0)
            if projective:
                assert camera is not None
                proj = _projective_index(tree.points, camera, spacing, self.config)
            radius = self.config.lm_disc_radius * spacing if lm_surface else 0.0
            self._levels.append(_Level(voxel, dmax, tree, nrm, use, proj, radius))

    def align(self, current: Cloud, T_init: Any = None) -> ICPResult:
        """Estimates T_ref_cur from the current cloud, starting at T_init (identity if None)."""
        cfg = self.config
        T = np.eye(4) if T_init is None else np.asarray(T_init, dtype=np.float64).copy()
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            return ICPResult(np.eye(4), False, reason="initial guess is not a finite 4x4 pose")
        if self.problem:
            return ICPResult(T, False, reason=self.problem)
        T_start = T.copy()
        need_n = cfg.variant == "symmetric"
        problem = _check_cloud(current, "current", cfg.min_points, need_n)
        if problem:
            return ICPResult(T, False, reason=problem)
        full = current
        current = self._crop(current, T)
        code = K.VARIANT_CODES[cfg.variant]
        total = 0
        status, pairs = K.ITERATION_LIMIT, 0
        src_cache: dict[float, tuple[NDF, NDF]] = {}
        memos: dict[tuple[int, float], Any] = {}  # the tree's answers, by `_Level.memo_key`
        cur_n = current.normals if need_n else None
        coarse = cfg.coarse_tolerance_in_use()
        for lv in self._levels:
            if lv.voxel not in src_cache:
                s, sn = _downsample(current.points, cur_n, lv.voxel)
                src_cache[lv.voxel] = (s, sn if sn is not None else np.zeros((0, 3)))
            src, src_n = src_cache[lv.voxel]
            tol_t, tol_r = cfg.tolerance_translation, cfg.tolerance_rotation
            if lv is not self._levels[-1]:  # a coarse level only has to reach the next one's basin
                tol_t = max(tol_t, coarse * lv.dmax)
                tol_r = max(tol_r, coarse * lv.dmax / 0.1)
            t = lv.tree
            if lv.memo_key not in memos:
                memos[lv.memo_key] = S.new_memo(len(src))
            memo = memos[lv.memo_key]
            try:
                T, status, it, pairs, _ = K.register_level(
                    src, src_n, t.arrays, lv.normals, lv.use, T, lv.dmax, code,
                    cfg.max_iterations, tol_t, tol_r,
                    cfg.min_correspondences, cfg.huber_delta, _threads(), cfg.accelerate,
                    lv.proj, lv.lm_radius, memo,
                )  # fmt: skip
            except np.linalg.LinAlgError as exc:  # a safety net: the kernels test what they solve
                return ICPResult(T, False, iterations=total, reason=f"numerical failure: {exc}")
            total += it
            if status in (K.FEW_PAIRS, K.SINGULAR):
                break
        lv = self._levels[-1]
        cycle_note = ""
        if status == K.ITERATION_LIMIT and cfg.cycle_translation > 0 and cfg.cycle_rotation > 0:
            cycle_note = self._limit_cycle(
                src_cache[lv.voxel], lv, T, code, memos.get(lv.memo_key, S.NO_MEMO)
            )
            if cycle_note:
                status = K.CONVERGED
        src = full.points
        t = lv.tree
        # the final level's memo serves when its copy is the whole cloud (nothing cropped, the
        # clouds as given): its last search was one small update ago, so few points search again
        same = current is full and lv.voxel <= 0 and lv.proj is S.NO_PROJECTIVE
        memo = memos.get(lv.memo_key, S.NO_MEMO) if same else S.NO_MEMO
        q, idx, d2 = S.associate(src, T, t.arrays, lv.dmax, _threads(), memo)
        ok = idx >= 0
        n_ok = int(ok.sum())
        result = ICPResult(
            T,
            status == K.CONVERGED,
            fitness=n_ok / len(src),
            overlap=n_ok / min(len(src), len(self.reference.points)),
            coverage=self._coverage(src, T, idx[ok], t.points, lv.dmax),
            inlier_rmse=float(np.sqrt(d2[ok].mean())) if n_ok else float("nan"),
            correspondences=n_ok,
            iterations=total,
        )
        result.reason = cycle_note
        if status == K.FEW_PAIRS:
            result.reason = f"too few correspondences ({pairs} < {cfg.min_correspondences}) within {lv.dmax:.4f} m"
        elif status == K.SINGULAR:
            result.reason = "degenerate geometry: singular linear system (the cloud does not constrain all six degrees of freedom)"
        elif status == K.ITERATION_LIMIT:
            result.reason = f"did not converge in {cfg.max_iterations} iterations"
        if result.converged and n_ok < cfg.min_correspondences:
            result.converged = False
            result.reason = f"too few correspondences ({n_ok} < {cfg.min_correspondences}) within {lv.dmax:.4f} m"
        elif result.converged and min(result.overlap, result.coverage) < cfg.min_overlap:
            result.converged = False
            result.reason = (
                f"diverged: {100 * result.overlap:.0f}% of the smaller cloud paired and "
                f"{100 * result.coverage:.0f}% of the reference covered within "
                f"{1000 * lv.dmax:.1f} mm (minimum {100 * cfg.min_overlap:.0f}%)"
            )
        if result.converged and cfg.max_rotation_correction > 0:
            turned = pose_error(T, T_start)[1]
            if turned > cfg.max_rotation_correction:
                result.converged = False
                result.reason = (
                    f"turned {np.degrees(turned):.1f} deg from its initial guess, more than "
                    f"max_rotation_correction ({np.degrees(cfg.max_rotation_correction):.0f} "
                    "deg): a false convergence (onto another part of the vine), or a guess too "
                    "far off for a local registration"
                )
        if result.converged:
            degenerate = self._degeneracy(q[ok], idx[ok])
            if degenerate:
                result.converged = False
                result.reason = degenerate
        return result

    def _crop(self, current: Cloud, T: NDF) -> Cloud:
        """The current points that the guess `T` places within `crop_margin` of the
        reference's view (all of them without a camera, or when too few would remain)."""
        margin = self.config.crop_margin
        cam = self._camera
        if cam is None or margin <= 0:
            return current
        p = current.points @ T[:3, :3].T + T[:3, 3]
        z = np.maximum(p[:, 2], 1e-9)
        u = cam.fx * p[:, 0] / z + cam.cx
        v = cam.fy * p[:, 1] / z + cam.cy
        mu, mv = margin * cam.fx / z, margin * cam.fy / z
        keep = (
            (p[:, 2] > 0)
            & (p[:, 2] < self._max_depth + margin)
            & (u > -mu)
            & (u < cam.width + mu)
            & (v > -mv)
            & (v < cam.height + mv)
        )
        if keep.all() or keep.sum() < self.config.min_points:
            return current
        normals = None if current.normals is None else current.normals[keep]
        return Cloud(current.points[keep], normals)

    def _coverage(self, src: NDF, T: NDF, idx: Any, ref: NDF, dmax: float) -> float:
        """The share of the reference's own points `ref` (the final level's, tree order) that
        the current camera, placed by `T`, has in view (`_in_view`) paired with some current
        point."""
        if self._coverage_tree is not None:
            c = self._coverage_tree
            _, idx, _ = S.associate(src, T, c.arrays, dmax, _threads(), S.NO_MEMO)
            idx, ref = idx[idx >= 0], c.points
        hit = np.zeros(len(ref), dtype=bool)
        hit[idx] = True
        seen = self._in_view(ref, T)
        return float((hit & seen).sum()) / max(int(seen.sum()), 1)

    def _in_view(self, ref: NDF, T: NDF) -> npt.NDArray[np.bool_]:
        """Which reference points the current camera at `T` (current in reference) has inside
        its image and depth range; every one without a camera, or when fewer than
        `min_points` would be. Coverage counts only these: a camera nearer the vine than its
        goal, or turned from it, sees part of the reference's view (a dense vine's pose from
        3.75 cm / 0.11 rad nearer: 16% of its reference in view, 75% of that paired at the
        right alignment, which over the whole reference read as 12%, "diverged"). Occlusion
        is not modelled: a hidden point counts as unpaired (the strict side)."""
        cam = self._camera
        if cam is None:
            return np.ones(len(ref), dtype=bool)
        Ti = invert(T)
        p = ref @ Ti[:3, :3].T + Ti[:3, 3]
        z = np.maximum(p[:, 2], 1e-9)
        u = cam.fx * p[:, 0] / z + cam.cx
        v = cam.fy * p[:, 1] / z + cam.cy
        seen = (p[:, 2] > 0) & (p[:, 2] < self._max_depth)
        seen &= (u >= -0.5) & (u < cam.width - 0.5) & (v >= -0.5) & (v < cam.height - 0.5)
        if seen.sum() < self.config.min_points:
            return np.ones(len(ref), dtype=bool)
        return seen

    def _limit_cycle(self, src: tuple[NDF, NDF], lv: Any, T: NDF, code: int, memo: Any) -> str:
        """The final level stopped at its iteration limit: follows it three more iterations.
        If the estimates stay within the cycle tolerances of each other (a cycle between pair
        sets, which the tolerances of a single update never call converged), returns the
        cycle's size as a note; else ""."""
        cfg = self.config
        states = [T]
        for _ in range(3):
            nxt, _st, _it, _p, _r = K.register_level(
                src[0], src[1], lv.tree.arrays, lv.normals, lv.use, states[-1], lv.dmax, code,
                1, 0.0, 0.0, cfg.min_correspondences, cfg.huber_delta, _threads(), False,
                lv.proj, lv.lm_radius, memo,
            )  # fmt: skip
            states.append(nxt)
        spread_t = spread_r = 0.0
        for a in states:
            for b in states:
                dt, dr = pose_error(a, b)
                spread_t, spread_r = max(spread_t, dt), max(spread_r, dr)
        if spread_t <= cfg.cycle_translation and spread_r <= cfg.cycle_rotation:
            return (
                f"settled in a limit cycle of {1000 * spread_t:.2f} mm / {1000 * spread_r:.2f} mrad"
            )
        return ""

    def _degeneracy(self, q: NDF, idx: Any) -> str:
        """Checks the final alignment constrains all six degrees of freedom (point-to-plane
        Hessian of the final pairs, with the reference normals; without normals, those of a
        local fit are not available, so variants without normals are not checked)."""
        cfg = self.config
        lv = self._levels[-1]
        if len(lv.normals) == 0 or len(q) < cfg.min_correspondences:
            return ""
        # point-to-plane Hessian about the cloud centre, rotations scaled to metres
        ev = np.linalg.eigvalsh(K.plane_hessian(q, lv.normals, np.ascontiguousarray(idx)))
        if ev[0] < cfg.degeneracy_ratio * ev[-1]:
            return (
                f"degenerate geometry: the cloud constrains a motion {ev[0] / ev[-1]:.1e} times less than the "
                f"best one (e.g. a single straight cane: sliding along it or rolling about it)"
            )
        return ""
