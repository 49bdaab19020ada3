"""Simulation jobs on the executor (`vinetwin.executor`: this process, a local pool or Ray):
the twin as plain data for a worker (`twin_context`), each worker's cached renderer and Panda
scenes, and `run_jobs`, which the campaign and the validation both run their jobs through."""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from typing import Any

import numpy as np

from vinetwin.cloud import PerceptionConfig
from vinetwin.executor import (
    ExecutorConfig,
    clear_worker_cache,
    run_unordered,
    worker_cache,
    worker_threads,
    workers_used,
)
from vinetwin.files import file_sha256
from vinetwin.mesh import load_mesh_arrays
from vinetwin.sim.session import SimSpec, SimWorld
from vinetwin.twin.model import Twin

log = logging.getLogger(__name__)


def twin_context(twin: Twin) -> dict[str, Any]:
    """What a worker needs to rebuild a twin's renderer: plain data, sent with each job."""
    return {
        "mesh_path": str(twin.mesh_path),
        "mesh_sha256": file_sha256(twin.mesh_path),
        "camera": twin.camera.to_dict(),
        "perception": twin.perception.to_dict(),
        "T_flange_camera": np.asarray(twin.T_flange_camera).tolist(),
    }


class _TwinWorker:
    """A twin's mesh, renderer and Panda scenes in one worker process."""

    def __init__(self, ctx: dict[str, Any]) -> None:
        from vinetwin.camera import CameraModel
        from vinetwin.render.backends import scene_backend

        self.vertices, self.faces = load_mesh_arrays(ctx["mesh_path"])
        cam = CameraModel.from_dict(ctx["camera"])
        # any thread: with one worker the jobs run in the caller's thread (a web server's)
        self.backend = scene_backend(
            self.vertices, self.faces, cam, any_thread=True, threads=worker_threads()
        )
        self.perception = PerceptionConfig.from_dict(ctx["perception"])
        self.arms: dict[tuple[str, bytes], Any] = {}

    def close(self) -> None:
        self.backend.close()


def _worker_twin(ctx: dict[str, Any]) -> _TwinWorker:
    key = ("sim", ctx["mesh_path"], ctx["mesh_sha256"], json.dumps(ctx["camera"]))
    return worker_cache(key, lambda: _TwinWorker(ctx))


def worker_world(ctx: dict[str, Any], reference: dict[str, Any], spec: SimSpec) -> SimWorld:
    """The world a run (`spec`) is built on in this worker process: the twin's (`twin_context`)
    renderer and perception settings, the renderer of the reference when `reference` names
    another mesh (the field profile's reconstructed twin: `mesh_path`, `mesh_sha256`), and the
    spec's Panda; each built on first use and kept for the worker's next runs."""
    w = _worker_twin(ctx)
    ref = _worker_twin({**ctx, **reference}).backend if reference else None
    arm = worker_arm(ctx, spec.robot, spec.goal)
    T_flange_camera = np.asarray(ctx["T_flange_camera"]) if arm is not None else None
    return SimWorld(w.backend, w.perception, ref, arm=arm, T_flange_camera=T_flange_camera)


def worker_arm(ctx: dict[str, Any], robot: str | None, goal: Any) -> Any:
    """This worker's Panda (None for the kinematic camera), its scene holding the vine placed so
    the goal is comfortably reachable; compiled once per robot and goal (each run starts by
    reaching its start pose from home)."""
    if robot is None:
        return None
    from vinetwin.sim.panda import PandaArm, goal_placement

    w = _worker_twin(ctx)
    key = (robot, np.asarray(goal, float).tobytes())
    if key not in w.arms:
        w.arms[key] = PandaArm(
            robot or None,
            T_flange_camera=np.asarray(ctx["T_flange_camera"]),
            camera=w.backend.camera,
            vine=(w.vertices, w.faces),
            T_base_vine=goal_placement(goal),
        )
    return w.arms[key]


def run_jobs(
    jobs: list[Any],
    executor: ExecutorConfig,
    fn: Callable[[Any], dict[str, Any]],
    progress: Callable[[dict[str, Any], int, int], None] | None = None,
    on_result: Callable[[Any, dict[str, Any]], None] | None = None,
) -> tuple[list[tuple[Any, dict[str, Any]]], list[tuple[Any, str]], int]:
    """Runs simulation jobs (`fn(job)` each) on the executor (a
    local process pool, one worker per core when `workers` is 0, or Ray), each worker with its
    own renderer. Returns (job, result) in completion order, the failed jobs with their error,
    and the number of workers. `on_result(job, result)` is called as each job finishes (to keep
    it on disk before the others end)."""
    results: list[tuple[Any, dict[str, Any]]] = []
    failed: list[tuple[Any, str]] = []
    workers = workers_used(executor, len(jobs))
    try:
        for outcome in run_unordered(fn, jobs, executor):
            if outcome.ok:
                results.append((jobs[outcome.index], outcome.value))
                if on_result:
                    on_result(jobs[outcome.index], outcome.value)
                if progress:
                    progress(outcome.value, len(results) + len(failed), len(jobs))
            else:
                failed.append((jobs[outcome.index], outcome.error))
                log.error("job %d failed: %s", outcome.index, outcome.error)
    finally:
        if executor.kind == "local" and workers <= 1:
            clear_worker_cache()
    return results, failed, workers
