"""Markdown tables from `benchmarks/icp.py --json` files: per vine and voxel, each variant's time
as a ratio to the fastest peer implementing it (LM: to our point-to-plane), and the servo cycle.

    .venv/bin/python benchmarks/icp_tables.py benchmarks/results/icp*.json
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

VARIANTS = ("point_to_point", "point_to_plane", "symmetric", "lm")


def main() -> None:
    print_icp([json.loads(Path(p).read_text()) for p in sys.argv[1:]])


def print_icp(runs: list[dict]) -> None:
    """The two tables of `benchmarks/icp.py` runs (one per vine)."""
    print("ICP time / fastest peer's (same objective, same clouds, same levels; LM: / our "
          "point-to-plane); median translation error ours / the peer's (mm); where the run "
          "records each case's error, the median of the paired differences with its 95% "
          "bootstrap interval and the verdict (benchmarks/icp.py paired_accuracy)\n")  # fmt: skip
    print("| vine | voxel | start | points | point-to-point | point-to-plane | symmetric | LM |")
    print("|---|---|---|---|---|---|---|---|")
    for run in runs:
        for t in run["tables"]:
            rows = {r["method"]: r for r in t["rows"]}
            cells = []
            for v in VARIANTS:
                r = rows[f"vinetwin {v}"]
                if v == "lm":
                    cells.append(f"{r['ratio_to_our_point_to_plane']:.2f}")
                    continue
                peer = rows[r["fastest_peer"]]
                acc = r.get("accuracy_vs_fastest_peer")
                paired = (
                    f"; {acc['median_diff_mm']:+.2f} [{acc['ci95_mm'][0]:+.2f}, "
                    f"{acc['ci95_mm'][1]:+.2f}] {acc['verdict']}"
                    if acc
                    else ""
                )
                cells.append(
                    f"{r['ratio_to_fastest_peer']:.2f} ({r['ms']:.1f} vs {peer['ms']:.1f} ms; "
                    f"{r['t_mm_median']:.2f} / {peer['t_mm_median']:.2f}{paired})"
                )
            print(f"| {run.get('twin', run.get('sample'))} | {1000 * t['voxel']:.0f} mm | "
                  f"{t['start']} | {t['points']} | " + " | ".join(cells) + " |")  # fmt: skip
    print("\nServo cycle (perception + ICP + control), Hz; in brackets perception ms and, tracking, "
          "the share of frames the final ICP level alone aligned (runs that record it)\n")  # fmt: skip
    print("| vine | voxel | start | point-to-point | point-to-plane | symmetric | LM |")
    print("|---|---|---|---|---|---|---|")
    for run in runs:
        cyc = run.get("cycles", [])
        keys = sorted(
            {(c["voxel"], c.get("start", "warm")) for c in cyc},
            key=lambda k: (-k[0], k[1] != "tracking"),
        )
        for voxel, start in keys:
            by = {
                c["variant"]: c
                for c in cyc
                if c["voxel"] == voxel and c.get("start", "warm") == start
            }
            cells = [
                f"{by[v]['hz']:.0f} ({by[v]['perception_ms']:.1f}"
                + (
                    f"; {100 * by[v]['tracked']:.0f}%)"
                    if start == "tracking" and "tracked" in by[v]
                    else ")"
                )
                for v in VARIANTS
                if v in by
            ]
            print(
                f"| {run.get('twin', run.get('sample'))} | {1000 * voxel:.0f} mm | {start} | "
                + " | ".join(cells)
                + " |"
            )


if __name__ == "__main__":
    main()
