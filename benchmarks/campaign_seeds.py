"""Several campaign reports side by side: cells converged, final errors, refusal streaks,
re-acquisitions and named stops per report (a seed, a simulation), and the grid per start and
variant over all of them.

    python benchmarks/campaign_seeds.py OUT.md DIR [DIR ...]

Each DIR is a campaign's report folder (its campaign.json); OUT.md receives the tables, which are
also printed.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import numpy as np


def _name(data: dict[str, Any]) -> str:
    c = data["config"]
    return f"{c['sim']}, seed {c['seed']}"


def per_report(datas: list[dict[str, Any]]) -> list[str]:
    rows = [
        "| report | grid converged | p2p/LM median final t (mm) | plane/symm median final t (mm) "
        "| longest refusal streak of a run that went on (s) | re-acquisitions | named stops "
        "| disturbance recovered |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for d in datas:
        grid = [r["summary"] for r in d["runs"] if r["group"] == "grid"]
        dist = [r["summary"] for r in d["runs"] if r["group"] == "disturbance"]
        pp = [s["final_translation"] for s in grid if s["variant"] in ("point_to_point", "lm")]
        pl = [
            s["final_translation"] for s in grid if s["variant"] in ("point_to_plane", "symmetric")
        ]
        every = [r["summary"] for r in d["runs"]]
        dc = d["config"]
        rows.append(
            f"| {_name(d)} | {sum(s['converged'] for s in grid)}/{len(grid)} "
            f"| {1000 * np.median(pp):.2f} | {1000 * np.median(pl):.2f} "
            f"| {max(s.get('longest_refusal_s', 0.0) for s in every if not s.get('lost')):.2f} "
            f"| {sum(s.get('reacquisitions', 0) for s in every)} "
            f"| {sum(bool(s.get('lost')) for s in every)} "
            f"| {sum(s['converged'] for s in dist)}/{len(dist)} at "
            f"{1000 * float(np.linalg.norm(dc['disturbance_translation'])):.0f} mm / "
            f"{float(np.linalg.norm(dc['disturbance_rotation'])):.2f} rad |"
        )
    return rows


def per_cell(datas: list[dict[str, Any]]) -> list[str]:
    cells: dict[tuple[int, str], list[str]] = {}
    for d in datas:
        for r in d["runs"]:
            if r["group"] != "grid":
                continue
            s = r["summary"]
            mark = (
                f"{1000 * s['final_translation']:.2f} mm"
                if s["converged"]
                else ("lost" if s.get("lost") else "no")
            )
            cells.setdefault((r["start_index"], s["variant"]), []).append(mark)
    variants = list(dict.fromkeys(v for _, v in cells))
    rows = [
        "| start | " + " | ".join(variants) + " |",
        "|---|" + "---|" * len(variants),
    ]
    for i in sorted({i for i, _ in cells}):
        rows.append(
            f"| {i + 1} | " + " | ".join(", ".join(cells.get((i, v), [])) for v in variants) + " |"
        )
    return rows


def main(argv: list[str]) -> None:
    if len(argv) < 2:
        raise SystemExit(__doc__)
    out, dirs = Path(argv[0]), [Path(a) for a in argv[1:]]
    datas = [json.loads((d / "campaign.json").read_text()) for d in dirs]
    text = "\n".join(
        [
            f"# {datas[0]['twin']}: {len(datas)} campaign reports",
            "",
            *per_report(datas),
            "",
            "Final translation error of each grid cell, one entry per report in the order above "
            "(no: not converged; lost: the named stop).",
            "",
            *per_cell(datas),
            "",
        ]
    )
    out.write_text(text)
    print(text)


if __name__ == "__main__":
    main(sys.argv[1:])
