"""OpenGL rasterisation with pyrender (the maintained fork), headless via EGL or OSMesa: the
`pyrender` backend."""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from vinetwin import conventions as cv
from vinetwin.camera import CameraModel
from vinetwin.errors import BackendUnavailable
from vinetwin.frames import check_pose
from vinetwin.render.backends._base import DepthImage, check_mesh
from vinetwin.render.backends._egl import _keep_egl_display_alive, _require_gl


class PyrenderBackend:
    """OpenGL rasterisation with pyrender (the maintained fork), headless via EGL or OSMesa."""

    name = "pyrender"

    def __init__(self, vertices: Any, faces: Any, camera: CameraModel) -> None:
        _require_gl("pyrender")
        try:
            import pyrender
            import trimesh
        except Exception as exc:  # ImportError, or OpenGL errors raised at import
            raise BackendUnavailable("pyrender", f"cannot import pyrender: {exc}") from exc
        V, F = check_mesh(vertices, faces)
        self.camera = camera
        self._pyrender = pyrender
        self.scene = pyrender.Scene(bg_color=[0, 0, 0, 0])
        self._mesh_node = self.scene.add(
            pyrender.Mesh.from_trimesh(trimesh.Trimesh(V, F, process=False), smooth=False)
        )
        fx, fy, cx, cy = cv.pyrender_intrinsics(camera.fx, camera.fy, camera.cx, camera.cy)
        znear = max(1e-3, 0.5 * camera.min_depth) if camera.min_depth > 0 else 0.01
        self._cam = pyrender.IntrinsicsCamera(
            fx, fy, cx, cy, znear=znear, zfar=max(10.0, 2 * camera.max_depth)
        )
        self._cam_node = self.scene.add(self._cam, pose=np.eye(4))
        try:
            self.renderer = pyrender.OffscreenRenderer(camera.width, camera.height)
        except Exception as exc:
            raise BackendUnavailable(
                "pyrender",
                f"cannot create an offscreen OpenGL context ({os.environ.get('PYOPENGL_PLATFORM')}): {exc}",
            ) from exc
        _keep_egl_display_alive(self.renderer)

    def render(self, T_vine_camera: Any) -> DepthImage:
        T = check_pose(T_vine_camera, "T_vine_camera")
        self.scene.set_pose(self._cam_node, cv.T_world_camera_opengl(T))
        # pyrender rasterises into a 4x multisample buffer and resolves depth by picking one
        # sample, whose position is off the pixel centre: depth then disagrees with ray casting
        # by millimetres along silhouettes. Its SEG mode disables multisampling, so depth is
        # sampled at pixel centres like the other backends.
        flags = self._pyrender.RenderFlags
        out = self.renderer.render(
            self.scene,
            flags=flags.DEPTH_ONLY | flags.SEG,
            seg_node_map={self._mesh_node: (255, 255, 255)},
        )
        depth = out[1] if isinstance(out, tuple) else out
        return np.asarray(depth, dtype=np.float32)

    def close(self) -> None:
        self.renderer.delete()
