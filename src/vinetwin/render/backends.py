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

import ctypes
import functools
import logging
import os
import threading
from typing import Any, Literal, Protocol, cast

import numpy as np
import numpy.typing as npt

from vinetwin import _bands, _kernels, _lazy
from vinetwin import conventions as cv
from vinetwin.camera import CameraModel
from vinetwin.errors import BackendUnavailable, InputError
from vinetwin.frames import check_pose
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

MUJOCO_STL_FACES = 200_000
"""The most faces MuJoCo's STL reader takes in one file."""
MUJOCO_CHUNK_FACES = 4096
"""The MuJoCo backend holds the vine as spatially compact pieces of at most this many faces (in
its own buffers, or as MuJoCo geoms), and each view draws only the pieces whose bounding box
meets the camera's frustum: OpenGL (llvmpipe on a CPU) otherwise transforms every vertex of the
vine per view, though a D405 15 cm from a cane sees 8-19% of it. The images are the same
(`tests/test_render.py`); the time per view falls with the share culled
(`benchmarks/render.py`)."""
FRUSTUM_MARGIN_PX = 2.0
"""Pieces within this many pixels outside the image are still drawn."""
MUJOCO_FLUSH_FACES = 4096
"""Where the MuJoCo backend draws the vine from its own vertex and index buffers (`_VineBuffers`,
in the state `mjr_render` leaves), a `glFlush` follows each run of about this many faces: Mesa's
llvmpipe transforms and bins triangles on the calling thread and rasterises on its own threads
only when the commands are flushed, so MuJoCo's draw (one flush, at the read-back) leaves the
second core idle while the first transforms. Flushed piece by piece, the second core rasterises
what is drawn while the first transforms the next piece: the same image (within 0.1 mm but for
a few pixels), the view in 0.73-0.91x the time (/tmp A/B on views around the poses of four
vines, the two draws interleaved; `docs/results/speed.md`)."""

log = logging.getLogger(__name__)


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


def raycasting_scene(vertices: Any, faces: Any, threads: int = 0) -> Any:
    """Open3D's ray-casting scene of a checked mesh (`threads`: 0, all cores): what
    `Open3DBackend` renders with and the web app picks on."""
    o3d = _lazy.open3d()
    V, F = check_mesh(vertices, faces)
    scene = o3d.t.geometry.RaycastingScene(nthreads=threads)
    scene.add_triangles(o3d.core.Tensor(V), o3d.core.Tensor(F))
    return scene


class Open3DBackend:
    """Ray casting with Open3D's `RaycastingScene` (CPU, no OpenGL).

    With `coarse_step` s > 1 it first casts every s-th pixel in both directions, then casts the
    full resolution only within s pixels of a coarse hit. The result equals the exact render for
    every surface at least s pixels wide (a 4.5 mm cane is 2 px wide at 1 m, the D405's maximum
    range) and costs a fraction of it, since a vine fills a small part of the image. Thinner
    features can be missed: pass coarse_step=1 for the exact render.
    """

    name = "open3d"

    def __init__(
        self, vertices: Any, faces: Any, camera: CameraModel, threads: int = 0, coarse_step: int = 2
    ) -> None:
        try:
            o3d = _lazy.open3d()
        except (ImportError, OSError) as exc:  # OSError: libusb missing on a bare Debian
            raise BackendUnavailable("open3d", f"cannot import open3d: {exc}") from exc
        V, F = check_mesh(vertices, faces)
        if coarse_step < 1:
            raise InputError(f"coarse_step must be >= 1, got {coarse_step}")
        self._o3d = o3d
        self.camera = camera
        self.threads = threads
        self.coarse_step = coarse_step
        self.scene = raycasting_scene(V, F, threads)
        # ray directions in the camera frame (z = 1), rotated per pose; t_hit is then z-depth
        self._dirs = camera.ray_directions().astype(np.float32)

    def _cast(self, T: Any, dirs: npt.NDArray[np.float32]) -> npt.NDArray[np.float32]:
        rays = np.empty((dirs.shape[0], 6), np.float32)
        rays[:, :3] = T[:3, 3]
        rays[:, 3:] = dirs @ T[:3, :3].T.astype(np.float32)
        t = self.scene.cast_rays(self._o3d.core.Tensor(rays), nthreads=self.threads)[
            "t_hit"
        ].numpy()
        return np.where(np.isfinite(t), t, 0.0).astype(np.float32)

    def render(self, T_vine_camera: Any) -> DepthImage:
        T = check_pose(T_vine_camera, "T_vine_camera")
        cam = self.camera
        s = self.coarse_step
        if s == 1:
            return self._cast(T, self._dirs.reshape(-1, 3)).reshape(cam.height, cam.width)
        from scipy import ndimage

        coarse_dirs = self._dirs[::s, ::s]
        coarse = self._cast(T, coarse_dirs.reshape(-1, 3)).reshape(coarse_dirs.shape[:2]) > 0
        # every full-resolution pixel within s px of a coarse hit
        near = ndimage.binary_dilation(coarse, iterations=1)
        todo = np.repeat(np.repeat(near, s, axis=0), s, axis=1)[: cam.height, : cam.width]
        if s > 2:
            todo = ndimage.binary_dilation(todo, iterations=s - 1)
        todo = np.asarray(todo, dtype=bool)
        depth = np.zeros((cam.height, cam.width), np.float32)
        if todo.any():
            depth[todo] = self._cast(T, self._dirs[todo])
        return depth

    def close(self) -> None:
        pass


def _require_gl(backend: str) -> None:
    plat = os.environ.get("PYOPENGL_PLATFORM")
    if plat is None and not os.environ.get("DISPLAY"):
        os.environ["PYOPENGL_PLATFORM"] = "egl"
    elif plat not in (None, "egl", "osmesa") and not os.environ.get("DISPLAY"):
        raise BackendUnavailable(
            backend, f"PYOPENGL_PLATFORM={plat} needs a display; use egl or osmesa"
        )


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


def _keep_egl_display_alive(renderer: Any) -> None:
    """pyrender's EGL teardown calls eglTerminate on the display, which EGL shares across the
    whole process: a MuJoCo renderer in the same process then fails with EGL_BAD_DISPLAY. Make
    this renderer destroy only its own context."""
    platform = getattr(renderer, "_platform", None)
    if platform is None or type(platform).__name__ != "EGLPlatform":
        return

    def delete_context() -> None:
        from OpenGL.EGL import eglDestroyContext

        if platform._egl_display is not None and platform._egl_context is not None:
            eglDestroyContext(platform._egl_display, platform._egl_context)
        platform._egl_context = None
        platform._egl_display = None

    platform.delete_context = delete_context


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
    if not len(faces):
        return True
    F = np.ascontiguousarray(faces, dtype=np.int64)
    if not _kernels.closed_consistent(F, len(vertices)):
        return False
    return _kernels.signed_volume(np.ascontiguousarray(vertices, dtype=np.float64), F) > 0


class RasterBackend:
    """vinetwin's z-buffer rasteriser (`_kernels.raster_pieces`, compiled, one thread): the mesh in
    pieces (`RASTER_PIECE_FACES`), those in the view's frustum projected vertex by vertex and
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
        T = check_pose(T_vine_camera, "T_vine_camera")
        cam = self.camera
        visible = np.flatnonzero(frustum_hits(self._corners, T, cam, FRUSTUM_MARGIN_PX))
        out = np.empty((cam.height, cam.width), np.float32)
        R = np.ascontiguousarray(T[:3, :3], dtype=np.float64)
        t = np.ascontiguousarray(T[:3, 3], dtype=np.float64)
        with self._lock:
            self.drawn = len(visible)
            _kernels.raster_pieces(
                self._V, self._F, visible, self._vstart, self._fstart, R, t, self._k,
                self.two_sided, self._zbuf, self._P,
            )  # fmt: skip
            _kernels.zbuffer_depth(self._zbuf, out)
        return out

    def close(self) -> None:
        pass


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
        _bands.run(_kernels.gl_reverse_z_depth, args, _bands.even(out.shape[0], bands))
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


def _mujoco_gl() -> str:
    """The OpenGL platform a MuJoCo renderer made now would use: MUJOCO_GL, else EGL without a
    display (what `MujocoBackend` sets) and GLFW with one (MuJoCo's own default)."""
    gl = os.environ.get("MUJOCO_GL")
    if gl:
        return gl.lower()
    return "glfw" if os.environ.get("DISPLAY") else "egl"


def _mujoco_egl() -> Any:
    """`mujoco.egl` where MuJoCo renders through EGL (`_mujoco_gl`), else None."""
    if _mujoco_gl() != "egl":
        return None
    try:
        from mujoco import egl
    except Exception:
        return None
    return egl


def _egl_reinitialize() -> None:
    """With EGL: initialises again the EGL display MuJoCo keeps for the process, in case a
    library sharing it (pyrender's `OffscreenRenderer.delete`, used directly) terminated it;
    MuJoCo would otherwise fail with EGL_NOT_INITIALIZED until the process ends. A no-op on an
    initialised display."""
    egl = _mujoco_egl()
    if egl is not None and egl.EGL_DISPLAY is not None:
        egl.EGL.eglInitialize(egl.EGL_DISPLAY, None, None)


def _egl_release() -> Any:
    """With EGL: a function releasing this thread's current EGL context (a context is current in
    one thread at a time; released, another thread can take it); else None."""
    egl = _mujoco_egl()
    if egl is None:
        return None

    def release() -> None:
        E = egl.EGL
        if egl.EGL_DISPLAY is not None:
            E.eglMakeCurrent(egl.EGL_DISPLAY, E.EGL_NO_SURFACE, E.EGL_NO_SURFACE, E.EGL_NO_CONTEXT)

    return release


def mesh_pieces(
    vertices: npt.NDArray[np.float32], faces: npt.NDArray[np.uint32], size: int
) -> list[npt.NDArray[np.int64]]:
    """The faces split into spatially compact pieces of at most `size` faces each (indices into
    `faces`): halved at the median of their centres along the longest side, recursively."""
    centres = vertices[faces].mean(axis=1) if len(faces) else np.zeros((0, 3), np.float32)
    # one row per axis, gathered with `take` (C-ordered: reduced along rows 10x faster than the
    # strided copy that fancy indexing makes; 0.9-1.4 -> 0.2-0.6 s for the dense vine's 897k faces)
    rows = np.ascontiguousarray(centres.T)
    out: list[npt.NDArray[np.int64]] = []
    todo = [np.arange(len(faces))]
    while todo:
        idx = todo.pop()
        if len(idx) <= max(size, 1):
            out.append(idx)
            continue
        c = np.take(rows, idx, axis=1)
        axis = int(np.argmax(c.max(axis=1) - c.min(axis=1)))
        half = len(idx) // 2
        order = np.argpartition(c[axis], half)
        todo += [idx[order[:half]], idx[order[half:]]]
    return out


def piece_corners(
    vertices: npt.NDArray[np.float32],
    faces: npt.NDArray[np.uint32],
    pieces: list[npt.NDArray[np.int64]],
) -> npt.NDArray[np.float64]:
    """The 8 corners of each piece's axis-aligned bounding box, (n, 8, 3) in the vertices' frame
    (what `frustum_hits` tests). Each piece's vertices are gathered axis by axis (`take`) and
    reduced along rows: 0.03 s for the dense vine's 256 pieces, against 0.26 s for (n, 3) copies."""
    rows = np.ascontiguousarray(vertices.T)
    lo = np.empty((len(pieces), 3), np.float32)
    hi = np.empty((len(pieces), 3), np.float32)
    for k, idx in enumerate(pieces):
        pts = np.take(rows, faces[idx].ravel(), axis=1)
        lo[k], hi[k] = pts.min(axis=1), pts.max(axis=1)
    pick = np.array([[(k >> a) & 1 for a in range(3)] for k in range(8)], dtype=bool)
    return np.where(pick[None], hi[:, None], lo[:, None]).astype(np.float64)


def frustum_hits(
    corners: npt.NDArray[np.float64], T_vine_camera: Any, camera: CameraModel, margin_px: float
) -> npt.NDArray[np.float64]:
    """1 for each box (`corners`: (n, 8, 3), vine frame) that may show in the camera's image at
    `T_vine_camera`, 0 for each that cannot: all its corners lie behind one side of the view
    frustum (the near plane at 5 mm, the four image borders widened by `margin_px`). A box
    straddling a side is kept, so nothing that shows is ever left out."""
    T = np.asarray(T_vine_camera, dtype=np.float64)
    R, t = T[:3, :3], T[:3, 3]
    P = (corners - t) @ R  # camera frame (OpenCV: x right, y down, z forward)
    x, y, z = P[..., 0], P[..., 1], P[..., 2]
    c = camera
    u0, u1 = -0.5 - margin_px, c.width - 0.5 + margin_px
    v0, v1 = -0.5 - margin_px, c.height - 0.5 + margin_px
    # u = fx x / z + cx >= u0  <=>  fx x + (cx - u0) z >= 0 for z > 0 (and likewise)
    outside = (
        (z < 0.005).all(axis=1)
        | (c.fx * x + (c.cx - u0) * z < 0).all(axis=1)
        | (c.fx * x + (c.cx - u1) * z > 0).all(axis=1)
        | (c.fy * y + (c.cy - v0) * z < 0).all(axis=1)
        | (c.fy * y + (c.cy - v1) * z > 0).all(axis=1)
    )
    return np.asarray(~outside, dtype=np.float64)


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
