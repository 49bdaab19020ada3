"""Benchmark: milliseconds per reference cloud per backend, and batch export throughput.

For each backend and resolution (848x480, 1280x720) it times, over a twin's poses (`--twin`,
default the bundled sample) and perturbed copies of them: the depth render, the D405 sensor model, the perception chain, and
the whole reference. Side by side, in the same run, it times the perception chain a user would
otherwise write with Open3D (create_from_depth_image, voxel_down_sample, the chain's outlier
rule, estimate_normals + orient towards the camera) on the same images.
Then it exports N references (default 1000) with the default backend (`--export-backend`; auto:
`vinetwin.render.backends.resolve_backend`) in 1 and 2 worker processes.

Goals: at most 50 ms per reference (issue: render); 1000 references in at most 10 s on 2 cores
with the default backend (issue: speed).

    .venv/bin/python benchmarks/render.py [--quick] [--json out.json] [--export-backend NAME]
        [--workdir DIR]
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
from results_file import write_json

from vinetwin import _lazy
from vinetwin import frames as fr
from vinetwin.camera import CameraModel, d405
from vinetwin.cloud import PerceptionConfig, perceive
from vinetwin.errors import BackendUnavailable
from vinetwin.render.backends import BACKENDS, get_backend, resolve_backend
from vinetwin.render.export import export_references
from vinetwin.render.sensor import apply_d405_model
from vinetwin.twin import Approach, Twin, pruning_pose

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "samples" / "vine_bilateral.twin"


def open3d_chain(depth: np.ndarray, cam: CameraModel, cfg: PerceptionConfig) -> int:
    """What a user would write with Open3D for the same perception steps and outlier rule."""
    o3d = _lazy.open3d()
    intr = o3d.camera.PinholeCameraIntrinsic(cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy)
    img = o3d.geometry.Image(depth.astype(np.float32))
    pc = o3d.geometry.PointCloud.create_from_depth_image(
        img, intr, depth_scale=1.0, depth_trunc=cfg.max_depth
    )
    pc = pc.voxel_down_sample(cfg.voxel_size)
    if cfg.outlier_rule == "radius":
        pc, _ = pc.remove_radius_outlier(cfg.radius_neighbors, cfg.outlier_radius)
    elif cfg.outlier_rule == "statistical":
        pc, _ = pc.remove_statistical_outlier(cfg.sor_neighbors, cfg.sor_std_ratio)
    pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(cfg.normal_radius, cfg.normal_max_nn))
    pc.orient_normals_towards_camera_location(np.zeros(3))
    return len(pc.points)


def poses_around(twin: Twin, n: int, rng: np.random.Generator) -> list[np.ndarray]:
    out = []
    for i in range(n):
        p = twin.poses[i % len(twin.poses)]
        out.append(p.T_vine_camera @ fr.random_pose(rng, rng.uniform(0, 0.02), rng.uniform(0, 0.1)))
    return out


def time_backends(twin: Twin, n_poses: int, rng: np.random.Generator) -> list[dict[str, Any]]:
    mesh = twin.load_mesh()
    rows = []
    poses = poses_around(twin, n_poses, rng)
    cfg = twin.perception
    for res in ("848x480", "1280x720"):
        cam = d405(res)
        for name in BACKENDS:
            try:
                backend = get_backend(name, mesh.vertices, mesh.faces, cam)
            except BackendUnavailable as exc:
                rows.append({"backend": name, "resolution": res, "skipped": exc.reason})
                continue
            backend.render(poses[0])  # warm up
            t_render, t_sensor, t_chain, t_total, t_o3d, npts = [], [], [], [], [], []
            for i, T in enumerate(poses):
                t0 = time.perf_counter()
                depth = backend.render(T)
                t1 = time.perf_counter()
                noisy = apply_d405_model(depth, cam, np.random.default_rng(i))
                t2 = time.perf_counter()
                cloud = perceive(noisy, cam, cfg)
                t3 = time.perf_counter()
                t_render.append(t1 - t0)
                t_sensor.append(t2 - t1)
                t_chain.append(t3 - t2)
                t_total.append(t3 - t0)
                npts.append(len(cloud))
                if name == "open3d":
                    t4 = time.perf_counter()
                    open3d_chain(noisy, cam, cfg)
                    t_o3d.append(time.perf_counter() - t4)
            backend.close()
            med = lambda xs: 1000 * statistics.median(xs) if xs else float("nan")  # noqa: E731
            rows.append(
                {
                    "backend": name,
                    "resolution": res,
                    "render_ms": med(t_render),
                    "sensor_ms": med(t_sensor),
                    "perception_ms": med(t_chain),
                    "reference_ms": med(t_total),
                    "open3d_perception_ms": med(t_o3d) if t_o3d else None,
                    "points": int(statistics.median(npts)),
                    "n": len(poses),
                }
            )
    return rows


def time_export(
    twin: Twin,
    n_refs: int,
    workers: int,
    rng: np.random.Generator,
    backend: str,
    workdir: Path | None = None,
) -> dict[str, Any]:
    tmp = Path(tempfile.mkdtemp(prefix="vinetwin-bench-", dir=workdir))
    try:
        dst = Path(
            shutil.copytree(
                twin.root,
                tmp / twin.root.name,
                ignore=shutil.ignore_patterns("references", "validation"),
            )
        )
        t = Twin.load(dst)
        cuts = list(t.cut_points)
        t.poses.clear()
        for i in range(n_refs):
            c = cuts[i % len(cuts)]
            base = t.add_pose(c.id).approach  # the default pose, jittered below
            jitter = Approach(
                base.standoff + rng.uniform(-0.03, 0.05),
                base.azimuth + rng.uniform(-0.5, 0.5),
                base.elevation + rng.uniform(-0.4, 0.4),
                rng.uniform(-0.5, 0.5),
            )
            t.set_pose(t.poses[-1].id, pruning_pose(c.point, c.cane_axis, jitter))
        t.save()
        t0 = time.perf_counter()
        report = export_references(t, workers=workers, backend=backend)
        seconds = time.perf_counter() - t0
        t1 = time.perf_counter()
        again = export_references(t, workers=workers, backend=backend)
        resume_s = time.perf_counter() - t1
        return {
            "backend": resolve_backend(backend, n_refs),
            "references": n_refs,
            "workers": workers,
            "seconds": seconds,
            "refs_per_s": n_refs / seconds,
            "failed": report.count("failed"),
            "rerun_skipped": again.count("skipped"),
            "rerun_seconds": resume_s,
        }
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="few poses and references (CI smoke run)")
    ap.add_argument("--poses", type=int, default=40, help="poses timed per backend and resolution")
    ap.add_argument("--refs", type=int, default=1000, help="references in the export run")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--export-backend", default="auto", help="backend of the export run")
    ap.add_argument("--twin", type=Path, default=SAMPLE, help="twin folder (default: the sample)")
    ap.add_argument(
        "--workdir",
        type=Path,
        help="where the export's twin copies go (default: the system's temporary folder; on "
        "a machine where creating a file there is slow, a folder on the twin's disk)",
    )
    ap.add_argument("--json", type=Path, help="write the figures here")
    args = ap.parse_args()
    n_poses, n_refs = (5, 20) if args.quick else (args.poses, args.refs)
    rng = np.random.default_rng(0)
    twin = Twin.load(args.twin)
    rows = time_backends(twin, n_poses, rng)
    print(
        f"\nPer reference, median over {n_poses} poses of {twin.name} ({len(twin.load_mesh().faces)} triangles), ms:"
    )
    print(
        f"{'backend':9} {'res':9} {'render':>7} {'sensor':>7} {'chain':>7} {'total':>7} {'o3d chain':>9} {'ratio':>6} {'points':>6}"
    )
    for r in rows:
        if "skipped" in r:
            print(f"{r['backend']:9} {r['resolution']:9} skipped: {r['skipped']}")
            continue
        o3d_ms = r["open3d_perception_ms"]
        ratio = f"{r['perception_ms'] / o3d_ms:6.2f}" if o3d_ms else "     -"
        o3d_s = f"{o3d_ms:9.1f}" if o3d_ms else "        -"
        print(
            f"{r['backend']:9} {r['resolution']:9} {r['render_ms']:7.1f} {r['sensor_ms']:7.1f} "
            f"{r['perception_ms']:7.1f} {r['reference_ms']:7.1f} {o3d_s} {ratio} {r['points']:6d}"
        )
    print(
        "(chain = vinetwin's perception chain; o3d chain = the same steps with Open3D's functions;"
    )
    print(" ratio = ours / Open3D's, lower is faster)\n")
    exports = []
    for workers in sorted({1, args.workers}):
        exp = time_export(twin, n_refs, workers, rng, args.export_backend, args.workdir)
        exports.append(exp)
        print(
            f"Export: {exp['references']} references with {exp['backend']}, {exp['workers']} worker(s): "
            f"{exp['seconds']:.1f} s = {exp['refs_per_s']:.1f} references/s ({exp['failed']} failed); "
            f"re-run skipped {exp['rerun_skipped']} in {exp['rerun_seconds']:.1f} s"
        )
    write_json(args.json, {"twin": twin.name, "per_reference": rows, "export": exports})


if __name__ == "__main__":
    main()
