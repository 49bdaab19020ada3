"""The vine as the page draws it: the twin's mesh with at most `WebConfig.display_faces`
triangles.

A browser draws every triangle of the scene each frame, and one that draws WebGL in software
(headless Chromium, a machine without a GPU) redraws the view after each click: on the large
vines a click's preview came 2-3x sooner with 60k triangles drawn (`WebConfig.display_faces`,
`docs/web.md`). Clicks are not affected: the server casts the click's ray on the full mesh
(`AuthoringSession.click`).

`display_mesh` decimates by quadric error (Open3D's `simplify_quadric_decimation`: the bundled
sample 0.4 s, the dense vine 8.8 s, its surface within 0.15 mm of the full mesh's vertices at
the median, 0.9 mm at most). For a mesh over `web.app.SYNC_DECIMATION_FACES` the app first sends
`quick_display_mesh`, vertices clustered on a grid coarse enough for the budget (Open3D's
`simplify_vertex_clustering`, under a second, rough on thin canes), so that the page has a vine
at once, and the decimated one when it is done.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

from vinetwin import _lazy

Mesh = tuple[npt.NDArray[np.float32], npt.NDArray[np.uint32]]


def _o3d_mesh(vertices: np.ndarray, faces: np.ndarray) -> Any:
    o3d = _lazy.open3d()
    return o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(np.asarray(vertices, np.float64)),
        o3d.utility.Vector3iVector(np.asarray(faces, np.int32)),
    )


def _arrays(mesh: Any) -> Mesh:
    return (
        np.asarray(mesh.vertices, np.float32),
        np.asarray(mesh.triangles, np.uint32).reshape(-1, 3),
    )


def quick_display_mesh(vertices: np.ndarray, faces: np.ndarray, max_faces: int) -> Mesh:
    """The mesh with its vertices merged on a grid coarse enough to leave at most `max_faces`
    triangles (the grid's cell grows by half until it does; at most 12 tries, the last kept)."""
    V = np.asarray(vertices, np.float64)
    mesh = _o3d_mesh(V, faces)
    extent = float(np.max(V.max(0) - V.min(0))) if len(V) else 0.0
    # a first cell from the surface's area spread over the budget's triangles
    area = mesh.get_surface_area()
    cell = max(np.sqrt(2.0 * area / max(max_faces, 1)), extent * 1e-4, 1e-6)
    out = mesh
    for _ in range(12):
        out = mesh.simplify_vertex_clustering(cell)
        if len(out.triangles) <= max_faces:
            break
        cell *= 1.5
    return _arrays(out)


def display_mesh(vertices: np.ndarray, faces: np.ndarray, max_faces: int) -> Mesh:
    """The mesh decimated by quadric error to at most `max_faces` triangles."""
    out = _o3d_mesh(vertices, faces).simplify_quadric_decimation(int(max_faces))
    return _arrays(out)
