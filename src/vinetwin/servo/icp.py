"""ICP: the pose of the current camera in the reference camera frame, four variants.

- `point_to_point`: closed-form SVD step on closest-point pairs (Besl & McKay 1992);
- `lm`: Levenberg-Marquardt on the point-to-point residuals, optionally Huber-weighted
  (Fitzgibbon 2003);
- `point_to_plane`: linearised 6x6 solve of `sum ((R p + t - q) . n_q)^2` (Chen & Medioni 1992);
- `symmetric`: `sum ((n_p + n_q) . (R p - R^-1 q + t))^2`, linearised with half rotations
  (Rusinkiewicz 2019).

The reference never changes during a servo: `ICP(reference_cloud, config)` builds its search
tree once; `align(current_cloud, T_init)` runs per frame. Correspondences farther than
`max_correspondence_distance` are rejected. An optional coarse-to-fine `schedule` of voxel sizes
runs the registration on downsampled clouds first.

Failures come back as a result with `converged=False` and a `reason`, never as an exception from
inside numpy: an empty or non-finite cloud, too few points or correspondences, or a geometry that
constrains fewer than six degrees of freedom (a single straight cane: sliding along it and
rolling about it are unobservable).

This is the correctness reference implementation (numpy + scipy's KD-tree); the speed work of
the servo issue (compiled kernels, projective association) is not in it yet.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from vinetwin.cloud import ICP_VARIANTS, Cloud, voxel_downsample
from vinetwin.errors import InputError
from vinetwin.frames import Array, make_pose, skew, so3_exp

NDF = npt.NDArray[np.float64]


@dataclass(frozen=True, kw_only=True)
class ICPConfig:
    """Settings of one registration."""

    variant: str = "point_to_plane"
    """One of point_to_point, lm, point_to_plane, symmetric."""
    max_correspondence_distance: float = 0.01
    """Pairs farther apart than this (m) are rejected."""
    max_iterations: int = 40
    """Iterations per level."""
    tolerance_translation: float = 1e-6
    """Convergence when an update moves less than this (m)..."""
    tolerance_rotation: float = 1e-6
    """...and turns less than this (rad)."""
    schedule: tuple[float, ...] = ()
    """Coarse-to-fine voxel sizes (m), e.g. (0.016, 0.008); the last level uses the clouds as
    given. The correspondence distance scales with the voxel size at coarse levels."""
    min_points: int = 30
    """Fewer points than this in a cloud is a failure."""
    min_correspondences: int = 20
    """Fewer accepted pairs than this is a failure."""
    huber_delta: float = 0.0
    """LM only: Huber kernel width (m); 0 disables the robust kernel."""
    degeneracy_ratio: float = 1e-3
    """A cloud whose weakest constrained motion is this much weaker than its strongest fails as
    degenerate (smallest / largest eigenvalue of the scaled point-to-plane Hessian)."""

    def __post_init__(self) -> None:
        if self.variant not in ICP_VARIANTS:
            raise InputError(
                f"unknown ICP variant '{self.variant}'; choose one of: {', '.join(ICP_VARIANTS)}"
            )
        if self.max_correspondence_distance <= 0 or self.max_iterations <= 0:
            raise InputError("max_correspondence_distance and max_iterations must be positive")


@dataclass
class ICPResult:
    """Outcome of `ICP.align`."""

    T_ref_cur: Array
    """Current camera in the reference camera frame (the last estimate, even on failure)."""
    converged: bool
    fitness: float = 0.0
    """Fraction of current points with an accepted correspondence."""
    inlier_rmse: float = float("nan")
    """RMS point-to-point distance of the accepted pairs (m)."""
    correspondences: int = 0
    iterations: int = 0
    reason: str = ""
    """Why it failed (empty when converged)."""
    history: list[float] = field(default_factory=list)


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


def _kabsch(src: NDF, dst: NDF, w: NDF | None = None) -> Array:
    """Rigid transform minimising sum w |R src + t - dst|^2."""
    w = np.ones(len(src)) if w is None else w
    ws = w.sum()
    cs = (w[:, None] * src).sum(0) / ws
    cd = (w[:, None] * dst).sum(0) / ws
    H = ((src - cs) * w[:, None]).T @ (dst - cd)
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, float(np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0)])
    R = Vt.T @ D @ U.T
    return make_pose(R, cd - R @ cs)


def _solve6(A: NDF, b: NDF) -> NDF | None:
    try:
        return np.asarray(np.linalg.solve(A, b), dtype=np.float64)
    except np.linalg.LinAlgError:
        return None


class ICP:
    """Registration of current clouds to one reference cloud (both in camera frames)."""

    def __init__(self, reference: Cloud, config: ICPConfig | None = None) -> None:
        from scipy.spatial import KDTree

        self.config = config or ICPConfig()
        self.reference = reference
        need_n = self.config.variant in ("point_to_plane", "symmetric")
        self.problem = _check_cloud(reference, "reference", self.config.min_points, need_n)
        self._levels: list[tuple[float, NDF, NDF | None, Any]] = []
        if self.problem:
            return
        ref_n = reference.normals
        for voxel in [*self.config.schedule, 0.0]:
            if voxel > 0:
                pts, nrm = voxel_downsample(reference.points, voxel, ref_n)
                if nrm is not None:
                    nrm = nrm / np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
            else:
                pts, nrm = reference.points, ref_n
            self._levels.append((voxel, pts, nrm, KDTree(pts)))

    def align(self, current: Cloud, T_init: Any = None) -> ICPResult:
        """Estimates T_ref_cur from the current cloud, starting at T_init (identity if None)."""
        cfg = self.config
        T = np.eye(4) if T_init is None else np.asarray(T_init, dtype=np.float64).copy()
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            return ICPResult(np.eye(4), False, reason="initial guess is not a finite 4x4 pose")
        if self.problem:
            return ICPResult(T, False, reason=self.problem)
        need_n = cfg.variant == "symmetric"
        problem = _check_cloud(current, "current", cfg.min_points, need_n)
        if problem:
            return ICPResult(T, False, reason=problem)
        total_iter = 0
        result = ICPResult(T, False)
        for voxel, ref_pts, ref_nrm, tree in self._levels:
            if voxel > 0:
                src, src_n = voxel_downsample(current.points, voxel, current.normals)
                if src_n is not None:
                    src_n = src_n / np.maximum(np.linalg.norm(src_n, axis=1, keepdims=True), 1e-12)
                dmax = max(cfg.max_correspondence_distance, 2.0 * voxel)
            else:
                src, src_n, dmax = current.points, current.normals, cfg.max_correspondence_distance
            result = self._level(T, src, src_n, ref_pts, ref_nrm, tree, dmax)
            total_iter += result.iterations
            T = result.T_ref_cur
            if result.reason and voxel == 0:
                break
        result.iterations = total_iter
        if not result.reason:
            degenerate = self._degeneracy(result.T_ref_cur, current.points)
            if degenerate:
                result.converged = False
                result.reason = degenerate
        return result

    # ---------------------------------------------------------------- one level
    def _level(
        self,
        T: Array,
        src: NDF,
        src_n: NDF | None,
        ref: NDF,
        ref_n: NDF | None,
        tree: Any,
        dmax: float,
    ) -> ICPResult:
        cfg = self.config
        mu = 1e-3  # LM damping
        hist: list[float] = []
        converged = False
        it = 0
        for it in range(1, cfg.max_iterations + 1):
            q = src @ T[:3, :3].T + T[:3, 3]
            d, j = tree.query(q, distance_upper_bound=dmax)
            ok = np.isfinite(d)
            if ok.sum() < cfg.min_correspondences:
                return ICPResult(
                    T,
                    False,
                    float(ok.mean()),
                    float("nan"),
                    int(ok.sum()),
                    it,
                    f"too few correspondences ({int(ok.sum())} < {cfg.min_correspondences}) within {dmax:.4f} m",
                    hist,
                )
            qi, yi = q[ok], ref[j[ok]]
            hist.append(float(np.sqrt(np.mean(d[ok] ** 2))))
            if cfg.variant == "point_to_point":
                dT = _kabsch(qi, yi)
            elif cfg.variant == "lm":
                dT, mu = self._lm_step(qi, yi, mu, tree, ref, dmax)
            elif cfg.variant == "point_to_plane":
                assert ref_n is not None
                dT = self._plane_step(qi, yi, ref_n[j[ok]])
            else:
                assert ref_n is not None and src_n is not None
                dT = self._symmetric_step(qi, yi, src_n[ok] @ T[:3, :3].T, ref_n[j[ok]])
            if dT is None:
                return ICPResult(
                    T,
                    False,
                    float(ok.mean()),
                    hist[-1],
                    int(ok.sum()),
                    it,
                    "degenerate geometry: singular linear system (the cloud does not constrain all six degrees of freedom)",
                    hist,
                )
            T = dT @ T
            step_t = float(np.linalg.norm(dT[:3, 3]))
            step_r = float(np.arccos(np.clip((np.trace(dT[:3, :3]) - 1) / 2, -1, 1)))
            if step_t < cfg.tolerance_translation and step_r < cfg.tolerance_rotation:
                converged = True
                break
        q = src @ T[:3, :3].T + T[:3, 3]
        d, _ = tree.query(q, distance_upper_bound=dmax)
        ok = np.isfinite(d)
        rmse = float(np.sqrt(np.mean(d[ok] ** 2))) if ok.any() else float("nan")
        reason = "" if converged else f"did not converge in {cfg.max_iterations} iterations"
        return ICPResult(T, converged, float(ok.mean()), rmse, int(ok.sum()), it, reason, hist)

    @staticmethod
    def _plane_step(q: NDF, y: NDF, n: NDF) -> Array | None:
        r = np.einsum("ij,ij->i", q - y, n)
        J = np.hstack([n, np.cross(q, n)])  # d r / d(t, w) for q' = q + w x q + t
        x = _solve6(J.T @ J, -J.T @ r)
        if x is None:
            return None
        return make_pose(so3_exp(x[3:]), x[:3])

    @staticmethod
    def _symmetric_step(p: NDF, q: NDF, n_p: NDF, n_q: NDF) -> Array | None:
        n = n_p + n_q
        r = np.einsum("ij,ij->i", p - q, n)
        J = np.hstack([n, np.cross(p + q, n)])
        x = _solve6(J.T @ J, -J.T @ r)
        if x is None:
            return None
        t_tilde, a_tilde = x[:3], x[3:]
        a_norm = float(np.linalg.norm(a_tilde))
        theta = float(np.arctan(a_norm))
        half = so3_exp(a_tilde / a_norm * theta) if a_norm > 1e-15 else np.eye(3)
        # R p - R^-1 q + t = 0  ->  the full step is R_half * Trans(t cos(theta)) * R_half
        return make_pose(half) @ make_pose(np.eye(3), t_tilde * np.cos(theta)) @ make_pose(half)

    def _lm_step(
        self, q: NDF, y: NDF, mu: float, tree: Any, ref: NDF, dmax: float
    ) -> tuple[Array, float]:
        cfg = self.config
        r = q - y  # (N, 3)
        w = np.ones(len(q))
        if cfg.huber_delta > 0:
            nr = np.linalg.norm(r, axis=1)
            w = np.where(nr <= cfg.huber_delta, 1.0, cfg.huber_delta / np.maximum(nr, 1e-15))
        # J_i = [I, -[q_i]x] for q' = q + w x q + t; normal equations summed over points
        A = np.zeros((6, 6))
        g = np.zeros(6)
        sw = w.sum()
        qx = q * w[:, None]
        A[:3, :3] = sw * np.eye(3)
        S = qx.sum(0)
        A[:3, 3:] = -skew(S)
        A[3:, :3] = skew(S)
        qq = (q * qx).sum()  # sum w |q|^2
        A[3:, 3:] = qq * np.eye(3) - (q.T * w) @ q
        g[:3] = (r * w[:, None]).sum(0)
        g[3:] = (np.cross(q, r) * w[:, None]).sum(0)
        cost0 = float((w * (r**2).sum(1)).sum())
        for _ in range(10):
            x = _solve6(A + mu * np.diag(np.diag(A)), -g)
            if x is None:
                mu *= 10
                continue
            dT = make_pose(so3_exp(x[3:]), x[:3])
            qn = q @ dT[:3, :3].T + dT[:3, 3]
            rn = qn - y
            cost = float((w * (rn**2).sum(1)).sum())
            if cost < cost0:
                return dT, max(mu / 10, 1e-9)
            mu *= 10
        return np.eye(4), mu

    def _degeneracy(self, T: Array, src: NDF) -> str:
        """Checks the final alignment constrains all six degrees of freedom."""
        cfg = self.config
        _, _ref_pts, ref_n, tree = self._levels[-1]
        if ref_n is None:
            return ""
        q = src @ T[:3, :3].T + T[:3, 3]
        d, j = tree.query(q, distance_upper_bound=cfg.max_correspondence_distance)
        ok = np.isfinite(d)
        if ok.sum() < cfg.min_correspondences:
            return ""
        qi, n = q[ok], ref_n[j[ok]]
        c = qi.mean(0)
        scale = float(np.sqrt(((qi - c) ** 2).sum(1).mean())) or 1.0
        # point-to-plane Hessian about the cloud centre, rotations scaled to metres
        J = np.hstack([n, np.cross(qi - c, n) / scale])
        ev = np.linalg.eigvalsh(J.T @ J)
        if ev[0] < cfg.degeneracy_ratio * ev[-1]:
            return (
                f"degenerate geometry: the cloud constrains a motion {ev[0] / ev[-1]:.1e} times less than the "
                f"best one (e.g. a single straight cane: sliding along it or rolling about it)"
            )
        return ""
