"""The authoring session behind the web app, without a browser: one twin being edited.

Every edit goes through here (so it is tested without Viser): a click ray picks a point on the
mesh, which becomes a cut point with its default pruning pose; poses are adjusted by their
approach (standoff, azimuth, elevation, roll) or by a full pose from the gizmo, snapped back onto
their cut point, renamed, given an ICP variant, deleted; every edit can be undone and redone and
is saved at once (atomic write of twin.json, the only file an edit writes). A twin that cannot be
saved (read-only folder) or loaded (invalid twin.json) is reported in `problem`, never raised out
of a callback.
"""

from __future__ import annotations

import copy
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from vinetwin.errors import VinetwinError
from vinetwin.frames import Array
from vinetwin.twin.model import CutPoint, PruningPose, Twin
from vinetwin.twin.poses import Approach, estimate_cane_axis, snap_to_cut_point

log = logging.getLogger("vinetwin.web")


@dataclass
class Preview:
    """What the camera would see at a pose: the reference cloud (vine frame) and depth image."""

    points: Array
    depth: Any
    """Depth image (H, W) in metres, float32."""


class AuthoringSession:
    """One twin under edit."""

    def __init__(self, root: str | Path, autosave: bool = True) -> None:
        self.root = Path(root)
        self.autosave = autosave
        self.problem = ""
        """The last error a person should see ('' when all is well)."""
        self.twin: Twin | None = None
        self.vertices: Array = np.zeros((0, 3))
        self.faces = np.zeros((0, 3), dtype=np.int64)
        self._undo: list[dict[str, Any]] = []
        self._redo: list[dict[str, Any]] = []
        self._renderer: Any = None
        self._picker: Any = None
        self._obstacles: Any = None
        self.selected = ""
        self.reload()

    # ------------------------------------------------------------------ loading
    def reload(self) -> bool:
        """(Re)reads the twin and its mesh; False with `problem` set when it cannot."""
        try:
            twin = Twin.load(self.root)
            mesh = twin.load_mesh()
        except VinetwinError as exc:
            self._fail(str(exc))
            return False
        self.twin = twin
        self.vertices = np.asarray(mesh.vertices, dtype=np.float64)
        self.faces = np.asarray(mesh.faces, dtype=np.int64)
        self.close()
        self.problem = ""
        self.selected = twin.poses[0].id if twin.poses else ""
        return True

    def _fail(self, message: str) -> None:
        self.problem = message
        log.error("%s", message)

    def _require(self) -> Twin:
        if self.twin is None:
            raise VinetwinError(self.problem or "no twin loaded")
        return self.twin

    # ------------------------------------------------------------------ picking
    def renderer(self) -> Any:
        """The renderer of this twin's mesh (built once): the simulation's, `scene_backend`,
        which may be used from any thread (the app's clicks and validations run in server
        threads): vinetwin's raster backend (`render.backends.BATCH_BACKEND`). It renders the
        previews and the validations' scene."""
        from vinetwin.render.backends import scene_backend

        if self._renderer is None:
            twin = self._require()
            self._renderer = scene_backend(self.vertices, self.faces, twin.camera, any_thread=True)
        return self._renderer

    def picker(self) -> Any:
        """Open3D's ray-casting scene of this twin's mesh (built once), which answers the
        picks: the renderer's own where it is Open3D's."""
        from vinetwin.render.backends import picking_scene

        if self._picker is None:
            self._picker = picking_scene(self.renderer(), self.vertices, self.faces)
        return self._picker

    def close(self) -> None:
        """Releases the renderer and the picking scene (built again when next needed)."""
        if self._renderer is not None:
            self._renderer.close()
        self._renderer = self._picker = self._obstacles = None

    def pick(self, origin: Any, direction: Any) -> Array | None:
        """The first point where a ray (vine frame) hits the mesh, or None."""
        from vinetwin import _lazy

        o3d = _lazy.open3d()
        d = np.asarray(direction, dtype=np.float64)
        d = d / (np.linalg.norm(d) or 1.0)
        ray = np.concatenate([np.asarray(origin, dtype=np.float64), d])[None].astype(np.float32)
        t = float(self.picker().cast_rays(o3d.core.Tensor(ray))["t_hit"].numpy()[0])
        if not np.isfinite(t):
            return None
        return np.asarray(origin, dtype=np.float64) + t * d

    # ------------------------------------------------------------------ edits
    def _edit(self) -> Twin:
        twin = self._require()
        self._undo.append(copy.deepcopy(twin.to_json()))
        self._redo.clear()
        return twin

    def save_if_auto(self) -> bool:
        """Saves when the session autosaves (True when saved)."""
        return self.save() if self.autosave else False

    def click(
        self, origin: Any, direction: Any, save: bool = True
    ) -> tuple[CutPoint, PruningPose] | None:
        """A click on the mesh: a cut point at the hit and its default pruning pose. `save`:
        autosave now (False: the caller calls `save_if_auto` itself, the web app after it has
        sent the preview)."""
        point = self.pick(origin, direction)
        if point is None:
            return None
        axis = estimate_cane_axis(self.vertices, point)
        twin = self._edit()
        cut = twin.add_cut_point(point, axis, source="click")
        pose = twin.add_pose(cut.id)
        self.selected = pose.id
        if save:
            self.save_if_auto()
        return cut, pose

    def set_approach(self, pose_id: str, approach: Approach) -> PruningPose:
        from vinetwin.twin.poses import pruning_pose

        twin = self._edit()
        pose = twin.pose(pose_id)
        cut = twin.cut_point(pose.cut_point)
        pose.approach = approach
        pose.standoff = approach.standoff
        pose.T_vine_camera = pruning_pose(cut.point, cut.cane_axis, approach)
        self.save_if_auto()
        return pose

    def set_transform(self, pose_id: str, T_vine_camera: Any) -> PruningPose:
        twin = self._edit()
        pose = twin.set_pose(pose_id, T_vine_camera)
        self.save_if_auto()
        return pose

    def snap(self, pose_id: str) -> PruningPose:
        """Turns the pose so its optical axis goes through its cut point again."""
        twin = self._require()
        pose = twin.pose(pose_id)
        cut = twin.cut_point(pose.cut_point)
        return self.set_transform(
            pose_id, snap_to_cut_point(pose.T_vine_camera, cut.point, cut.cane_axis)
        )

    def rename(self, pose_id: str, name: str) -> None:
        self._edit().pose(pose_id).name = name
        self.save_if_auto()

    def set_variant(self, pose_id: str, variant: str) -> None:
        from vinetwin.cloud import ICP_VARIANTS
        from vinetwin.errors import InputError

        if variant not in ICP_VARIANTS:
            raise InputError(f"unknown ICP variant '{variant}'")
        self._edit().pose(pose_id).icp_variant = variant
        self.save_if_auto()

    def delete_pose(self, pose_id: str) -> None:
        twin = self._edit()
        pose = twin.delete_pose(pose_id)
        if not any(p.cut_point == pose.cut_point for p in twin.poses):
            twin.delete_cut_point(pose.cut_point)  # a clicked cut point without poses goes too
        self.selected = twin.poses[-1].id if twin.poses else ""
        self.save_if_auto()

    # ------------------------------------------------------------------ proposals
    def obstacles(self) -> Any:
        """The vine as the pose search sees it (built once)."""
        from vinetwin.plan.search import VineObstacles

        if self._obstacles is None:
            self._obstacles = VineObstacles(self.vertices, self.faces, self._require().camera)
        return self._obstacles

    def propose(self, cfg: Any) -> Any:
        """Cut proposals by a rule (`propose.proposer.propose`), an edit like any other (undo
        removes them all); returns the `ProposeResult`."""
        from vinetwin.plan.proposer import propose

        twin = self._edit()
        try:
            result = propose(twin, cfg, obstacles=self.obstacles(), save=False)
        except VinetwinError:
            self._undo.pop()  # nothing changed
            raise
        first = next(
            (p.id for p in twin.poses if p.cut_point in {r["id"] for r in result.rows}), ""
        )
        self.selected = first or self.selected
        self.save_if_auto()
        return result

    def review(self, accept: bool, all_proposals: bool = False) -> list[str]:
        """Accepts or rejects the selected pose's proposal (or every open one)."""
        from vinetwin.plan.proposer import review

        twin = self._require()
        if all_proposals:
            ids = None
        elif self.selected:
            ids = [twin.pose(self.selected).cut_point]
        else:
            return []
        twin = self._edit()
        try:
            done = review(twin, accept, ids)
        except VinetwinError:
            self._undo.pop()  # nothing changed
            raise
        ids_left = [p.id for p in twin.poses]
        if self.selected not in ids_left:
            self.selected = ids_left[-1] if ids_left else ""
        self.save_if_auto()
        return done

    def undo(self) -> bool:
        return self._swap(self._undo, self._redo)

    def redo(self) -> bool:
        return self._swap(self._redo, self._undo)

    def _swap(self, source: list[dict[str, Any]], target: list[dict[str, Any]]) -> bool:
        twin = self._require()
        if not source:
            return False
        target.append(copy.deepcopy(twin.to_json()))
        self.twin = twin.restored(source.pop())
        ids = [p.id for p in self.twin.poses]
        if self.selected not in ids:
            self.selected = ids[-1] if ids else ""
        self.save_if_auto()
        return True

    def save(self) -> bool:
        """Writes twin.json (atomically); False with `problem` set when it cannot."""
        try:
            self._require().save()
        except (VinetwinError, OSError) as exc:
            self._fail(f"not saved: {exc}")
            return False
        self.problem = ""
        return True

    # ------------------------------------------------------------------ what the camera sees
    def preview(self, pose_id: str) -> Preview:
        """The reference cloud of a pose as it stands now (rendered with this session's
        renderer and the export's noise seed: `render.reference.reference_for`)."""
        from vinetwin.frames import transform_points
        from vinetwin.render.reference import reference_for

        twin = self._require()
        pose = twin.pose(pose_id)
        ref = reference_for(twin, pose.id, use_exported=False, renderer=self.renderer())
        assert ref.depth is not None  # rendered, not read
        pts = (
            transform_points(pose.T_vine_camera, ref.cloud.points)
            if len(ref.cloud)
            else ref.cloud.points
        )
        return Preview(pts, ref.depth)
