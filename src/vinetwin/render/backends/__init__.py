"""Depth rendering backends behind one interface.

Every backend renders metric z-depth (float32, metres, OpenCV camera, 0 where nothing is hit) of
a triangle mesh (vine frame) seen by a `CameraModel` at `T_vine_camera`:

- `open3d`: Open3D ray casting (`RaycastingScene`): no OpenGL needed, exact;
- `pyrender`: OpenGL rasterisation, headless through EGL (or OSMesa with PYOPENGL_PLATFORM=osmesa);
- `mujoco`: MuJoCo's offscreen renderer (EGL), the vine drawn from our own buffers in its context;
- `raster`: vinetwin's own z-buffer rasteriser, compiled (numba) on the CPU: no OpenGL needed,
  the image of Open3D's ray casting (every pixel centre takes the depth of the nearest front
  face along its ray), the fastest of the four on a machine without a GPU.

A backend that cannot start raises `BackendUnavailable` with the reason; `get_backend` never
falls back to another backend. Where a user names none ("auto"), `resolve_backend` picks by the
number of views: see `BATCH_BACKEND`, `SINGLE_BACKEND`, `AUTO_MIN_VIEWS`.
"""

from __future__ import annotations

import functools
import logging
from typing import Any, cast

import numpy as np

from vinetwin import _lazy
from vinetwin.camera import CameraModel
from vinetwin.errors import BackendUnavailable, InputError
from vinetwin.render.backends._base import (
    AUTO_MIN_VIEWS,
    BACKENDS,
    BATCH_BACKEND,
    SINGLE_BACKEND,
    BackendName,
    DepthBackend,
    DepthImage,
    check_mesh,
)
from vinetwin.render.backends._egl import _mujoco_gl
from vinetwin.render.backends.mujoco_gl import MujocoBackend
from vinetwin.render.backends.pyrender_gl import PyrenderBackend
from vinetwin.render.backends.raster import RasterBackend
from vinetwin.render.backends.raycast import Open3DBackend, raycasting_scene

__all__ = [
    "AUTO_MIN_VIEWS",
    "BACKENDS",
    "BATCH_BACKEND",
    "SINGLE_BACKEND",
    "BackendName",
    "DepthBackend",
    "DepthImage",
    "MujocoBackend",
    "Open3DBackend",
    "PyrenderBackend",
    "RasterBackend",
    "check_mesh",
    "get_backend",
    "picking_scene",
    "raycaster",
    "raycasting_scene",
    "resolve_backend",
    "scene_backend",
]

log = logging.getLogger(__name__)


def resolve_backend(name: str | None, views: int = 1) -> BackendName:
    """The backend to render `views` views with: `name` when it names one (InputError if
    unknown; never replaced); None or "auto": `BATCH_BACKEND` for `AUTO_MIN_VIEWS` views or
    more where it can start in this process (else a warning naming why), `SINGLE_BACKEND`
    otherwise."""
    if name in BACKENDS:
        return cast(BackendName, name)
    if name not in (None, "auto"):
        raise InputError(
            f"unknown render backend '{name}'; choose auto or one of: {', '.join(BACKENDS)}"
        )
    if views < AUTO_MIN_VIEWS:
        return SINGLE_BACKEND
    why = _cannot_start(BATCH_BACKEND)
    if not why:
        return BATCH_BACKEND
    log.warning("rendering with %s: %s", SINGLE_BACKEND, why)
    return SINGLE_BACKEND


@functools.cache
def _cannot_start(name: BackendName) -> str:
    """Why `name` cannot render in this process ("" when it can), tried once on a tetrahedron."""
    cam = CameraModel(width=16, height=16, fx=20.0, fy=20.0, cx=7.5, cy=7.5)
    V = [[0, 0, 0.3], [0.1, 0, 0.3], [0, 0.1, 0.3], [0, 0, 0.4]]
    F = [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]
    try:
        get_backend(name, V, F, cam).close()
    except BackendUnavailable as exc:
        return str(exc)
    except Exception as exc:  # anything else that stops it here is said, not hidden
        return f"render backend '{name}' failed to start: {type(exc).__name__}: {exc}"
    return ""


def get_backend(
    name: str, vertices: Any, faces: Any, camera: CameraModel, **kwargs: Any
) -> DepthBackend:
    """Creates the named backend; raises BackendUnavailable (with the reason) if it cannot start,
    or InputError for an unknown name."""
    if name == "open3d":
        return Open3DBackend(vertices, faces, camera, **kwargs)
    if name == "pyrender":
        return PyrenderBackend(vertices, faces, camera)
    if name == "mujoco":
        return MujocoBackend(vertices, faces, camera)
    if name == "raster":
        return RasterBackend(vertices, faces, camera, **kwargs)
    raise InputError(f"unknown render backend '{name}'; choose one of: {', '.join(BACKENDS)}")


def picking_scene(renderer: DepthBackend, vertices: Any, faces: Any) -> Any:
    """Open3D's ray-casting scene of a mesh, for picks (`cast_rays`): the renderer's own when it
    ray casts, else one built here, its BVH built now rather than at the first query (75 ms on
    the sample)."""
    if isinstance(renderer, Open3DBackend):
        return renderer.scene
    scene = raycasting_scene(vertices, faces)
    ray = np.array([[0, 0, 0, 0, 0, 1]], np.float32)
    scene.cast_rays(_lazy.open3d().core.Tensor(ray))
    return scene


def raycaster(vertices: Any, faces: Any, camera: CameraModel, **kwargs: Any) -> DepthBackend:
    """The renderer of one view at a time, where a view follows the last (a robot's rendered
    camera, a fusion's frames, the field profile's synthetic captures): `SINGLE_BACKEND`, which
    needs no OpenGL and may be used from any thread. `kwargs` go to its constructor (`threads`,
    `coarse_step`)."""
    return get_backend(SINGLE_BACKEND, vertices, faces, camera, **kwargs)


def scene_backend(
    vertices: Any, faces: Any, camera: CameraModel, *, any_thread: bool = False, threads: int = 0
) -> DepthBackend:
    """The renderer of a simulation's scene, which renders a view per camera frame (hundreds a
    run): `resolve_backend` for a batch (`BATCH_BACKEND` where it can start, else
    `SINGLE_BACKEND` with a warning). `any_thread`: the caller may render from threads other
    than this one (a web server's validations), which MuJoCo allows only with EGL; elsewhere
    `SINGLE_BACKEND`. `threads`: Open3D's ray-casting threads (0: all)."""
    name = resolve_backend(None, AUTO_MIN_VIEWS)
    if name == "mujoco" and any_thread and _mujoco_gl() != "egl":
        name = SINGLE_BACKEND
    kwargs = {"threads": threads} if name == "open3d" and threads else {}
    return get_backend(name, vertices, faces, camera, **kwargs)
