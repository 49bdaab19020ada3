"""The row's far side: the poses that look at the row from the far aisle (+Y: a divided canopy's
far curtain, which `vinetwin propose` approaches from there) are planned, and pruned, from that
aisle on the twin seen from it: everything turned half a turn about the vine frame's vertical
axis (x -> -x, y -> -y), so that the far aisle is the robot's side (-Y) and every part of the
plan and the job (platform placement, reach, stops, transits, servo, cut, field twin) runs as on
any vine. `sim.prune_sides` runs the far pass and merges it; the web app's plan panel plans it."""

from __future__ import annotations

import math
import shutil
from pathlib import Path

import numpy as np

from vinetwin.frames import Array
from vinetwin.twin.model import CutPoint, PruningPose, Twin
from vinetwin.twin.poses import Approach, from_far_side

#: The half turn about the vine frame's Z axis: the far aisle's view of the vine (its own
#: inverse).
HALF_TURN = np.diag([-1.0, -1.0, 1.0, 1.0])
#: The far pass's twin, inside the vine's twin folder (a twin inside another is that twin's, not
#: a row's: `twin.model.find_twins`).
FAR_FOLDER = "far_side.twin"


def far_pose_ids(twin: Twin) -> list[str]:
    """The poses that look at the row from its far side (`twin.poses.from_far_side`)."""
    return [p.id for p in twin.poses if from_far_side(p.T_vine_camera)]


def turned(points: Array) -> Array:
    """Points (N, 3) of the vine frame as the far aisle sees them (and back)."""
    return np.asarray(points, float) @ HALF_TURN[:3, :3].T


def far_side_twin(
    twin: Twin, pose_ids: list[str], dest: Path | None = None, write: bool = True
) -> Twin:
    """The twin seen from the row's far aisle (see the module), holding the poses `pose_ids` and
    their cut points under the same ids; the camera, hand-eye and tool transforms and the
    perception settings are the twin's. Written to `dest` (default TWIN/far_side.twin, replaced
    each time) with its mesh and skeleton turned; with `write` False only in memory (its mesh:
    `turned` of the twin's vertices)."""
    dest = dest or twin.root / FAR_FOLDER
    R = HALF_TURN[:3, :3]
    far = Twin(root=dest, name=f"{twin.name} (far side)", camera=twin.camera,
               T_world_vine=np.asarray(twin.T_world_vine, float) @ HALF_TURN,
               T_flange_camera=twin.T_flange_camera, T_flange_tool=twin.T_flange_tool,
               perception=twin.perception)  # fmt: skip
    for pid in pose_ids:
        p = twin.pose(pid)
        c = twin.cut_point(p.cut_point)
        if all(x.id != c.id for x in far.cut_points):
            far.cut_points.append(CutPoint(c.id, R @ c.point, R @ c.cane_axis, c.name, c.source,
                                           dict(c.extra)))  # fmt: skip
        ap = p.approach
        far.poses.append(PruningPose(
            p.id, p.cut_point, HALF_TURN @ np.asarray(p.T_vine_camera, float), p.standoff,
            p.icp_variant, p.name,
            Approach(ap.standoff, math.remainder(ap.azimuth + math.pi, 2 * math.pi),
                     ap.elevation, ap.roll), dict(p.extra)))  # fmt: skip
    if not write:
        return far
    if dest.exists():
        shutil.rmtree(dest)
    mesh = twin.load_mesh()
    sk = twin.load_skeleton()
    if sk is not None:
        for b in sk.branches:
            b.points = turned(b.points)
        for cand in sk.candidates:
            cand.point, cand.cane_axis = R @ cand.point, R @ cand.cane_axis
    out = Twin.create(dest, turned(mesh.vertices), np.asarray(mesh.faces), name=far.name,
                      camera=twin.camera, skeleton=sk,
                      source={"far_side_of": str(twin.root)})  # fmt: skip
    out.T_world_vine, out.perception = far.T_world_vine, far.perception
    out.T_flange_camera, out.T_flange_tool = far.T_flange_camera, far.T_flange_tool
    out.cut_points, out.poses = far.cut_points, far.poses
    out.save()
    return out
