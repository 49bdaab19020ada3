"""MuJoCo's offscreen renderer (EGL), the vine drawn from vinetwin's own buffers in its context:
the `mujoco` backend."""

from __future__ import annotations

import ctypes
import logging
import os
import threading
from typing import Any

import numpy as np
import numpy.typing as npt

from vinetwin import _bands, _lazy
from vinetwin import conventions as cv
from vinetwin.camera import CameraModel
from vinetwin.errors import BackendUnavailable, InputError
from vinetwin.frames import check_pose
from vinetwin.render.backends._base import DepthImage, check_mesh
from vinetwin.render.backends._egl import (
    _egl_reinitialize,
    _egl_release,
)
from vinetwin.render.backends._pieces import (
    FRUSTUM_MARGIN_PX,
    frustum_hits,
    mesh_pieces,
    piece_corners,
)

log = logging.getLogger(__name__)

MUJOCO_STL_FACES = 200_000
"""The most faces MuJoCo's STL reader takes in one file."""
MUJOCO_CHUNK_FACES = 4096
"""The MuJoCo backend holds the vine as spatially compact pieces of at most this many faces (in
its own buffers, or as MuJoCo geoms), and each view draws only the pieces whose bounding box
meets the camera's frustum: OpenGL (llvmpipe on a CPU) otherwise transforms every vertex of the
vine per view, though a D405 15 cm from a cane sees 8-19% of it. The images are the same
(`tests/test_render.py`); the time per view falls with the share culled
(`benchmarks/render.py`)."""

MUJOCO_FLUSH_FACES = 4096
"""Where the MuJoCo backend draws the vine from its own vertex and index buffers (`_VineBuffers`,
in the state `mjr_render` leaves), a `glFlush` follows each run of about this many faces: Mesa's
llvmpipe transforms and bins triangles on the calling thread and rasterises on its own threads
only when the commands are flushed, so MuJoCo's draw (one flush, at the read-back) leaves the
second core idle while the first transforms. Flushed piece by piece, the second core rasterises
what is drawn while the first transforms the next piece: the same image (within 0.1 mm but for
a few pixels), the view in 0.73-0.91x the time (/tmp A/B on views around the poses of four
vines, the two draws interleaved; `docs/results/speed.md`)."""


class MujocoBackend:
    """MuJoCo's offscreen renderer and a camera at the pose; the vine drawn from our own buffers
    in its context (`_VineBuffers`), or, where those cannot be made (or `own_draw` is False),
    as MuJoCo mesh geoms."""

    name = "mujoco"

    def __init__(
        self, vertices: Any, faces: Any, camera: CameraModel, own_draw: bool = True
    ) -> None:
        if "MUJOCO_GL" not in os.environ and not os.environ.get("DISPLAY"):
            os.environ["MUJOCO_GL"] = "egl"
        # PyOpenGL (MuJoCo's EGL, our buffers) says at INFO that its optional C module is missing
        logging.getLogger("OpenGL.acceleratesupport").setLevel(logging.WARNING)
        try:
            mujoco = _lazy.mujoco()
        except Exception as exc:
            raise BackendUnavailable("mujoco", f"cannot import mujoco: {exc}") from exc
        V, F = check_mesh(vertices, faces)
        self.camera = camera
        self._mujoco = mujoco
        pieces = mesh_pieces(V, F, MUJOCO_CHUNK_FACES)
        self._corners = piece_corners(V, F, pieces)  # for the frustum test
        self.pieces = len(pieces)
        """The vine's pieces (`MUJOCO_CHUNK_FACES` faces at most)."""
        self.drawn = len(pieces)
        """Pieces the last view drew (of `pieces`)."""
        self._thread = threading.get_ident()
        self._lock = threading.Lock()
        self._buf = np.empty((camera.height, camera.width), np.float32)
        self._vine: _VineBuffers | None = None
        """The vine in our own OpenGL buffers, drawn flushed piece by piece; None: MuJoCo draws
        its mesh geoms."""
        # Drawn from our buffers, the vine stays out of MuJoCo's model: compiling its meshes
        # and uploading them to OpenGL took 2.7 s for the dense vine (897k faces) and 0.4 s for
        # the sample, the model of the camera alone 0.04 s.
        self._start(V, F, [] if own_draw else pieces)
        if own_draw:
            if self._fused is not None:
                self._vine = _VineBuffers.create(self.renderer, V, F, pieces)
                if self._release is not None:
                    self._release()
            if self._vine is None:  # MuJoCo draws the vine: a model with its geoms
                self.renderer.close()
                self._start(V, F, pieces)

    def _start(
        self,
        V: npt.NDArray[np.float32],
        F: npt.NDArray[np.uint32],
        pieces: list[npt.NDArray[np.int64]],
    ) -> None:
        """The MuJoCo model (a mesh geom `vine<k>` per piece of `pieces`; none: the camera
        alone), its data and its offscreen renderer."""
        mujoco = self._mujoco
        self.model = mujoco.MjModel.from_xml_string(*vine_scene_xml(V, F, self.camera, pieces))
        self.data = mujoco.MjData(self.model)
        self._cam_id = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_CAMERA, "d405")
        geom = mujoco.mjtObj.mjOBJ_GEOM
        self._geoms = np.array(
            [mujoco.mj_name2id(self.model, geom, f"vine{k}") for k in range(len(pieces))],
            dtype=np.int64,
        )
        try:
            _egl_reinitialize()
            self.renderer = mujoco.Renderer(self.model, self.camera.height, self.camera.width)
        except Exception as exc:
            raise BackendUnavailable(
                "mujoco",
                f"cannot create an offscreen context (MUJOCO_GL={os.environ.get('MUJOCO_GL')}): {exc}",
            ) from exc
        self.renderer.enable_depth_rendering()
        self._far = float(self.model.vis.map.zfar * self.model.stat.extent)
        self._release = _egl_release()
        if self._release is not None:
            self._release()  # not current in this thread: any thread may take it (one at a time)
        self._fused = self._fused_readback()

    def _fused_readback(self) -> tuple[float, float] | None:
        """The reverse-Z coefficients `mujoco.Renderer.render` converts the depth buffer with,
        where this MuJoCo's renderer is the one they were read from (MuJoCo 3.3-4.x: its
        rect, context and reverse-Z depth map); None: render through `Renderer.render`."""
        r, mj = self.renderer, self._mujoco
        if not all(hasattr(r, a) for a in ("_rect", "_mjr_context", "_scene", "_gl_context")):
            return None
        depth_map = getattr(mj, "mjtDepthMap", None)
        ctx = r._mjr_context
        if depth_map is None or getattr(ctx, "readDepthMap", None) != depth_map.mjDEPTH_ZEROFAR:
            return None
        if r._gl_context is None:  # no flip to undo (Filament): not what the kernel does
            return None
        extent = self.model.stat.extent
        zfar = np.float32(self.model.vis.map.zfar * extent)
        znear = np.float32(self.model.vis.map.znear * extent)
        c = -(zfar + znear) / (zfar - znear)
        d = -(np.float32(2) * zfar * znear) / (zfar - znear)
        return float(np.float32(-0.5) * c - np.float32(0.5)), float(np.float32(-0.5) * d)

    def render(self, T_vine_camera: Any) -> DepthImage:
        if self._release is None and threading.get_ident() != self._thread:
            # an OSMesa or GLFW context stays current in the thread that made it (another gets
            # an error from deep inside OpenGL); an EGL one is released after each view
            raise BackendUnavailable(
                "mujoco",
                "a MuJoCo renderer renders in the thread that created it, not another "
                f"(MUJOCO_GL={os.environ.get('MUJOCO_GL')}; with egl any thread may)",
            )
        T = check_pose(T_vine_camera, "T_vine_camera")
        with self._lock:
            try:
                return self._render(T)
            finally:
                if self._release is not None:
                    self._release()

    def _render(self, T: Any) -> DepthImage:
        visible = frustum_hits(self._corners, T, self.camera, FRUSTUM_MARGIN_PX)
        if len(self._geoms):  # MuJoCo draws the vine: alpha 0 leaves a piece out of its scene
            self.model.geom_rgba[self._geoms, 3] = visible
        self.drawn = int(np.count_nonzero(visible))
        pos, quat = cv.mujoco_camera_pos_quat(T)
        self.model.cam_pos[self._cam_id] = pos
        self.model.cam_quat[self._cam_id] = quat
        self._mujoco.mj_kinematics(self.model, self.data)
        self._mujoco.mj_camlight(self.model, self.data)
        self.renderer.update_scene(self.data, camera=self._cam_id)
        if self._fused is None:
            depth = self.renderer.render()
            return np.where(depth >= 0.999 * self._far, 0.0, depth).astype(np.float32)
        # what Renderer.render does for depth, the conversion fused in one compiled pass
        from vinetwin.render import _zbuffer_kernels  # compiled: loaded at the first render

        r, mj = self.renderer, self._mujoco
        flags = r._scene.flags
        flags[mj.mjtRndFlag.mjRND_SEGMENT] = flags[mj.mjtRndFlag.mjRND_IDCOLOR] = True
        r._gl_context.make_current()
        mj.mjr_render(r._rect, r._scene, r._mjr_context)  # cleared, the camera's matrices set
        if self._vine is not None:
            self._vine.draw(visible)
        mj.mjr_readPixels(None, self._buf, r._rect, r._mjr_context)
        out = np.empty_like(self._buf)
        args = (self._buf, *self._fused, 0.999 * self._far, out)
        bands = min(_bands.threads(), 2)  # memory-bound: more bands gain nothing
        _bands.run(_zbuffer_kernels.gl_reverse_z_depth, args, _bands.even(out.shape[0], bands))
        return out

    def close(self) -> None:
        with self._lock:
            if self._release is None and threading.get_ident() != self._thread:
                log.debug("MuJoCo renderer left to the process's end: closed from another thread")
                return
            if self._vine is not None:
                self.renderer._gl_context.make_current()
                self._vine.delete()
                self._vine = None
            self.renderer.close()
            if self._release is not None:
                self._release()


class _VineBuffers:
    """The vine's vertices (vine frame, float32) and its faces, piece after piece, in a vertex and
    an index buffer of a MuJoCo renderer's OpenGL context (PyOpenGL on MuJoCo's current context).
    `draw` draws the pieces in view, depth only, in the state MuJoCo's `mjr_render` leaves: the
    offscreen framebuffer cleared, the camera's projection and view matrices, its reverse-Z
    depth test, back faces culled. The image is MuJoCo's own draw of the pieces, up to the
    float32 rounding of vertices MuJoCo re-centres per piece (`tests/test_render.py`)."""

    def __init__(self, gl: Any, buffers: Any, starts: npt.NDArray[np.int64]) -> None:
        self._gl = gl
        self._buffers = buffers
        self._starts = starts  # piece k's faces: starts[k]..starts[k + 1] in the index buffer

    @classmethod
    def create(
        cls,
        renderer: Any,
        vertices: npt.NDArray[np.float32],
        faces: npt.NDArray[np.uint32],
        pieces: list[npt.NDArray[np.int64]],
    ) -> _VineBuffers | None:
        """The buffers in `renderer`'s context (made current, left current), or None where
        PyOpenGL cannot make them there (MuJoCo then draws its geoms: the same image)."""
        try:
            from OpenGL import GL

            renderer._gl_context.make_current()
            idx = np.ascontiguousarray(faces[np.concatenate(pieces)], dtype=np.uint32)
            starts = np.concatenate([[0], np.cumsum([len(p) for p in pieces])]).astype(np.int64)
            V = np.ascontiguousarray(vertices, dtype=np.float32)
            buffers = GL.glGenBuffers(2)
            GL.glBindBuffer(GL.GL_ARRAY_BUFFER, buffers[0])
            GL.glBufferData(GL.GL_ARRAY_BUFFER, V.nbytes, V, GL.GL_STATIC_DRAW)
            GL.glBindBuffer(GL.GL_ELEMENT_ARRAY_BUFFER, buffers[1])
            GL.glBufferData(GL.GL_ELEMENT_ARRAY_BUFFER, idx.nbytes, idx, GL.GL_STATIC_DRAW)
            GL.glBindBuffer(GL.GL_ARRAY_BUFFER, 0)
            GL.glBindBuffer(GL.GL_ELEMENT_ARRAY_BUFFER, 0)
        except Exception as exc:  # no PyOpenGL, or one bound to another platform
            log.debug("MuJoCo draws the vine's geoms: cannot make our own buffers (%s)", exc)
            return None
        return cls(GL, buffers, starts)

    def draw(self, visible: npt.NDArray[np.float64]) -> None:
        """Draws the pieces with `visible` > 0, a flush after each `MUJOCO_FLUSH_FACES` faces."""
        GL, starts = self._gl, self._starts
        GL.glBindBuffer(GL.GL_ARRAY_BUFFER, self._buffers[0])
        GL.glBindBuffer(GL.GL_ELEMENT_ARRAY_BUFFER, self._buffers[1])
        GL.glEnableClientState(GL.GL_VERTEX_ARRAY)
        GL.glVertexPointer(3, GL.GL_FLOAT, 0, None)
        GL.glColorMask(GL.GL_FALSE, GL.GL_FALSE, GL.GL_FALSE, GL.GL_FALSE)
        try:
            pending = 0
            for k in np.flatnonzero(visible):
                n = int(starts[k + 1] - starts[k])
                offset = ctypes.c_void_p(int(starts[k]) * 12)  # 3 uint32 indices per face
                GL.glDrawElements(GL.GL_TRIANGLES, 3 * n, GL.GL_UNSIGNED_INT, offset)
                pending += n
                if pending >= MUJOCO_FLUSH_FACES:
                    GL.glFlush()
                    pending = 0
        finally:
            GL.glColorMask(GL.GL_TRUE, GL.GL_TRUE, GL.GL_TRUE, GL.GL_TRUE)
            GL.glDisableClientState(GL.GL_VERTEX_ARRAY)
            GL.glBindBuffer(GL.GL_ARRAY_BUFFER, 0)
            GL.glBindBuffer(GL.GL_ELEMENT_ARRAY_BUFFER, 0)

    def delete(self) -> None:
        """Frees the buffers (their context current)."""
        self._gl.glDeleteBuffers(2, self._buffers)


def stl_bytes(vertices: npt.NDArray[np.float32], faces: npt.NDArray[np.uint32]) -> bytes:
    """Binary STL of the triangles `faces` (their unit normals, the vertices as float32)."""
    tri = np.asarray(vertices, np.float32)[np.asarray(faces)]  # (n, 3, 3)
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    length = np.linalg.norm(n, axis=1, keepdims=True)
    n = np.divide(n, length, out=np.zeros_like(n), where=length > 0)
    rec = np.zeros(len(tri), dtype=[("n", "<f4", 3), ("v", "<f4", 9), ("attr", "<u2")])
    rec["n"] = n
    rec["v"] = tri.reshape(-1, 9)
    return b"vinetwin vine".ljust(80, b" ") + np.uint32(len(tri)).tobytes() + rec.tobytes()


def vine_scene_xml(
    vertices: npt.NDArray[np.float32],
    faces: npt.NDArray[np.uint32],
    camera: CameraModel,
    pieces: list[npt.NDArray[np.int64]] | None = None,
) -> tuple[str, dict[str, bytes]]:
    """MJCF (and its assets) of a static vine mesh and a D405 camera named `d405`: one mesh geom
    `vine<k>` per piece (`pieces`: face indices; None: pieces of `MUJOCO_STL_FACES`, the most
    MuJoCo's STL reader takes in one file).

    Intrinsics go in through `resolution`, `focalpixel`, `principalpixel` and `sensorsize`, so an
    off-centre principal point and fx != fy are honoured.
    """
    if pieces is None:
        pieces = [
            np.arange(start, min(start + MUJOCO_STL_FACES, len(faces)))
            for start in range(0, max(len(faces), 1), MUJOCO_STL_FACES)
        ]
    assets = {}
    for k, idx in enumerate(pieces):
        if len(idx) > MUJOCO_STL_FACES:
            raise InputError(f"a MuJoCo mesh piece holds at most {MUJOCO_STL_FACES} faces")
        assets[f"vine{k}.stl"] = stl_bytes(vertices, faces[idx])
    meshes = "".join(f'<mesh name="{n[:-4]}" file="{n}"/>' for n in assets)
    geoms = "\n    ".join(
        f'<geom name="{n[:-4]}" type="mesh" mesh="{n[:-4]}" contype="0" conaffinity="0"/>'
        for n in assets
    )
    pixel = 1e-6  # sensor pixel pitch used to express intrinsics (any positive value works)
    c = camera
    # MuJoCo's principal point is the image centre's offset from it, in pixels, both axes
    # (pinned by tests/test_render.py::test_known_point_lands_on_expected_pixel).
    px = (c.width - 1) / 2 - c.cx
    py = (c.height - 1) / 2 - c.cy
    xml = f"""
<mujoco model="vinetwin_vine">
  <compiler boundmass="1e-6" boundinertia="1e-12" inertiafromgeom="false"/>
  <statistic extent="1" center="0 0 0"/>
  <visual>
    <global offwidth="{c.width}" offheight="{c.height}"/>
    <map znear="0.005" zfar="10"/>
    <quality shadowsize="0" offsamples="0"/>
  </visual>
  <asset>{meshes}</asset>
  <worldbody>
    {geoms}
    <camera name="d405" mode="fixed" pos="0 0 0" resolution="{c.width} {c.height}"
            focalpixel="{c.fx} {c.fy}" principalpixel="{px} {py}"
            sensorsize="{c.width * pixel} {c.height * pixel}"/>
  </worldbody>
</mujoco>"""
    return xml, assets
