"""The far pass of `vinetwin prune --sides both` (the default) merged with the near one: the
poses that look at the row from its far side are pruned with the platform in the aisle beyond
the row, on the twin seen from there (`plan.sides`). The far pass's cuts, points and stops are
turned back into the vine frame and merged with the near pass's: a vine's time is the two
passes' sum (the platform's drive round to the next aisle is the row's, not the vine's, and is
not counted)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from vinetwin.frames import transform_points
from vinetwin.twin.model import Twin
from vinetwin.twin.poses import HALF_TURN


def _back(point: Any) -> Any:
    """A point of the far twin in the vine frame."""
    return None if point is None else transform_points(HALF_TURN, [point])[0].tolist()


def merge(near: dict[str, Any], far: dict[str, Any], twin: Twin) -> dict[str, Any]:
    """One vine's result from its two passes: the near pass's, its cuts on far-side poses
    replaced by the far pass's (`side` says which pass did each; points and stops in the vine
    frame, a far stop at x along the row from the far aisle is -x; each pass's cuts in the order
    it did them, as the report's timeline draws them, the near pass first), the far plan as
    `plan.far_side`, collisions, contacts, events, transits, planning and times added."""
    done_far = {c["pose"] for c in far["cuts"]}
    cuts = [{**c, "side": "near"} for c in near["cuts"] if c["pose"] not in done_far]
    for c in far["cuts"]:
        stop = c.get("stop")
        cuts.append({**c, "side": "far", "point": _back(c.get("point")),
                     "stop": None if stop is None else -stop})  # fmt: skip
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
