"""Benchmark: vineyard-size batches through each executor, side by side in one run.

A vineyard folder of N twins (copies of the two bundled samples, 4-5 pruning poses each) is
exported with the default backend (Open3D ray casting):
- in this process (the default for open3d: its ray caster already uses every core);
- a local pool of 2 worker processes (`--workers 2`);
- Ray with 2 CPUs (`--ray --workers 2`), timed with Ray already started and, separately, the
  start-up a one-off command pays.
Then closed-loop validation runs (kinematic simulation, point-to-plane, 2 starts of pose p1
per twin) over a smaller vineyard (`--validate-twins`) through the local pool and Ray. Each figure is the median of `--repeats` (fresh folders).

    .venv/bin/python benchmarks/scale.py [--twins 24] [--repeats 3] [--quick] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

from vinetwin.executor import ExecutorConfig
from vinetwin.render.export import export_many
from vinetwin.sim.config import ValidateConfig
from vinetwin.sim.validate import validate_many
from vinetwin.twin.model import Twin, find_twins

ROOT = Path(__file__).resolve().parents[1]
SAMPLES = ("vine_bilateral", "vine_unilateral")


def make_vineyard(root: Path, n: int) -> Path:
    for k in range(n):
        sample = SAMPLES[k % 2]
        shutil.copytree(
            ROOT / "samples" / f"{sample}.twin",
            root / f"row{k // 8 + 1}" / f"vine{k:03d}.twin",
            ignore=shutil.ignore_patterns("references", "validation", "campaign", "servo"),
        )
    return root


def load(root: Path) -> list[Twin]:
    return [Twin.load(p) for p in find_twins(root)]


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--twins", type=int, default=24)
    ap.add_argument("--validate-twins", type=int, default=6, help="twins in the validation job")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--quick", action="store_true", help="4 twins, 1 repeat")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    if args.quick:
        args.twins, args.repeats, args.validate_twins = 4, 1, 2

    import ray

    work = Path(tempfile.mkdtemp(prefix="vinetwin-scale-"))
    rows: list[dict[str, Any]] = []
    try:
        t0 = time.perf_counter()
        ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, configure_logging=False,
                 runtime_env={"env_vars": {"OMP_NUM_THREADS": "1", "VINETWIN_WORKER_THREADS": "1",
                                           "NUMBA_NUM_THREADS": "1"}})  # fmt: skip
        ray_start = time.perf_counter() - t0
        ray.shutdown()

        executors = {
            "in process (open3d default)": ExecutorConfig(workers=1),
            "local pool, 2 workers": ExecutorConfig(workers=2),
            "Ray, 2 CPUs": ExecutorConfig(kind="ray", workers=2),
        }
        n_refs = 0
        for name, ex in executors.items():
            times = []
            for r in range(args.repeats):
                root = make_vineyard(work / f"export-{len(rows)}-{r}", args.twins)
                twins = load(root)
                n_refs = sum(len(t.poses) for t in twins)
                t0 = time.perf_counter()
                report = export_many(twins, executor=ex)
                times.append(time.perf_counter() - t0)
                assert report.ok and report.count("rendered") == n_refs
                shutil.rmtree(root)
            med = statistics.median(times)
            rows.append({"job": "export", "executor": name, "items": n_refs, "seconds": med,
                         "per_second": n_refs / med})  # fmt: skip

        vcfg = ValidateConfig(
            variants=("point_to_plane",), poses=("p1",), starts=2, duration=4.0,
            radius_translation=0.03, radius_rotation=0.1,
        )  # fmt: skip
        for name, ex in list(executors.items())[1:]:
            times = []
            n_runs = 0
            for r in range(args.repeats):
                root = make_vineyard(work / f"validate-{len(rows)}-{r}", args.validate_twins)
                twins = load(root)
                n_runs = len(twins) * vcfg.starts
                t0 = time.perf_counter()
                summaries = validate_many(twins, vcfg, executor=ex)
                times.append(time.perf_counter() - t0)
                assert all("failed" not in s for s in summaries)
                shutil.rmtree(root)
            med = statistics.median(times)
            rows.append({"job": "validate", "executor": name, "items": n_runs, "seconds": med,
                         "per_second": n_runs / med})  # fmt: skip
    finally:
        shutil.rmtree(work, ignore_errors=True)

    base = {r["job"]: r["per_second"] for r in rows if r["executor"].startswith("local pool")}
    print(f"\nvineyard of {args.twins} twins, median of {args.repeats}; Ray start-up "
          f"{ray_start:.1f} s (included in the Ray rows: each call starts and stops a local Ray)\n")  # fmt: skip
    print(f"{'job':<9} {'executor':<28} {'items':>6} {'seconds':>8} {'per s':>7} {'vs pool':>8}")
    for r in rows:
        r["ratio_to_local_pool"] = r["per_second"] / base[r["job"]]
        print(f"{r['job']:<9} {r['executor']:<28} {r['items']:>6} {r['seconds']:>8.2f} "
              f"{r['per_second']:>7.2f} {r['ratio_to_local_pool']:>7.2f}x")  # fmt: skip
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(
            json.dumps(
                {
                    "twins": args.twins,
                    "repeats": args.repeats,
                    "ray_start_s": ray_start,
                    "rows": rows,
                },
                indent=1,
            )
            + "\n"
        )


if __name__ == "__main__":
    main()
