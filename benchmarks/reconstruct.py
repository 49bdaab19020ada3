"""Benchmark: reconstruction of the bundled sample vine from synthetic D405 captures.

For 100 and 200 frames (848x480, D405 noise): the time to render the capture, to fuse it with
vinetwin (Open3D's VoxelBlockGrid, 1.5 mm) and, side by side, with the fusion a user would first
reach for in Open3D (the legacy ScalableTSDFVolume, same voxel and truncation), the triangle
counts, and the accuracy against the ground truth (Chamfer distance, F-score at 2 and 5 mm on the
measured ground truth). Then structure-from-motion poses (pycolmap) on the 100-frame capture.

    .venv/bin/python benchmarks/reconstruct.py [--quick] [--json out.json]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
from results_file import write_json

from vinetwin import _lazy
from vinetwin.capture.folder import Capture, read_capture
from vinetwin.frames import invert
from vinetwin.reconstruct.fusion import FusionConfig, evaluate, fuse, kinematic_poses, observed
from vinetwin.reconstruct.synthetic import synthetic_capture
from vinetwin.twin import Twin

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "samples" / "vine_bilateral.twin"


def open3d_legacy(
    cap: Capture, poses: dict[str, np.ndarray], cfg: FusionConfig
) -> tuple[float, int]:
    """What a user would write with Open3D's legacy integration API."""
    o3d = _lazy.open3d()
    cam = cap.camera
    t0 = time.perf_counter()
    vol = o3d.pipelines.integration.ScalableTSDFVolume(
        voxel_length=cfg.voxel,
        sdf_trunc=cfg.truncation,
        color_type=o3d.pipelines.integration.TSDFVolumeColorType.RGB8,
    )
    intr = o3d.camera.PinholeCameraIntrinsic(cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy)
    for f in cap.frames:
        rgbd = o3d.geometry.RGBDImage.create_from_color_and_depth(
            o3d.geometry.Image(f.color()),
            o3d.geometry.Image(f.depth(cap.depth_unit)),
            depth_scale=1.0,
            depth_trunc=cfg.depth_max,
            convert_rgb_to_intensity=False,
        )
        vol.integrate(rgbd, intr, invert(poses[f.id]))
    mesh = vol.extract_triangle_mesh()
    return time.perf_counter() - t0, len(mesh.triangles)


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="30 frames, no structure-from-motion")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    twin = Twin.load(SAMPLE)
    gt = twin.load_mesh()
    Vg, Fg = np.asarray(gt.vertices), np.asarray(gt.faces)
    sizes = (30,) if args.quick else (100, 200)
    rows: list[dict[str, Any]] = []
    cfg = FusionConfig()
    with tempfile.TemporaryDirectory() as tmp:
        for n in sizes:
            t0 = time.perf_counter()
            cap = read_capture(synthetic_capture(twin, Path(tmp) / f"cap{n}", frames=n))
            t_cap = time.perf_counter() - t0
            poses = kinematic_poses(cap)
            res = fuse(cap, poses, cfg)
            t_legacy, tri_legacy = open3d_legacy(cap, poses, cfg)
            ev = evaluate(
                res.vertices, res.faces, Vg, Fg,
                gt_mask_fn=lambda p, nn, cap=cap, poses=poses: observed(p, nn, cap, poses, Vg, Fg),
            )  # fmt: skip
            row = {
                "frames": n,
                "capture_s": t_cap,
                "fusion_s": res.seconds,
                "triangles": len(res.faces),
                "open3d_legacy_s": t_legacy,
                "open3d_legacy_triangles": tri_legacy,
                **ev,
            }
            if not args.quick and n == 100:
                from vinetwin.reconstruct.sfm import align_to, colmap_poses

                sfm = colmap_poses(cap)
                aligned = align_to(sfm.poses, poses)
                r2 = fuse(cap, aligned, cfg)
                ev2 = evaluate(
                    r2.vertices, r2.faces, Vg, Fg,
                    gt_mask_fn=lambda p, nn, cap=cap, poses=poses: observed(p, nn, cap, poses, Vg, Fg),
                )  # fmt: skip
                row["sfm"] = {"seconds": sfm.seconds, "registered": len(sfm.poses), **ev2}
            rows.append(row)
    print(
        f"{'frames':>6} {'capture s':>9} {'fusion s':>8} {'triangles':>9} {'o3d legacy s':>12} {'legacy tris':>11} {'chamfer mm':>10} {'F@2mm':>6} {'F@5mm':>6}"
    )
    for r in rows:
        print(
            f"{r['frames']:>6} {r['capture_s']:9.1f} {r['fusion_s']:8.1f} {r['triangles']:>9} "
            f"{r['open3d_legacy_s']:12.1f} {r['open3d_legacy_triangles']:>11} {r['chamfer_mm']:10.2f} "
            f"{r['fscore@2mm']:6.3f} {r['fscore@5mm']:6.3f}"
        )
        if "sfm" in r:
            s = r["sfm"]
            print(
                f"       structure-from-motion: {s['registered']}/{r['frames']} registered in "
                f"{s['seconds']:.1f} s; chamfer {s['chamfer_mm']:.2f} mm, F@2mm {s['fscore@2mm']:.3f}, "
                f"F@5mm {s['fscore@5mm']:.3f}"
            )
    write_json(args.json, rows)


if __name__ == "__main__":
    main()
