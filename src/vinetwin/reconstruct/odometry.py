"""Camera poses from depth odometry: the fallback when there are neither robot poses nor a
structure-from-motion result.

Open3D's dense RGB-D odometry was tried first and failed on vine captures (thin canes against an
empty background: a single pair's error exceeded the motion between the frames; see
docs/reconstruct.md). vinetwin instead chains its own point-to-plane ICP (`registration.icp`,
the same perception chain as the servo) between consecutive frames, each starting from the
previous motion (constant velocity; scaled by the ratio of the frames' intervals when the
capture has stamps, so that a dropped frame doubles the predicted step). It needs a video-like
capture (frames a few centimetres and degrees apart).

A pair that does not align from there (the sweep sped up or turned: a start several centimetres
off) is registered again by the servo's wide search (`registration.search`, from hypotheses
`SEARCH_TRANSLATION` / `SEARCH_ROTATION` around the same prediction, and after a failed pair
also around standing still) and reported as searched. After a searched or failed pair, a pair
whose own guess fails is tried from the last step tracking found. Each answer is checked
backwards (the earlier frame registered onto the later one from its inverse:
`CONSISTENCY_TRANSLATION`). A pair none of these places (or the search places ambiguously)
keeps the guess and is reported as failed: it starts a new run (`OdometryResult.runs`), since
its pose relative to the frames before it is a guess. The runs are then joined where they can
be (`join_runs`): each other run's frames, merged, are registered onto the longest run's by
Open3D's global registration (FPFH features and RANSAC, the best of `JOIN_SEEDS` by fitness,
refined by point-to-plane ICP) and checked backwards. The reconstruction fuses the longest run
and the runs joined to it (`OdometryResult.linked`). Poses come out in the first frame's
camera frame, metric; the drift grows with the path length.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from functools import partial
from typing import Any

import numpy as np

from vinetwin import _lazy
from vinetwin.capture.folder import Capture, CaptureError
from vinetwin.cloud import Cloud, perceive
from vinetwin.frames import Array, invert, pose_error, se3_exp, se3_log, transform_points
from vinetwin.reconstruct.config import OdometryConfig
from vinetwin.registration.features import fpfh, ransac_proposal
from vinetwin.registration.icp import ICP, ICPResult
from vinetwin.registration.search import WideSearch

#: A pair's alignment (tracked or searched) is kept when it converged and pairs at least this
#: share of the smaller cloud (`ICPResult.overlap`): consecutive frames of a video-like capture
#: see mostly the same vine, and one pair of frames is all the evidence there is (the servo asks
#: `reacquire_frames` frames to agree). On the sample's 50-frame sweep over 6 noise streams,
#: with and without two frames dropped twice, right answers paired 69-100%; two wrong ones,
#: 254 and 145 mm off, 44% (one tracked from a guess 78 mm short, one searched): both were kept
#: when this was 0.3.
MIN_OVERLAP = 0.5
#: The wide search's hypotheses around the constant-velocity prediction, for a pair tracking
#: could not align: moved by this much (m) along, and turned by `SEARCH_ROTATION` (rad) about,
#: each axis of the previous camera.
SEARCH_TRANSLATION = 0.03
SEARCH_ROTATION = 0.1
#: A pair's alignment is also registered backwards (the earlier frame onto the later one, from
#: the inverse of the answer) and kept only when the two agree within this (m) and
#: `CONSISTENCY_ROTATION` (rad): a slide along the canes between frames that barely overlap is
#: not found again from the other side. Right answers on video-like sweeps of three vines
#: (the sample, hydroshoot vsp, the dense vine; with frames dropped) agreed within 2.8 mm /
#: 0.44 deg; on a sweep of gdc_can1 stepping 8-12 cm, three pairs 24-43 mm off disagreed by
#: 12.5-141 mm / 2.8-17 deg (and three right ones, 1-5 mm off, by 6-8 mm: refused too).
CONSISTENCY_TRANSLATION = 0.005
CONSISTENCY_ROTATION = 0.0175
#: The fewest frames of a run the reconstruction fuses: TSDF fusion keeps a surface seen by 3
#: frames (Open3D's weight threshold), so a shorter run gives an empty mesh. Shorter runs are
#: not joined either.
MIN_RUN_FRAMES = 3
#: Joining runs (`join_runs`): the merged clouds' voxel (m), which sets FPFH's radius (5x), the
#: normals' (2.5x) and RANSAC's reach (1.5x).
JOIN_VOXEL = 0.005
#: RANSAC runs from this many seeds, the answer of best fitness kept: on the sample's gap, 7 of
#: 10 seeds found the right basin (the wrong ones 242-774 mm off, fitness 0.07-0.15), on
#: hydroshoot vsp's and the dense vine's 10 of 10.
JOIN_SEEDS = 5
#: A join is kept when, refined, it pairs at least this share of the joined run's points within
#: `JOIN_VOXEL` (right joins on three vines: 0.59-0.68; wrong RANSAC answers: 0.07-0.15) and the
#: backwards registration agrees within `CONSISTENCY_TRANSLATION` / `CONSISTENCY_ROTATION`.
JOIN_MIN_FITNESS = 0.4


@dataclass
class OdometryResult:
    poses: dict[str, Array]
    """T_first_camera per frame."""
    failed: list[str] = field(default_factory=list)
    """Frames whose alignment to their predecessor failed (pose extrapolated)."""
    searched: list[str] = field(default_factory=list)
    """Frames that tracking did not align to their predecessor and the wide search did."""
    seconds: float = 0.0
    joined: dict[str, float] = field(default_factory=dict)
    """First frames of the runs joined to the longest one by global registration
    (`join_runs`; their poses are in the longest run's frame), with the join's fitness."""
    not_joined: dict[str, str] = field(default_factory=dict)
    """First frames of the other runs, with why they were not joined."""

    @property
    def runs(self) -> list[list[str]]:
        """The frames (in capture order, as `poses` holds them) in runs linked by aligned pairs:
        a failed frame starts a new run, since its pose relative to the frames before it is a
        guess. `longest_run` is what can be fused."""
        failed = set(self.failed)
        runs: list[list[str]] = []
        for fid in self.poses:
            if not runs or fid in failed:
                runs.append([])
            runs[-1].append(fid)
        return runs

    @property
    def longest_run(self) -> list[str]:
        """The longest run (the first of equals)."""
        runs = self.runs
        return max(runs, key=len) if runs else []

    @property
    def linked(self) -> list[str]:
        """The frames whose poses relate: the longest run and the runs joined to it, in
        capture order. What the reconstruction fuses."""
        first = self.longest_run[:1]
        return [f for r in self.runs if r[:1] == first or r[0] in self.joined for f in r]


def odometry_poses(capture: Capture, config: OdometryConfig | None = None) -> OdometryResult:
    """Each frame's pose in the first's (`OdometryResult`), by frame-to-frame ICP."""
    t0 = time.perf_counter()
    settings = config or OdometryConfig()
    per = settings.perception()
    cfg = settings.icp()
    cam = capture.camera
    clouds = [perceive(f.depth(capture.depth_unit), cam, per) for f in capture.frames]
    poses = {capture.frames[0].id: np.eye(4)}
    T = np.eye(4)
    step = tracked = np.eye(4)  # the last step, and the last one tracking found
    step_tracked = True  # whether `step` is `tracked`
    failed: list[str] = []
    searched: list[str] = []
    icp_next = ICP(clouds[0], cfg)
    for k in range(1, len(clouds)):
        # the previous frame is the reference; the current frame's pose in it is the step
        fid = capture.frames[k].id
        guess = _prediction(step, capture, k)
        icp, icp_next = icp_next, ICP(clouds[k], cfg)  # this frame's is the next pair's
        why_not = partial(_refusal, backwards=icp_next, earlier=clouds[k - 1])
        r = icp.align(clouds[k], guess)
        kept = not why_not(r)
        if not kept and not step_tracked:
            # the last step came from the search (a gap, a dropped frame, rather than a new
            # speed, when the frames have no stamps to tell) or was extrapolated: the step
            # tracking found, then
            r = icp.align(clouds[k], _prediction(tracked, capture, k))
            kept = not why_not(r)
        step_tracked = kept
        if not step_tracked:
            search = WideSearch(clouds[k - 1])
            found = search.align(
                clouds[k], guess, translation=SEARCH_TRANSLATION, rotation=SEARCH_ROTATION,
                accept=why_not,
            )  # fmt: skip
            if found.best is None and failed and failed[-1] == capture.frames[k - 1].id:
                # after a failed pair the guess carries the motion from before the gap, which a
                # sweep that turned there no longer has: also search around standing still
                found = search.align(
                    clouds[k], np.eye(4), translation=SEARCH_TRANSLATION, rotation=SEARCH_ROTATION,
                    accept=why_not,
                )  # fmt: skip
            if found.best is not None:
                r = found.best
                kept = True
                searched.append(fid)
        if kept:
            step = r.T_ref_cur
        else:
            step = guess
            failed.append(fid)
        if step_tracked:
            tracked = step
        T = T @ step
        poses[fid] = T.copy()
    if len(failed) == len(clouds) - 1:
        raise CaptureError(f"{capture.root}: odometry aligned no frame pair")
    odo = OdometryResult(poses, failed, searched)
    join_runs(odo, dict(zip([f.id for f in capture.frames], clouds, strict=True)))
    odo.seconds = time.perf_counter() - t0
    return odo


def join_runs(odo: OdometryResult, clouds: dict[str, Cloud]) -> None:
    """Joins the other runs (longest first) to the longest run, in place: each run's clouds,
    merged by its own poses, are registered onto those of the runs joined so far
    (`_global_registration`); a join that passes its checks re-expresses the run's poses in
    the longest run's frame (`OdometryResult.joined`), others are named (`not_joined`)."""
    runs = odo.runs
    if len(runs) < 2:
        return
    main = odo.longest_run
    P0 = odo.poses[main[0]]
    merged = _merged(odo, clouds, main, invert(P0))
    for run in sorted((r for r in runs if r[0] != main[0]), key=len, reverse=True):
        if len(run) < MIN_RUN_FRAMES:
            odo.not_joined[run[0]] = f"{len(run)} frames, fewer than {MIN_RUN_FRAMES}"
            continue
        own = _merged(odo, clouds, run, invert(odo.poses[run[0]]))
        T, fitness, why = _global_registration(_pcd(own), _pcd(merged))
        if why:
            odo.not_joined[run[0]] = why
            continue
        # the run's frames in the longest run's first frame, then in the poses' frame
        to_main = P0 @ T @ invert(odo.poses[run[0]])
        for fid in run:
            odo.poses[fid] = to_main @ odo.poses[fid]
        odo.joined[run[0]] = fitness
        merged = _downsampled(np.concatenate([merged, transform_points(T, own)]))


def _downsampled(points: np.ndarray) -> np.ndarray:
    """The points at `JOIN_VOXEL` (Open3D's grid, as the joins were measured with)."""
    return np.asarray(_pcd(points).voxel_down_sample(JOIN_VOXEL).points)


def _pcd(points: np.ndarray) -> Any:
    o3d = _lazy.open3d()
    return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.ascontiguousarray(points)))


def _merged(odo: OdometryResult, clouds: dict[str, Cloud], run: list[str], T0: Array) -> np.ndarray:
    """The run's clouds in one frame (`T0` @ each pose), at `JOIN_VOXEL`."""
    pts = [transform_points(T0 @ odo.poses[fid], clouds[fid].points) for fid in run]
    return _downsampled(np.concatenate(pts))


def _global_registration(src: Any, dst: Any) -> tuple[Array, float, str]:
    """T_dst_src by FPFH + RANSAC (`registration.features`; the best of `JOIN_SEEDS` seeds by
    fitness after point-to-plane ICP at `JOIN_VOXEL`), refined at 2 mm, and checked: fitness at
    `JOIN_VOXEL` and the backwards registration. Returns (T, fitness, why not; "" if kept)."""
    o3d = _lazy.open3d()
    reg = o3d.pipelines.registration
    v = JOIN_VOXEL
    for pc in (src, dst):
        pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2.5 * v, max_nn=30))
    f_src, f_dst = fpfh(src, 5 * v), fpfh(dst, 5 * v)
    plane = reg.TransformationEstimationPointToPlane()
    best: tuple[float, Array] | None = None
    for seed in range(JOIN_SEEDS):
        T, _ = ransac_proposal(
            src, dst, f_src, f_dst, reach=1.5 * v, iterations=100_000, seed=seed, mutual=True
        )
        fine = reg.registration_icp(src, dst, v, T, plane)
        if best is None or fine.fitness > best[0]:
            best = (float(fine.fitness), np.asarray(fine.transformation))
    assert best is not None
    fitness, T = best
    T = np.asarray(reg.registration_icp(src, dst, 0.002, T, plane).transformation)
    if fitness < JOIN_MIN_FITNESS:
        why = (
            f"global registration paired {100 * fitness:.0f}% of its points within "
            f"{1000 * v:.0f} mm (minimum {100 * JOIN_MIN_FITNESS:.0f}%)"
        )
        return T, fitness, why
    back = np.asarray(reg.registration_icp(dst, src, 0.002, invert(T), plane).transformation)
    off = _disagreement(T, back)
    return T, fitness, f"the backwards registration disagreed by {off}" if off else ""


def _disagreement(forward: Array, backward: Array) -> str:
    """How far `backward` (registered the other way) is from undoing `forward`, when more than
    `CONSISTENCY_TRANSLATION` / `CONSISTENCY_ROTATION` ("" within them)."""
    dt, dr = pose_error(backward @ forward, np.eye(4))
    if dt > CONSISTENCY_TRANSLATION or dr > CONSISTENCY_ROTATION:
        return f"{1000 * dt:.1f} mm / {np.degrees(dr):.2f} deg"
    return ""


def _refusal(r: ICPResult, backwards: ICP, earlier: Cloud) -> str:
    """Why a pair's answer is not kept ("" when it is): ICP's failure, too little overlap, or
    the earlier frame registered onto the later one (`backwards`, over the later frame's
    cloud) from the answer's inverse not landing back within the consistency limits."""
    if not r.converged:
        return f"ICP failed: {r.reason}"
    if r.overlap < MIN_OVERLAP:
        return f"overlap {r.overlap:.2f} < {MIN_OVERLAP}"
    b = backwards.align(earlier, invert(r.T_ref_cur))
    if not b.converged:
        return f"backwards, ICP failed: {b.reason}"
    off = _disagreement(r.T_ref_cur, b.T_ref_cur)
    return f"backwards, {off} off" if off else ""


def _prediction(step: Array, capture: Capture, k: int) -> Array:
    """Frame k's pose in frame k-1's at constant velocity: the last step (frame k-2 to k-1),
    scaled by the ratio of the intervals when the three frames have increasing stamps."""
    if k >= 2:
        s0, s1, s2 = (capture.frames[i].stamp for i in (k - 2, k - 1, k))
        if s0 is not None and s1 is not None and s2 is not None and s2 > s1 > s0:
            return se3_exp(se3_log(step) * ((s2 - s1) / (s1 - s0)))
    return step
