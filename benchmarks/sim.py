"""Benchmark: how fast the closed-loop simulation runs, its scene rendered by each backend.

For each twin (`--twin`, repeatable; default the bundled sample): one kinematic run
(`sim.simulate`, `SimConfig` defaults: a D405 at 30 Hz, point-to-plane, the twin's perception) of
`--duration` simulated seconds from a 4 cm / 0.1 rad start of its first pose that still sees the
cut, once with the scene rendered by each of Open3D's ray casting, MuJoCo and vinetwin's raster
backend, side by side in the same run, after a short warm-up run each (compilation). The
simulation's default (`render.backends.scene_backend`) is the raster backend. A backend that
cannot start here (MuJoCo without EGL) is left out with its reason.

Printed per twin and backend: frames, process seconds (wall, one process), simulated seconds per
process second, milliseconds per frame and where they go (the scene's render, the D405 model and
quantisation, the servo's step: perception + ICP + control, and the rest: the loop, the simulated
robot and the logs), and the run's final translation error (against the truth).

Goal (issue: speed): at least 3 simulated seconds per process second.

    .venv/bin/python benchmarks/sim.py [--twin TWIN ...] [--duration 6] [--quick] [--json out.json]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

import numpy as np
from results_file import write_json

from vinetwin.errors import BackendUnavailable
from vinetwin.render.backends import get_backend
from vinetwin.servo import rendered_camera
from vinetwin.sim.config import SimConfig
from vinetwin.sim.session import SimSpec, SimWorld, start_pose
from vinetwin.sim.simulate import simulate
from vinetwin.twin import Twin

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "samples" / "vine_bilateral.twin"
BACKENDS = ("open3d", "mujoco", "raster")


class _Timed:
    """A depth backend that adds up the time of its renders."""

    def __init__(self, backend: Any) -> None:
        self.backend = backend
        self.camera = backend.camera
        self.name = backend.name
        self.seconds = 0.0

    def render(self, T_vine_camera: Any) -> Any:
        t0 = time.perf_counter()
        try:
            return self.backend.render(T_vine_camera)
        finally:
            self.seconds += time.perf_counter() - t0

    def close(self) -> None:
        self.backend.close()


class _Clock:
    """Wraps the rendered camera's D405 model and quantisation to add up their time."""

    def __init__(self) -> None:
        self.seconds = 0.0
        self._orig = (rendered_camera.apply_d405_model, rendered_camera.quantize_depth)

    def __enter__(self) -> _Clock:
        model, quantize = self._orig

        def timed(fn: Any) -> Any:
            def inner(*a: Any, **k: Any) -> Any:
                t0 = time.perf_counter()
                try:
                    return fn(*a, **k)
                finally:
                    self.seconds += time.perf_counter() - t0

            return inner

        rendered_camera.apply_d405_model = timed(model)
        rendered_camera.quantize_depth = timed(quantize)
        return self

    def __exit__(self, *exc: Any) -> None:
        rendered_camera.apply_d405_model, rendered_camera.quantize_depth = self._orig


def run_twin(path: Path, duration: float) -> list[dict[str, Any]]:
    twin = Twin.load(path)
    mesh = twin.load_mesh()
    pose = twin.poses[0]
    goal = np.asarray(pose.T_vine_camera, float)
    cut = twin.cut_point(pose.cut_point).point
    start = start_pose(
        goal, cut, (0.04, 0.1), np.random.default_rng(0), twin.camera, twin.perception.max_depth
    )
    rows = []
    for name in BACKENDS:
        t0 = time.perf_counter()
        try:
            backend = _Timed(get_backend(name, mesh.vertices, mesh.faces, twin.camera))
        except BackendUnavailable as exc:
            print(f"{twin.root.name}: {name} left out: {exc}")
            continue
        build = time.perf_counter() - t0
        warm = SimConfig(duration=0.3, settle=0.0)
        simulate(SimSpec(goal, start, warm, reference_seed=0), SimWorld(backend, twin.perception))
        backend.seconds = 0.0
        cfg = SimConfig(duration=duration, settle=0.0)
        with _Clock() as sensor:
            t0 = time.perf_counter()
            run = simulate(
                SimSpec(goal, start, cfg, reference_seed=0), SimWorld(backend, twin.perception)
            )
            wall = time.perf_counter() - t0
        backend.close()
        n = max(len(run.t), 1)
        step = float(np.sum(run.compute))
        rows.append(
            {
                "twin": twin.root.name,
                "faces": len(mesh.faces),
                "backend": name,
                "scene_build_s": build,
                "simulated_s": duration,
                "frames": len(run.t),
                "wall_s": wall,
                "x_real_time": duration / wall,
                "ms_per_frame": 1000 * wall / n,
                "render_ms": 1000 * backend.seconds / n,
                "sensor_ms": 1000 * sensor.seconds / n,
                "servo_step_ms": 1000 * step / n,
                "rest_ms": 1000 * (wall - backend.seconds - sensor.seconds - step) / n,
                "final_error_mm": 1000 * run.error_t[-1] if run.error_t else float("nan"),
            }
        )
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--twin", type=Path, action="append", help="twin folder (repeatable)")
    ap.add_argument("--duration", type=float, default=6.0, help="simulated seconds per run")
    ap.add_argument("--quick", action="store_true", help="1 simulated second")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    duration = 1.0 if args.quick else args.duration
    rows = []
    for path in args.twin or [SAMPLE]:
        rows += run_twin(path, duration)
    head = (
        f"{'twin':28} {'faces':>7} {'scene':7} {'frames':>6} {'wall s':>7} {'x real':>6} "
        f"{'ms/fr':>6} {'render':>6} {'D405':>5} {'servo':>5} {'rest':>5} {'err mm':>6}"
    )
    print(head)
    for r in rows:
        print(
            f"{r['twin']:28} {r['faces']:7d} {r['backend']:7} {r['frames']:6d} {r['wall_s']:7.2f} "
            f"{r['x_real_time']:6.2f} {r['ms_per_frame']:6.1f} {r['render_ms']:6.1f} "
            f"{r['sensor_ms']:5.1f} {r['servo_step_ms']:5.1f} {r['rest_ms']:5.1f} "
            f"{r['final_error_mm']:6.3f}"
        )
    for twin in dict.fromkeys(r["twin"] for r in rows):
        scenes = ", ".join(
            f"{r['backend']} {r['x_real_time']:.2f}x" for r in rows if r["twin"] == twin
        )
        print(f"{twin}: real time with the scene rendered by {scenes} (goal 3x)")
    write_json(args.json, {"duration": duration, "rows": rows})


if __name__ == "__main__":
    main()
