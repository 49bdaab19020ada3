"""The up axis of `vinetwin import-scan` on trees scanned without ground: each Tree-Models-Library
tree model in a folder (`*.txt` cylinder lists) scanned by the simulated LiDAR
(`scan.synthetic`, no trellis, no ground), written in metres in a scanner's frame (y up at a
random heading) and analysed by the command's own code with the up axis left to be found:
the angle between the up found and the truth's, what it was found from, and whether the import
says the up axis is uncertain.

The bundled trees (`../shared/data/trees/tree-models-library`) are the ones the import's settings
were chosen on; the library's other 39 models (CearLab/Tree-Models-Library on GitHub, MIT) are
not bundled: clone it and name its `Tree Models` folder to check the rule on trees it was not
chosen on.

    .venv/bin/python benchmarks/scan_up.py --trees "Tree-Models-Library/Tree Models" \\
        --qualities realistic coarse [--json benchmarks/results/scan_up.json]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from results_file import machine

ROOT = Path(__file__).resolve().parents[1]
BUNDLED = ROOT.parent / "shared" / "data" / "trees" / "tree-models-library"


def run_one(job: tuple[Path, str, int, Path]) -> dict[str, Any]:
    import warnings

    from scan_accuracy import write_ply

    from vinetwin.errors import VinetwinError
    from vinetwin.scan.config import ScanImportConfig
    from vinetwin.scan.importer import analyse_scan
    from vinetwin.scan.synthetic import QUALITY_LADDER, scanner_frame, simulate_scan
    from vinetwin.twin.importers import read_cylinders
    from vinetwin.twin.skeleton import tube_mesh

    warnings.simplefilter("ignore")
    path, quality, seed, work = job
    V, F = tube_mesh(read_cylinders(path), edge=0.004, caps="round")
    P, _ = simulate_scan(V, F, QUALITY_LADDER[quality], seed)
    T_sv = scanner_frame(seed)
    f = work / f"{path.stem}_{quality}_{seed}.ply"
    write_ply(f, P @ T_sv[:3, :3].T + T_sv[:3, 3])
    row: dict[str, Any] = {"tree": path.stem, "quality": quality, "seed": seed, "points": len(P)}
    try:
        scan = analyse_scan(f, ScanImportConfig(plant="tree"))
    except VinetwinError as e:
        return {**row, "error": str(e)}
    finally:
        f.unlink()
    T = scan.T_vine_scan @ T_sv
    return {**row, "up_error_deg": round(float(np.degrees(np.arccos(np.clip(T[2, 2], -1, 1)))), 1),
            "up_from": scan.up_from,
            "uncertain": any("up axis is uncertain" in n for n in scan.notes)}  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--trees", type=Path, default=BUNDLED,
                    help="a folder of Tree-Models-Library *.txt models")  # fmt: skip
    ap.add_argument("--qualities", nargs="*", default=["realistic", "coarse"])
    ap.add_argument("--seeds", type=int, default=1)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--json", type=Path)
    a = ap.parse_args()
    trees = sorted(a.trees.glob("*.txt"))
    if not trees:
        sys.exit(f"no *.txt tree models in {a.trees}")
    print("| tree | quality | seed | points | up error deg | found from | says uncertain |")
    print("|---|---|---|---|---|---|---|")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        jobs = [(t, q, s, Path(tmp)) for t in trees for q in a.qualities for s in range(a.seeds)]
        with ProcessPoolExecutor(a.workers) as ex:
            for r in ex.map(run_one, jobs):
                rows.append(r)
                if "error" in r:
                    print(f"| {r['tree']} | {r['quality']} | {r['seed']} | {r['points']} | "
                          f"refused: {r['error']} | | |", flush=True)  # fmt: skip
                    continue
                print(f"| {r['tree']} | {r['quality']} | {r['seed']} | {r['points']} | "
                      f"{r['up_error_deg']} | {r['up_from']} | {'yes' if r['uncertain'] else 'no'} |",
                      flush=True)  # fmt: skip
    ok = [r for r in rows if "error" not in r]
    right = sum(r["up_error_deg"] <= 5.0 for r in ok)
    silent = sum(r["up_error_deg"] > 5.0 and not r["uncertain"] for r in ok)
    print(f"\n{right} of {len(rows)} scans within 5 degrees; {silent} more than 5 degrees off "
          f"without saying so; {len(rows) - len(ok)} refused")  # fmt: skip
    if a.json:
        a.json.write_text(json.dumps({"machine": machine(), "trees": str(a.trees), "rows": rows},
                                     indent=1))  # fmt: skip


if __name__ == "__main__":
    main()
