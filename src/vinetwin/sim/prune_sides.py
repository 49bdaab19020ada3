"""The row's far side (`vinetwin prune --sides both`, the default): the poses that look at the row from its
far side (+Y: a divided canopy's far curtain, which `vinetwin propose` approaches from there) are
pruned in a second pass, with the platform in the aisle beyond the row.

The far pass is the same job (`sim.prune`) on the twin seen from the far aisle: everything turned
half a turn about the vine frame's vertical axis (x -> -x, y -> -y), so the far aisle is the
robot's side (-Y) and every part of the job (plan, platform placement, transits, servo, cut,
field twin) runs as on any vine. Its cuts, points and stops are turned back into the vine frame
and merged with the near pass's: a vine's time is the two passes' sum (the platform's drive
round to the next aisle is the row's, not the vine's, and is not counted)."""

from __future__ import annotations

import math
import shutil
from pathlib import Path
from typing import Any

import numpy as np

from vinetwin.plan.job import FAR_SIDE
from vinetwin.twin.model import CutPoint, PruningPose, Twin
from vinetwin.twin.poses import Approach

#: The half turn about the vine frame's Z axis: the far aisle's view of the vine (its own
#: inverse).
HALF_TURN = np.diag([-1.0, -1.0, 1.0, 1.0])
#: The far pass's twin, inside the vine's twin folder (a twin inside another is that twin's, not
#: a row's: `twin.model.find_twins`).
FAR_FOLDER = "far_side.twin"


def far_pose_ids(twin: Twin) -> list[str]:
    """The poses that look at the row from its far side (`plan.job.FAR_SIDE`)."""
    return [p.id for p in twin.poses if float(np.asarray(p.T_vine_camera)[1, 2]) <= -FAR_SIDE]


def far_side_twin(twin: Twin, pose_ids: list[str], dest: Path | None = None) -> Twin:
    """The twin seen from the row's far aisle (see the module), holding the poses `pose_ids` and
    their cut points under the same ids; written to `dest` (default TWIN/far_side.twin),
    replaced each time. The camera, hand-eye and tool transforms and the perception settings
    are the twin's."""
    dest = dest or twin.root / FAR_FOLDER
    if dest.exists():
        shutil.rmtree(dest)
    R = HALF_TURN[:3, :3]
    mesh = twin.load_mesh()
    sk = twin.load_skeleton()
    if sk is not None:
        for b in sk.branches:
            b.points = b.points @ R.T
        for c in sk.candidates:
            c.point, c.cane_axis = R @ c.point, R @ c.cane_axis
    far = Twin.create(dest, np.asarray(mesh.vertices) @ R.T, np.asarray(mesh.faces),
                      name=f"{twin.name} (far side)", camera=twin.camera, skeleton=sk,
                      source={"far_side_of": str(twin.root)})  # fmt: skip
    far.T_world_vine = np.asarray(twin.T_world_vine, float) @ HALF_TURN
    far.T_flange_camera, far.T_flange_tool = twin.T_flange_camera, twin.T_flange_tool
    far.perception = twin.perception
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
    far.save()
    return far


def _back(point: Any) -> Any:
    """A point of the far twin in the vine frame."""
    return None if point is None else (HALF_TURN[:3, :3] @ np.asarray(point, float)).tolist()


def merge(near: dict[str, Any], far: dict[str, Any], twin: Twin) -> dict[str, Any]:
    """One vine's result from its two passes: the near pass's, its cuts on far-side poses
    replaced by the far pass's (`side` says which pass did each; points and stops in the vine
    frame, a far stop at x along the row from the far aisle is -x), the far plan as
    `plan.far_side`, collisions, contacts, events, transits, planning and times added."""
    done_far = {c["pose"] for c in far["cuts"]}
    cuts = [{**c, "side": "near"} for c in near["cuts"] if c["pose"] not in done_far]
    for c in far["cuts"]:
        stop = c.get("stop")
        cuts.append({**c, "side": "far", "point": _back(c.get("point")),
                     "stop": None if stop is None else -stop})  # fmt: skip
    order = {p.id: i for i, p in enumerate(twin.poses)}
    cuts.sort(key=lambda c: (c["side"] == "far", order.get(c["pose"], 0)))
    plan = dict(near["plan"])
    fp = dict(far["plan"])
    fp["stops"] = [-s for s in fp.get("stops", [])]
    plan["far_side"] = fp
    out = dict(near)
    out.update(
        cuts=cuts, plan=plan,
        collisions=near["collisions"] + far["collisions"],
        contacts=near["contacts"] + [{**e, "side": "far"} for e in far["contacts"]],
        planning_s=near["planning_s"] + far["planning_s"],
        reach_planning_s=near["reach_planning_s"] + far["reach_planning_s"],
        events=near["events"] + [f"far side: {e}" for e in far["events"]],
        transits=near["transits"] + [{**t, "side": "far"} for t in far["transits"]],
    )  # fmt: skip
    ns, fs = near["summary"], far["summary"]
    # the near pass names each far-side pose skipped; the far pass says whether it is reachable
    reachable = ns["reachable"] + fs["reachable"]
    out["summary"] = summary(cuts, len(twin.poses), reachable,
                             ns["simulated_s"] + fs["simulated_s"], ns["wall_s"] + fs["wall_s"],
                             near["config"]["job"]["cut"]["max_blade_error"])  # fmt: skip
    out["summary"]["far_side_poses"] = len(done_far)
    return out


def summary(cuts: list[dict[str, Any]], poses: int, reachable: int, simulated: float,
            wall: float, tol: float) -> dict[str, Any]:  # fmt: skip
    """A vine's figures from its cuts: done, done with the blade within `tol`, skipped, the
    median time per cut and blade error, simulated and wall time."""
    done = [c for c in cuts if c["status"] == "done"]
    right = [c for c in done if c["blade_error_m"] <= tol]
    times = [c["time_s"] for c in done]
    return {
        "poses": poses,
        "reachable": reachable,
        "done": len(done),
        "done_right": len(right),
        "skipped": len(cuts) - len(done),
        "median_time_per_cut_s": float(np.median(times)) if times else math.nan,
        "median_blade_error_mm": (
            1000 * float(np.median([c["blade_error_m"] for c in done])) if done else math.nan
        ),
        "simulated_s": simulated,
        "wall_s": wall,
        "realtime_factor": simulated / wall if wall > 0 else math.nan,
    }
