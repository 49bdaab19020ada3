"""Each conversion in vinetwin.conventions pinned against the real library: a known 3D point is
rendered or projected by that library and must land on the pixel our camera model predicts."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from vinetwin import conventions as cv
from vinetwin import frames as fr
from vinetwin.camera import CameraModel

CAM = CameraModel(width=320, height=240, fx=260.0, fy=260.0, cx=159.5, cy=119.5, name="test")
# A camera looking at the scene from an oblique pose, and a small ball off the optical axis.
T_WORLD_CAMERA = fr.look_at([0.25, -0.35, 0.9], [0.0, 0.05, 0.72])
BALL = np.array([0.05, 0.0, 0.78])
BALL_RADIUS = 0.012


def expected_pixel() -> np.ndarray:
    uv, _ = CAM.project(fr.transform_points(fr.invert(T_WORLD_CAMERA), BALL))
    return uv[0]


def ball_centroid(depth: np.ndarray) -> np.ndarray:
    hit = np.isfinite(depth) & (depth > 0)
    assert hit.sum() > 10, "the ball is not in the image"
    v, u = np.nonzero(hit)
    return np.array([u.mean(), v.mean()])


def ball_mesh():  # type: ignore[no-untyped-def]
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=4, radius=BALL_RADIUS)
    m.apply_translation(BALL)
    return m


def test_expected_pixel_is_off_centre() -> None:
    uv = expected_pixel()
    assert 20 < uv[0] < 300 and 20 < uv[1] < 220
    assert np.linalg.norm(uv - [CAM.cx, CAM.cy]) > 20


def test_open3d_extrinsic_against_raycasting() -> None:
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    m = ball_mesh()
    scene.add_triangles(
        o3d.core.Tensor(np.asarray(m.vertices, np.float32)),
        o3d.core.Tensor(np.asarray(m.faces, np.uint32)),
    )
    rays = scene.create_rays_pinhole(
        intrinsic_matrix=o3d.core.Tensor(cv.open3d_raycast_intrinsics(CAM.K)),
        extrinsic_matrix=o3d.core.Tensor(cv.open3d_extrinsic(T_WORLD_CAMERA)),
        width_px=CAM.width,
        height_px=CAM.height,
    )
    t_hit = scene.cast_rays(rays)["t_hit"].numpy()
    np.testing.assert_allclose(
        ball_centroid(np.where(np.isinf(t_hit), 0, t_hit)), expected_pixel(), atol=0.5
    )
    np.testing.assert_allclose(
        cv.T_world_camera_from_open3d(cv.open3d_extrinsic(T_WORLD_CAMERA)),
        T_WORLD_CAMERA,
        atol=1e-12,
    )


def test_pyrender_opengl_camera_pose() -> None:
    pyrender = pytest.importorskip("pyrender")
    scene = pyrender.Scene()
    scene.add(pyrender.Mesh.from_trimesh(ball_mesh()))
    fx, fy, cx, cy = cv.pyrender_intrinsics(CAM.fx, CAM.fy, CAM.cx, CAM.cy)
    cam = pyrender.IntrinsicsCamera(fx, fy, cx, cy, znear=0.01, zfar=10.0)
    scene.add(cam, pose=cv.T_world_camera_opengl(T_WORLD_CAMERA))
    r = pyrender.OffscreenRenderer(CAM.width, CAM.height)
    # its delete would otherwise terminate the EGL display MuJoCo shares in this process
    from vinetwin.render.backends._egl import _keep_egl_display_alive

    _keep_egl_display_alive(r)
    try:
        depth = r.render(scene, flags=pyrender.RenderFlags.DEPTH_ONLY)
    finally:
        r.delete()
    np.testing.assert_allclose(ball_centroid(depth), expected_pixel(), atol=0.5)


def test_mujoco_camera_pos_quat_and_fovy() -> None:
    mujoco = pytest.importorskip("mujoco")
    pos, quat = cv.mujoco_camera_pos_quat(T_WORLD_CAMERA)
    fovy = cv.mujoco_fovy_deg(CAM.fy, CAM.height)
    xml = f"""
    <mujoco><visual><global offwidth="{CAM.width}" offheight="{CAM.height}"/>
      <map znear="0.01" zfar="20"/></visual>
      <worldbody>
        <geom type="sphere" size="{BALL_RADIUS}" pos="{BALL[0]} {BALL[1]} {BALL[2]}"/>
        <camera name="c" pos="{pos[0]} {pos[1]} {pos[2]}" quat="{quat[0]} {quat[1]} {quat[2]} {quat[3]}" fovy="{fovy}"/>
      </worldbody></mujoco>"""
    model = mujoco.MjModel.from_xml_string(xml)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    with mujoco.Renderer(model, CAM.height, CAM.width) as r:
        r.enable_depth_rendering()
        r.update_scene(data, camera="c")
        depth = r.render()
    depth = np.where(depth > 2.0, 0, depth)  # background reads as MuJoCo's far plane
    np.testing.assert_allclose(ball_centroid(depth), expected_pixel(), atol=0.7)


def test_pycolmap_cam_from_world() -> None:
    pycolmap = pytest.importorskip("pycolmap")
    M = cv.colmap_cam_from_world(T_WORLD_CAMERA)
    rigid = pycolmap.Rigid3d(pycolmap.Rotation3d(M[:, :3]), M[:, 3])
    camera = pycolmap.Camera(
        model="PINHOLE",
        width=CAM.width,
        height=CAM.height,
        params=[CAM.fx, CAM.fy, CAM.cx + 0.5, CAM.cy + 0.5],
    )
    p_cam = rigid * BALL
    uv = camera.img_from_cam(np.asarray(p_cam).reshape(1, 3))[0]
    # COLMAP puts pixel centres at +0.5; vinetwin (like OpenCV) at integers.
    np.testing.assert_allclose(uv - 0.5, expected_pixel(), atol=1e-6)
    np.testing.assert_allclose(
        cv.T_world_camera_from_colmap(rigid.matrix()), T_WORLD_CAMERA, atol=1e-9
    )


def test_scipy_quaternion_order(rng: np.random.Generator) -> None:
    for _ in range(50):
        R = Rotation.random(random_state=int(rng.integers(1 << 30)))
        q_wxyz = cv.quat_wxyz_from_matrix(R.as_matrix())
        np.testing.assert_allclose(
            Rotation.from_quat(cv.quat_wxyz_to_xyzw(q_wxyz)).as_matrix(), R.as_matrix(), atol=1e-12
        )
        np.testing.assert_allclose(cv.matrix_from_quat_wxyz(q_wxyz), R.as_matrix(), atol=1e-12)
        np.testing.assert_allclose(cv.quat_xyzw_to_wxyz(cv.quat_wxyz_to_xyzw(q_wxyz)), q_wxyz)


def test_viser_wxyz_position() -> None:
    vtf = pytest.importorskip("viser.transforms")
    wxyz, pos = cv.viser_wxyz_position(T_WORLD_CAMERA)
    T = vtf.SE3.from_rotation_and_translation(vtf.SO3(wxyz), pos).as_matrix()
    np.testing.assert_allclose(T, T_WORLD_CAMERA, atol=1e-12)
    np.testing.assert_allclose(cv.T_from_viser(wxyz, pos), T_WORLD_CAMERA, atol=1e-12)


def test_opengl_flip_round_trip() -> None:
    T_gl = cv.T_world_camera_opengl(T_WORLD_CAMERA)
    np.testing.assert_allclose(T_gl[:3, 2], -T_WORLD_CAMERA[:3, 2])  # GL looks along -Z
    np.testing.assert_allclose(cv.T_world_camera_from_opengl(T_gl), T_WORLD_CAMERA)
