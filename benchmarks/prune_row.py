"""A row of generated vines pruned by `vinetwin prune` on each executor: the local pool and Ray
(a local Ray cluster), each vine's result compared to the in-process one's (`comparable`: the
per-vine results rounded to 1e-9: cuts, statuses, reasons, blade errors, times, collisions and
plans; wall-clock fields left out). Prints a table per vine and whether every executor agreed,
with each executor's wall time.

    .venv/bin/python benchmarks/prune_row.py [--vines 10] [--cuts 4] [--sim mujoco]
        [--profile ideal] [--workers 2] [--no-ray] [--keep DIR] [--json FILE]
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
from results_file import write_json


def make_row(row: Path, vines: int, cuts: int) -> None:
    """`vinetwin sample --seed k` for k < vines: one generated vine per seed."""
    row.mkdir(parents=True, exist_ok=True)
    exe = Path(sys.executable).parent / "vinetwin"
    for k in range(vines):
        out = row / f"vine{k:02d}.twin"
        if not out.exists():
            subprocess.run([str(exe), "sample", "--seed", str(k), "--cut-points", str(cuts),
                            "--out", str(out)], check=True, capture_output=True)  # fmt: skip


def main() -> None:
    from vinetwin.executor import ExecutorConfig
    from vinetwin.sim.prune import PruneConfig
    from vinetwin.sim.prune_row import comparable, prune_row

    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--vines", type=int, default=10)
    ap.add_argument("--cuts", type=int, default=4)
    ap.add_argument("--sim", default="mujoco", choices=["kinematic", "mujoco"])
    ap.add_argument("--profile", default="ideal")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--no-ray", action="store_true")
    ap.add_argument("--keep", type=Path)
    ap.add_argument("--json", type=Path)
    a = ap.parse_args()
    work = Path(a.keep) if a.keep else Path(tempfile.mkdtemp(prefix="prune-row-"))
    row = work / "row"
    make_row(row, a.vines, a.cuts)
    cfg = PruneConfig(sim=a.sim, profile=a.profile)  # type: ignore[arg-type]
    executors: dict[str, ExecutorConfig] = {
        "in process": ExecutorConfig(workers=1),
        f"local pool ({a.workers})": ExecutorConfig(workers=a.workers),
    }
    if not a.no_ray:
        executors["Ray (local)"] = ExecutorConfig(kind="ray", workers=a.workers)
    results: dict[str, dict[str, Any]] = {}
    walls: dict[str, float] = {}
    for name, ex in executors.items():
        t0 = time.perf_counter()
        out = prune_row(row, cfg, work / f"out_{len(results)}", ex, force=True)
        walls[name] = time.perf_counter() - t0
        results[name] = out["vines"]
        print(f"{name}: {len(out['vines'])} vines in {walls[name]:.0f} s", flush=True)
    first = next(iter(results))
    vines = sorted(results[first])
    same = {
        name: [comparable(results[name][v]) == comparable(results[first][v]) for v in vines]
        for name in results
    }
    print("\n| vine | cuts done | done right | collisions | planning s | "
          + " | ".join(f"same on {n}" for n in results if n != first) + " |")  # fmt: skip
    print("|---|---|---|---|---|" + "---|" * (len(results) - 1))
    for i, v in enumerate(vines):
        s = results[first][v]["summary"]
        cells = " | ".join("yes" if same[n][i] else "NO" for n in results if n != first)
        print(f"| {v} | {s['done']}/{s['poses']} | {s['done_right']} | "
              f"{results[first][v]['collisions']} | {results[first][v]['planning_s']:.2f} | "
              f"{cells} |")  # fmt: skip
    agree = all(all(x) for x in same.values())
    print(f"\nevery executor gave identical per-vine results: {'yes' if agree else 'NO'}")
    write_json(a.json, {
        "vines": a.vines, "sim": a.sim, "profile": a.profile, "agree": agree,
        "wall_s": walls, "same": same,
        "per_vine": {v: results[first][v]["summary"] for v in vines},
    })  # fmt: skip
    if not agree:
        raise SystemExit(1)


if __name__ == "__main__":
    main()
