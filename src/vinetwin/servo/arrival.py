"""Arrival registration: where the vine is, from the first live view and the whole twin.

In the field the robot knows where the vine stands only as well as its platform is localised
(centimetres, degrees). Before servoing, the first live view is registered against the twin's
whole surface near that belief; the result (the camera's pose in the vine frame) replaces the
belief as the servo's first guess (eq. 11).

Method (Open3D 0.20's feature matching and ICP; what is ours is the choice and the verdict):

1. **Candidates.** A grid of corrections of the belief: translations every `grid_step` within
   `search_translation` of it, each with the rotations 0, +-1 and +-2 `rotation_step` about each
   axis (about the live view's centre), several thousand in all. Each is screened cheaply (the
   share of a few hundred live points within `grid_step` / 3 of the twin once moved), and the
   `refine` best at clearly different poses go on, with one global proposal from FPFH features
   matched by RANSAC. (FPFH alone is weak on thin canes: a handful of matches survive.)
2. **Refinement.** Each candidate is refined by point-to-plane ICP against the twin's surface,
   coarse to fine (5, 2 and 1 voxels, then `final_threshold` on the full clouds).
3. **Render and compare (the verdict).** Each refined pose is scored two-sided: the twin is
   rendered from it (Open3D ray casting, `score_scale` of the camera's resolution) and run
   through the perception chain, and the score is the F-score of the live cloud against that
   expected view (the share of live points within `final_threshold` of an expected point, and
   of expected points within it of a live point). One-sided fitness was the first attempt's
   downfall: a live view slid along a cane still lies on the twin (76-92% of its points), but
   the view expected from the slid pose then shows cane ends and forks where the camera saw
   none.
4. **Failures, named; no motion.** The best candidate within the allowed correction wins,
   unless its score is below `min_score` ("too little agreement") or another candidate at a
   clearly different pose scores nearly as well (`ambiguity`: "ambiguous", a repetitive vine).
   A failed result carries no pose: the caller does not move.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from vinetwin import _lazy
from vinetwin.camera import CameraModel
from vinetwin.cloud import Cloud, PerceptionConfig, perceive
from vinetwin.errors import InputError, raise_if_interrupt
from vinetwin.frames import Array, check_pose, make_pose, pose_error, so3_exp, transform_points
from vinetwin.registration.features import fpfh, ransac_proposal
from vinetwin.servo.config import ArrivalConfig


@dataclass
class ArrivalResult:
    """The outcome: `ok` with the camera's pose in the vine frame, or the reason and no pose."""

    ok: bool
    reason: str
    T_vine_camera: Array | None
    score: float = 0.0
    """F-score of the live view against the view expected from the chosen pose."""
    runner_up: float = 0.0
    """The best score among candidates at a clearly different pose (0: none)."""
    candidates: int = 0
    seconds: float = 0.0
    scores: list[tuple[float, Array]] = field(default_factory=list)
    """Every candidate's score and pose (T_vine_camera), best first."""


class ArrivalRegistration:
    """Registers first live views against one twin: built once per twin (its surface sampled,
    its ray-casting scene), `register` per arrival."""

    def __init__(
        self,
        vertices: Any,
        faces: Any,
        camera: CameraModel,
        perception: PerceptionConfig | None = None,
        config: ArrivalConfig | None = None,
        spacing: float = 0.0025,
    ) -> None:
        """`vertices`, `faces`: the twin's mesh in the vine frame; `camera` and `perception`:
        the twin's (the expected views go through the same chain as the live one)."""
        from vinetwin.render.backends import Open3DBackend

        self.config = config or ArrivalConfig()
        self.camera = camera
        self.perception = perception or PerceptionConfig()
        o3d = _lazy.open3d()
        self._o3d = o3d
        v = np.asarray(vertices, np.float64)
        f = np.asarray(faces, np.int64)
        if v.ndim != 2 or v.shape[1] != 3 or len(f) < 10:
            raise InputError("arrival registration needs the twin's mesh (>= 10 triangles)")
        mesh = o3d.geometry.TriangleMesh(
            o3d.utility.Vector3dVector(v), o3d.utility.Vector3iVector(f.astype(np.int32))
        )
        mesh.compute_triangle_normals()
        n = int(min(max(mesh.get_surface_area() / spacing**2, 1000), 2_000_000))
        o3d.utility.random.seed(0)
        pcd = mesh.sample_points_uniformly(number_of_points=n, use_triangle_normal=True)
        self.points = np.asarray(pcd.points)
        self.normals = np.asarray(pcd.normals)
        s = self.config.score_scale
        self._score_camera = camera.scaled(
            max(round(camera.width * s), 16), max(round(camera.height * s), 16)
        )
        self._renderer = Open3DBackend(v, f, self._score_camera)

    # ------------------------------------------------------------------ helpers
    def _pcd(self, points: Array, normals: Array | None = None) -> Any:
        o3d = self._o3d
        p = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.ascontiguousarray(points)))
        if normals is not None:
            p.normals = o3d.utility.Vector3dVector(np.ascontiguousarray(normals))
        return p

    def expected_view(self, T_vine_camera: Array) -> Cloud:
        """The cloud the camera would see from `T_vine_camera` (camera frame): the twin rendered
        at the score resolution, through the perception chain."""
        depth = self._renderer.render(T_vine_camera)
        return perceive(depth, self._score_camera, self.perception, normals=False)

    def score(self, live: Cloud, T_vine_camera: Array) -> float:
        """F-score (within `final_threshold`) of the live cloud against the expected view."""
        from scipy.spatial import KDTree

        exp = self.expected_view(T_vine_camera)
        if len(exp) == 0 or len(live) == 0:
            return 0.0
        thr = self.config.final_threshold
        a = float(
            np.mean(KDTree(exp.points).query(live.points, distance_upper_bound=thr)[0] <= thr)
        )
        b = float(
            np.mean(KDTree(live.points).query(exp.points, distance_upper_bound=thr)[0] <= thr)
        )
        return 0.0 if a + b == 0 else 2 * a * b / (a + b)

    # ------------------------------------------------------------------ the registration
    def register(self, live_depth: Any, believed: Any) -> ArrivalResult:
        """The camera's pose in the vine frame from the first live depth image (metres, the
        twin's camera) and the believed pose (`believed`: T_vine_camera from the platform)."""
        t0 = time.perf_counter()
        cfg, o3d = self.config, self._o3d
        reg = o3d.pipelines.registration
        believed = check_pose(believed, "believed")

        def fail(reason: str, **kw: Any) -> ArrivalResult:
            return ArrivalResult(False, reason, None, seconds=time.perf_counter() - t0, **kw)

        try:
            live = perceive(live_depth, self.camera, self.perception, normals=False)
        except Exception as exc:  # a malformed image is a named failure
            raise_if_interrupt(exc)
            return fail(f"bad depth image: {exc}")
        if len(live) < 30:
            return fail(f"too few live points ({len(live)}): nothing to register")
        src_pts = transform_points(believed, live.points)
        # the twin near what the camera could see: within the correction bound of the live cloud
        lo = src_pts.min(0) - cfg.max_translation - cfg.feature_radius
        hi = src_pts.max(0) + cfg.max_translation + cfg.feature_radius
        near = np.all((self.points >= lo) & (self.points <= hi), axis=1)
        if near.sum() < 100:
            return fail("the twin has no surface near the believed view")
        tgt = self._pcd(self.points[near], self.normals[near])
        src = self._pcd(src_pts)
        tgt_d = tgt.voxel_down_sample(cfg.voxel)
        src_d = src.voxel_down_sample(cfg.voxel)
        src_d.estimate_normals(
            o3d.geometry.KDTreeSearchParamHybrid(radius=3 * cfg.voxel, max_nn=30)
        )
        src_d.orient_normals_towards_camera_location(believed[:3, 3])
        candidates = self._screen(src_pts, self.points[near], believed)
        if cfg.ransac_iterations > 0 and len(src_d.points) >= 10 and len(tgt_d.points) >= 10:
            T, fitness = ransac_proposal(
                src_d, tgt_d, fpfh(src_d, cfg.feature_radius), fpfh(tgt_d, cfg.feature_radius),
                reach=1.5 * cfg.voxel, iterations=cfg.ransac_iterations, seed=cfg.seed,
                mutual=False,
            )  # fmt: skip
            if fitness > 0:
                candidates.append(T)
        crit = reg.ICPConvergenceCriteria(max_iteration=30)
        plane = reg.TransformationEstimationPointToPlane()
        levels = (5 * cfg.voxel, 2 * cfg.voxel, cfg.voxel)
        scored: list[tuple[float, Array]] = []
        for C in candidates:
            T = C
            for thr in levels:
                T = np.asarray(
                    reg.registration_icp(src_d, tgt_d, thr, T, plane, crit).transformation
                )
            T = np.asarray(
                reg.registration_icp(src, tgt, cfg.final_threshold, T, plane, crit).transformation
            )
            pose = T @ believed
            dt, dr = pose_error(pose, believed)
            if dt <= cfg.max_translation and dr <= cfg.max_rotation:
                scored.append((self.score(live, pose), pose))
        n = len(candidates)
        if not scored:
            return fail(
                f"no candidate within the allowed correction ({cfg.max_translation} m, "
                f"{cfg.max_rotation} rad)",
                candidates=n,
            )
        scored.sort(key=lambda x: -x[0])
        best_score, best = scored[0]
        runner = max((s for s, P in scored[1:] if not self._same(P, best)), default=0.0)
        kw = {"score": best_score, "runner_up": runner, "candidates": n, "scores": scored}
        if best_score < cfg.min_score:
            return fail(
                f"too little agreement: the live view and the view expected from the best pose "
                f"agree to F = {best_score:.2f} within {1000 * cfg.final_threshold:.0f} mm "
                f"(minimum {cfg.min_score:.2f})",
                **kw,
            )
        if runner >= cfg.ambiguity * best_score:
            return fail(
                f"ambiguous: two different poses explain the view (F = {best_score:.2f} and "
                f"{runner:.2f}): a repetitive vine, or too little of it in view",
                **kw,
            )
        return ArrivalResult(True, "", best, seconds=time.perf_counter() - t0, **kw)  # type: ignore[arg-type]

    def _screen(self, src_pts: Array, twin_pts: Array, believed: Array) -> list[Array]:
        """The grid of corrections (see the module's step 1), best screened first, at most
        `refine` of them, pairwise distinct; the identity (the belief) always among them."""
        from scipy.spatial import KDTree

        cfg = self.config
        rng = np.random.default_rng(cfg.seed)
        pick = rng.choice(len(src_pts), min(cfg.screen_points, len(src_pts)), replace=False)
        live = src_pts[pick]
        c = src_pts.mean(0)
        g = np.arange(-cfg.search_translation, cfg.search_translation + 1e-9, cfg.grid_step)
        shifts = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
        shifts = shifts[np.linalg.norm(shifts, axis=1) <= cfg.search_translation + 1e-9]
        shifts = shifts @ believed[:3, :3].T  # along the camera's axes
        rotations = [np.eye(3)]
        for k in range(3):
            for m in (-2, -1, 1, 2):
                rotations.append(so3_exp(m * cfg.rotation_step * believed[:3, k]))
        tree = KDTree(twin_pts)
        thr = cfg.grid_step / 3
        found: list[tuple[float, Array]] = []
        for R in rotations:
            turned = (live - c) @ R.T + c
            moved = turned[None, :, :] + shifts[:, None, :]  # (shifts, points, 3)
            d, _ = tree.query(moved.reshape(-1, 3), distance_upper_bound=thr)
            share = (d.reshape(len(shifts), -1) <= thr).mean(axis=1)
            for i in np.argsort(-share)[: 4 * cfg.refine]:
                found.append((float(share[i]), make_pose(R, c - R @ c + shifts[i])))
        found.sort(key=lambda x: -x[0])
        out = [np.eye(4)]
        for _, C in found:
            if len(out) >= cfg.refine:
                break
            if all(not self._same(C @ believed, O @ believed) for O in out):
                out.append(C)
        return out

    def _same(self, A: Array, B: Array) -> bool:
        dt, dr = pose_error(A, B)
        return dt <= self.config.distinct_translation and dr <= self.config.distinct_rotation

    def close(self) -> None:
        self._renderer.close()


__all__ = ["ArrivalConfig", "ArrivalRegistration", "ArrivalResult"]
