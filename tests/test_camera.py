"""The D405 camera model: presets, projection round trips, noise formula, RealSense intrinsics."""

from __future__ import annotations

import math

import numpy as np
import pytest

from vinetwin.camera import D405_RESOLUTIONS, CameraModel, d405
from vinetwin.errors import CameraError, InputError


@pytest.mark.parametrize(
    ("res", "min_depth"),
    [
        ("1280x720", 0.100),
        ("848x480", 0.070),
        ("640x480", 0.055),
        ("640x360", 0.055),
        ("480x270", 0.045),
    ],
)
def test_presets(res: str, min_depth: float) -> None:
    cam = d405(res)
    w, h = map(int, res.split("x"))
    assert (cam.width, cam.height) == (w, h)
    assert cam.min_depth == min_depth
    assert cam.depth_unit == pytest.approx(1e-4)
    assert cam.baseline == pytest.approx(0.018)
    hfov, vfov = cam.fov_deg
    if w * 9 == h * 16:
        assert hfov == pytest.approx(87.0, abs=1e-9)
        assert 54 < vfov < 60
    else:
        assert vfov == pytest.approx(58.0, abs=1e-9)
    assert cam.fx == cam.fy  # square pixels


def test_all_resolutions_listed() -> None:
    assert set(D405_RESOLUTIONS) == {"1280x720", "848x480", "640x480", "640x360", "480x270"}
    with pytest.raises(CameraError, match="choose one of"):
        d405("1920x1080")


def test_noise_rms_matches_intel_model() -> None:
    cam = d405("848x480")
    # z^2 * subpixel / (f * B): at 15 cm about 0.2 mm, at 50 cm about 2.2 mm for f ~ 447 px
    assert cam.depth_noise_rms(0.15) == pytest.approx(0.15**2 * 0.08 / (cam.fx * 0.018))
    assert 0.15e-3 < cam.depth_noise_rms(0.15) < 0.26e-3
    assert 1.6e-3 < cam.depth_noise_rms(0.50) < 2.9e-3


def test_project_deproject_round_trip(rng: np.random.Generator) -> None:
    cam = d405("848x480")
    pts = np.column_stack(
        [rng.uniform(-0.1, 0.1, 100), rng.uniform(-0.05, 0.05, 100), rng.uniform(0.1, 0.5, 100)]
    )
    uv, z = cam.project(pts)
    np.testing.assert_allclose(cam.deproject_pixels(uv, z), pts, atol=1e-12)
    # the principal point deprojects onto the optical axis
    np.testing.assert_allclose(
        cam.deproject_pixels([[cam.cx, cam.cy]], [0.3]), [[0, 0, 0.3]], atol=1e-15
    )


def test_deproject_image_skips_invalid() -> None:
    cam = d405("480x270")
    depth = np.zeros((270, 480), np.float32)
    depth[100, 200] = 0.25
    depth[10, 10] = np.nan
    pts, mask = cam.deproject(depth)
    assert pts.shape == (1, 3) and mask.sum() == 1
    uv, _z = cam.project(pts)
    np.testing.assert_allclose(uv[0], [200, 100], atol=1e-6)
    with pytest.raises(InputError, match="shape"):
        cam.deproject(np.zeros((10, 10), np.float32))
    with pytest.raises(InputError, match="float metres"):
        cam.deproject(np.zeros((270, 480), np.uint16))


def test_points_behind_camera_project_to_nan() -> None:
    uv, _ = d405().project([[0, 0, -1.0]])
    assert np.all(np.isnan(uv))


def test_bad_models_are_refused() -> None:
    with pytest.raises(CameraError, match="focal"):
        CameraModel(width=10, height=10, fx=-1, fy=1, cx=5, cy=5)
    with pytest.raises(CameraError, match="depth range"):
        CameraModel(width=10, height=10, fx=1, fy=1, cx=5, cy=5, min_depth=1.0, max_depth=0.5)
    with pytest.raises(CameraError, match="finite"):
        CameraModel(width=10, height=10, fx=math.nan, fy=1, cx=5, cy=5)


def test_from_realsense_intrinsics() -> None:
    rs = pytest.importorskip("pyrealsense2")
    intr = rs.intrinsics()
    intr.width, intr.height = 848, 480
    intr.fx, intr.fy, intr.ppx, intr.ppy = 431.2, 430.8, 421.7, 238.9
    cam = CameraModel.from_realsense(intr, depth_scale=1e-4)
    assert (cam.fx, cam.cy, cam.min_depth) == pytest.approx((431.2, 238.9, 0.07))  # float32 in rs
    # our deprojection equals librealsense's own
    for u, v, z in [(100, 50, 0.2), (700, 400, 0.45)]:
        ours = cam.deproject_pixels([[u, v]], [z])[0]
        theirs = rs.rs2_deproject_pixel_to_point(intr, [u, v], z)
        np.testing.assert_allclose(ours, theirs, atol=1e-6)


def test_scaled_and_dict_round_trip() -> None:
    cam = d405("1280x720")
    small = cam.scaled(640, 360)
    assert small.fx == pytest.approx(cam.fx / 2)
    assert small.cx == pytest.approx((640 - 1) / 2)
    assert CameraModel.from_dict(cam.to_dict()) == cam
