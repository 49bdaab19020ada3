"""Benchmark: the perception chain's outlier rules, their time and the ICP accuracy they give.

For each twin (`--twin`, repeatable; default the bundled sample) and voxel (4 and 2 mm), the
twin's poses are rendered at 848x480 with Open3D ray casting through the D405 sensor model: a
reference at each pose and `--trials` current views at known offsets from it (warm: 2 cm /
3 deg, as in `benchmarks/icp.py`), each with its own noise. The same depth images then go
through the perception chain once per outlier rule (`PerceptionConfig.outlier_rule`: radius,
statistical, none), and each rule's clouds through our four ICP variants (the servo's
`ICPConfig` defaults, the reference's camera given).

Printed per twin, voxel and rule: the chain's median time per current image, the outlier step's
alone, the median number of points, the same chain written with Open3D (create_from_depth_image,
voxel_down_sample, the same outlier rule, estimate_normals) on the same images, and per ICP
variant the median and 90th-percentile translation error (mm) against the true offset.

`--decimation 1 2` compares `PerceptionConfig.decimation` values instead of the rules (each row
one decimation, with the twin's rule), reference and current clouds alike.

    .venv/bin/python benchmarks/perception.py [--twin TWIN ...] [--trials 3] [--quick]
        [--decimation N ...] [--json out.json]
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import statistics
import time
from pathlib import Path
from typing import Any

import numpy as np
from icp import STARTS
from render import open3d_chain  # benchmarks/render.py: the same chain written with Open3D
from results_file import write_json

from vinetwin import frames as fr
from vinetwin.cloud import ICP_VARIANTS, OUTLIER_RULES, PerceptionConfig, outlier_mask, perceive
from vinetwin.registration.icp import ICP, ICPConfig
from vinetwin.render.backends import get_backend
from vinetwin.render.sensor import SensorConfig, apply_d405_model
from vinetwin.twin import Twin

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "samples" / "vine_bilateral.twin"
WARM = STARTS["warm"]  # benchmarks/icp.py's warm start: 2 cm / 3 deg


def _median_ms(repeats: int, fn: Any, *args: Any) -> float:
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn(*args)
        ts.append(time.perf_counter() - t0)
    return 1000 * statistics.median(ts)


def views(twin: Twin, trials: int, rng: np.random.Generator) -> list[dict[str, Any]]:
    """Per pose: the reference depth and `trials` current depths at known offsets."""
    mesh = twin.load_mesh()
    backend = get_backend("open3d", mesh.vertices, mesh.faces, twin.camera)
    sensor = SensorConfig()
    out = []
    for pose in twin.poses:
        Tg = pose.T_vine_camera
        ref = apply_d405_model(backend.render(Tg), twin.camera, np.random.default_rng(1), sensor)
        cur = []
        for k in range(trials):
            D = fr.random_pose(rng, WARM[0], np.radians(WARM[1]))
            depth = apply_d405_model(
                backend.render(Tg @ D), twin.camera, np.random.default_rng(100 + k), sensor
            )
            cur.append((depth, D))
        out.append({"pose": pose.id, "reference": ref, "currents": cur})
    backend.close()
    return out


def run_rule(
    twin: Twin, data: list[dict[str, Any]], per: PerceptionConfig, repeats: int
) -> dict[str, Any]:
    cam = twin.camera
    t_chain, t_rule, t_o3d, npts = [], [], [], []
    errors: dict[str, list[float]] = {v: [] for v in ICP_VARIANTS}
    icp_ms: dict[str, list[float]] = {v: [] for v in ICP_VARIANTS}
    for view in data:
        reference = perceive(view["reference"], cam, per)
        icps = {
            v: ICP(reference, ICPConfig(variant=v), camera=cam, max_depth=per.max_depth)
            for v in ICP_VARIANTS
        }
        for depth, D in view["currents"]:
            cloud = perceive(depth, cam, per)
            t_chain.append(_median_ms(repeats, perceive, depth, cam, per))
            npts.append(len(cloud))
            raw = perceive(depth, cam, dataclasses.replace(per, outlier_rule="none"))
            t_rule.append(_median_ms(repeats, outlier_mask, raw.points, per))
            t_o3d.append(_median_ms(repeats, open3d_chain, depth, cam, per))
            for v, icp in icps.items():
                t0 = time.perf_counter()
                r = icp.align(cloud, np.eye(4))
                icp_ms[v].append(1000 * (time.perf_counter() - t0))
                errors[v].append(1000 * fr.pose_error(r.T_ref_cur, D)[0])
    row: dict[str, Any] = {
        "rule": per.outlier_rule,
        "decimation": per.decimation,
        "perception_ms": statistics.median(t_chain),
        "outlier_ms": statistics.median(t_rule),
        "open3d_ms": statistics.median(t_o3d),
        "points": int(statistics.median(npts)),
        "icp": {},
    }
    row["ratio_to_open3d"] = row["perception_ms"] / row["open3d_ms"]
    for v in ICP_VARIANTS:
        e = np.array(errors[v])
        row["icp"][v] = {
            "t_mm_median": float(np.median(e)),
            "t_mm_p90": float(np.percentile(e, 90)),
            "within_1mm": float(np.mean(e < 1.0)),
            "ms": float(np.median(icp_ms[v])),
        }
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--twin", type=Path, action="append", help="twin folder (repeatable)")
    ap.add_argument("--trials", type=int, default=3, help="current views per pruning pose")
    ap.add_argument("--repeats", type=int, default=3, help="timed runs per image (median)")
    ap.add_argument("--quick", action="store_true", help="1 trial, 1 repeat, 4 mm only")
    ap.add_argument(
        "--decimation", type=int, nargs="+", help="compare these decimations (twin's rule)"
    )
    ap.add_argument("--json", type=Path, help="write the figures here")
    args = ap.parse_args()
    if args.quick:
        args.trials, args.repeats = 1, 1
    voxels = (0.004,) if args.quick else (0.004, 0.002)
    print(f"{os.cpu_count()} CPUs; rules {', '.join(OUTLIER_RULES)}; ICP from a warm start "
          f"({WARM[0] * 100:.0f} cm / {WARM[1]:.0f} deg), translation error in mm")  # fmt: skip
    results: dict[str, Any] = {"trials": args.trials, "tables": []}
    for path in args.twin or [SAMPLE]:
        twin = Twin.load(path)
        data = views(twin, args.trials, np.random.default_rng(7))
        for voxel in voxels:
            rows = []
            if args.decimation:
                for dec in args.decimation:
                    per = dataclasses.replace(twin.perception, voxel_size=voxel, decimation=dec)
                    rows.append(run_rule(twin, data, per, args.repeats))
            else:
                for rule in OUTLIER_RULES:
                    per = dataclasses.replace(twin.perception, voxel_size=voxel, outlier_rule=rule)
                    rows.append(run_rule(twin, data, per, args.repeats))
            n = sum(len(v["currents"]) for v in data)
            print(f"\n{twin.name}, voxel {1000 * voxel:.0f} mm, {n} current views")
            head = " ".join(f"{v[:14]:>14}" for v in ICP_VARIANTS)
            print(f"{'rule/decim.':12} {'chain ms':>8} {'rule ms':>7} {'Open3D ms':>9} {'points':>6} "
                  f"{head}   (ICP error median/p90 mm)")  # fmt: skip
            for r in rows:
                acc = " ".join(
                    f"{r['icp'][v]['t_mm_median']:6.3f}/{r['icp'][v]['t_mm_p90']:7.3f}"
                    for v in ICP_VARIANTS
                )
                name = f"{r['rule']} /{r['decimation']}"
                print(f"{name:12} {r['perception_ms']:8.2f} {r['outlier_ms']:7.2f} "
                      f"{r['open3d_ms']:9.2f} {r['points']:6d} {acc}")  # fmt: skip
            results["tables"].append({"twin": twin.name, "voxel": voxel, "views": n, "rows": rows})
    write_json(args.json, results)


if __name__ == "__main__":
    main()
