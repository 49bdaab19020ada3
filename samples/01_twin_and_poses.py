"""Open a twin, place a cut point on a cane and derive its pruning pose.

Shows the twin API: load the bundled sample, take a cut-point candidate from its skeleton, add it
as a cut point, derive the default pruning pose (camera 15 cm away, optical axis through the cut,
approach perpendicular to the cane, cane across the image), adjust it, and save into a copy.

    .venv/bin/python samples/01_twin_and_poses.py [--out /tmp/my.twin]
"""

from __future__ import annotations

import argparse
import math
import shutil
import tempfile
from pathlib import Path

import numpy as np

from vinetwin.twin import Approach, Twin, pruning_pose
from vinetwin.twin.poses import axis_miss_distance

SAMPLE = Path(__file__).resolve().parent / "vine_unilateral.twin"


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--out", type=Path, default=Path(tempfile.mkdtemp()) / "copy.twin")
    ap.add_argument(
        "--quick", action="store_true", help="accepted for CI; this sample is quick anyway"
    )
    args = ap.parse_args()
    shutil.copytree(SAMPLE, args.out, dirs_exist_ok=True)
    twin = Twin.load(args.out)
    skeleton = twin.load_skeleton()
    assert skeleton is not None
    cand = skeleton.candidates[-1]
    cut = twin.add_cut_point(cand.point, cand.cane_axis, name="my cut")
    pose = twin.add_pose(cut.id, icp_variant="symmetric")
    cam = pose.T_vine_camera[:3, 3]
    print(f"cut {cut.id} at {np.round(cut.point, 3)}; pose {pose.id}: camera at {np.round(cam, 3)}")
    print(
        f"  standoff {np.linalg.norm(cut.point - cam):.3f} m, axis misses the cut by {axis_miss_distance(pose.T_vine_camera, cut.point):.1e} m"
    )
    # look 20 degrees down from 12 cm instead
    a = pose.approach
    twin.set_pose(
        pose.id,
        pruning_pose(cut.point, cut.cane_axis, Approach(0.12, a.azimuth, math.radians(20), 0.0)),
    )
    twin.save()
    again = Twin.load(args.out).pose(pose.id)
    print(
        f"  adjusted and saved: standoff {again.standoff:.3f} m, elevation {math.degrees(again.approach.elevation):.1f} deg -> {args.out}"
    )


if __name__ == "__main__":
    main()
