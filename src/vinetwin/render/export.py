"""Batch export of reference clouds: every pruning pose of a twin to `references/`.

For each pose: `<pose_id>.ply`, `<pose_id>.pcd` and, written last, `<pose_id>.json` (pose,
intrinsics, backend, noise seed, perception and sensor settings, tool version, and the digest of
all inputs). A reference whose JSON carries the same digest as its current inputs, with both
cloud files present, is skipped, so an interrupted export resumes where it stopped. A pose that
fails is reported and the others still finish. Work is spread over worker processes (spawned,
each loading the mesh and its backend once, BLAS/OpenMP capped to their share of the cores).

Measured on 2 cores (benchmarks/render.py): Open3D's ray caster (Embree) already uses every core
from one process and pins its own threads, so with the default backend 2 workers give no more
throughput than 1; pyrender and MuJoCo render on one core and do gain from workers.
"""

from __future__ import annotations

import datetime as _dt
import json
import logging
import os
import time
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

import vinetwin
from vinetwin.camera import CameraModel
from vinetwin.cloud import PerceptionConfig
from vinetwin.errors import InputError, VinetwinError
from vinetwin.render.backends import BACKENDS, DepthBackend, get_backend
from vinetwin.render.reference import (
    REFERENCE_FORMAT,
    file_sha256,
    inputs_digest,
    pose_seed,
    render_reference,
    write_pcd,
    write_ply,
)
from vinetwin.render.sensor import SensorConfig
from vinetwin.twin.model import Twin, atomic_write_text, load_mesh

log = logging.getLogger(__name__)

Status = Literal["rendered", "skipped", "failed"]


@dataclass
class PoseResult:
    pose_id: str
    status: Status
    points: int = 0
    seconds: float = 0.0
    error: str = ""
    warning: str = ""


@dataclass
class ExportReport:
    results: list[PoseResult] = field(default_factory=list)
    seconds: float = 0.0

    def count(self, status: Status) -> int:
        return sum(r.status == status for r in self.results)

    @property
    def ok(self) -> bool:
        return self.count("failed") == 0


@dataclass(frozen=True)
class _Job:
    pose_id: str
    T_vine_camera: list[list[float]]
    seed: int
    out_dir: str
    meta: dict[str, Any]


# ----------------------------------------------------------------------------- workers
_WORKER: dict[str, Any] = {}
_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def _init_worker(
    mesh_path: str,
    camera: dict[str, Any],
    backend: str,
    perception: dict[str, Any],
    sensor: dict[str, Any],
    threads: int,
) -> None:
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
    os.environ.setdefault("MUJOCO_GL", "egl")
    mesh = load_mesh(mesh_path)
    cam = CameraModel.from_dict(camera)
    kwargs = {"threads": threads} if backend == "open3d" else {}
    _WORKER["backend"] = get_backend(backend, mesh.vertices, mesh.faces, cam, **kwargs)
    _WORKER["perception"] = PerceptionConfig.from_dict(perception)
    _WORKER["sensor"] = SensorConfig.from_dict(sensor)


def _run_job(job: _Job) -> PoseResult:
    t0 = time.perf_counter()
    try:
        backend: DepthBackend = _WORKER["backend"]
        ref = render_reference(
            backend,
            np.asarray(job.T_vine_camera),
            _WORKER["perception"],
            _WORKER["sensor"],
            job.seed,
        )
        out = Path(job.out_dir)
        write_ply(out / f"{job.pose_id}.ply", ref.cloud)
        write_pcd(out / f"{job.pose_id}.pcd", ref.cloud)
        warning = "" if len(ref.cloud) else "the view sees nothing: empty reference cloud"
        meta = {
            **job.meta,
            "points": len(ref.cloud),
            "has_normals": ref.cloud.normals is not None,
            "valid_depth_pixels": int((ref.depth > 0).sum()),
            "warning": warning,
            "created": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        }
        atomic_write_text(out / f"{job.pose_id}.json", json.dumps(meta, indent=1) + "\n")
        return PoseResult(
            job.pose_id, "rendered", len(ref.cloud), time.perf_counter() - t0, warning=warning
        )
    except Exception as exc:  # isolate one pose's failure from the others
        return PoseResult(
            job.pose_id,
            "failed",
            seconds=time.perf_counter() - t0,
            error=f"{type(exc).__name__}: {exc}",
        )


# ----------------------------------------------------------------------------- driver
def _is_current(out: Path, pose_id: str, digest: str) -> bool:
    meta = out / f"{pose_id}.json"
    if not (
        meta.exists() and (out / f"{pose_id}.ply").exists() and (out / f"{pose_id}.pcd").exists()
    ):
        return False
    try:
        return json.loads(meta.read_text()).get("inputs_sha256") == digest
    except (OSError, ValueError):
        return False


def export_references(
    twin: Twin,
    pose_ids: Sequence[str] | None = None,
    *,
    backend: str = "open3d",
    workers: int = 0,
    seed: int = 0,
    sensor: SensorConfig | None = None,
    force: bool = False,
    progress: Callable[[PoseResult, int, int], None] | None = None,
) -> ExportReport:
    """Renders the reference cloud of each selected pose into `twin.references_dir`.

    Args:
        twin: the loaded twin.
        pose_ids: poses to export (default: all).
        backend: depth backend (open3d, pyrender, mujoco).
        workers: worker processes; 1 renders in this process; 0 chooses: 1 for open3d (its
            ray caster already uses every core), one per core for pyrender and mujoco.
        seed: base noise seed; each pose derives its own from it and its id.
        sensor: D405 model settings (default SensorConfig()).
        force: re-render even references whose inputs did not change.
        progress: called after each pose with (result, done, total).
    """
    if backend not in BACKENDS:
        raise InputError(
            f"unknown render backend '{backend}'; choose one of: {', '.join(BACKENDS)}"
        )
    t_start = time.perf_counter()
    sensor = sensor or SensorConfig()
    ids = list(pose_ids) if pose_ids else [p.id for p in twin.poses]
    poses = [twin.pose(i) for i in ids]  # raises TwinError naming an unknown id
    load_mesh(twin.mesh_path)  # refuse a bad mesh once, before any worker starts
    mesh_sha = file_sha256(twin.mesh_path)
    out = twin.references_dir
    out.mkdir(exist_ok=True)
    report = ExportReport()
    jobs: list[_Job] = []
    for p in poses:
        s = pose_seed(seed, p.id)
        digest = inputs_digest(
            mesh_sha, p.T_vine_camera, twin.camera, twin.perception, sensor, backend, s
        )
        if not force and _is_current(out, p.id, digest):
            report.results.append(PoseResult(p.id, "skipped"))
            if progress:
                progress(report.results[-1], len(report.results), len(poses))
            continue
        meta = {
            "reference_format": REFERENCE_FORMAT,
            "pose_id": p.id,
            "cut_point": p.cut_point,
            "frame": "reference camera (OpenCV: +x right, +y down, +z forward), metres",
            "T_vine_camera": np.asarray(p.T_vine_camera).tolist(),
            "T_world_camera": (np.asarray(twin.T_world_vine) @ p.T_vine_camera).tolist(),
            "icp_variant": p.icp_variant,
            "camera": twin.camera.to_dict(),
            "backend": backend,
            "noise_seed": s,
            "sensor": sensor.to_dict(),
            "perception": twin.perception.to_dict(),
            "mesh_sha256": mesh_sha,
            "inputs_sha256": digest,
            "vinetwin_version": vinetwin.__version__,
        }
        jobs.append(_Job(p.id, np.asarray(p.T_vine_camera).tolist(), s, str(out), meta))

    if workers <= 0:
        workers = 1 if backend == "open3d" else max(1, os.cpu_count() or 1)
    init_args = (
        str(twin.mesh_path),
        twin.camera.to_dict(),
        backend,
        twin.perception.to_dict(),
        sensor.to_dict(),
    )
    done = len(report.results)
    if jobs and workers <= 1:
        _init_worker(*init_args, 0)
        try:
            for job in jobs:
                r = _run_job(job)
                report.results.append(r)
                done += 1
                if progress:
                    progress(r, done, len(poses))
        finally:
            _WORKER.pop("backend").close()
    elif jobs:
        import multiprocessing as mp

        n = min(workers, len(jobs))
        ctx = mp.get_context("spawn")
        threads = max(1, (os.cpu_count() or 1) // n)
        saved = {k: os.environ.get(k) for k in _THREAD_VARS}
        os.environ.update({k: str(threads) for k in _THREAD_VARS})  # inherited by spawned workers
        try:
            pool = ProcessPoolExecutor(
                n, mp_context=ctx, initializer=_init_worker, initargs=(*init_args, threads)
            )
        finally:
            for k, v in saved.items():
                if v is None:
                    os.environ.pop(k, None)
                else:
                    os.environ[k] = v
        with pool:
            pending: set[Future[PoseResult]] = set()
            queue = list(jobs)
            by_future: dict[Future[PoseResult], _Job] = {}
            # keep a bounded number in flight so progress is honest and memory flat
            while queue or pending:
                while queue and len(pending) < 4 * n:
                    job = queue.pop(0)
                    fut = pool.submit(_run_job, job)
                    by_future[fut] = job
                    pending.add(fut)
                finished, pending = wait(pending, return_when=FIRST_COMPLETED)
                for fut in finished:
                    job = by_future.pop(fut)
                    try:
                        r = fut.result()
                    except Exception as exc:  # a worker that died (killed, crashed)
                        r = PoseResult(
                            job.pose_id, "failed", error=f"worker died: {type(exc).__name__}: {exc}"
                        )
                    report.results.append(r)
                    done += 1
                    if progress:
                        progress(r, done, len(poses))
    order = {pid: i for i, pid in enumerate(ids)}
    report.results.sort(key=lambda r: order[r.pose_id])
    report.seconds = time.perf_counter() - t_start
    for r in report.results:
        if r.status == "failed":
            log.error("pose %s failed: %s", r.pose_id, r.error)
        elif r.warning:
            log.warning("pose %s: %s", r.pose_id, r.warning)
    return report


def check_export_ok(report: ExportReport) -> None:
    """Raises VinetwinError listing the failed poses, if any."""
    failed = [r for r in report.results if r.status == "failed"]
    if failed:
        raise VinetwinError(
            f"{len(failed)} of {len(report.results)} references failed: "
            + "; ".join(f"{r.pose_id}: {r.error}" for r in failed)
        )
