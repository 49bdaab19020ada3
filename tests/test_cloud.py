"""The perception chain shared by reference and live clouds: against Open3D, and on scenes
whose answer is known."""

from __future__ import annotations

import numpy as np
import pytest

from vinetwin import _lazy
from vinetwin.camera import d405
from vinetwin.cloud import Cloud, PerceptionConfig, perceive, statistical_outliers, voxel_downsample
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
    cloud = perceive(depth, cam, PerceptionConfig(max_depth=0.40, sor_neighbors=0))
    z = cloud.points[:, 2]
    assert z.max() < 0.151  # the wall is cut and the flying pixels are dropped
    assert np.all(np.einsum("ij,ij->i", cloud.normals, cloud.points) < 0)  # normals face the camera
    # the flying-pixel filter is what drops the smeared column: without it the deprojection
    # keeps it (perception then drops it too, as a rim without a normal: one pixel wide)
    from vinetwin import _kernels

    args = (depth, cam.fx, cam.fy, cam.cx, cam.cy, 1e-6, 0.40)
    raw, _ = _kernels.organised_points(*args, 0.0, 2, False)
    filtered, _ = _kernels.organised_points(*args, 0.03, 2, False)
    assert raw[:, 2].max() > 0.29 and filtered[:, 2].max() < 0.151
    no_filter = perceive(
        depth, cam, PerceptionConfig(max_depth=0.40, edge_threshold=0, sor_neighbors=0),
        normals=False,
    )  # fmt: skip
    assert no_filter.points[:, 2].max() < 0.151


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
