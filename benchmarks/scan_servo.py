"""The servo on scanned twins, judged against the TRUE vine (issue 43's last measurement).

Per plant: the true vine (its skeleton's tube mesh) is scanned by the simulated LiDAR at the
realistic quality (`scan.synthetic`, as `scan_accuracy.py`), written in a scanner's frame
(millimetres, y up at a random heading) and imported with `import_scan` (`--cut-points N`: N cut
points with pruning poses on the scan's candidates). The true vine is moved into the scanned
twin's vine frame (the simulation knows the transform) and written as the world. Then
`vinetwin validate`, ideal and field profiles, on:

- **true twin**: the scanned twin's poses and cut points on the TRUE vine's mesh (the same poses,
  the twin without error; under the field profile its reference comes from the profile's own
  reconstructed twin, as on any twin);
- **scanned twin**: the scanned twin itself, the camera seeing the true vine (`--world`): its
  reference is rendered from the scan's tube mesh, so the twin's own error counts.

Each row: runs converged (the profile's band), runs that stopped "lost the vine", the median final
translation and rotation errors and the median error at the cut (the cut point's offset in the
camera from where the pose puts it), all against the true vine.

    .venv/bin/python benchmarks/scan_servo.py [--plants sample vsp_ww] [--cut-points 4]
        [--starts 4] [--variants point_to_plane] [--json benchmarks/results/scan_servo.json]
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))

from results_file import machine
from scan_accuracy import truth_skeleton, write_ply

from vinetwin.scan.config import ScanImportConfig
from vinetwin.scan.importer import import_scan
from vinetwin.scan.synthetic import QUALITY_LADDER, scanner_frame, simulate_scan
from vinetwin.sim.config import ValidateConfig
from vinetwin.sim.validate import validate
from vinetwin.twin.model import Twin
from vinetwin.twin.skeleton import tube_mesh


def twins(name: str, work: Path, cut_points: int, seed: int) -> tuple[Twin, Twin, Path]:
    """The scanned twin, the true twin with its poses, and the world's mesh file."""
    truth = truth_skeleton(name)
    V, F = tube_mesh(truth, edge=0.003, caps="round")
    wire = float(truth.branches[0].points[-1][2])
    P, _ = simulate_scan(V, F, QUALITY_LADDER["realistic"], seed, wire_height=wire)
    T_scan_vine = scanner_frame(seed)
    f = work / f"{name}_scan.ply"
    write_ply(f, (P @ T_scan_vine[:3, :3].T + T_scan_vine[:3, 3]) * 1000.0)
    cfg = ScanImportConfig(cut_points=cut_points)
    scanned, scan = import_scan(f, work / f"{name}_scanned.twin", cfg, overwrite=True)
    T = scan.T_vine_scan @ T_scan_vine  # the truth's vine frame -> the scanned twin's
    Vw = V @ T[:3, :3].T + T[:3, 3]
    true_dir = work / f"{name}_true.twin"
    shutil.rmtree(true_dir, ignore_errors=True)
    shutil.copytree(scanned.root, true_dir)
    true_twin = Twin.load(true_dir)
    true_twin.write_mesh(Vw, F)
    return scanned, true_twin, true_twin.mesh_path


def row(label: str, twin: Twin, cfg: ValidateConfig) -> dict[str, Any]:
    t0 = time.perf_counter()
    summary = validate(twin, cfg)
    cells = [c for r in summary["poses"] for c in r["variants"].values()]
    ran = [c for c in cells if "failed" not in c]
    runs = sum(c["starts"] for c in ran)
    conv = sum(round(c["success_rate"] * c["starts"]) for c in ran)

    def med(key: str) -> float:
        v = [c[key] for c in ran if c.get(key) is not None]
        return float(np.median(v)) if v else float("nan")

    return {
        "twin": label, "profile": cfg.profile, "poses": len(summary["poses"]),
        "refused": len(cells) - len(ran), "runs": runs, "converged": conv,
        "lost": sum(c.get("lost", 0) for c in ran),
        "final_translation_mm": round(1000 * med("median_final_translation"), 2),
        "final_rotation_deg": round(float(np.degrees(med("median_final_rotation"))), 2),
        "final_cut_mm": round(1000 * med("median_final_cut_error"), 2),
        "wall_s": round(time.perf_counter() - t0, 1),
    }  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--plants", nargs="*", default=["sample", "vsp_ww"])
    ap.add_argument("--profiles", nargs="*", default=["ideal", "field"])
    ap.add_argument("--cut-points", type=int, default=4)
    ap.add_argument("--starts", type=int, default=4)
    ap.add_argument("--variants", nargs="*", default=["point_to_plane"])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--keep", type=Path, help="leave the twins here")
    ap.add_argument("--json", type=Path)
    a = ap.parse_args()
    rows = []
    print("| plant | profile | twin | poses (refused) | converged / runs | lost | final mm | "
          "final deg | at the cut mm | s |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        work = a.keep or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        for name in a.plants:
            scanned, true_twin, world = twins(name, work, a.cut_points, a.seed)
            for profile in a.profiles:
                base = dict(variants=tuple(a.variants), starts=a.starts, profile=profile,
                            seed=a.seed, force=True)  # fmt: skip
                for label, twin, cfg in (
                    ("true", true_twin, ValidateConfig(**base)),  # type: ignore[arg-type]
                    ("scanned", scanned, ValidateConfig(**base, world=str(world))),  # type: ignore[arg-type]
                ):
                    r = {"plant": name, **row(label, Twin.load(twin.root), cfg)}
                    rows.append(r)
                    print(f"| {name} | {profile} | {label} | {r['poses']} ({r['refused']}) | "
                          f"{r['converged']}/{r['runs']} | {r['lost']} | "
                          f"{r['final_translation_mm']:.2f} | {r['final_rotation_deg']:.2f} | "
                          f"{r['final_cut_mm']:.2f} | {r['wall_s']:.0f} |", flush=True)  # fmt: skip
    if a.json:
        a.json.write_text(json.dumps({"machine": machine(), "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
