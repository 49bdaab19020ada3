"""The perception chain shared by reference and live clouds: against Open3D, and on scenes
whose answer is known."""

from __future__ import annotations

import itertools
from typing import Any

import numpy as np
import pytest

from vinetwin import _lazy
from vinetwin.camera import d405
from vinetwin.cloud import (
    Cloud,
    PerceptionConfig,
    perceive,
    radius_outliers,
    statistical_outliers,
    voxel_downsample,
)
from vinetwin.errors import InputError


def plane_depth(cam, normal: np.ndarray, point: np.ndarray) -> np.ndarray:  # type: ignore[no-untyped-def]
    """Exact z-depth of the plane n.(p - p0) = 0 seen by `cam` at the origin."""
    rays = cam.ray_directions()
    t = (normal @ point) / (rays @ normal)
    return np.where(t > 0, t, 0).astype(np.float32)


def test_voxel_grid_matches_open3d(rng: np.random.Generator) -> None:
    o3d = _lazy.open3d()
    pts = rng.uniform([-0.1, -0.1, 0.1], [0.1, 0.1, 0.4], size=(20_000, 3))
    ours, _ = voxel_downsample(pts, 0.004, origin=pts.min(0) - 0.002)
    theirs = np.asarray(
        o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts)).voxel_down_sample(0.004).points
    )
    assert len(ours) == len(theirs)
    order = lambda a: a[np.lexsort(a.T)]  # noqa: E731
    np.testing.assert_allclose(order(ours), order(theirs), atol=1e-12)


def test_voxel_grid_default_anchor_is_the_frame_origin() -> None:
    pts = np.array([[0.0011, 0.0, 0.0], [0.0039, 0.0, 0.0], [0.0041, 0.0, 0.0]])
    out, _ = voxel_downsample(pts, 0.004)
    np.testing.assert_allclose(out, [[0.0025, 0, 0], [0.0041, 0, 0]])


def test_statistical_outliers_match_open3d(rng: np.random.Generator) -> None:
    o3d = _lazy.open3d()
    pts = np.vstack([rng.normal(size=(2000, 3)) * 0.01, rng.uniform(-0.2, 0.2, size=(30, 3))])
    keep = statistical_outliers(pts, 16, 2.0)
    _, idx = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts)).remove_statistical_outlier(
        16, 2.0
    )
    expected = np.zeros(len(pts), bool)
    expected[np.asarray(idx)] = True
    np.testing.assert_array_equal(keep, expected)
    assert keep[2000:].sum() < 5  # the scattered points go


@pytest.mark.parametrize(("neighbors", "radius"), [(1, 0.003), (2, 0.006), (5, 0.01)])
def test_radius_outliers_match_open3d(
    rng: np.random.Generator, neighbors: int, radius: float
) -> None:
    """The compiled grid search keeps exactly the points Open3D's remove_radius_outlier keeps:
    a voxel-grid cloud of a cane and a leaf at 2 mm, with scattered points and isolated pairs."""
    o3d = _lazy.open3d()
    t = rng.uniform(0, 0.2, 20_000)
    cane = np.c_[t, 0.01 * np.sin(20 * t), 0.2 + 0.002 * rng.normal(size=t.size)]
    leaf = np.c_[rng.uniform(-0.05, 0, (8000, 2)), 0.25 + rng.normal(0, 0.001, 8000)]
    far = rng.uniform(-0.3, 0.3, (40, 3)) + [0, 0, 0.3]
    pairs = np.repeat(far[:10], 2, axis=0) + [0.004, 0, 0] * np.tile([[0], [1]], (10, 1))
    pts, _ = voxel_downsample(np.vstack([cane, leaf, far, pairs]), 0.002)
    keep = radius_outliers(pts, neighbors, radius)
    _, idx = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts)).remove_radius_outlier(
        neighbors, radius
    )
    expected = np.zeros(len(pts), bool)
    expected[np.asarray(idx)] = True
    np.testing.assert_array_equal(keep, expected)
    assert 40 <= (~keep).sum() < 0.05 * len(pts)  # the scattered points go, the vine stays


def test_the_radius_rule_drops_a_floating_speckle_and_keeps_a_thin_cane() -> None:
    """A few pixels of depth floating in front of a wall (a D405 speckle) go; a 3-pixel wide
    cane stays whole; "none" keeps the speckle; an unknown rule is named."""
    cam = d405("848x480")
    depth = plane_depth(cam, np.array([0.0, 0.0, -1.0]), np.array([0, 0, 0.30]))
    depth[:, 400:403] = 0.20  # a thin cane, about 0.7 mm wide
    depth[100:106, 100:106] = 0.12  # a 6x6-pixel speckle, 18 cm in front of the wall
    cfg = PerceptionConfig(voxel_size=0.002)
    kept = perceive(depth, cam, cfg, normals=False).points
    assert not np.any(kept[:, 2] < 0.15)
    cane = kept[np.abs(kept[:, 2] - 0.20) < 0.005]
    none = perceive(depth, cam, PerceptionConfig(voxel_size=0.002, outlier_rule="none"))
    none_cane = none.points[np.abs(none.points[:, 2] - 0.20) < 0.005]
    assert len(cane) > 50 and len(cane) == len(none_cane)
    assert np.any(none.points[:, 2] < 0.15)
    with pytest.raises(InputError, match="outlier rule"):
        PerceptionConfig(outlier_rule="median")


@pytest.mark.parametrize("voxel", [0.002, 0.004])
def test_statistical_outliers_grid_search_equals_the_tree(
    rng: np.random.Generator, voxel: float
) -> None:
    """With the cloud's spacing, the compiled grid search gives the k-d tree's answer: a
    voxel-grid cloud of canes and a leaf, with far outliers the cells leave to the tree."""
    from scipy.spatial import KDTree

    from vinetwin import _outlier_kernels

    t = rng.uniform(0, 0.2, 20_000)
    cane = np.c_[t, 0.01 * np.sin(20 * t), 0.2 + 0.002 * rng.normal(size=t.size)]
    leaf = np.c_[rng.uniform(-0.05, 0, (8000, 2)), 0.25 + rng.normal(0, 0.001, 8000)]
    far = rng.uniform(-0.3, 0.3, (40, 3)) + [0, 0, 0.3]
    pts, _ = voxel_downsample(np.vstack([cane, leaf, far]), voxel)
    mean_d = _outlier_kernels.knn_mean_distance(pts, 16, 3 * voxel, 3, 2)
    tree_d = KDTree(pts).query(pts, k=16)[0].mean(axis=1)
    solved = ~np.isnan(mean_d)
    assert solved.mean() > 0.9 and (~solved).sum() >= 10  # the far points go to the tree
    np.testing.assert_allclose(mean_d[solved], tree_d[solved], rtol=1e-12, atol=1e-15)
    np.testing.assert_array_equal(
        statistical_outliers(pts, 16, 2.0, spacing=voxel), statistical_outliers(pts, 16, 2.0)
    )


@pytest.mark.parametrize("voxel", [0.002, 0.004])
def test_fused_perception_pass_equals_the_two_steps(
    voxel: float, monkeypatch: pytest.MonkeyPatch
) -> None:
    """`depth_voxel_band` over all rows (one pass) gives the voxels of `organised_points`
    followed by `voxel_grid`, in the same order, with the same points and normal sums to
    rounding, on a noisy scene with canes, a slanted leaf and flying pixels; and so does the
    chain's pass in 2 and 3 bands of rows run in threads and merged in order
    (`cloud._depth_voxels`)."""
    from vinetwin import _cloud_kernels, cloud

    cam = d405("848x480")
    rng = np.random.default_rng(5)
    depth = plane_depth(cam, np.array([0.3, 0.1, -0.95]), np.array([0, 0, 0.3]))
    depth[depth > 0.38] = 0
    depth[:, 300:340] = 0.15
    depth[200:230, :] = 0.18
    depth = (depth + rng.normal(0, 2e-4, depth.shape) * (depth > 0)).astype(np.float32)
    depth[rng.random(depth.shape) < 0.02] = np.nan
    args = (depth, cam.fx, cam.fy, cam.cx, cam.cy, 1e-6, 0.4, 0.03, 2)
    o = (0.0005, -0.0003, 0.0001)
    pts, nrm = _cloud_kernels.organised_points(*args, True)
    a, an = _cloud_kernels.voxel_grid(pts, nrm, voxel, *o, True)
    whole = _cloud_kernels.depth_voxel_band(*args, voxel, *o, 0, depth.shape[0])
    b, bn = _cloud_kernels.merge_voxel_bands(*whole, np.array([len(whole[3])]))
    assert len(a) > 1000
    np.testing.assert_allclose(b, a, rtol=0, atol=1e-15)
    np.testing.assert_allclose(bn, an, rtol=1e-12, atol=1e-18)
    calls: list[tuple[int, int]] = []
    band = _cloud_kernels.depth_voxel_band

    def counted(*a: Any) -> Any:
        calls.append((a[-2], a[-1]))
        return band(*a)

    monkeypatch.setattr(_cloud_kernels, "depth_voxel_band", counted)
    monkeypatch.setattr(cloud, "_MIN_BAND_PIXELS", 1000)
    cfg = PerceptionConfig(min_depth=0.0, max_depth=0.4, edge_threshold=0.03, voxel_size=voxel)
    for threads in (2, 3):
        calls.clear()
        c, cn = cloud._depth_voxels(depth, cam, cfg, 2, o, threads)
        calls.sort()
        assert len(calls) == threads and calls[0][0] == 0 and calls[-1][1] == cam.height
        assert all(calls[i][1] == calls[i + 1][0] for i in range(threads - 1))
        np.testing.assert_allclose(c, a, rtol=0, atol=1e-15)
        np.testing.assert_allclose(cn, an, rtol=1e-12, atol=1e-18)


@pytest.mark.parametrize("tilt_deg", [0, 30, 55])
def test_normals_of_a_tilted_plane(tilt_deg: float) -> None:
    cam = d405("848x480")
    t = np.radians(tilt_deg)
    n_true = np.array([np.sin(t), 0.0, -np.cos(t)])  # facing the camera
    depth = plane_depth(cam, n_true, np.array([0, 0, 0.2]))
    cloud = perceive(depth, cam, PerceptionConfig(max_depth=0.5))
    assert cloud.normals is not None and len(cloud) > 500
    angles = np.degrees(np.arccos(np.clip(cloud.normals @ n_true, -1, 1)))
    assert np.median(angles) < 0.5 and angles.max() < 5
    # points lie on the plane (voxel centroids of a plane stay on it)
    assert np.abs((cloud.points - [0, 0, 0.2]) @ n_true).max() < 1e-4


def test_depth_threshold_and_flying_pixels() -> None:
    cam = d405("480x270")
    depth = np.full((cam.height, cam.width), 0.45, np.float32)  # a wall beyond max_depth
    depth[:, 200:240] = 0.15  # a cane
    depth[:, 240] = 0.30  # a smeared column between cane and wall
    cloud = perceive(depth, cam, PerceptionConfig(max_depth=0.40, outlier_rule="none"))
    z = cloud.points[:, 2]
    assert z.max() < 0.151  # the wall is cut and the flying pixels are dropped
    assert np.all(np.einsum("ij,ij->i", cloud.normals, cloud.points) < 0)  # normals face the camera
    # the flying-pixel filter is what drops the smeared column: without it the deprojection
    # keeps it (perception then drops it too, as a rim without a normal: one pixel wide)
    from vinetwin import _cloud_kernels

    args = (depth, cam.fx, cam.fy, cam.cx, cam.cy, 1e-6, 0.40)
    raw, _ = _cloud_kernels.organised_points(*args, 0.0, 2, False)
    filtered, _ = _cloud_kernels.organised_points(*args, 0.03, 2, False)
    assert raw[:, 2].max() > 0.29 and filtered[:, 2].max() < 0.151
    no_filter = perceive(
        depth, cam, PerceptionConfig(max_depth=0.40, edge_threshold=0, outlier_rule="none"),
        normals=False,
    )  # fmt: skip
    assert no_filter.points[:, 2].max() < 0.151


def test_flying_pixel_mask_follows_its_rule_at_every_pixel(rng: np.random.Generator) -> None:
    """The compiled keep mask is the rule written with numpy: in range, and not the far side
    (z - zn > threshold * zn) of a jump to any valid 4-neighbour; borders, NaN and zeros too."""
    from vinetwin import _cloud_kernels

    depth = rng.uniform(0.1, 0.5, (270, 480)).astype(np.float32)
    depth[rng.random(depth.shape) < 0.2] = 0.0
    depth[rng.random(depth.shape) < 0.05] = np.nan
    depth[40:80, 100:160] = 0.2  # flat patches: long runs without a jump
    dmin, dmax, t = 1e-6, 0.4, 0.03
    z = depth.astype(np.float64)
    ok = (z > dmin) & (z <= dmax)
    far = np.zeros(z.shape, bool)
    pad = np.pad(z, 1, constant_values=np.nan)
    for dv, du in ((-1, 0), (1, 0), (0, -1), (0, 1)):
        zn = pad[1 + dv : 1 + dv + z.shape[0], 1 + du : 1 + du + z.shape[1]]
        with np.errstate(invalid="ignore"):
            far |= (zn > dmin) & (zn <= dmax) & (z > zn) & (z - zn > t * zn)
    expected = ok & ~far
    for cuts in ((0, 270), (0, 101, 270)):  # one band of rows, and two
        keep = np.zeros(depth.shape, bool)
        for v0, v1 in itertools.pairwise(cuts):
            _cloud_kernels._keep_rows(depth, dmin, dmax, t, keep, v0, v1)
        np.testing.assert_array_equal(keep, expected)
    keep = np.zeros(depth.shape, bool)  # no flying-pixel filter: the range alone
    _cloud_kernels._keep_rows(depth, dmin, dmax, 0.0, keep, 0, 270)
    np.testing.assert_array_equal(keep, ok)
    assert 0.2 < expected.mean() < 0.6


def test_points_do_not_depend_on_asking_for_normals() -> None:
    """Live clouds (no normals) and references (normals) sample a depth image alike."""
    cam = d405("480x270")
    rng = np.random.default_rng(3)
    depth = np.full((cam.height, cam.width), 0.0, np.float32)
    depth[:, 200:206] = 0.15 + rng.normal(0, 2e-4, (cam.height, 6))  # a thin cane
    depth[100:104, :] = 0.20  # a cane across
    a = perceive(depth, cam, PerceptionConfig(), normals=True)
    b = perceive(depth, cam, PerceptionConfig(), normals=False)
    assert len(a.points) > 30 and b.normals is None
    np.testing.assert_array_equal(a.points, b.points)


@pytest.mark.parametrize("fill", [0.0, np.nan, np.inf, -1.0])
def test_empty_or_invalid_images_give_empty_clouds(fill: float) -> None:
    cam = d405("480x270")
    cloud = perceive(np.full((cam.height, cam.width), fill, np.float32), cam)
    assert (
        isinstance(cloud, Cloud)
        and cloud.empty
        and cloud.normals is not None
        and cloud.normals.shape == (0, 3)
    )


def test_wrong_image_size_is_named() -> None:
    with pytest.raises(InputError, match="expects"):
        perceive(np.zeros((10, 10), np.float32), d405())


def test_config_round_trip() -> None:
    cfg = PerceptionConfig(voxel_size=0.002)
    assert PerceptionConfig.from_dict(cfg.to_dict() | {"future": 1}) == cfg


def test_perception_off_the_main_thread_gives_the_same_cloud() -> None:
    """Perception in another thread (the web app's handlers) gives the same cloud."""
    import threading

    cam = d405("848x480")
    depth = plane_depth(cam, np.array([0.3, 0.1, -0.95]), np.array([0, 0, 0.25]))
    depth[:, 300:340] = 0.15
    out: dict[str, Cloud] = {}
    t = threading.Thread(target=lambda: out.update(c=perceive(depth, cam, PerceptionConfig())))
    t.start()
    t.join()
    main = perceive(depth, cam, PerceptionConfig())
    assert len(main) > 500 and len(out["c"]) == len(main)
    np.testing.assert_allclose(out["c"].points, main.points, atol=1e-12)
    assert main.normals is not None and out["c"].normals is not None
    np.testing.assert_allclose(out["c"].normals, main.normals, atol=1e-9)


def test_decimation_samples_the_same_rays_and_keeps_the_surface() -> None:
    """`decimation=2` deprojects pixel (2u, 2v) along the same ray as the full image does, and
    on a tilted plane gives the same surface: points on the plane, normals within 1 degree of
    the full chain's, voxels at least 85% of its (each voxel has a quarter of the pixels)."""
    cam = d405("848x480")
    small = cam.decimated(2)
    uv = np.array([[0, 0], [211, 97], [423, 239]], float)
    z = np.array([0.2, 0.25, 0.3])
    np.testing.assert_allclose(
        small.deproject_pixels(uv, z), cam.deproject_pixels(2 * uv, z), atol=1e-12
    )
    n_true = np.array([0.2, -0.1, -1.0]) / np.linalg.norm([0.2, -0.1, -1.0])
    depth = plane_depth(cam, n_true, np.array([0, 0, 0.25]))
    full = perceive(depth, cam, PerceptionConfig(voxel_size=0.002))
    half = perceive(depth, cam, PerceptionConfig(voxel_size=0.002, decimation=2))
    assert 0.85 * len(full) <= len(half) <= len(full)
    assert half.normals is not None and full.normals is not None
    assert np.abs((half.points - [0, 0, 0.25]) @ n_true).max() < 1e-4
    assert np.degrees(np.arccos(np.clip(half.normals @ n_true, -1, 1))).max() < 1.0
    assert np.degrees(np.arccos(np.clip(full.normals @ n_true, -1, 1))).max() < 1.0
    for bad in (0, 9, 1.5, True):
        with pytest.raises(InputError, match="decimation"):
            PerceptionConfig(decimation=bad)  # type: ignore[arg-type]


def test_bands_run_in_order_on_threads_and_raise_a_band_s_error() -> None:
    """`_bands.run` calls each band of rows once, the first in the calling thread, returns their
    results in band order, and raises an exception from any band; `_bands.cuts` splits rows
    into bands of about equal work."""
    import threading

    from vinetwin import _bands

    work = np.concatenate([[0], np.cumsum([0, 5, 5, 0, 0, 10, 0, 10, 0, 0])])  # 10 rows
    cuts = _bands.cuts(work, 3)
    assert cuts == [0, 3, 6, 10]
    assert [int(work[b] - work[a]) for a, b in itertools.pairwise(cuts)] == [10, 10, 10]
    assert _bands.cuts(work, 1) == [0, 10]
    main = threading.get_ident()
    seen: list[tuple[int, int, bool]] = []

    def band(scale: int, v0: int, v1: int) -> list[int]:
        seen.append((v0, v1, threading.get_ident() == main))
        return [scale * v for v in range(v0, v1)]

    out = _bands.run(band, (2,), [0, 3, 7, 10])
    assert out == [[0, 2, 4], [6, 8, 10, 12], [14, 16, 18]]
    assert sorted(seen) == [(0, 3, True), (3, 7, False), (7, 10, False)]

    def failing(v0: int, v1: int) -> int:
        if v0 == 5:
            raise ValueError("band 2")
        return v1 - v0

    with pytest.raises(ValueError, match="band 2"):
        _bands.run(failing, (), [0, 5, 10])


def test_import_sets_the_openmp_spin_count_unless_the_environment_does() -> None:
    """`import vinetwin` sets GOMP_SPINCOUNT (read by libgomp when it loads) to
    `vinetwin.GOMP_SPINCOUNT`, and keeps a value the environment already holds."""
    import os
    import subprocess
    import sys

    import vinetwin

    code = "import os, vinetwin; print(os.environ['GOMP_SPINCOUNT'])"
    env = {k: v for k, v in os.environ.items() if k != "GOMP_SPINCOUNT"}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    assert out.stdout.strip() == vinetwin.GOMP_SPINCOUNT == "10000"
    env["GOMP_SPINCOUNT"] = "123"
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    assert out.stdout.strip() == "123"
