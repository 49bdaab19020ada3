"""How long a scan of a 2 m vine with 500k points takes to become a twin, with the command a user
runs (`vinetwin import-scan`, in a subprocess, writing the twin), beside what a user would
otherwise do with Open3D (statistical outlier removal, normals, Poisson meshing at depth 9, the
route the issue tried first) on the same file, with both results' Chamfer distance and F-score at
2 mm against the true mesh.

The vine is the dense generated vine (`vinetwin sample --dense --seed 5`, 2.0 m along the row)
scanned with the simulated LiDAR (`scan.synthetic`) from four stations at the spacing that
gives 500k points (about 1.1 mm), with
1.5 mm noise, 2 cm gaps, 2 mm misregistration and strays, written as binary PLY in a y-up
scanner frame in millimetres.

    .venv/bin/python benchmarks/scan_speed.py [--repeats 3] [--json benchmarks/results/scan_speed.json]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from vinetwin import _lazy
from vinetwin.mesh import load_mesh_arrays
from vinetwin.scan.evaluate import mesh_accuracy
from vinetwin.scan.synthetic import QUALITY_LADDER, scanner_frame, simulate_scan
from vinetwin.twin.generator import DENSE, VineParams, generate_vine
from vinetwin.twin.skeleton import tube_mesh

sys.path.insert(0, str(Path(__file__).resolve().parent))
from results_file import machine

TARGET_POINTS = 500_000


def make_scan(folder: Path) -> tuple[Path, np.ndarray, np.ndarray, np.ndarray]:
    sk = generate_vine(5, VineParams(**DENSE))  # type: ignore[arg-type]
    V, F = tube_mesh(sk, edge=0.003)
    q = QUALITY_LADDER["realistic"]
    n4 = len(simulate_scan(V, F, q, seed=0)[0])  # points scale with 1 / spacing^2
    q = dataclasses.replace(q, spacing=q.spacing * (n4 / TARGET_POINTS) ** 0.5)
    P, _ = simulate_scan(V, F, q, seed=0)
    T = scanner_frame(0)
    o3d = _lazy.open3d()
    path = folder / "vine_500k.ply"
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector((P @ T[:3, :3].T + T[:3, 3]) * 1000))
    o3d.io.write_point_cloud(str(path), pc, write_ascii=False)
    return path, V, F, T


def poisson(path: Path) -> tuple[float, np.ndarray, np.ndarray]:
    """Open3D's route, in metres: outliers, normals, Poisson (depth 9), low-density trim."""
    o3d = _lazy.open3d()
    t0 = time.perf_counter()
    pc = o3d.io.read_point_cloud(str(path))
    pc.scale(0.001, center=np.zeros(3))
    pc, _ = pc.remove_statistical_outlier(nb_neighbors=16, std_ratio=3.0)
    pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=0.01, max_nn=30))
    pc.orient_normals_consistent_tangent_plane(15)
    mesh, dens = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(pc, depth=9)
    dens = np.asarray(dens)
    mesh.remove_vertices_by_mask(dens < np.quantile(dens, 0.05))
    secs = time.perf_counter() - t0
    return secs, np.asarray(mesh.vertices), np.asarray(mesh.triangles)


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--json", type=Path)
    a = ap.parse_args()
    exe = Path(sys.executable).with_name("vinetwin")
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        path, V, F, T_scan_vine = make_scan(work)
        n = int(_lazy.open3d().io.read_point_cloud(str(path)).points.__len__())
        ours, theirs = [], []
        PV, PF = np.zeros((0, 3)), np.zeros((0, 3), np.int64)
        for r in range(a.repeats):
            out = work / f"v{r}.twin"
            t0 = time.perf_counter()
            subprocess.run([str(exe), "import-scan", str(path), "--out", str(out), "--cut-points",
                            "10", "--report", str(work / f"rep{r}")], check=True,
                           capture_output=True)  # fmt: skip
            ours.append(time.perf_counter() - t0)
            secs, PV, PF = poisson(path)
            theirs.append(secs)
        rep = json.loads((work / "rep0" / "report.json").read_text())
        T = np.asarray(rep["T_vine_scan"]) @ T_scan_vine
        Vt = V @ T[:3, :3].T + T[:3, 3]
        ch_o, f_o = mesh_accuracy(*load_mesh_arrays(work / "v0.twin" / "vine.ply"), Vt, F)
        # Poisson's mesh is in the scanner's frame (metres): bring the truth there
        Vs = V @ T_scan_vine[:3, :3].T + T_scan_vine[:3, 3]
        ch_p, f_p = mesh_accuracy(PV, PF, Vs, F)
    mo, mp = statistics.median(ours), statistics.median(theirs)
    ext = np.ptp(V, axis=0)
    print(
        f"scan: {n} points of the dense generated vine (seed 5, {ext[0]:.2f} x {ext[1]:.2f} x "
        f"{ext[2]:.2f} m), {a.repeats} repeats\n"
    )
    print("| route | median s | runs s | Chamfer mm | F-score at 2 mm | gives |")
    print("|---|---|---|---|---|---|")
    print(f"| vinetwin import-scan (the command, twin written) | {mo:.1f} | "
          f"{', '.join(f'{x:.1f}' for x in ours)} | {ch_o:.2f} | {f_o:.2f} | twin, skeleton, "
          f"{rep['skeleton']['candidates']} candidates, report |")  # fmt: skip
    print(f"| Open3D outliers + normals + Poisson depth 9 | {mp:.1f} | "
          f"{', '.join(f'{x:.1f}' for x in theirs)} | {ch_p:.2f} | {f_p:.2f} | a mesh |")  # fmt: skip
    print(
        f"\nratio import-scan / Open3D Poisson: {mo / mp:.2f}; stages of import-scan: {rep['seconds']}"
    )
    if a.json:
        a.json.write_text(json.dumps({
            "machine": machine(), "points": n, "import_scan_s": ours, "poisson_s": theirs,
            "import_scan_chamfer_mm": ch_o, "import_scan_fscore_2mm": f_o,
            "poisson_chamfer_mm": ch_p, "poisson_fscore_2mm": f_p, "stages_s": rep["seconds"],
        }, indent=1))  # fmt: skip


if __name__ == "__main__":
    main()
