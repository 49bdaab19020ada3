"""The current tables of `docs/results/speed.md`, printed from the files in `benchmarks/results/`
(one current file per benchmark and vine), each headed by the machine and commit it was measured
on: what the document shows is what the files hold.

    .venv/bin/python benchmarks/tables.py > /tmp/tables.md
"""

from __future__ import annotations

import json
import statistics
from pathlib import Path
from typing import Any

from icp_tables import print_icp

RESULTS = Path(__file__).resolve().parent / "results"
#: The vines, in the documents' order, by the suffix of their results files (a file's vine is
#: named by its suffix: the twin's own name is its folder's, which a user chooses).
VINES = {"": "vine_bilateral", "_dense": "dense", "_vsp_ww_grapevine": "vsp_ww_grapevine",
         "_gdc_can1_grapevine": "gdc_can1_grapevine"}  # fmt: skip


def _load(name: str) -> dict[str, Any] | None:
    path = RESULTS / name
    return json.loads(path.read_text()) if path.exists() else None


def provenance(name: str, data: dict[str, Any]) -> str:
    m = data.get("machine") or {}
    where = f"{m.get('cpu', '?')} ({m.get('simd', '')}), {m.get('cores', '?')} cores"
    return f"`{name}`: {where}, commit {m.get('commit', '?')}, {m.get('measured', '?')[:16]} UTC"


def per_vine(benchmark: str, title: str) -> list[dict[str, Any]]:
    """The benchmark's file of each vine, after a heading and their provenance."""
    files = [(f"{benchmark}{v}.json", {**d, "twin": name}) for v, name in VINES.items()
             if (d := _load(f"{benchmark}{v}.json"))]  # fmt: skip
    print(f"\n## {title} (`benchmarks/{benchmark}.py`)\n")
    print("\n".join(f"- {provenance(n, d)}" for n, d in files) + "\n")
    return [d for _, d in files]


def one_file(benchmark: str, title: str) -> dict[str, Any] | None:
    """The benchmark's one file (every vine in it), after a heading and its provenance."""
    data = _load(f"{benchmark}.json")
    print(f"\n## {title} (`benchmarks/{benchmark}.py`)\n")
    if data is not None:
        print(f"- {provenance(f'{benchmark}.json', data)}\n")
    return data


def main() -> None:
    print_icp(per_vine("icp", "ICP and the servo cycle"))

    if (per := one_file("perception", "Perception")) is not None:
        print("| vine | voxel | rule | ours ms | Open3D ms | ours / Open3D | points |")
        print("|---|---|---|---|---|---|---|")
        for t in per["tables"]:
            for r in t["rows"]:
                print(f"| {t['twin']} | {1000 * t['voxel']:.0f} mm | {r['rule']} | "
                      f"{r['perception_ms']:.2f} | {r['open3d_ms']:.2f} | "
                      f"{r['ratio_to_open3d']:.2f} | {r['points']} |")  # fmt: skip

    renders = per_vine("render", "References: one view, and the export of 1000")
    print("| vine | backend | render ms | D405 model ms | perception ms | reference ms |")
    print("|---|---|---|---|---|---|")
    for d in renders:
        for r in d["per_reference"]:
            if r.get("resolution", "848x480") != "848x480":
                continue
            print(f"| {d['twin']} | {r['backend']} | {r['render_ms']:.1f} | "
                  f"{r['sensor_ms']:.1f} | {r['perception_ms']:.1f} | {r['reference_ms']:.1f} |")  # fmt: skip
    print("\n| vine | backend | workers | 1000 references (s) | rerun, all skipped (s) |")
    print("|---|---|---|---|---|")
    for d in renders:
        for e in d["export"]:
            print(f"| {d['twin']} | {e['backend']} | {e['workers']} | {e['seconds']:.1f} | "
                  f"{e['rerun_seconds']:.2f} |")  # fmt: skip

    if (sim := one_file("sim", "Closed-loop simulation")) is not None:
        print("| vine | faces | backend | x real time | ms per frame | render ms | servo step ms |")
        print("|---|---|---|---|---|---|---|")
        for r in sim["rows"]:
            print(f"| {r['twin']} | {r['faces']} | {r['backend']} | {r['x_real_time']:.2f} | "
                  f"{r['ms_per_frame']:.1f} | {r['render_ms']:.1f} | {r['servo_step_ms']:.1f} |")  # fmt: skip

    webs = per_vine("web", "The web app: a click to its preview on the page")
    print("| vine | page's WebGL | triangles drawn | server ms (median, p90) | click to preview "
          "ms (median, p90) | measured by |")  # fmt: skip
    print("|---|---|---|---|---|---|")
    for d in webs:
        for r in d["runs"].values():
            # drawn: the page's own clock; idle: the harness's (files made before it had one)
            key, clock = ("drawn_ms", "the page") if "drawn_ms" in r else ("idle_ms", "harness")
            s, b = r["server_ms"], r[key]
            print(f"| {d['twin']} | {d['gl']} | {r['drawn_faces']} | {s['median']:.0f}, "
                  f"{s['p90']:.0f} | {b['median']:.0f}, {b['p90']:.0f} | {clock} |")  # fmt: skip

    scan = one_file("scan_speed", "A scan of a vine, 500k points, to a twin")
    if scan is not None:
        print("| route | median s | runs s | Chamfer mm | F-score at 2 mm |")
        print("|---|---|---|---|---|")
        for name, key, acc in (
            ("vinetwin import-scan", "import_scan", "import_scan"),
            ("Open3D outliers, normals, Poisson depth 9", "poisson", "poisson"),
        ):
            runs = scan[f"{key}_s"]
            print(f"| {name} | {statistics.median(runs):.1f} | "
                  f"{', '.join(f'{x:.1f}' for x in runs)} | {scan[f'{acc}_chamfer_mm']:.2f} | "
                  f"{scan[f'{acc}_fscore_2mm']:.2f} |")  # fmt: skip


if __name__ == "__main__":
    main()
