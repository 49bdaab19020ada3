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

from vinetwin.frames import transform_points
from vinetwin.twin.model import CutPoint, PruningPose, Twin
from vinetwin.twin.poses import HALF_TURN, Approach, from_far_side
from vinetwin.twin.skeleton import transform_skeleton

#: The far pass's twin, inside the vine's twin folder (a twin inside another is that twin's, not
#: a row's: `twin.model.find_twins`).
FAR_FOLDER = "far_side.twin"


def far_pose_ids(twin: Twin) -> list[str]:
    """The poses that look at the row from its far side (`twin.poses.from_far_side`)."""
    return [p.id for p in twin.poses if from_far_side(p.T_vine_camera)]


def far_side_twin(
    twin: Twin, pose_ids: list[str], dest: Path | None = None, write: bool = True
) -> Twin:
    """The twin seen from the row's far aisle (see the module: `twin.poses.HALF_TURN`), holding
    the poses `pose_ids` and their cut points under the same ids; the camera, hand-eye and tool
    transforms and the perception settings are the twin's. Written to `dest` (default
    TWIN/far_side.twin, replaced each time) with its mesh and skeleton turned; with `write`
    False only in memory (its mesh: the twin's vertices turned, `frames.transform_points`)."""
    dest = dest or twin.root / FAR_FOLDER
    name = f"{twin.name} (far side)"
    if write:
        if dest.exists():
            shutil.rmtree(dest)
        mesh = twin.load_mesh()
        sk = twin.load_skeleton()
        far = Twin.create(dest, transform_points(HALF_TURN, mesh.vertices), np.asarray(mesh.faces),
                          name=name, camera=twin.camera,
                          skeleton=None if sk is None else transform_skeleton(sk, HALF_TURN),
                          source={"far_side_of": str(twin.root)})  # fmt: skip
    else:
        far = Twin(root=dest, name=name, camera=twin.camera)
    far.T_world_vine = np.asarray(twin.T_world_vine, float) @ HALF_TURN
    far.T_flange_camera, far.T_flange_tool = twin.T_flange_camera, twin.T_flange_tool
    far.perception = twin.perception
    R = HALF_TURN[:3, :3]
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
    if write:
        far.save()
    return far
