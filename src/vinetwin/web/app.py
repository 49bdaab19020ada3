"""The Viser authoring app: `vinetwin web [TWIN]`.

The page shows the vine mesh, its skeleton and cut-point candidates (when the twin has them),
world axes and a ground grid, the cut points and a camera frustum per pruning pose. A click on
the mesh places a cut point at the hit and proposes its pruning pose `DEFAULT_STANDOFF` away; the side panel
adjusts the selected pose (standoff, approach azimuth and elevation, roll, ICP variant, name),
snaps its optical axis back onto the cut point, deletes it, undoes and redoes, previews the
reference cloud (coloured by depth) and the D405 depth image, and exports the references.
Every edit is saved to twin.json at once (`AuthoringSession`); errors show in the page and the
log, and the server keeps running. `web.server` starts it (`serve`, `serve_folder`).
"""

from __future__ import annotations

import functools
import logging
import math
import threading
import time
from pathlib import Path
from typing import Any, cast

import numpy as np

from vinetwin.cloud import ICP_VARIANTS
from vinetwin.conventions import viser_wxyz_position
from vinetwin.errors import VinetwinError
from vinetwin.twin.poses import DEFAULT_STANDOFF, STANDOFF_RANGE, Approach
from vinetwin.web import plan_view, proposals
from vinetwin.web.config import WebConfig
from vinetwin.web.session import AuthoringSession

log = logging.getLogger("vinetwin.web")

SYNC_DECIMATION_FACES = 300_000
"""A mesh up to this size is decimated for the page before the app starts (about 1 s: the
bundled sample's 128k triangles 0.4 s, hydroshoot vsp's 217k 1.2 s); a larger one is shown
clustered at once and decimated in the background (`web.display`)."""


@functools.cache
def _turbo() -> np.ndarray:
    """The turbo colour map as a 256-entry uint8 table."""
    import matplotlib

    return (matplotlib.colormaps["turbo"](np.linspace(0, 1, 256))[:, :3] * 255).astype(np.uint8)


def _depth_rgb(depth: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """Depths coloured from lo (blue) to hi (red); black where there is none."""
    valid = np.isfinite(depth) & (depth > 0)
    x = np.clip((np.where(valid, depth, lo) - lo) * (255 / max(hi - lo, 1e-9)), 0, 255)
    rgb = _turbo()[x.astype(np.uint8)]
    rgb[~valid] = 0
    return rgb


class App:
    """The page bound to one `AuthoringSession`."""

    def __init__(
        self,
        root: str | Path,
        host: str = "127.0.0.1",
        port: int = 8080,
        config: WebConfig | None = None,
    ) -> None:
        import viser

        self.config = config or WebConfig()
        self.session = AuthoringSession(root)
        self.server = viser.ViserServer(host=host, port=port, label="vinetwin", verbose=False)
        self.lock = threading.RLock()
        self.last_latency = math.nan
        self._warming_up = False  # the start's warm-up is running (said in the status line)
        self._build_panel()
        # the scene nodes the page has, by id, with what they were drawn from (`_sync_scene`)
        self._cut_nodes: dict[str, tuple[Any, Any]] = {}
        self._pose_nodes: dict[str, tuple[Any, ...]] = {}
        self.gizmo: Any = None
        self._gizmo_key: tuple[str, bytes] | None = None
        self._preview: Any = None  # the preview's point cloud, once shown
        self._closing = threading.Event()
        self._display: threading.Thread | None = None  # the vine's decimation for the page
        self.vine: Any = None
        # the vine as the page has it: vertices and faces; full, clustered or decimated
        self.vine_mesh: tuple[np.ndarray, np.ndarray] | None = None
        self.vine_display = "none"
        self._static_scene()
        self.server.scene.on_click()(self._on_click)
        self.refresh()
        self._warming = threading.Thread(target=self._warm_up, daemon=True, name="warm-up")
        self._warming.start()

    def wait_ready(self, timeout: float = 120.0) -> bool:
        """Waits for the start's warm-up (the renderer and picking scene built, the compiled
        kernels loaded or compiled: seconds on a fresh install) and the vine's decimation for
        the page; True once both are done."""
        end = time.monotonic() + timeout
        for t in (self._warming, self._display):
            if t is not None:
                t.join(timeout=max(end - time.monotonic(), 0.0))
        return not any(t is not None and t.is_alive() for t in (self._warming, self._display))

    def close(self) -> None:
        """Stops the server, once the renderer's warm-up (in its own thread) is done, and
        releases the renderer."""
        self._closing.set()
        self.wait_ready(timeout=60)
        self.server.stop()
        with self.lock:
            self.session.close()

    def _warm_up(self) -> None:
        """Builds the renderer and the picking scene and compiles the perception chain before
        the first click."""
        sess = self.session
        if sess.twin is None or not sess.twin.poses:
            return
        t0 = time.perf_counter()
        with self.lock:
            self._warming_up = True
            self.refresh()  # the page says why a first click may wait
            try:
                sess.picker()
                sess.preview(sess.twin.poses[0].id)
            except VinetwinError as exc:
                log.warning("preview warm-up failed: %s", exc)
            finally:
                self._warming_up = False
                if not self._closing.is_set():
                    self.refresh()
        log.info("camera preview ready (warm-up %.1f s)", time.perf_counter() - t0)

    # ------------------------------------------------------------------ scene
    def _static_scene(self) -> None:
        s = self.server.scene
        sess = self.session
        s.add_frame("/world", axes_length=0.1, axes_radius=0.003)
        if sess.twin is None:
            return
        V, F = sess.vertices, sess.faces
        lo = V.min(0)
        s.add_grid(
            "/ground",
            width=2.0,
            height=2.0,
            cell_size=0.1,
            position=(float(V[:, 0].mean()), float(V[:, 1].mean()), float(lo[2])),
        )
        full = self.config.shading == "full"
        if not full:  # no shadow pass (the default lights cast one) in each frame
            s.configure_default_lights(enabled=True, cast_shadow=False)
        # The page (viser's client) makes a new material for a point cloud whose colours change
        # and disposes the old one; the shader program goes with the last material using it, so
        # each preview compiled it again (with Mesa's llvmpipe: a median click 431 -> 275 ms
        # without it, docs/web.md).
        # Two points with colours of their own, never changed, keep the preview's program in use.
        # They are far below the ground's grid and smaller than a pixel.
        keep = np.array([[V[:, 0].mean(), V[:, 1].mean(), lo[2] - 10.0]] * 2, np.float32)
        self._shader_keeper = s.add_point_cloud(
            "/preview_shader", keep, np.array([[0, 0, 0], [1, 1, 1]], np.uint8), point_size=1e-6
        )
        # the vine as drawn: at most `display_faces` triangles (`web.display`); clicks hit the
        # full mesh on the server
        budget = self.config.display_faces
        if budget and budget < len(F) <= SYNC_DECIMATION_FACES:
            self._decimate_vine(V, F, budget)
        elif budget and len(F) > budget:
            from vinetwin.web.display import quick_display_mesh

            t0 = time.perf_counter()
            self._show_vine(*quick_display_mesh(V, F, budget), "clustered")
            log.info(
                "the page draws the vine with %d of its %d triangles (vertices clustered, %.1f s); "
                "a quadric decimation to %d follows",
                self.vine_faces, len(F), time.perf_counter() - t0, budget,
            )  # fmt: skip
            self._display = threading.Thread(
                target=self._decimate_vine, args=(V, F, budget), daemon=True, name="display-mesh"
            )
            self._display.start()
        else:
            self._show_vine(V.astype(np.float32), F.astype(np.uint32), "full")
        try:
            sk = sess.twin.load_skeleton()
        except VinetwinError:
            sk = None
        if sk is not None:
            segs = [
                np.stack([b.points[:-1], b.points[1:]], 1) for b in sk.branches if len(b.points) > 1
            ]
            if segs:
                seg = np.concatenate(segs).astype(np.float32)
                self._skeleton = s.add_line_segments(
                    "/skeleton",
                    seg,
                    (60, 160, 60),
                    thickness=1.5,
                    thickness_units="screen",
                    visible=False,
                )
            cands = (
                np.array([c.point for c in sk.candidates]) if sk.candidates else np.zeros((0, 3))
            )
            if len(cands):
                self._candidates = s.add_point_cloud(
                    "/candidates",
                    cands.astype(np.float32),
                    (250, 200, 0),
                    point_size=0.008,
                    point_shape="circle",
                )
        # start looking at the first pose's cut point
        twin = sess.twin
        if twin.poses:
            p = twin.poses[0]
            cut = twin.cut_point(p.cut_point).point
            cam = np.asarray(p.T_vine_camera)[:3, 3]
            d = (cam - cut) / (np.linalg.norm(cam - cut) or 1.0)
            # from the pose's side, farther and higher, so the pose's frustum is not in the way:
            # the view's centre is the cut point on its cane
            self.server.initial_camera.position = tuple(cut + 0.45 * d + np.array([0.0, 0.0, 0.25]))
            self.server.initial_camera.look_at = tuple(cut)
        else:
            self.server.initial_camera.look_at = tuple(V.mean(0))
            self.server.initial_camera.position = tuple(V.mean(0) + np.array([0.0, -1.2, 0.3]))
        self.server.initial_camera.up = (0.0, 0.0, 1.0)

    def _show_vine(self, V: np.ndarray, F: np.ndarray, how: str) -> None:
        full = self.config.shading == "full"
        self.vine = self.server.scene.add_mesh_simple(
            "/vine", V, F, color=(140, 100, 70), material="standard" if full else "toon3",
            cast_shadow=full, receive_shadow=full,
        )  # fmt: skip
        self.vine_mesh, self.vine_display = (V, F), how

    @property
    def vine_faces(self) -> int:
        """The triangles of the vine as the page has it."""
        return 0 if self.vine_mesh is None else len(self.vine_mesh[1])

    def _decimate_vine(self, V: np.ndarray, F: np.ndarray, budget: int) -> None:
        """The quadric-decimated vine, sent (in place of the clustered one, when the app shows
        that first) once done; if decimation fails, the page keeps what it has, or gets the
        full mesh."""
        from vinetwin.web.display import display_mesh

        t0 = time.perf_counter()
        try:
            mesh = display_mesh(V, F, budget)
        except Exception as exc:  # the app goes on
            log.warning("the vine's decimation for the page failed (%s)", exc)
            if self.vine_mesh is None:
                self._show_vine(V.astype(np.float32), F.astype(np.uint32), "full")
            return
        with self.lock:
            if self._closing.is_set():
                return
            self._show_vine(*mesh, "decimated")
        log.info(
            "the page draws the vine decimated to %d of its %d triangles (%.1f s)",
            self.vine_faces, len(F), time.perf_counter() - t0,
        )  # fmt: skip

    def refresh(self) -> None:
        """Redraws cut points and poses and the side panel from the session, under the app's
        lock (reentrant): two refreshes at once (the warm-up's and a caller's) would add and
        remove the same scene nodes."""
        with self.lock:
            self._refresh()

    def _refresh(self) -> None:
        sess = self.session
        twin = sess.twin
        msg = (
            f"**{twin.name}**: {len(twin.cut_points)} cut points, {len(twin.poses)} poses. Click a cane to add a cut."
            if twin
            else ""
        )
        if self._warming_up:
            msg += (
                "\n\n*Preparing the camera preview (after an install its compiled kernels are "
                "built first, which can take a minute); a click waits for it.*"
            )
        if sess.problem:
            msg = f"**Problem:** {sess.problem}\n\n" + msg
        if not math.isnan(self.last_latency):
            msg += f"\n\nlast click to preview: {1000 * self.last_latency:.0f} ms"
        self.status.content = msg
        if twin is None:
            return
        self._sync_scene(twin)
        lines = ["| pose | cut | variant | standoff | status |", "|---|---|---|---|---|"]
        for p in twin.poses:
            mark = "**" if p.id == sess.selected else ""
            rec = twin.cut_point(p.cut_point).extra.get("proposal") or {}
            lines.append(f"| {mark}{p.name}{mark} | {p.cut_point} | {p.icp_variant} | "
                         f"{p.standoff:.3f} m | {rec.get('status', 'own')} |")  # fmt: skip
        self.listing.content = "\n".join(lines) if twin.poses else "No pruning poses yet."
        self.proposal_status.content = proposals.status(self)
        ids = tuple(p.id for p in twin.poses) or ("-",)
        self.pose_dd.options = ids
        if sess.selected in ids:
            self.pose_dd.value = sess.selected
        if sess.selected:
            p = twin.pose(sess.selected)
            self.name.value = p.name
            self.variant.value = p.icp_variant
            self.standoff.value = round(p.standoff, 4)
            self.azimuth.value = round(math.degrees(p.approach.azimuth), 2)
            self.elevation.value = round(math.degrees(p.approach.elevation), 2)
            self.roll.value = round(math.degrees(p.approach.roll), 2)

    def _sync_scene(self, twin: Any) -> None:
        """Brings the cut points, pose frustums, pose-to-cut lines and the gizmo in the page up
        to date with the twin, sending only what changed: a click adds one cut point and one
        pose and recolours the previously selected pose, instead of every node being removed
        and sent again after each edit."""
        s = self.server.scene
        sess = self.session
        cam = twin.camera
        fov = 2 * math.atan(cam.height / (2 * cam.fy))
        cuts = {
            c.id: (float(c.point[0]), float(c.point[1]), float(c.point[2])) for c in twin.cut_points
        }
        by_id = {c.id: c for c in twin.cut_points}
        for cid in set(self._cut_nodes) - set(cuts):
            self._cut_nodes.pop(cid)[1].remove()
        for cid, point in cuts.items():
            old = self._cut_nodes.get(cid)
            colour = proposals.cut_colour(by_id[cid])
            if old is not None and old[0] == (point, colour):
                continue
            if old is not None:
                old[1].remove()
            handle = s.add_icosphere(f"/cuts/{cid}", radius=0.004 if colour == proposals.COLOURS["cut"] else 0.006,
                                     color=colour, position=point)  # fmt: skip
            self._cut_nodes[cid] = ((point, colour), handle)
        poses = {p.id: p for p in twin.poses}
        for pid in set(self._pose_nodes) - set(poses):
            for h in self._pose_nodes.pop(pid)[1:]:
                h.remove()
        for pid, p in poses.items():
            T = np.asarray(p.T_vine_camera, float)
            cut = cuts.get(p.cut_point)
            sel = pid == sess.selected
            shape = (fov, cam.width / cam.height)
            key = (T.tobytes(), cut, sel, shape, proposals.pose_colour(by_id.get(p.cut_point), sel))
            old = self._pose_nodes.get(pid)
            if old is not None and old[0] == key:
                continue
            wxyz, pos = viser_wxyz_position(T)
            color = proposals.pose_colour(by_id.get(p.cut_point), sel)
            end = cut if cut is not None else pos
            segment = np.array([[pos, end]], np.float32)
            if old is not None and old[0][3] == shape:
                # the same frustum moved or recoloured: updated in place. A node removed and
                # sent again makes the page compile its shaders again when its material was
                # the last of its kind (docs/web.md)
                _, frustum, line = old
                with self.server.atomic():
                    frustum.wxyz, frustum.position, frustum.color = wxyz, pos, color
                    line.points = segment
                    line.colors = np.broadcast_to(np.array(color, np.uint8), (1, 2, 3)).copy()
                self._pose_nodes[pid] = (key, frustum, line)
                continue
            if old is not None:
                for h in old[1:]:
                    h.remove()
            frustum = s.add_camera_frustum(
                f"/poses/{pid}", fov=fov, aspect=cam.width / cam.height, scale=0.04,
                color=color, wxyz=wxyz, position=pos, thickness=0.0015,
            )  # fmt: skip
            line = s.add_line_segments(
                f"/axes/{pid}", segment, color, thickness=1.0, thickness_units="screen",
            )  # fmt: skip
            self._pose_nodes[pid] = (key, frustum, line)
        selected = poses.get(sess.selected)
        if selected is None:
            if self.gizmo is not None:
                self.gizmo.remove()
                self.gizmo, self._gizmo_key = None, None
            return
        T = np.asarray(selected.T_vine_camera, float)
        key = (selected.id, T.tobytes())
        if self.gizmo is not None and self._gizmo_key == key:
            return
        wxyz, pos = viser_wxyz_position(T)
        if self.gizmo is not None:  # moved to the pose (kept: see the frustums above)
            self.gizmo.wxyz, self.gizmo.position = wxyz, pos
        else:
            self.gizmo = s.add_transform_controls("/gizmo", scale=0.05, wxyz=wxyz, position=pos)
            self.gizmo.on_update(self._on_gizmo)
        self._gizmo_key = key

    # ------------------------------------------------------------------ events
    def _build_panel(self) -> None:
        """The side panel, each widget with its callback attached where it is made."""
        g, sess, on = self.server.gui, self.session, self._guarded
        self.status = g.add_markdown("")
        with g.add_folder("Pose"):
            self.pose_dd: Any = g.add_dropdown("pose", ("-",))
            self.pose_dd.on_update(on(lambda: setattr(sess, "selected", self._dropdown_pose())))
            self.name = g.add_text("name", "")
            self.variant: Any = g.add_dropdown(
                "ICP variant", ICP_VARIANTS, initial_value="point_to_plane"
            )
            lo, hi = STANDOFF_RANGE
            self.standoff = g.add_number(
                "standoff (m)", DEFAULT_STANDOFF, min=lo, max=hi, step=0.005
            )
            self.azimuth = g.add_number("azimuth (deg)", 0.0, step=1.0)
            self.elevation = g.add_number("elevation (deg)", 0.0, min=-89, max=89, step=1.0)
            self.roll = g.add_number("roll (deg)", 0.0, step=1.0)
            self.apply = g.add_button("Apply")
            self.apply.on_click(on(self._apply))
            self.snap = g.add_button("Snap axis to cut point")
            self.snap.on_click(on(lambda: sess.snap(sess.selected) if sess.selected else None))
            self.delete = g.add_button("Delete pose")
            self.delete.on_click(
                on(lambda: sess.delete_pose(sess.selected) if sess.selected else None)
            )
        self.proposal_status = proposals.add_panel(self)
        self.plan_status = plan_view.add_panel(self)
        with g.add_folder("Edit"):
            self.undo = g.add_button("Undo")
            self.undo.on_click(on(sess.undo))
            self.redo = g.add_button("Redo")
            self.redo.on_click(on(sess.redo))
            self.save = g.add_button("Save")
            self.save.on_click(on(sess.save))
        with g.add_folder("Camera view"):
            self.preview_btn = g.add_button("Preview")
            self.preview_btn.on_click(
                on(lambda: self._show_preview(sess.selected) if sess.selected else None)
            )
            self.image = g.add_image(np.zeros((48, 85, 3), np.uint8), label="D405 depth")
        with g.add_folder("References and servo"):
            self.export_btn = g.add_button("Export references")
            self.export_btn.on_click(lambda _: self._in_thread(self._export))
            self.progress = g.add_progress_bar(0.0, animated=False)
            self.validate_btn = g.add_button("Validate pose (simulated servo)")
            self.validate_btn.on_click(lambda _: self._in_thread(self._validate))
            self.validation = g.add_markdown("")
        with g.add_folder("View", expand_by_default=False):
            self.show_skeleton = g.add_checkbox("skeleton", False)
            self.show_skeleton.on_update(self._toggle_layers)
            self.show_candidates = g.add_checkbox("cut candidates", True)
            self.show_candidates.on_update(self._toggle_layers)
        self.listing = g.add_markdown("")

    def _dropdown_pose(self) -> str:
        return self.pose_dd.value if self.pose_dd.value != "-" else ""

    @staticmethod
    def _in_thread(fn: Any) -> None:
        """Runs a long job (propose, validate) beside the server. Its BLAS runs on one thread:
        OpenBLAS's worker threads spin while they wait, and with the browser's renderer busy on
        the other of two cores a propose once ran for over ten minutes instead of 15 s."""

        def run() -> None:
            from threadpoolctl import threadpool_limits

            with threadpool_limits(limits=1, user_api="blas"):
                fn()

        threading.Thread(target=run, daemon=True).start()

    def _guarded(self, fn: Any) -> Any:
        """A widget callback: a person's edit (not the server's own refresh) under the lock, its
        error shown in the status line, the panel refreshed."""

        def run(event: Any) -> None:
            if getattr(event, "client", None) is None:
                return  # the server changed the widget itself (refresh): not a person's edit
            with self.lock:
                try:
                    fn()
                except VinetwinError as exc:
                    self.session.problem = str(exc)
                    log.error("%s", exc)
                self.refresh()

        return run

    def _toggle_layers(self, _: Any) -> None:
        for name, box in (("_skeleton", self.show_skeleton), ("_candidates", self.show_candidates)):
            handle = getattr(self, name, None)
            if handle is not None:
                handle.visible = bool(box.value)

    def _on_click(self, event: Any) -> None:
        """A click on the vine: a cut point and its pruning pose, previewed at once."""
        if event.ray_origin is None:
            return
        t0 = time.perf_counter()
        with self.lock:
            try:
                # saved right after the preview is on its way, not before
                hit = self.session.click(event.ray_origin, event.ray_direction, save=False)
            except VinetwinError as exc:
                self.session.problem = f"cannot place a cut point there: {exc}"
                hit = None
            if hit is None:
                self.refresh()
                return
            try:
                # one batch of messages, so the page applies the preview, the new pose and the
                # panel in one frame (each frame is costly where the page draws in software)
                with self.server.atomic():
                    try:
                        self._show_preview(hit[1].id)
                    finally:
                        self.last_latency = time.perf_counter() - t0
                        self.refresh()
            finally:
                self.session.save_if_auto()  # saved once the preview is on its way
                if self.session.problem:
                    self.refresh()  # the save failed: say so
            log.info(
                "cut point %s, pose %s in %.0f ms", hit[0].id, hit[1].id, 1000 * self.last_latency
            )

    def _apply(self) -> None:
        sess = self.session
        if not sess.selected:
            return
        ap = Approach(
            standoff=float(self.standoff.value),
            azimuth=math.radians(float(self.azimuth.value)),
            elevation=math.radians(float(self.elevation.value)),
            roll=math.radians(float(self.roll.value)),
        )
        sess.set_approach(sess.selected, ap)
        pose = sess._require().pose(sess.selected)
        if self.name.value != pose.name:
            sess.rename(pose.id, self.name.value)
        if self.variant.value != pose.icp_variant:
            sess.set_variant(pose.id, self.variant.value)

    def _on_gizmo(self, event: Any) -> None:
        from vinetwin.conventions import T_from_viser

        if getattr(event, "client", None) is None:
            return
        with self.lock:
            sess = self.session
            if sess.selected:
                try:
                    sess.set_transform(
                        sess.selected, T_from_viser(self.gizmo.wxyz, self.gizmo.position)
                    )
                except VinetwinError as exc:
                    sess.problem = str(exc)
            self.refresh()

    def _show_preview(self, pose_id: str) -> None:
        pv = self.session.preview(pose_id)
        pts = pv.points
        if len(pts):
            cam = np.asarray(self.session._require().pose(pose_id).T_vine_camera)
            z = (pts - cam[:3, 3]) @ cam[:3, 2]
            colors = _depth_rgb(z, float(z.min()), float(z.max()))
            pts32 = pts.astype(np.float32)
            if self._preview is None:
                self._preview = self.server.scene.add_point_cloud(
                    "/preview", pts32, colors, point_size=0.002
                )
            else:  # updated in place (see `_sync_scene`): the page keeps its shaders
                with self.server.atomic():  # points and colours of one size in each frame
                    self._preview.points, self._preview.colors = pts32, colors
                    self._preview.visible = True
        elif self._preview is not None:
            self._preview.visible = False  # nothing seen: not another pose's points
        d = pv.depth
        valid = np.isfinite(d) & (d > 0)
        if valid.any():
            lo, hi = float(d[valid].min()), float(d[valid].max())
            self.image.image = _depth_rgb(d[::2, ::2], lo, hi)  # colour only what is shown

    def _export(self) -> None:
        from vinetwin.render.export import export_references

        with self.lock:
            twin = self.session.twin
        if twin is None:
            return

        def progress(result: object, done: int, total: int) -> None:
            self.progress.value = 100.0 * done / max(total, 1)

        try:
            report = export_references(twin, workers=1, progress=progress)
            self.session.problem = (
                "" if report.ok else f"{report.count('failed')} references failed"
            )
        except VinetwinError as exc:
            self.session.problem = str(exc)
        with self.lock:
            self.refresh()

    def _validate(self) -> None:
        """One closed-loop run to the selected pose (kinematic simulation, the pose's ICP
        variant, the library's default settings) from the campaign's quick start; draws the
        camera path and reports the outcome."""
        from vinetwin.servo.config import Variant
        from vinetwin.sim.config import SimConfig
        from vinetwin.sim.paper import PRESETS
        from vinetwin.sim.session import SimSpec, SimWorld, start_pose
        from vinetwin.sim.simulate import simulate

        with self.lock:
            sess = self.session
            twin = sess.twin
            pid = sess.selected
            if twin is None or not pid:
                return
            pose = twin.pose(pid)
            cut = twin.cut_point(pose.cut_point).point
            goal = np.asarray(pose.T_vine_camera)
            self.validation.content = f"simulating the servo to {pose.name}..."
            backend = sess.renderer()
        rng = np.random.default_rng(0)
        far_t, far_r = PRESETS["quick"][0]
        start = start_pose(goal, cut, (far_t, far_r), rng, twin.camera, twin.perception.max_depth)
        spec = SimSpec(
            goal, start, SimConfig(variant=cast(Variant, pose.icp_variant)), pose.id, cut
        )
        try:
            run = simulate(spec, SimWorld(backend, twin.perception))
        except VinetwinError as exc:
            self.validation.content = f"validation failed: {exc}"
            return
        sm = run.summary()
        path = np.array([T[:3, 3] for T in run.T], np.float32)
        if len(path) > 1:
            self.server.scene.add_line_segments(
                "/validation", np.stack([path[:-1], path[1:]], 1), (0, 170, 0),
                thickness=2.0, thickness_units="screen",
            )  # fmt: skip
        verdict = "converged" if sm["converged"] else "did not converge"
        ct = sm["convergence_time"]
        self.validation.content = (
            f"{pose.name} ({pose.icp_variant}) from {100 * far_t:.0f} cm / {far_r:.2f} rad: "
            f"**{verdict}**, final error "
            f"{1000 * sm['final_translation']:.2f} mm / {sm['final_rotation']:.4f} rad"
            + (f" in {ct:.1f} s" if ct is not None else "")
            + f", {sm['refused']} frames refused"
            + (f", re-acquired {sm['reacquisitions']} times" if sm["reacquisitions"] else "")
            + (f". **Stopped: {sm['lost']}**" if sm["lost"] else "")
            + "."
        )
