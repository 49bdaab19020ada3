"""What every depth backend shares: the backend names and `auto`'s policy constants, the
`DepthBackend` interface and the mesh check."""

from __future__ import annotations

from typing import Any, Literal, Protocol

import numpy as np
import numpy.typing as npt

from vinetwin.camera import CameraModel
from vinetwin.mesh import check_mesh_arrays

BackendName = Literal["open3d", "pyrender", "mujoco", "raster"]
BACKENDS: tuple[BackendName, ...] = ("open3d", "pyrender", "mujoco", "raster")
DepthImage = npt.NDArray[np.float32]

BATCH_BACKEND: BackendName = "raster"
"""What `auto` (the default of export, the simulation's scene and the web app's previews)
renders `AUTO_MIN_VIEWS` views or more with: the fastest per view of the four on a CPU
(`benchmarks/render.py`, 848x480, this stop's machine: 1.0 ms against MuJoCo's 2.0 and Open3D's
14.2 on the sample, 4.9-5.4 against 9.3-10.0 ms on the dense vine), the image of Open3D's exact
ray casting (`tests/test_render.py`), and it needs no OpenGL. Where it cannot start, `auto` takes
`SINGLE_BACKEND`."""
SINGLE_BACKEND: BackendName = "open3d"
"""What `auto` renders with where `BATCH_BACKEND` cannot start (or for fewer than
`AUTO_MIN_VIEWS` views). Code that renders a few views of a mesh it has just loaded (a reference
rendered on the fly by the servo or the field's rebuilt twin) names it too: it needs no OpenGL
and its scene builds in 0.04-0.4 s."""
AUTO_MIN_VIEWS = 1
"""The batch size from which `auto` takes `BATCH_BACKEND`. It was 100 while MuJoCo compiled the
vine into its model (0.5-0.8 s for the sample, 4-6 s for 900k triangles); with the vine drawn
from our own buffers and a model of the camera alone, MuJoCo starts in 0.07-0.44 s and exports
(`render.export` in a fresh process, its default workers, two runs each, 6924020) took, against
Open3D: the sample 1 view 1.27-1.35 s against 2.21-2.49, 3 views 2.13-2.18 against 2.31-2.37,
10 views 1.94-2.12 against 2.78-2.99, 50 views 2.18-2.43 against 3.95-4.20; the dense vine 1
view 1.44-2.07 against 2.82-3.35 and 4 views 2.34-2.50 against 3.21-3.36; gdc_can1 (987k
triangles) 1.64-1.97 against 3.49-3.61 and 2.23-2.53 against 3.66-3.99 s."""


class DepthBackend(Protocol):
    """What every backend offers."""

    name: str
    camera: CameraModel

    def render(self, T_vine_camera: Any) -> DepthImage:
        """Z-depth image (H, W) float32 metres, 0 where invalid."""
        ...

    def close(self) -> None: ...


def check_mesh(vertices: Any, faces: Any) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.uint32]]:
    """Validates mesh arrays for rendering (MeshError naming the problem); returns float32
    vertices and uint32 faces."""
    V, F = np.asarray(vertices), np.asarray(faces)
    check_mesh_arrays(V, F, "mesh")
    return V.astype(np.float32), F.astype(np.uint32)
