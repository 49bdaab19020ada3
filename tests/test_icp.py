"""ICP variants: the compiled k-d tree against scipy, the real scan pair with ground truth,
agreement with Open3D, known transforms recovered on D405 vine views, bad inputs and degenerate
geometry. (Speed is measured by benchmarks/icp.py, never asserted here.)"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import VineViews, shared
from vinetwin import _lazy
from vinetwin import frames as fr
from vinetwin.camera import d405
from vinetwin.cloud import Cloud
from vinetwin.registration import _kernels as K
from vinetwin.registration import _search_kernels as S
from vinetwin.registration.icp import ICP, ICPConfig, view_edge_mask

VARIANTS = ["point_to_point", "lm", "point_to_plane", "symmetric"]


@pytest.fixture(scope="module")
def scan_pair() -> tuple[Cloud, Cloud, np.ndarray]:
    o3d = _lazy.open3d()
    base = shared("icp", "small_gicp")
    clouds = []
    for name in ("target", "source"):
        pc = o3d.io.read_point_cloud(str(base / f"{name}.ply")).voxel_down_sample(0.25)
        pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(1.0, 20))
        pc.orient_normals_towards_camera_location(np.zeros(3))
        clouds.append(Cloud(np.asarray(pc.points), np.asarray(pc.normals)))
    rows = np.loadtxt(base / "T_target_source.txt")
    T = np.eye(4)
    T[:3] = rows[:3]
    return clouds[0], clouds[1], T


@pytest.mark.parametrize("variant", VARIANTS)
def test_scan_pair_registers_to_ground_truth(scan_pair, variant: str) -> None:  # type: ignore[no-untyped-def]
    target, source, T_true = scan_pair
    icp = ICP(
        target,
        ICPConfig(
            variant=variant,
            max_correspondence_distance=1.0,
            schedule=((2.0, 4.0), (1.0, 2.0)),
            max_iterations=60,
        ),
    )
    r = icp.align(source, np.eye(4))
    dt, dr = fr.pose_error(r.T_ref_cur, T_true)
    assert r.converged, r.reason
    assert dt < 0.15 and dr < np.radians(0.5), (dt, np.degrees(dr))
    assert r.fitness > 0.5


@pytest.mark.parametrize("variant", ["point_to_point", "point_to_plane"])
def test_agrees_with_open3d(scan_pair, variant: str) -> None:  # type: ignore[no-untyped-def]
    o3d = _lazy.open3d()
    target, source, T_true = scan_pair
    init = T_true @ fr.random_pose(np.random.default_rng(0), 0.3, np.radians(2))
    ours = ICP(
        target,
        ICPConfig(
            variant=variant, max_correspondence_distance=1.0, max_iterations=100, schedule=()
        ),
    ).align(source, init)
    est = (
        o3d.pipelines.registration.TransformationEstimationPointToPoint()
        if variant == "point_to_point"
        else o3d.pipelines.registration.TransformationEstimationPointToPlane()
    )
    crit = o3d.pipelines.registration.ICPConvergenceCriteria(1e-12, 1e-12, 100)
    pcs = [o3d.geometry.PointCloud(o3d.utility.Vector3dVector(c.points)) for c in (source, target)]
    pcs[1].normals = o3d.utility.Vector3dVector(target.normals)
    theirs = o3d.pipelines.registration.registration_icp(pcs[0], pcs[1], 1.0, init, est, crit)
    dt, dr = fr.pose_error(ours.T_ref_cur, np.asarray(theirs.transformation))
    assert dt < 0.02 and dr < np.radians(0.05), (dt, np.degrees(dr))
    assert ours.fitness == pytest.approx(theirs.fitness, abs=0.01)


@pytest.mark.parametrize("variant", VARIANTS)
def test_bad_inputs_give_named_failures(variant: str) -> None:
    rng = np.random.default_rng(0)
    pts = rng.uniform(-0.05, 0.05, (500, 3)) + [0, 0, 0.2]
    nrm = rng.normal(size=(500, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    ref = Cloud(pts, nrm)
    icp = ICP(ref, ICPConfig(variant=variant))
    cases = {
        "is empty": Cloud(np.empty((0, 3)), np.empty((0, 3))),
        "non-finite": Cloud(np.where(np.arange(500)[:, None] == 3, np.nan, pts), nrm),
        "fewer than the minimum": Cloud(pts[:5], nrm[:5]),
    }
    for needle, cloud in cases.items():
        r = icp.align(cloud)
        assert not r.converged and needle in r.reason
    r = icp.align(Cloud(pts + 1.0, nrm))  # nothing within reach
    assert not r.converged and "too few correspondences" in r.reason
    assert (
        "reference cloud is empty"
        in ICP(Cloud(np.empty((0, 3)), np.empty((0, 3))), ICPConfig(variant=variant))
        .align(ref)
        .reason
    )


def test_single_straight_cane_is_degenerate() -> None:
    # a cylinder of radius 4 mm along x, 15 cm in front of the camera: sliding along it and
    # rolling about it are unobservable
    s, a = np.meshgrid(np.linspace(-0.1, 0.1, 200), np.linspace(0, 2 * np.pi, 24, endpoint=False))
    n = np.column_stack([np.zeros(s.size), np.cos(a.ravel()), np.sin(a.ravel())])
    pts = np.column_stack([s.ravel(), np.zeros(s.size), np.full(s.size, 0.15)]) + 0.004 * n
    cane = Cloud(pts, n)
    r = ICP(cane, ICPConfig(variant="point_to_plane")).align(cane, fr.make_pose(t=[0.002, 0, 0]))
    assert not r.converged and "degenerate" in r.reason


def test_unknown_variant_is_named() -> None:
    from vinetwin.errors import InputError

    with pytest.raises(InputError, match="choose one of"):
        ICPConfig(variant="p2l")


@pytest.mark.parametrize("dmax", [0.002, 0.01, 0.05])
def test_tree_gives_the_exact_nearest_within_reach(dmax: float) -> None:
    from scipy.spatial import KDTree

    rng = np.random.default_rng(3)
    ref = rng.uniform(-0.1, 0.1, (3000, 3))
    ref[:40] = ref[40:80]  # duplicates
    src = np.vstack([ref[:1000] + rng.normal(0, 0.003, (1000, 3)), rng.uniform(-1, 1, (300, 3))])
    T = fr.random_pose(rng, 0.01, 0.05)
    tree = S.NNTree(ref)
    q, idx, d2 = S.associate(src, T, tree.arrays, dmax, 2, S.NO_MEMO)
    d_ref, _ = KDTree(ref).query(fr.transform_points(T, src), distance_upper_bound=dmax)
    found = np.isfinite(d_ref)
    assert np.array_equal(idx >= 0, found)
    np.testing.assert_allclose(np.sqrt(d2[found]), d_ref[found], atol=1e-12)
    # the index maps back to a point at that distance (ties may pick another duplicate)
    back = tree.order[idx[found]]
    np.testing.assert_allclose(
        np.linalg.norm(ref[back] - q[found], axis=1), d_ref[found], atol=1e-12
    )


def test_memoised_tree_answers_stay_exact() -> None:
    """Across a sequence of poses (steps from hundredths of a millimetre to a centimetre), the
    tree's memo answers every point with its exact closest reference point within reach (scipy's
    k-d tree), and the small steps do skip most searches."""
    from scipy.spatial import KDTree

    rng = np.random.default_rng(5)
    ref = rng.uniform(-0.05, 0.05, (4000, 3))
    ref[:30] = ref[30:60]  # duplicates
    src = ref[rng.choice(len(ref), 1500)] + rng.normal(0, 0.002, (1500, 3))
    tree = S.NNTree(ref)
    exact = KDTree(tree.points)
    n, dmax = len(src), 0.005
    memo = S.new_memo(n)
    q, idx, d2 = np.empty((n, 3)), np.empty(n, np.int64), np.empty(n)
    T = np.eye(4)
    skipped = []
    for step in (0.0, 1e-5, 3e-5, 1e-4, 0.01, 2e-5, 0.0, 3e-4, 1e-5):
        T = fr.random_pose(rng, step, step / 0.1) @ T
        where_before = memo[1].copy()
        S._associate_range(src, T, tree.arrays, dmax, 0, n, q, idx, d2, S.NO_PROJECTIVE, memo)
        d_ref, _ = exact.query(q, distance_upper_bound=dmax)
        found = np.isfinite(d_ref)
        assert np.array_equal(idx >= 0, found)
        np.testing.assert_allclose(np.sqrt(d2[found]), d_ref[found], atol=1e-12)
        np.testing.assert_allclose(
            np.linalg.norm(tree.points[idx[found]] - q[found], axis=1), d_ref[found], atol=1e-12
        )
        skipped.append(float(np.mean(np.all(memo[1] == where_before, axis=1) & (memo[0] >= 0))))
    assert skipped[0] == 0.0  # the first call searches every point
    assert min(skipped[1], skipped[2], skipped[8]) > 0.5  # hundredths of a mm: most kept
    assert skipped[4] < 0.2  # a centimetre: searched again


@pytest.mark.parametrize("variant", ["point_to_plane", "symmetric", "lm"])
def test_vine_views_recover_known_transforms(vine_views: VineViews, variant: str) -> None:
    """Warm start (2 cm / 3 deg) on the sample's D405 views, each cloud with its own noise: the
    median within 0.5 mm / 0.12 deg, every case within 2 mm / 0.75 deg. (The issue's goal is
    1 mm / 0.1 deg for every case; about one case in seven misses it in rotation, see the
    closing note of issue 4 and benchmarks/icp.py.) LM measures its distances to the reference
    surface by default (`lm_model`), so it is held to the same bounds.

    The bounds hold for other D405 noise, not only this stream's (docs/testing.md): over 16
    streams and the quantile draws of e8410dc, the medians were at most 0.28 mm / 0.096 deg
    (LM) and the worst cases 1.44 mm / 0.61 deg (LM; point-to-plane 1.36 mm / 0.59 deg). The
    earlier 1.5 mm / 0.5 deg for every case failed in 4 of the 17."""
    twin = vine_views.twin
    errs = []
    for _pose, ref, cur, D in vine_views.cases(0.02, 3.0, per_pose=2):
        icp = ICP(ref, ICPConfig(variant=variant), camera=twin.camera, max_depth=0.4)
        r = icp.align(cur)
        assert r.converged, r.reason
        dt, dr = fr.pose_error(r.T_ref_cur, D)
        errs.append((1000 * dt, np.degrees(dr)))
    e = np.array(errs)
    assert np.median(e[:, 0]) < 0.5 and np.median(e[:, 1]) < 0.12, e
    assert e[:, 0].max() < 2.0 and e[:, 1].max() < 0.75, e


#: point-to-point's residuals: point-to-point itself and LM on the points
POINT_RESIDUALS = [
    pytest.param({"variant": "point_to_point"}, id="point_to_point"),
    pytest.param({"variant": "lm", "lm_model": "points"}, id="lm_points"),
]


@pytest.mark.parametrize("settings", POINT_RESIDUALS)
def test_point_to_point_variants_on_vine_views(vine_views: VineViews, settings: dict) -> None:
    """Point-to-point residuals have a floor on these clouds (both are 4 mm voxel lattices: the
    nearest sample is not the true correspondent, and the cost has local minima about a spacing
    apart), so this checks what they do reach: from a warm start the error is cut at least
    fivefold and lands within 3 mm / 1 deg; from 1 mm / 0.1 deg it stays within 1.5 mm / 0.4
    deg."""
    twin = vine_views.twin
    for offset, deg, lim_t, lim_r in ((0.02, 3.0, 3.0, 1.0), (0.001, 0.1, 1.5, 0.4)):
        errs = []
        for _pose, ref, cur, D in vine_views.cases(offset, deg, per_pose=2):
            r = ICP(ref, ICPConfig(**settings), camera=twin.camera, max_depth=0.4).align(cur)
            assert r.converged, r.reason
            dt, dr = fr.pose_error(r.T_ref_cur, D)
            errs.append((1000 * dt, np.degrees(dr)))
        e = np.array(errs)
        assert np.median(e[:, 0]) < lim_t and np.median(e[:, 1]) < lim_r, e
        if offset == 0.02:
            assert np.median(e[:, 0]) < 1000 * offset / 5, e


@pytest.mark.parametrize("settings", POINT_RESIDUALS)
def test_a_dense_final_reference_lifts_the_lattice_floor(
    vine_views: VineViews, settings: dict
) -> None:
    """The same reference depth at a quarter of the voxel (1 mm) for the final level only
    (`ICP(final_reference=...)`, what the servo gives point-to-point): from 5 mm / 1 deg
    (a tracking servo's start) the median error drops below 0.6 mm, at least a third below the
    4 mm reference's. (Measured with numpy 2.4.6 and scipy 1.17.1: 0.47 mm point-to-point and
    0.50 mm LM on points, against 1.32 mm with the 4 mm reference; an earlier environment's
    LM median was under 0.5 mm, the bound this test held until that drift.)"""
    from dataclasses import replace

    from vinetwin.cloud import perceive

    twin = vine_views.twin
    dense_perception = replace(twin.perception, voxel_size=twin.perception.voxel_size / 4)
    plain, dense = [], []
    for pose_id, ref, cur, D in vine_views.cases(0.005, 1.0, per_pose=2):
        depth = vine_views.depth(twin.pose(pose_id).T_vine_camera, 1)  # the reference's depth
        fine = perceive(depth, twin.camera, dense_perception, normals=True)
        for out, final in ((plain, None), (dense, fine)):
            icp = ICP(ref, ICPConfig(**settings), camera=twin.camera, max_depth=0.4,
                      final_reference=final)  # fmt: skip
            r = icp.align(cur)
            assert r.converged, r.reason
            assert r.coverage > 0.3, "coverage counts the reference's own points"
            out.append(1000 * fr.pose_error(r.T_ref_cur, D)[0])
    assert np.median(dense) < 0.6, dense
    assert np.median(dense) < 0.67 * np.median(plain), (plain, dense)


def test_lm_on_points_minimises_the_point_to_point_objective(scan_pair) -> None:  # type: ignore[no-untyped-def]
    target, source, T_true = scan_pair
    init = T_true @ fr.random_pose(np.random.default_rng(2), 0.3, np.radians(2))
    cfg = {
        "max_correspondence_distance": 1.0, "max_iterations": 200, "schedule": (),
        "lm_model": "points",
    }  # fmt: skip
    p2p = ICP(target, ICPConfig(variant="point_to_point", **cfg)).align(source, init)
    lm = ICP(target, ICPConfig(variant="lm", **cfg)).align(source, init)
    robust = ICP(target, ICPConfig(variant="lm", huber_delta=0.3, **cfg)).align(source, init)
    dt, dr = fr.pose_error(p2p.T_ref_cur, lm.T_ref_cur)
    assert dt < 0.01 and dr < np.radians(0.02)
    dt, dr = fr.pose_error(robust.T_ref_cur, T_true)
    assert robust.converged and dt < 0.15 and dr < np.radians(0.5)


def test_view_edge_mask_marks_border_and_far_points() -> None:
    from vinetwin.camera import d405

    cam = d405("848x480")
    z = 0.2
    inside = cam.deproject_pixels(np.array([[424.0, 240.0], [100.0, 100.0]]), np.array([z, z]))
    border = cam.deproject_pixels(np.array([[2.0, 240.0], [424.0, 478.0]]), np.array([z, z]))
    far = np.array([[0.0, 0.0, 0.397]])
    m = view_edge_mask(np.vstack([inside, border, far]), cam, 0.005, max_depth=0.4)
    assert m.tolist() == [False, False, True, True, True]


@pytest.fixture(scope="module")
def dense_real_vine(tmp_path_factory: pytest.TempPathFactory):  # type: ignore[no-untyped-def]
    """A digitised real vine (hydroshoot's VSP grapevine, ../shared/data) as a twin, with a
    renderer and perception at 2 mm: dense views of a vine that is not the bundled sample."""
    from dataclasses import replace

    from vinetwin.render.backends import get_backend
    from vinetwin.twin.importers import import_twin

    path = shared("vines", "hydroshoot", "vsp_ww_grapevine", "digit.input")
    twin = import_twin(path, tmp_path_factory.mktemp("vsp") / "v.twin", edge=0.003, cut_points=6)
    mesh = twin.load_mesh()
    backend = get_backend("open3d", mesh.vertices, mesh.faces, twin.camera)
    return twin, backend, replace(twin.perception, voxel_size=0.002)


def _dense_view(vine, T: np.ndarray, seed: int) -> Cloud:  # type: ignore[no-untyped-def]
    from vinetwin.cloud import perceive
    from vinetwin.render.sensor import SensorConfig, apply_d405_model

    twin, backend, perception = vine
    depth = apply_d405_model(
        backend.render(T), twin.camera, np.random.default_rng(seed), SensorConfig()
    )
    return perceive(depth, twin.camera, perception, normals=True)


@pytest.mark.parametrize("variant", ["point_to_plane", "symmetric"])
def test_no_false_success_on_dense_real_vine_views(dense_real_vine, variant: str) -> None:  # type: ignore[no-untyped-def]
    """Dense (2 mm) views of a digitised real vine, ICP from 0.5-4 cm / 1-6 deg off: a result
    that claims convergence is within 1 cm / 0.05 rad of the truth at up to 2 cm / 3 deg (the
    case of the issue: point-to-plane from 2 cm / 3 deg once ended 184 mm off claiming
    success). At 4 cm / 6 deg, beyond the tracking basin, wrong answers whose pairs look right
    can remain (a spur that looks like its neighbour); those the servo's pose-jump rule and
    the wide search's ambiguity check are for: here, fewer than one in ten."""
    twin, _, perception = dense_real_vine
    false_near, false_far, far = 0, 0, 0
    for pose in twin.poses:
        ref = _dense_view(dense_real_vine, pose.T_vine_camera, 1)
        icp = ICP(
            ref, ICPConfig(variant=variant), camera=twin.camera, max_depth=perception.max_depth
        )
        for off_m, off_deg, seeds in ((0.005, 1, 1), (0.02, 3, 3), (0.04, 6, 2)):
            for s in range(seeds):
                D = fr.random_pose(np.random.default_rng(s), off_m, np.radians(off_deg))
                r = icp.align(_dense_view(dense_real_vine, pose.T_vine_camera @ D, 100 + s))
                et, er = fr.pose_error(r.T_ref_cur, D)
                wrong = r.converged and (et > 0.01 or er > 0.05)
                if not r.converged:
                    assert r.reason, "a failure always says why"
                if off_m <= 0.02:
                    false_near += int(wrong)
                else:
                    far += 1
                    false_far += int(wrong)
    assert false_near == 0
    assert false_far <= 0.1 * far, (false_far, far)


def test_a_diverged_result_is_not_converged(vine_views: VineViews) -> None:
    """An estimate far off (ICP capped at one iteration from a 12 cm guess, so its update
    criterion cannot have stopped it) pairs too little to be called converged, and says why:
    too little of the clouds paired ("diverged"), or fewer pairs than `min_correspondences` at
    all, whichever the noise gives (over 16 D405 noise streams, 7 gave the second; at most 7%
    paired in any)."""
    twin = vine_views.twin
    pose = twin.poses[0]
    ref = vine_views.reference(pose.id)
    icp = ICP(ref, ICPConfig(variant="point_to_plane", schedule=(), max_iterations=1,
                             tolerance_translation=1.0, tolerance_rotation=1.0))  # fmt: skip
    r = icp.align(ref, fr.make_pose(t=[0.12, 0.0, 0.0]))
    assert not r.converged, (r.reason, r.overlap, r.coverage)
    assert "diverged" in r.reason or "too few correspondences" in r.reason, r.reason
    assert r.overlap < 0.1 and r.coverage < 0.1, (r.overlap, r.coverage)
    ok = icp.align(ref, np.eye(4))
    assert ok.converged and ok.coverage > 0.9 and ok.overlap > 0.9


def test_coverage_counts_what_the_current_camera_has_in_view(vine_views: VineViews) -> None:
    """A camera nearer the vine than its goal, and turned from it, sees part of the reference's
    view: at the right alignment coverage counts the reference points in its view (most of them
    paired), not the whole reference (which its narrower view cannot cover). Without a camera
    the ICP cannot tell, and counts every reference point."""
    twin = vine_views.twin
    pose = twin.poses[0]
    ref = vine_views.reference(pose.id)
    D = fr.make_pose(fr.so3_exp([0.0, 0.15, 0.0]), [0.03, 0.0, 0.06])
    cur = vine_views.cloud(pose.T_vine_camera @ D, 5)
    cfg = ICPConfig(variant="point_to_plane", crop_margin=0.0)
    r = ICP(ref, cfg, camera=twin.camera, max_depth=0.4).align(cur, D)
    assert r.converged, r.reason
    assert fr.pose_error(r.T_ref_cur, D)[0] < 0.002
    blind = ICP(ref, cfg).align(cur, D)  # the same alignment, every reference point counted
    assert fr.pose_error(blind.T_ref_cur, r.T_ref_cur)[0] < 1e-3
    assert blind.coverage < 0.6 * r.coverage and r.coverage > 0.7, (blind.coverage, r.coverage)


def _tripod(rng: np.random.Generator) -> np.ndarray:
    """Points on three perpendicular arms of 12, 7 and 4 cm, 0.3 m ahead: no symmetry."""
    arms = np.diag([0.12, 0.07, 0.04])
    pts = np.concatenate([np.outer(np.linspace(0.0, 1.0, 200), a) for a in arms])
    return pts + rng.normal(0.0, 0.0005, pts.shape) + np.array([0.0, 0.0, 0.3])


@pytest.mark.parametrize("degrees", [30.0, 50.0, 60.0])
def test_a_turn_beyond_max_rotation_correction_is_a_named_failure(
    rng: np.random.Generator, degrees: float
) -> None:
    """A known turn about the cloud's centre is recovered within 0.05 mm / 0.01 deg from the
    identity (a wide first level); beyond `max_rotation_correction` (45 deg by default) the same
    right answer is refused, with the turn named; 0 turns the check off, and a bad value is
    named."""
    from vinetwin.errors import InputError

    pts = _tripod(rng)
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    D = np.eye(4)
    D[:3, :3] = fr.so3_exp(np.radians(degrees) * axis)
    c = pts.mean(0)
    D[:3, 3] = c - D[:3, :3] @ c
    cur = Cloud((pts - D[:3, 3]) @ D[:3, :3])  # reference = D @ current
    levels = ((0.0, 0.2), (0.0, 0.05))
    for gate in (0.785, 1.2, 0.0):
        cfg = ICPConfig(variant="point_to_point", schedule=levels, max_rotation_correction=gate)
        r = ICP(Cloud(pts), cfg).align(cur)
        dt, dr = fr.pose_error(r.T_ref_cur, D)
        assert dt < 5e-5 and np.degrees(dr) < 0.01, (degrees, gate, dt, dr)  # the answer is right
        if gate and degrees > np.degrees(gate):
            assert not r.converged and f"turned {degrees:.1f} deg" in r.reason, r.reason
        else:
            assert r.converged, r.reason
    assert ICPConfig().max_rotation_correction == pytest.approx(np.radians(45), abs=1e-3)
    with pytest.raises(InputError, match="max_rotation_correction"):
        ICPConfig(max_rotation_correction=-0.1)


@pytest.mark.numpy_noise
def test_symmetric_false_convergence_on_the_sample_is_named(
    sample_twin_dir: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """From 5 cm / 10 deg, symmetric ICP (coarse to fine) converged far off on the sample's pose
    p2 under some D405 noise streams, pairing 60% of the smaller cloud and covering 31-33% of
    the reference, which `min_overlap` lets through. Under streams 2 and 4 the answer turned
    68-72 deg from its guess: `max_rotation_correction` names it. With the check off, the same
    registration reports success 78-88 mm from the truth. No pose is a false success."""
    from vinetwin.render import _sensor_kernels

    numpy_stream = _sensor_kernels.standard_normals
    named = 0
    for k in (2, 4):

        def stream(rng: np.random.Generator, n: int, k: int = k) -> np.ndarray:
            numpy_stream(rng, n)  # as tests/conftest.py's --noise-stream
            return np.random.default_rng([int(rng.integers(2**62)), k]).standard_normal(n)

        monkeypatch.setattr(_sensor_kernels, "standard_normals", stream)
        views = VineViews(sample_twin_dir)
        for pose, ref, cur, D in views.cases(0.05, 10.0, per_pose=1):
            make = functools.partial(ICPConfig.coarse_to_fine, variant="symmetric")
            icp = ICP(ref, make(), camera=views.twin.camera, max_depth=0.4)
            r = icp.align(cur)
            dt = fr.pose_error(r.T_ref_cur, D)[0]
            assert not r.converged or dt < 0.002, (k, pose, dt, r.reason)  # never a false success
            if pose != "p2":  # right, or a named failure (p5 diverged under stream 2)
                continue
            assert not r.converged and "turned" in r.reason, (k, r.reason)
            named += 1
            off = ICP(ref, make(max_rotation_correction=0.0), camera=views.twin.camera,
                      max_depth=0.4).align(cur)  # fmt: skip
            assert off.converged and fr.pose_error(off.T_ref_cur, D)[0] > 0.05, (k, off.reason)
    assert named == 2


def test_dithering_the_live_grid_removes_the_lattice_pull(vine_views: VineViews) -> None:
    """A camera 1.5 mm from its goal: with the live grid anchored like the reference's, the
    point-to-point estimates averaged over frames stay biased towards the goal (the lattices
    coincide there); with the grid origin drawn within a voxel each frame (what the servo
    does), their average is at least twice as close to the truth."""
    from vinetwin.cloud import perceive

    twin = vine_views.twin
    pose = twin.pose("p3")
    ref = vine_views.reference("p3")
    D = fr.make_pose(fr.so3_exp(np.array([0.0, 0.0, 0.004])), np.array([0.0015, -0.001, 0.0]))
    icp = ICP(ref, ICPConfig(variant="point_to_point"), camera=twin.camera, max_depth=0.4)
    voxel = twin.perception.voxel_size
    est: dict[bool, list[np.ndarray]] = {False: [], True: []}
    for k in range(16):
        depth = vine_views.depth(pose.T_vine_camera @ D, 500 + k)
        for dither in (False, True):
            origin = np.random.default_rng(k).uniform(0, voxel, 3) if dither else None
            cur = perceive(depth, twin.camera, twin.perception, normals=False, grid_origin=origin)
            r = icp.align(cur, D)
            assert r.converged, r.reason
            est[dither].append(r.T_ref_cur[:3, 3])
    bias = {d: float(np.linalg.norm(np.mean(v, axis=0) - D[:3, 3])) for d, v in est.items()}
    assert bias[True] < 0.5 * bias[False], bias


@pytest.mark.parametrize("window", [1, 2])
def test_projective_association_is_the_nearest_within_its_window(window: int) -> None:
    """Projective association (`ICPConfig.association`): each current point, placed in the
    reference camera frame, gets the closest reference point within reach among those whose
    projection lies within `window` cells of its own, checked against a brute-force search of
    the same cells; and never a partner closer than the exact nearest (the tree's)."""
    from scipy.spatial import KDTree

    rng = np.random.default_rng(11)
    cam = d405()
    # a wavy surface 15-25 cm in front of the camera, sampled at 2 mm, and a second layer
    # behind it (a cane behind a cane: the same pixels at another depth)
    g = np.arange(-0.06, 0.06, 0.002)
    X, Y = np.meshgrid(g, g)
    Z = 0.2 + 0.02 * np.sin(X / 0.02) * np.cos(Y / 0.03)
    front = np.column_stack([X.ravel(), Y.ravel(), Z.ravel()])
    ref = np.vstack([front, front[::3] * 1.15])
    tree = S.NNTree(ref)
    idx_ = S.ProjectiveIndex(
        tree.points, cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height, 0.002, window
    )
    src = ref[rng.choice(len(ref), 2000)] + rng.normal(0, 0.0015, (2000, 3))
    T = fr.random_pose(rng, 0.002, 0.01)
    dmax = 0.005
    n = len(src)
    q, idx, d2 = np.empty((n, 3)), np.empty(n, np.int64), np.empty(n)
    S._associate_range(src, T, tree.arrays, dmax, 0, n, q, idx, d2, idx_.arrays, S.NO_MEMO)

    def cell(p: np.ndarray) -> np.ndarray:
        u = (cam.fx * p[:, 0] / p[:, 2] + cam.cx) / idx_.scale
        v = (cam.fy * p[:, 1] / p[:, 2] + cam.cy) / idx_.scale
        return np.column_stack([np.floor(u), np.floor(v)]).astype(int)

    wc, hc = int(idx_.params[5]), int(idx_.params[6])
    rc = np.clip(cell(tree.points), 0, [wc - 1, hc - 1])
    qc = cell(q)
    for i in range(n):
        near = np.all(np.abs(rc - qc[i]) <= window, axis=1)
        d = np.linalg.norm(tree.points[near] - q[i], axis=1)
        if len(d) == 0 or d.min() > dmax:
            assert idx[i] == -1
            continue
        assert idx[i] >= 0
        assert np.sqrt(d2[i]) == pytest.approx(d.min(), abs=1e-12)
        assert np.linalg.norm(tree.points[idx[i]] - q[i]) == pytest.approx(d.min(), abs=1e-12)
    exact, _ = KDTree(ref).query(q, distance_upper_bound=dmax)
    found = idx >= 0
    assert np.all(np.sqrt(d2[found]) >= exact[found] - 1e-12)
    # nearly every point's exact partner lies within the window at this reach
    assert found.sum() >= 0.97 * np.isfinite(exact).sum()


def test_projective_and_tree_association_agree_on_vine_views(vine_views: VineViews) -> None:
    """The default (projective association at the levels of 1 cm reach or less) against the
    exact tree at every level, warm starts (2 cm / 3 deg) on the sample's D405 views: the same
    answer within 0.3 mm / 0.05 deg, both within 1.5 mm of the truth."""
    twin = vine_views.twin
    for _pose, ref, cur, D in vine_views.cases(0.02, 3.0, per_pose=1):
        out = {}
        for assoc in ("projective", "tree"):
            icp = ICP(ref, ICPConfig(association=assoc), camera=twin.camera, max_depth=0.4)
            r = icp.align(cur)
            assert r.converged, r.reason
            out[assoc] = r.T_ref_cur
            assert fr.pose_error(r.T_ref_cur, D)[0] < 0.0015
        dt, dr = fr.pose_error(out["projective"], out["tree"])
        assert dt < 0.0003 and dr < np.radians(0.05), (dt, dr)


def _disc_truth(x: np.ndarray, c: np.ndarray, n: np.ndarray, radius: float) -> float:
    """The distance from x to a disc (centre c, unit normal n), signed by the side over the
    disc itself: the nearest point of the disc found by clamping x's foot into it."""
    e = x - c
    h = float(e @ n)
    t = e - h * n
    tn = float(np.linalg.norm(t))
    if tn <= radius:
        return h
    return float(np.linalg.norm(e - t * (radius / tn)))


def test_disc_residual_and_its_gradient() -> None:
    """LM's surface residual: over the disc the signed height, past the rim the distance to the
    rim (checked against the clamped foot point), and its gradient against central
    differences, inside, outside and near the rim."""
    rng = np.random.default_rng(5)
    y = rng.normal(size=(1, 3))
    n = rng.normal(size=3)
    n /= np.linalg.norm(n)
    nrm = n[None, :].copy()
    radius = 0.002
    u = np.cross(n, [1.0, 0.0, 0.0])
    u /= np.linalg.norm(u)
    points = [
        y[0] + 0.0007 * n + 0.0012 * u,  # over the disc
        y[0] - 0.0011 * n + 0.0004 * np.cross(n, u),  # under it
        y[0] + 0.0009 * n + 0.0035 * u,  # past the rim
        y[0] - 0.0002 * n + 0.0021 * u,  # just past the rim, close to the plane
        *(y[0] + rng.normal(0, 0.003, (20, 3))),
    ]
    eps = 1e-7
    for x in points:
        r, *g = K.disc_residual(x[0], x[1], x[2], y, nrm, 0, radius)
        assert r == pytest.approx(_disc_truth(x, y[0], n, radius), abs=1e-12)
        if abs(np.linalg.norm((x - y[0]) - ((x - y[0]) @ n) * n) - radius) < 1e-6:
            continue  # on the rim the gradient jumps
        fd = [
            (
                K.disc_residual(*(x + eps * d), y, nrm, 0, radius)[0]
                - K.disc_residual(*(x - eps * d), y, nrm, 0, radius)[0]
            ) / (2 * eps)
            for d in np.eye(3)
        ]  # fmt: skip
        np.testing.assert_allclose(g, fd, atol=1e-6)


def _corner(offset: float, spacing: float = 0.002, half: int = 12) -> Cloud:
    """Three orthogonal square faces meeting at (0, 0, 0.2), sampled on a lattice of `spacing`
    shifted by `offset` along each face, with their normals."""
    g = (np.arange(1, 2 * half) * spacing + offset)[None, :].repeat(2 * half - 1, 0)
    a, b = g.ravel(), g.T.ravel()
    zero = np.zeros_like(a)
    pts = np.vstack(
        [
            np.column_stack([a, b, zero]),
            np.column_stack([a, zero, b]),
            np.column_stack([zero, a, b]),
        ]
    )
    nrm = np.repeat(np.eye(3)[::-1], len(a), axis=0)
    return Cloud(pts + [0.0, 0.0, 0.2], nrm)


def test_lm_on_the_surface_is_not_held_by_the_lattice() -> None:
    """A box corner sampled on a 2 mm lattice, and the same corner sampled on a lattice shifted
    by half a spacing and moved by a known 0.6 mm / 0.3 deg: LM on the surface recovers the
    motion within 20 um / 0.01 deg (the faces are exact planes); on the points, the closest
    sample is not the correspondent and it settles at least five times farther off. On one
    face alone the surface leaves three motions free: a named singular failure."""
    ref, cur = _corner(0.0), _corner(0.001)
    D = fr.make_pose(
        fr.so3_exp(np.radians(0.3) * np.array([0.6, -0.8, 0.0])), [0.0004, -0.0003, 0.0003]
    )
    moved = Cloud(fr.transform_points(D, cur.points), cur.normals @ D[:3, :3].T)
    settings = {"max_correspondence_distance": 0.004, "schedule": (), "max_iterations": 100}
    errs = {}
    for model in ("surface", "points"):
        r = ICP(ref, ICPConfig(variant="lm", lm_model=model, **settings)).align(moved)
        assert r.converged, (model, r.reason)
        errs[model] = fr.pose_error(r.T_ref_cur, fr.invert(D))
    dt, dr = errs["surface"]
    assert dt < 2e-5 and dr < np.radians(0.01), (dt, np.degrees(dr))
    assert errs["points"][0] > 5 * dt, errs
    face = Cloud(ref.points[: len(ref.points) // 3], ref.normals[: len(ref.points) // 3])
    r = ICP(face, ICPConfig(variant="lm", **settings)).align(face, fr.make_pose(t=[0, 0, 0.001]))
    assert not r.converged and "degenerate" in r.reason, r.reason


def test_lm_settings_are_checked_and_named() -> None:
    from vinetwin.errors import InputError

    with pytest.raises(InputError, match="choose one of: surface, points"):
        ICPConfig(variant="lm", lm_model="plane")
    with pytest.raises(InputError, match="lm_disc_radius"):
        ICPConfig(variant="lm", lm_disc_radius=0.0)
    # LM on the surface reads the reference's normals; on the points it does not
    rng = np.random.default_rng(1)
    bare = Cloud(rng.uniform(-0.05, 0.05, (300, 3)) + [0, 0, 0.2])
    r = ICP(bare, ICPConfig(variant="lm")).align(bare)
    assert not r.converged and "no normals" in r.reason
    r = ICP(bare, ICPConfig(variant="lm", lm_model="points")).align(bare)
    assert r.converged, r.reason
    # the defaults follow the model: the surface takes point-to-plane's, the points point-to-point's
    for model, like in (("surface", "point_to_plane"), ("points", "point_to_point")):
        cfg, ref = ICPConfig(variant="lm", lm_model=model), ICPConfig(variant=like)
        assert cfg.levels() == ref.levels()
        assert (cfg.edge_reach_m(), cfg.edge_at_final()) == (
            ref.edge_reach_m(),
            ref.edge_at_final(),
        )


def test_association_defaults_per_variant() -> None:
    """Point-to-point and LM pair by the exact tree by default, point-to-plane and symmetric by
    projection (the field profile's measurements, `ASSOCIATION_DEFAULTS`); an explicit choice
    wins, and an unknown one is named."""
    from vinetwin.errors import InputError

    want = {"point_to_point": "tree", "lm": "tree", "point_to_plane": "projective",
            "symmetric": "projective"}  # fmt: skip
    for variant, assoc in want.items():
        assert ICPConfig(variant=variant).association_in_use == assoc
        assert ICPConfig(variant=variant, association="tree").association_in_use == "tree"
    with pytest.raises(InputError, match="choose one of: tree, projective"):
        ICPConfig(association="nearest")


def test_coarse_levels_hand_on_early_without_moving_the_answer(vine_views: VineViews) -> None:
    """Symmetric's and LM's coarse levels stop once an update moves less than 1% of their reach
    (`COARSE_TOLERANCE`): from 2 cm / 3 deg and from 5 cm / 10 deg (`coarse_to_fine`) on the
    sample's views, the answer is the one of coarse levels run to the full tolerances within
    0.15 mm / 0.05 deg, well under its error to the truth (the final level settles it), in fewer
    iterations (point-to-plane too, given the setting; by default it keeps 0, as do
    point-to-point and LM on points); an explicit value wins and a bad one is named.

    The bounds are set so the test holds for other D405 noise, not just this stream's (an
    earlier bound of 0.05 mm / 0.01 deg held for this stream only): over 16 noise streams the
    largest difference between right answers was 0.04 mm / 0.03 deg, while the full runs'
    median errors to the truth were 0.06-0.23 mm / 0.04-0.08 deg."""
    from vinetwin.errors import InputError

    assert ICPConfig(variant="point_to_point").coarse_tolerance_in_use() == 0.0
    assert ICPConfig(variant="point_to_plane").coarse_tolerance_in_use() == 0.0
    assert ICPConfig(variant="lm", lm_model="points").coarse_tolerance_in_use() == 0.0
    for variant in ("symmetric", "lm"):
        assert ICPConfig(variant=variant).coarse_tolerance_in_use() == 0.01
    for variant in ("point_to_plane", "symmetric", "lm"):
        assert ICPConfig(variant=variant, coarse_tolerance=0.0).coarse_tolerance_in_use() == 0.0
    with pytest.raises(InputError, match="coarse_tolerance"):
        ICPConfig(coarse_tolerance=-0.1)
    twin = vine_views.twin
    for variant in ("point_to_plane", "symmetric", "lm"):
        fewer = wrong = compared = lost = 0
        for offset, angle, far in ((0.02, 3.0, False), (0.05, 10.0, True)):
            for _pose, ref, cur, D in vine_views.cases(offset, angle, per_pose=1):
                runs = []
                for tol in (0.01, 0.0):
                    make = ICPConfig.coarse_to_fine if far else ICPConfig
                    cfg = make(variant=variant, coarse_tolerance=tol)
                    r = ICP(ref, cfg, camera=twin.camera, max_depth=0.4).align(cur)
                    runs.append(r)
                early, full = runs
                if not full.converged:  # a failure, named: no answer to keep
                    continue
                if fr.pose_error(full.T_ref_cur, D)[0] > 0.002:
                    wrong += 1  # converged elsewhere
                    continue
                if not early.converged:  # the hand-on cost a right answer (a named failure)
                    lost += 1
                    continue
                compared += 1
                dt, dr = fr.pose_error(early.T_ref_cur, full.T_ref_cur)
                assert dt < 1.5e-4 and np.degrees(dr) < 0.05, (variant, dt, np.degrees(dr))
                fewer += early.iterations < full.iterations
        assert fewer > 0 and compared >= 6, (variant, fewer, compared)
        # the comparison is of right answers: at most one of the ten is wrong. Over 16 noise
        # streams, from 5 cm / 10 deg: symmetric's full run converged far off on p2 in 6 (in
        # the two examined 78-88 mm / 75-78 deg, pairing 60% of the smaller cloud and covering
        # 31-33% of the reference, above `min_overlap`; now named by `max_rotation_correction`,
        # test_symmetric_false_convergence_on_the_sample_is_named), LM's 2.0-2.6 mm off on p1
        # in 3. The early hand-on may cost a right answer:
        # once in 160 cases (LM on p2 from 5 cm / 10 deg, "diverged" where the full levels
        # found the truth)
        assert wrong <= 1 and lost <= 1, (variant, wrong, lost)
