"""Benchmark: arrival registration's success curve against the platform's initial error.

For each error level (translation, rotation), `--trials` arrivals: a pruning pose of the twin
(in turn), its live view rendered from the true pose through the D405 model, and a belief off
by exactly that error (random directions). `ArrivalRegistration.register` then answers with a
pose or a named refusal. Success: within 5 mm / 0.03 rad of the truth (what the servo's first
ICP takes from there). Printed per level: correct, answered wrongly (with the worst error),
refused (by reason), median seconds.

    .venv/bin/python benchmarks/arrival.py [--twin TWIN] [--trials 20] [--json out.json]
"""

from __future__ import annotations

import argparse
import statistics
from pathlib import Path
from typing import Any

import numpy as np
from results_file import write_json

from vinetwin import _lazy
from vinetwin.frames import make_pose, pose_error, so3_exp
from vinetwin.render.backends import get_backend
from vinetwin.render.sensor import apply_d405_model
from vinetwin.servo.arrival import ArrivalRegistration
from vinetwin.twin import Twin

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "samples" / "vine_bilateral.twin"
LEVELS = ((0.02, 2.0), (0.05, 5.0), (0.075, 10.0), (0.10, 15.0))
SUCCESS = (0.005, 0.03)


def off_by(rng: np.random.Generator, T: np.ndarray, t: float, deg: float) -> np.ndarray:
    """T with its position moved by t (m) and its orientation turned by deg, random axes."""
    u = rng.normal(size=3)
    a = rng.normal(size=3)
    R = so3_exp(np.radians(deg) * a / np.linalg.norm(a))
    return make_pose(R @ T[:3, :3], T[:3, 3] + t * u / np.linalg.norm(u))


def run(twin: Twin, trials: int, seed: int) -> list[dict[str, Any]]:
    _lazy.open3d().utility.set_verbosity_level(_lazy.open3d().utility.VerbosityLevel.Error)
    mesh = twin.load_mesh()
    live_cam = get_backend("open3d", mesh.vertices, mesh.faces, twin.camera)
    arrival = ArrivalRegistration(mesh.vertices, mesh.faces, twin.camera, twin.perception)
    rng = np.random.default_rng(seed)
    rows = []
    for t, deg in LEVELS:
        correct, wrong, refused, seconds = 0, [], {}, []
        for k in range(trials):
            T = np.asarray(twin.poses[k % len(twin.poses)].T_vine_camera)
            depth = apply_d405_model(live_cam.render(T), twin.camera, rng)
            r = arrival.register(depth, off_by(rng, T, t, deg))
            seconds.append(r.seconds)
            if r.ok and r.T_vine_camera is not None:
                et, er = pose_error(r.T_vine_camera, T)
                if et <= SUCCESS[0] and er <= SUCCESS[1]:
                    correct += 1
                else:
                    wrong.append((round(1000 * et, 1), round(er, 3)))
            else:
                key = r.reason.split(":")[0]
                refused[key] = refused.get(key, 0) + 1
        row = {
            "translation_m": t, "rotation_deg": deg, "trials": trials, "correct": correct,
            "wrong": wrong, "refused": refused, "median_s": statistics.median(seconds),
        }  # fmt: skip
        rows.append(row)
        print(
            f"{100 * t:5.1f} cm {deg:4.0f} deg: correct {correct}/{trials}, wrong {len(wrong)} "
            f"{wrong if wrong else ''}, refused {sum(refused.values())} {refused or ''}, "
            f"median {row['median_s']:.2f} s",
            flush=True,
        )
    arrival.close()
    live_cam.close()
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--twin", type=Path, default=SAMPLE, help="twin folder (default: the sample)")
    ap.add_argument("--trials", type=int, default=20, help="arrivals per error level")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", type=Path, help="write the figures here")
    args = ap.parse_args()
    twin = Twin.load(args.twin)
    print(f"twin {twin.name}: {len(twin.poses)} poses, {args.trials} arrivals per level; success "
          f"within {1000 * SUCCESS[0]:.0f} mm / {SUCCESS[1]} rad")  # fmt: skip
    rows = run(twin, args.trials, args.seed)
    write_json(args.json, {"twin": twin.name, "levels": rows})


if __name__ == "__main__":
    main()
