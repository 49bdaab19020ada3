"""Capture folders (round trip and named errors) and TSDF fusion against the ground truth."""

from __future__ import annotations

import dataclasses
import itertools
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import VineViews
from vinetwin import frames as fr
from vinetwin.capture.folder import CaptureError, read_capture
from vinetwin.cloud import Cloud
from vinetwin.reconstruct.config import ReconstructConfig
from vinetwin.reconstruct.fusion import FusionConfig, evaluate, fuse, kinematic_poses, observed
from vinetwin.reconstruct.synthetic import synthetic_capture


@pytest.fixture(scope="module")
def capture(vine_views: VineViews, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("cap") / "capture"
    return synthetic_capture(vine_views.twin, out, frames=40)


def fused_scores(cap, poses, truth, views: VineViews) -> dict:  # type: ignore[no-untyped-def]
    """Fuses the capture with `poses` and scores the mesh on the ground truth `truth` measured."""
    res = fuse(cap, poses)
    gt = views.twin.load_mesh()
    Vg, Fg = np.asarray(gt.vertices), np.asarray(gt.faces)
    return evaluate(
        res.vertices, res.faces, Vg, Fg,
        gt_mask_fn=lambda p, n: observed(p, n, cap, truth, Vg, Fg), samples=60_000,
    )  # fmt: skip


def test_capture_round_trip(capture: Path, vine_views: VineViews) -> None:
    cap = read_capture(capture)
    assert len(cap.frames) == 40 and cap.has_poses
    assert cap.camera == vine_views.twin.camera
    f = cap.frames[5]
    d = f.depth(cap.depth_unit)
    assert d.shape == (cap.camera.height, cap.camera.width)
    valid = d[d > 0]
    assert 0.15 < float(np.median(valid)) < 0.45  # the sweep is 0.3 m from the vine
    assert f.color().shape == (*d.shape, 3)


@pytest.mark.parametrize(
    ("field", "value", "needle"),
    [("frames", 0, "frames must be"), ("distance", 0.01, "depth range"),
     ("distance", float("nan"), "distance must be"), ("pose_noise", (-0.001, 0.0), "pose_noise"),
     ("seed", -1, "seed must be")],
)  # fmt: skip
def test_a_synthetic_capture_out_of_range_is_refused(
    field: str, value: object, needle: str
) -> None:
    """`capture-synthetic --frames 0` wrote an empty capture; a camera 1 cm from the vine, a NaN
    distance, a negative pose noise and a negative seed are refused by name, as is any setting
    past its range."""
    from vinetwin.errors import InputError
    from vinetwin.reconstruct.config import SyntheticCaptureConfig

    with pytest.raises(InputError, match=needle):
        SyntheticCaptureConfig(**{field: value})  # type: ignore[arg-type]
    SyntheticCaptureConfig(frames=1, distance=0.07)


@pytest.mark.parametrize(
    ("kwargs", "needle"),
    [({"voxel": 0.0}, "voxel must lie"), ({"voxel": -0.01}, "voxel must be >= 0"),
     ({"voxel": float("nan")}, "voxel must be"), ({"depth_max": 3.0}, "depth_max must lie"),
     ({"target_triangles": -5}, "target_triangles must be")],
)  # fmt: skip
def test_fusion_settings_out_of_range_are_refused(kwargs: dict, needle: str) -> None:
    """`reconstruct --voxel 0` stopped inside Open3D with its own exception; it and the other
    settings that make no mesh are refused by name, in the command's config and the fusion's."""
    from vinetwin.errors import InputError

    with pytest.raises(InputError, match=needle):
        ReconstructConfig(**kwargs)
    with pytest.raises(InputError, match=needle):
        FusionConfig(**kwargs)
    with pytest.raises(InputError, match="depth_max must lie"):
        FusionConfig(depth_min=0.3, depth_max=0.2)
    with pytest.raises(InputError, match="min_component is a share"):
        FusionConfig(min_component=2.0)


@pytest.mark.parametrize(
    ("damage", "needle"),
    [
        ("missing depth", "frame 000003: depth"),
        ("wrong unit", "wrong depth unit"),
        ("wrong intrinsics", "intrinsics are for"),
        ("too few frames", "at least 3 are needed"),
        ("hand-eye missing", "no T_flange_camera"),
    ],
)
def test_bad_captures_name_the_problem(
    capture: Path, tmp_path: Path, damage: str, needle: str
) -> None:
    bad = tmp_path / "bad"
    shutil.copytree(capture, bad)
    meta = json.loads((bad / "capture.json").read_text())
    if damage == "missing depth":
        (bad / "depth" / "000003.png").unlink()
    elif damage == "wrong unit":
        meta["depth_unit"] = 1e-7
    elif damage == "wrong intrinsics":
        meta["camera"]["width"] = 640
        meta["camera"]["cx"] = 319.5
    elif damage == "too few frames":
        meta["frames"] = meta["frames"][:2]
    elif damage == "hand-eye missing":
        fr0 = meta["frames"][0]
        fr0["T_base_flange"] = fr0.pop("T_base_camera")
    (bad / "capture.json").write_text(json.dumps(meta))
    with pytest.raises(CaptureError, match=needle):
        read_capture(bad)


def test_fusion_with_kinematic_poses_matches_the_ground_truth(
    capture: Path, vine_views: VineViews
) -> None:
    """40 frames at 2 mm voxels (the full-size figures are in the closing note of the
    reconstruction issue): the mesh lies on the ground truth (precision at 2 mm above 0.95) and
    covers most of what the frames saw (F-score at 5 mm above 0.85)."""
    cap = read_capture(capture)
    poses = kinematic_poses(cap)
    res = fuse(cap, poses, FusionConfig(voxel=0.002, truncation=0.008))
    assert len(res.frames_used) == 40 and res.frames_skipped == {}
    gt = vine_views.twin.load_mesh()
    Vg, Fg = np.asarray(gt.vertices), np.asarray(gt.faces)
    ev = evaluate(
        res.vertices, res.faces, Vg, Fg,
        gt_mask_fn=lambda p, n: observed(p, n, cap, poses, Vg, Fg), samples=60_000,
    )  # fmt: skip
    assert ev["precision@2mm"] > 0.95, ev
    assert ev["fscore@5mm"] > 0.9, ev
    # thin canes survive fusion: around each cut point the frames measured (cut points sit on
    # canes 6-12 mm thick), the measured ground truth is within 2 mm of the mesh
    from scipy.spatial import KDTree

    from vinetwin.reconstruct.fusion import _sample

    pts, nrm = _sample(Vg, Fg, 60_000, 5)
    seen = observed(pts, nrm, cap, poses, Vg, Fg)
    d = KDTree(_sample(res.vertices, res.faces, 100_000, 6)[0]).query(pts)[0]
    checked = 0
    for c in vine_views.twin.cut_points:
        near = seen & (np.linalg.norm(pts - c.point, axis=1) < 0.01)
        if near.sum() >= 30:
            checked += 1
            assert (d[near] < 0.002).mean() > 0.8, (c.id, (d[near] < 0.002).mean())
    assert checked >= 2


def test_structure_from_motion_poses(vine_views: VineViews, tmp_path: Path) -> None:
    """pycolmap on the colour frames of a 120-frame capture, scale from the depth: most frames
    register, the poses agree with the ground truth within millimetres, and the fused mesh
    reaches an F-score at 5 mm of at least 0.8 (the issue's goal)."""
    from vinetwin import frames as fr
    from vinetwin.reconstruct.sfm import align_to, colmap_poses

    cap = read_capture(synthetic_capture(vine_views.twin, tmp_path / "cap", frames=120))
    sfm = colmap_poses(cap)
    assert len(sfm.poses) >= 100, sfm.unregistered
    truth = kinematic_poses(cap)
    aligned = align_to(sfm.poses, truth)
    err = np.array([fr.pose_error(aligned[k], truth[k])[0] for k in aligned])
    assert np.median(err) < 0.005, np.median(err)
    ev = fused_scores(cap, aligned, truth, vine_views)
    assert ev["fscore@5mm"] >= 0.8, ev


def test_realsense_recording_round_trip(capture: Path, tmp_path: Path) -> None:
    """A capture written as a RealSense recording through pyrealsense2's software device and
    recorder (no camera needed) plays back into the same depth, intrinsics and colour."""
    pytest.importorskip("pyrealsense2")
    from vinetwin.capture.realsense import read_recording, write_recording

    cap = read_capture(capture)
    cap.frames = cap.frames[:5]
    rec = write_recording(cap, tmp_path / "vine.db3")
    back = read_capture(read_recording(rec, tmp_path / "back"))
    assert len(back.frames) == 5
    a, b = back.camera, cap.camera
    np.testing.assert_allclose([a.fx, a.fy, a.cx, a.cy], [b.fx, b.fy, b.cx, b.cy], rtol=1e-6)
    assert (a.width, a.height) == (b.width, b.height)
    assert back.depth_unit == pytest.approx(cap.depth_unit, rel=1e-6)
    for f0, f1 in zip(cap.frames, back.frames, strict=True):
        d0 = f0.depth(cap.depth_unit)
        np.testing.assert_allclose(f1.depth(back.depth_unit), d0, atol=1e-6)
        # colour comes back aligned to depth: compare it where there is depth
        m = d0 > 0
        diff = np.abs(f0.color()[m].astype(int) - f1.color()[m].astype(int))
        assert np.median(diff) < 10
    with pytest.raises(CaptureError, match="no such recording"):
        read_recording(tmp_path / "missing.db3", tmp_path / "x")


@pytest.fixture(scope="module")
def path_capture(vine_views: VineViews, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("path") / "capture"
    return synthetic_capture(vine_views.twin, out, frames=50, trajectory="path")


def test_depth_odometry_on_a_video_like_capture(vine_views: VineViews, path_capture: Path) -> None:
    """The fallback pose source: frame-to-frame ICP along a continuous sweep (50 frames, 3-8 cm
    apart) drifts by millimetres, every pair aligns (by tracking, or by the wide search where
    the sweep speeds up), and the fused mesh reaches an F-score at 5 mm above 0.95.

    Measured over 16 D405 noise streams and the quantile draws of e8410dc (docs/reconstruct.md):
    no pair failed (the wide search aligned the fastest step, 85 mm, in 6 of them; before it
    that pair failed), median pose error 0.85-1.82 mm, F-score at 5 mm 0.978-0.990 with the
    poses placed by `align_to` on the frames' orientations too (by the camera centres alone it
    was 0.80-0.99: the rotation about the sweep's line was left to chance)."""
    from vinetwin import frames as fr
    from vinetwin.reconstruct.odometry import odometry_poses
    from vinetwin.reconstruct.sfm import align_to

    cap = read_capture(path_capture)
    odo = odometry_poses(cap)
    assert odo.failed == []
    assert len(odo.searched) <= 2, odo.searched
    truth = kinematic_poses(cap)
    aligned = align_to(odo.poses, truth)
    err = np.array([fr.pose_error(aligned[k], truth[k])[0] for k in aligned])
    assert np.median(err) < 0.003, np.median(err)
    ev = fused_scores(cap, aligned, truth, vine_views)
    assert ev["fscore@5mm"] > 0.95, ev


def test_depth_odometry_bridges_dropped_frames_or_names_them(path_capture: Path) -> None:
    """Two frames dropped twice from the sweep (a recording that lost frames), so that the pairs
    of frames 12 and 42 span three steps. With stamps, the constant-velocity guess scales with
    the longer interval and tracking aligns both. Without stamps, tracking from the last step
    mostly fails there: the wide search aligns the pair or it is reported as failed, and the
    pair after a searched one is tracked from the step before the gap, not the gap's triple
    step. Either way every pair not reported failed is within 5 mm / 1 deg of the true motion.

    Over 16 D405 noise streams and the quantile draws tried in e8410dc, with stamps tracking
    aligned all 34 gaps; without stamps the search aligned 18 and the other 16 were reported
    failed. Two wrong answers, 145 mm (searched) and 254 mm (tracked) off, paired 44% of the
    smaller cloud and are refused (`odometry.MIN_OVERLAP`)."""

    from vinetwin import frames as fr
    from vinetwin.reconstruct.odometry import odometry_poses

    cap = read_capture(path_capture)
    gaps = {"000012", "000042"}
    for stamps in (True, False):
        frames = [
            dataclasses.replace(f, stamp=k / 30 if stamps else None)
            for k, f in enumerate(cap.frames)
            if k not in (10, 11, 40, 41)
        ]
        gappy = dataclasses.replace(cap, frames=frames)
        odo = odometry_poses(gappy)
        truth = kinematic_poses(gappy)
        if stamps:
            assert not gaps & set(odo.failed + odo.searched), (odo.failed, odo.searched)
        else:
            # tracking from the last step did not bridge any of the 34 gaps below
            assert gaps & set(odo.failed + odo.searched), (odo.failed, odo.searched)
        ids = [f.id for f in frames]
        for a, b in itertools.pairwise(ids):
            if b in odo.failed:
                continue
            step = np.linalg.inv(odo.poses[a]) @ odo.poses[b]
            true = np.linalg.inv(truth[a]) @ truth[b]
            et, er = fr.pose_error(step, true)
            assert et < 0.005 and np.degrees(er) < 1.0, (stamps, b, et, np.degrees(er))


def test_depth_odometry_on_a_sweep_too_fast_keeps_only_right_pairs(path_capture: Path) -> None:
    """Every third frame of the sweep (steps of 9-25 cm, views that barely overlap, no stamps):
    most pairs fail and are named (or all do, and odometry says so: one start in one of 13 noise
    streams); a pair that is kept is right, within 5 mm / 1 deg of the true motion. Measured
    with the seeded noise: without the backwards check
    (`odometry.CONSISTENCY_TRANSLATION`) two pairs were kept 217 mm / 25 deg and 204 mm / 21 deg
    off (starting at frames 0 and 2); with it none, and 12 and 7 of 16 and 15 pairs failed."""
    from vinetwin import frames as fr
    from vinetwin.reconstruct.odometry import odometry_poses

    cap = read_capture(path_capture)
    for start in (0, 2):
        fast = dataclasses.replace(
            cap, frames=[dataclasses.replace(f, stamp=None) for f in cap.frames[start::3]]
        )
        try:
            odo = odometry_poses(fast)
        except CaptureError as exc:  # no pair kept: none wrong either
            assert "odometry aligned no frame pair" in str(exc)
            continue
        truth = kinematic_poses(fast)
        assert odo.failed, "a sweep this fast should lose pairs"
        for a, b in itertools.pairwise([f.id for f in fast.frames]):
            if b in odo.failed:
                continue
            step = np.linalg.inv(odo.poses[a]) @ odo.poses[b]
            et, er = fr.pose_error(step, np.linalg.inv(truth[a]) @ truth[b])
            assert et < 0.005 and np.degrees(er) < 1.0, (start, b, et, np.degrees(er))


def test_odometry_runs_across_a_gap_are_joined_by_global_registration(
    path_capture: Path, sample_twin_dir: Path, tmp_path: Path
) -> None:
    """Ten frames lost from the middle of the sweep (a 30-40 cm jump no search bridges): the
    pairs there fail, and every frame after a failed pair is placed by a guess, so the frames
    fall in runs. The runs are joined by global registration of their merged clouds
    (`odometry.join_runs`: FPFH, RANSAC, ICP, checked backwards), and the joined frames are
    fused and placed on the robot poses.

    Measured (the seeded noise and 6 other streams, before the joining): runs 000000-000014
    (15 frames) and 000025-000049 (25 frames, the pass back along the vine at the upper
    height). The pipeline fused only the longer: Chamfer 8.0 mm, F-score at 2 mm 0.72, at 5 mm
    0.81. Joined (the seeded noise; hydroshoot vsp and the dense vine alike): all 40 frames
    fused, Chamfer 1.47 mm, precision at 2 mm 0.989 (0.958 for the run alone), F-score at 2 mm
    0.95, at 5 mm 0.99. Before the runs, every frame was fused as chained, 321 mm off."""
    from vinetwin.reconstruct.pipeline import ReconstructConfig, reconstruct

    gappy = tmp_path / "gappy"
    shutil.copytree(path_capture, gappy)
    meta = json.loads((gappy / "capture.json").read_text())
    meta["frames"] = [f for k, f in enumerate(meta["frames"]) if not 15 <= k < 25]
    (gappy / "capture.json").write_text(json.dumps(meta))
    report = reconstruct(
        gappy, tmp_path / "vine.twin", ReconstructConfig(poses="odometry"),
        ground_truth=sample_twin_dir,
    )  # fmt: skip
    odo = report["odometry_report"]
    runs = odo["runs"]
    assert len(runs) > 1 and odo["failed_pairs"], runs
    longest = max(r[2] for r in runs)
    joined = {r[0]: r[2] for r in runs if r[0] in odo["joined_runs"]}
    assert joined and all(f >= 0.4 for f in odo["joined_runs"].values()), odo
    assert report["frames_fused"] == longest + sum(joined.values()), (runs, odo["joined_runs"])
    assert report["frames_fused"] >= 35, runs
    skipped = report["frames_skipped"]
    assert len(skipped) == 40 - report["frames_fused"]
    ev = report["evaluation"]
    # joined right: more of the vine, and no less precise than one run (0.94-0.96 at 2 mm)
    assert ev["precision@2mm"] > 0.95 and ev["fscore@5mm"] > 0.95, ev


def test_runs_that_do_not_overlap_are_not_joined(vine_views: VineViews) -> None:
    """Two runs of views of different parts of the vine (the sample's poses p1 and p4, three
    frames each, a few millimetres apart): global registration finds no join that passes its
    checks, so each stays on its own, with the reason named, and the poses of the shorter run
    are not moved."""
    from vinetwin.reconstruct import odometry as O

    twin = vine_views.twin
    clouds: dict[str, Cloud] = {}
    poses: dict[str, np.ndarray] = {}
    k = 0
    for pose_id, n in (("p1", 4), ("p4", 3)):
        T = twin.pose(pose_id).T_vine_camera
        for j in range(n):
            D = fr.make_pose(t=[0.003 * j, 0.0, 0.0])
            clouds[f"{k:06d}"] = vine_views.cloud(T @ D, 500 + k)
            poses[f"{k:06d}"] = D  # in each run's own first frame
            k += 1
    odo = O.OdometryResult(dict(poses), failed=["000004"])
    assert [len(r) for r in odo.runs] == [4, 3]
    O.join_runs(odo, clouds)
    assert not odo.joined and list(odo.not_joined) == ["000004"], (odo.joined, odo.not_joined)
    assert (
        "global registration" in odo.not_joined["000004"] or "backwards" in odo.not_joined["000004"]
    )
    assert odo.linked == ["000000", "000001", "000002", "000003"]
    for fid in ("000004", "000005", "000006"):
        assert np.array_equal(odo.poses[fid], poses[fid])


def test_odometry_that_links_too_few_frames_is_refused_before_writing(
    vine_views: VineViews, tmp_path: Path
) -> None:
    """Two views from one place, then three from elsewhere on the vine (no video between them):
    odometry links two frames, fewer than a fused surface needs (`odometry.MIN_RUN_FRAMES`);
    the reconstruction says so and writes no twin."""
    from vinetwin.capture.folder import write_capture
    from vinetwin.reconstruct.pipeline import ReconstructConfig, reconstruct

    twin = vine_views.twin
    grey = np.full((twin.camera.height, twin.camera.width, 3), 128, np.uint8)
    views = [(twin.poses[0], 11), (twin.poses[0], 12), (twin.poses[2], 13), (twin.poses[4], 14),
             (twin.poses[1], 15)]  # fmt: skip
    frames = [(grey, vine_views.depth(p.T_vine_camera, seed), None) for p, seed in views]
    cap = write_capture(tmp_path / "cap", twin.camera, frames)
    with pytest.raises(CaptureError, match="odometry linked at most 2 consecutive frames of 5"):
        reconstruct(cap, tmp_path / "vine.twin", ReconstructConfig(poses="odometry"))
    assert not (tmp_path / "vine.twin").exists()


def test_aligning_poses_on_a_line_recovers_the_rotation_about_it() -> None:
    """`align_to` on cameras whose centres lie on a line (one pass of a sweep): the frames'
    orientations fix the rotation about the line, which their centres leave free."""
    from vinetwin import frames as fr
    from vinetwin.reconstruct.sfm import align_to

    rng = np.random.default_rng(3)
    G = fr.random_pose(rng, 0.5, 1.0)
    local = {
        f"{k:02d}": fr.make_pose(fr.so3_exp(rng.normal(0, 0.2, 3)), [0.05 * k, 0.0, 0.0])
        for k in range(12)
    }
    noisy = {k: T @ fr.random_pose(rng, 0.0005, 0.002) for k, T in local.items()}
    reference = {k: G @ T for k, T in noisy.items()}
    for lever, tol_m, tol_deg in ((0.2, 0.002, 0.3), (0.0, None, None)):
        aligned = align_to(local, reference, lever=lever)
        errs = [fr.pose_error(aligned[k], G @ local[k]) for k in local]
        et, er = max(e[0] for e in errs), np.degrees(max(e[1] for e in errs))
        if tol_m is None:  # the centres alone: the rotation about the line is a guess
            assert er > 1.0, er
        else:
            assert et < tol_m and er < tol_deg, (et, er)


def test_structure_from_motion_that_registers_nothing_is_named(
    capture: Path, tmp_path: Path
) -> None:
    import imageio.v3 as iio

    from vinetwin.reconstruct.sfm import colmap_poses

    blank = tmp_path / "blank"
    shutil.copytree(capture, blank)
    for png in (blank / "color").glob("*.png"):
        iio.imwrite(png, np.full((480, 848, 3), 128, np.uint8))  # no features to match
    with pytest.raises(CaptureError, match="registered no frame"):
        colmap_poses(read_capture(blank))


def test_a_frame_seeing_only_beyond_the_fusion_range_is_skipped(
    vine_views: VineViews, tmp_path: Path
) -> None:
    """A frame whose depth lies entirely beyond `depth_max` (a camera looking past the vine, as
    a sweep over a large real vine gives) is skipped and named, not an Open3D abort that loses
    the whole reconstruction (found fusing a capture of hydroshoot's gdc_can1_grapevine)."""
    from vinetwin.capture.folder import write_capture

    cam = vine_views.twin.camera
    pose = vine_views.twin.poses[0].T_vine_camera
    near = vine_views.depth(pose, 3)
    far = np.where(near > 0, 0.8, 0.0)  # everything at 0.8 m, beyond the default 0.5 m
    grey = np.full((cam.height, cam.width, 3), 128, np.uint8)
    frames = [(grey, near, pose), (grey, far, pose)]
    frames += [(grey, vine_views.depth(pose, 4 + k), pose) for k in range(4)]
    cap = read_capture(write_capture(tmp_path / "cap", cam, frames))
    res = fuse(cap, kinematic_poses(cap), FusionConfig(voxel=0.002, truncation=0.008))
    assert len(res.frames_used) == 5 and len(res.faces) > 100
    assert list(res.frames_skipped.values()) == ["no depth within range"]


def test_a_frame_with_a_few_scattered_pixels_is_skipped_and_named(
    vine_views: VineViews, tmp_path: Path
) -> None:
    """A frame with four scattered depth pixels within range, those of a frame of a sweep past
    hydroshoot's gdc_can1_grapevine: Open3D aborted the whole integration on it ("No block is
    touched"). Under `FusionConfig.min_pixels` it is skipped by that rule; with the rule off,
    Open3D's refusal is caught and named, and the other frames are fused either way."""
    from vinetwin.capture.folder import write_capture

    cam = vine_views.twin.camera
    pose = vine_views.twin.poses[0].T_vine_camera
    few = np.zeros((cam.height, cam.width))
    for v, u, z in ((2, 615, 0.3675), (23, 613, 0.1849), (31, 613, 0.3572), (103, 77, 0.3488)):
        few[v, u] = z
    grey = np.full((cam.height, cam.width, 3), 128, np.uint8)
    frames = [(grey, vine_views.depth(pose, 4 + k), pose) for k in range(4)]
    cap = read_capture(
        write_capture(tmp_path / "cap", cam, [*frames[:2], (grey, few, pose), *frames[2:]])
    )
    cfg = FusionConfig(voxel=0.002, truncation=0.008)
    for rule, reason in ((cfg, "4 depth pixels within range, fewer than the minimum 100"),
                         (dataclasses.replace(cfg, min_pixels=0), "Open3D could not integrate it: No block is touched")):  # fmt: skip
        res = fuse(cap, kinematic_poses(cap), rule)
        assert res.frames_used == ["000000", "000001", "000003", "000004"]
        assert list(res.frames_skipped) == ["000002"] and len(res.faces) > 100
        assert res.frames_skipped["000002"].startswith(reason), res.frames_skipped


def test_a_cane_seen_apart_is_kept_and_debris_dropped() -> None:
    """Fusion's clean-up drops floating debris (few triangles, millimetres across) but keeps a
    cane piece seen apart from the rest of the vine, however few its triangles against the
    largest piece's: a capture around far-apart pruning poses rebuilds each pose's cane as its own
    piece (on hydroshoot's gdc_can1_grapevine, the rule by triangle share alone dropped two
    poses' 11-14 cm canes, and those poses had no reference in the rebuilt twin)."""
    import open3d as o3d

    from vinetwin.reconstruct.fusion import drop_debris

    trunk = o3d.geometry.TriangleMesh.create_cylinder(0.02, 0.6, 64, 300)  # the vine's bulk
    cane = o3d.geometry.TriangleMesh.create_cylinder(0.004, 0.12, 8, 10).translate((0.5, 0, 0))
    blob = o3d.geometry.TriangleMesh.create_sphere(0.003, 3).translate((-0.5, 0, 0))
    speck = o3d.geometry.TriangleMesh.create_sphere(0.001, 2).translate((0, 0.4, 0))
    mesh = trunk + cane + blob + speck
    n = [len(m.triangles) for m in (trunk, cane, blob, speck)]
    assert n[1] < 0.02 * n[0] and n[2] < 0.02 * n[0]  # all three fail the share rule alone
    assert drop_debris(mesh, FusionConfig()) == 2
    assert len(mesh.triangles) == n[0] + n[1]
    V = np.asarray(mesh.vertices)
    assert V[:, 0].max() > 0.49 and V[:, 0].min() > -0.03  # the cane is kept, the blob gone
    share_only = trunk + cane + blob + speck
    assert drop_debris(share_only, FusionConfig(min_component_extent=0.0)) == 3
    assert len(share_only.triangles) == n[0]
