"""Every conversion between vinetwin's conventions and another library's, in one place.

Inside vinetwin: metres, radians, poses `T_a_b` (4x4, `p_a = T_a_b @ p_b`), OpenCV camera frames
(+X right, +Y down, +Z forward), quaternions `wxyz`. Each function here is pinned by a test
against the real library (tests/test_conventions.py): a known point rendered or projected by
that library lands where these functions say.

| library    | its convention                                   | functions                          |
|------------|--------------------------------------------------|------------------------------------|
| pyrender   | OpenGL camera (+X right, +Y up, -Z forward), pose = world_from_camera; principal point at +0.5 | `T_world_camera_opengl`, `pyrender_intrinsics` |
| MuJoCo     | OpenGL camera; quaternions wxyz; `fovy` in degrees | `mujoco_camera_pos_quat`, `mujoco_fovy_deg` |
| Open3D     | `extrinsic` = camera_from_world, OpenCV camera; ray casting puts pixel centres at +0.5 | `open3d_extrinsic`, `open3d_raycast_intrinsics` |
| pycolmap   | `cam_from_world` (3x4), OpenCV camera            | `T_world_camera_from_colmap`, `colmap_cam_from_world` |
| scipy      | quaternions xyzw                                 | `quat_wxyz_to_xyzw`, `quat_xyzw_to_wxyz` |
| viser      | `wxyz` + `position` of world_from_frame; camera frustums OpenCV | `viser_wxyz_position`, `T_from_viser` |
| RealSense  | OpenCV camera, depth in units of `depth_scale` m | `vinetwin.camera.CameraModel.from_realsense` |
"""

from __future__ import annotations

from typing import Any

import numpy as np

from vinetwin.frames import Array, invert, make_pose

#: Maps OpenGL camera coordinates to OpenCV ones (and back: it is its own inverse).
#: p_opencv = FLIP_YZ @ p_opengl.
FLIP_YZ: Array = np.diag([1.0, -1.0, -1.0, 1.0])


# ---------------------------------------------------------------- OpenGL cameras (pyrender, MuJoCo)
def T_world_camera_opengl(T_world_camera: Any) -> Array:
    """World pose of the OpenGL camera frame (pyrender, MuJoCo, trimesh) from an OpenCV one."""
    return np.asarray(T_world_camera, dtype=np.float64) @ FLIP_YZ


def T_world_camera_from_opengl(T_world_camera_gl: Any) -> Array:
    """OpenCV camera pose from the world pose of an OpenGL camera frame."""
    return np.asarray(T_world_camera_gl, dtype=np.float64) @ FLIP_YZ


def pyrender_intrinsics(
    fx: float, fy: float, cx: float, cy: float
) -> tuple[float, float, float, float]:
    """(fx, fy, cx, cy) to give `pyrender.IntrinsicsCamera` for OpenCV intrinsics: pyrender's
    principal point is in continuous coordinates (pixel centres at +0.5)."""
    return fx, fy, cx + 0.5, cy + 0.5


def mujoco_camera_pos_quat(T_world_camera: Any) -> tuple[Array, Array]:
    """(pos, quat wxyz) of a MuJoCo camera placed at an OpenCV camera pose.

    MuJoCo cameras look along their -Z axis with +Y up, like OpenGL.
    """
    T_gl = T_world_camera_opengl(T_world_camera)
    return T_gl[:3, 3].copy(), quat_wxyz_from_matrix(T_gl[:3, :3])


def mujoco_fovy_deg(fy: float, height: int) -> float:
    """MuJoCo's vertical field of view (degrees) for a pinhole with focal fy (px) and height."""
    return float(np.degrees(2.0 * np.arctan(0.5 * height / fy)))


# ---------------------------------------------------------------- Open3D
def open3d_extrinsic(T_world_camera: Any) -> Array:
    """Open3D's `extrinsic` (camera_from_world, OpenCV camera) of a camera pose."""
    return invert(T_world_camera)


def open3d_raycast_intrinsics(K: Any) -> Array:
    """Intrinsic matrix to give `RaycastingScene.create_rays_pinhole` for an OpenCV K.

    Open3D casts the ray of pixel (u, v) through image point (u + 0.5, v + 0.5), while vinetwin
    (like OpenCV and RealSense) puts pixel centres at integer coordinates: shift the principal
    point by half a pixel. pyrender's `IntrinsicsCamera` needs the same shift; MuJoCo's centred
    principal point is (W - 1) / 2 in our convention.
    """
    K2 = np.array(K, dtype=np.float64)
    K2[0, 2] += 0.5
    K2[1, 2] += 0.5
    return K2


def T_world_camera_from_open3d(extrinsic: Any) -> Array:
    """Camera pose from an Open3D `extrinsic` matrix."""
    return invert(np.asarray(extrinsic, dtype=np.float64))


# ---------------------------------------------------------------- COLMAP / pycolmap
def T_world_camera_from_colmap(cam_from_world: Any) -> Array:
    """Camera pose from pycolmap's `cam_from_world` as a 3x4 (or 4x4) matrix.

    Pass `image.cam_from_world().matrix()`; COLMAP cameras are OpenCV cameras.
    """
    M = np.asarray(cam_from_world, dtype=np.float64)
    T = np.eye(4)
    T[:3, :4] = M[:3, :4]
    return invert(T)


def colmap_cam_from_world(T_world_camera: Any) -> Array:
    """pycolmap's `cam_from_world` (3x4) of a camera pose."""
    return invert(T_world_camera)[:3, :4].copy()


# ---------------------------------------------------------------- quaternions (scipy xyzw, viser wxyz)
def quat_wxyz_to_xyzw(q: Any) -> Array:
    """Reorders a wxyz quaternion (vinetwin, viser, MuJoCo, trimesh) to scipy's xyzw."""
    q = np.asarray(q, dtype=np.float64)
    return np.concatenate([q[..., 1:], q[..., :1]], axis=-1)


def quat_xyzw_to_wxyz(q: Any) -> Array:
    """Reorders a scipy xyzw quaternion to wxyz."""
    q = np.asarray(q, dtype=np.float64)
    return np.concatenate([q[..., 3:], q[..., :3]], axis=-1)


def quat_wxyz_from_matrix(R: Any) -> Array:
    """Unit quaternion wxyz (w >= 0) of a 3x3 rotation matrix (Shepperd's method)."""
    R = np.asarray(R, dtype=np.float64)
    tr = np.trace(R)
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = np.array(
            [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
        )
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = np.array(
            [(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s]
        )
    elif R[1, 1] > R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q = np.array(
            [(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s]
        )
    else:
        s = 2.0 * np.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q = np.array(
            [(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s]
        )
    q /= np.linalg.norm(q)
    return -q if q[0] < 0 else q


def matrix_from_quat_wxyz(q: Any) -> Array:
    """3x3 rotation matrix of a wxyz quaternion (normalised first)."""
    w, x, y, z = np.asarray(q, dtype=np.float64).reshape(4) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


# ---------------------------------------------------------------- ROS (geometry_msgs)
def T_from_ros(translation: Any, quat_xyzw: Any) -> Array:
    """A pose from a ROS `Transform` / `Pose`: translation (x, y, z) and quaternion (x, y, z, w)."""
    return make_pose(matrix_from_quat_wxyz(quat_xyzw_to_wxyz(quat_xyzw)), translation)


def ros_quat_xyzw(R: Any) -> Array:
    """The ROS quaternion (x, y, z, w) of a rotation matrix."""
    return quat_wxyz_to_xyzw(quat_wxyz_from_matrix(R))


# ---------------------------------------------------------------- viser
def viser_wxyz_position(T_world_frame: Any) -> tuple[Array, Array]:
    """(wxyz, position) that viser's scene nodes take for a pose T_world_frame.

    viser's camera frustums use the OpenCV camera convention, so a camera pose passes as is.
    """
    T = np.asarray(T_world_frame, dtype=np.float64)
    return quat_wxyz_from_matrix(T[:3, :3]), T[:3, 3].copy()


def T_from_viser(wxyz: Any, position: Any) -> Array:
    """Pose from viser's (wxyz, position), e.g. a transform gizmo's state."""
    return make_pose(matrix_from_quat_wxyz(wxyz), position)
