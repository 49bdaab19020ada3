"""vinetwin's own z-buffer rasteriser, compiled (numba) on the CPU: the `raster` backend."""

from __future__ import annotations

import logging
import threading
from typing import Any

import numpy as np
import numpy.typing as npt

from vinetwin.camera import CameraModel
from vinetwin.frames import check_pose
from vinetwin.render.backends._base import DepthImage, check_mesh
from vinetwin.render.backends._pieces import (
    FRUSTUM_MARGIN_PX,
    frustum_hits,
    mesh_pieces,
    piece_corners,
)

log = logging.getLogger(__name__)

RASTER_PIECE_FACES = 1024
"""The raster backend holds the mesh as spatially compact pieces of at most this many faces, each
with its own vertices, and projects and draws only the pieces whose bounding box meets the
view's frustum. /tmp runs on views around the dense vine's poses: 4.9 ms a view with pieces of
512-1024 faces, 5.4 with 2048, 6.3 with 4096 and 16384 (more of the vine projected for nothing),
5.2 with 256."""
RASTER_ZNEAR = 1e-3
"""The raster backend's near plane (m): what lies nearer the camera is clipped away (a D405
sees nothing nearer than 7 cm)."""


def closed_outward(vertices: npt.NDArray[np.float32], faces: npt.NDArray[np.uint32]) -> bool:
    """Whether the mesh is a closed surface, consistently wound, its faces facing outward
    (positive enclosed volume): then a face seen from behind is always hidden behind one seen
    from the front. 0.04 s for the dense vine's 897k faces, where trimesh's `is_watertight`,
    `is_winding_consistent` and `volume` take 1.5 s, which each export worker would pay."""
    from vinetwin import _mesh_kernels  # compiled: loaded when first needed

    if not len(faces):
        return True
    F = np.ascontiguousarray(faces, dtype=np.int64)
    if not _mesh_kernels.closed_consistent(F, len(vertices)):
        return False
    return _mesh_kernels.signed_volume(np.ascontiguousarray(vertices, dtype=np.float64), F) > 0


class RasterBackend:
    """vinetwin's z-buffer rasteriser (`render._zbuffer_kernels.raster_pieces`, compiled, one
    thread): the mesh in pieces (`RASTER_PIECE_FACES`), those in the view's frustum projected vertex by vertex and
    drawn triangle by triangle, each pixel centre keeping its nearest depth. The image is the
    one a ray cast through each pixel centre sees (`tests/test_render.py`: Open3D's, to
    micrometres), with no OpenGL and no GPU.

    `two_sided`: draw each face from both sides, as a ray caster sees it (True), or only from
    the front (False: a face seen from behind, its vertices clockwise in the image, is left
    out, as OpenGL's backends leave it). On a closed surface whose faces all face outward (a
    cane's tube) the two give the same image, since its front faces hide its back ones, and
    front faces alone take half the time (dense vine: 4.9 against 9.9 ms a view). None (the
    default) decides by the mesh (`closed_outward`): front faces alone for a closed, outward
    surface (the generated and imported vines), both sides otherwise (a reconstruction's open
    TSDF surface, where culling lost 0-52 pixels a view and changed up to 18 more: an inner
    face seen through an opening)."""

    name = "raster"

    def __init__(
        self, vertices: Any, faces: Any, camera: CameraModel, two_sided: bool | None = None
    ) -> None:
        V, F = check_mesh(vertices, faces)
        self.camera = camera
        if two_sided is None:
            two_sided = not closed_outward(V, F)
            if two_sided:
                log.info("raster: the mesh is not closed and outward-facing: both sides drawn")
        self.two_sided = bool(two_sided)
        """Faces drawn from both sides (see the class)."""
        pieces = mesh_pieces(V, F, RASTER_PIECE_FACES)
        self._corners = piece_corners(V, F, pieces)
        self.pieces = len(pieces)
        """The mesh's pieces (`RASTER_PIECE_FACES` faces at most)."""
        self.drawn = len(pieces)
        """Pieces the last view drew (of `pieces`)."""
        # each piece's own vertices in one block (a vertex shared by two pieces is in both), its
        # faces indexing them: a view projects only the blocks of the pieces it draws
        verts, tris, vstart, fstart = [], [], [0], [0]
        for idx in pieces:
            used, local = np.unique(F[idx], return_inverse=True)
            verts.append(V[used])
            tris.append(local.reshape(-1, 3) + vstart[-1])
            vstart.append(vstart[-1] + len(used))
            fstart.append(fstart[-1] + len(idx))
        self._V = np.ascontiguousarray(np.concatenate(verts) if verts else V[:0], np.float64)
        tri = np.concatenate(tris) if tris else np.zeros((0, 3), np.int64)
        self._F = np.ascontiguousarray(tri, np.int32 if len(self._V) < 2**31 else np.int64)
        self._vstart = np.asarray(vstart, np.int64)
        self._fstart = np.asarray(fstart, np.int64)
        self._P = np.empty((len(self._V), 4), np.float64)  # a view's projected vertices
        self._zbuf = np.full((camera.height, camera.width), np.inf, np.float32)
        self._k = np.array([camera.fx, camera.fy, camera.cx, camera.cy, RASTER_ZNEAR], np.float64)
        self._lock = threading.Lock()  # the scratch arrays serve one view at a time

    def render(self, T_vine_camera: Any) -> DepthImage:
        from vinetwin.render import _zbuffer_kernels  # compiled: loaded at the first render

        T = check_pose(T_vine_camera, "T_vine_camera")
        cam = self.camera
        visible = np.flatnonzero(frustum_hits(self._corners, T, cam, FRUSTUM_MARGIN_PX))
        out = np.empty((cam.height, cam.width), np.float32)
        R = np.ascontiguousarray(T[:3, :3], dtype=np.float64)
        t = np.ascontiguousarray(T[:3, 3], dtype=np.float64)
        with self._lock:
            self.drawn = len(visible)
            _zbuffer_kernels.raster_pieces(
                self._V, self._F, visible, self._vstart, self._fstart, R, t, self._k,
                self.two_sided, self._zbuf, self._P,
            )  # fmt: skip
            _zbuffer_kernels.zbuffer_depth(self._zbuf, out)
        return out

    def close(self) -> None:
        pass
