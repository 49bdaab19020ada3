"""Batch export of reference clouds: every pruning pose of a twin to `references/`.

For each pose: `<pose_id>.ply`, `<pose_id>.pcd` and, written last, `<pose_id>.json` (pose,
intrinsics, backend, noise seed, perception and sensor settings, tool version, and the digest of
all inputs). A reference whose JSON carries the same digest as its current inputs, with both
cloud files present and matching the hashes it recorded, is skipped, so an interrupted export
resumes where it stopped. The files are not fsynced one by one but flushed together at the end
(a file a power loss truncated fails its hash and is rendered again). A pose that
fails is reported and the others still finish. Work is spread over worker processes (spawned,
each loading the mesh and its backend once, BLAS/OpenMP capped to their share of the cores).

Measured on 2 cores (benchmarks/render.py): Open3D's ray caster (Embree) already uses every core
from one process and pins its own threads, so with the default backend 2 workers give no more
throughput than 1; pyrender and MuJoCo render on one core and do gain from workers.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import logging
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

import vinetwin
from vinetwin._faults import fault_point
from vinetwin.camera import CameraModel
from vinetwin.cloud import PerceptionConfig
from vinetwin.errors import InputError, VinetwinError, raise_if_interrupt
from vinetwin.executor import (
    ExecutorConfig,
    clear_worker_cache,
    run_unordered,
    worker_cache,
    worker_threads,
    workers_used,
)
from vinetwin.files import atomic_write_bytes, file_sha256, sync_to_disk
from vinetwin.mesh import load_mesh_arrays
from vinetwin.render.backends import DepthBackend, get_backend, resolve_backend
from vinetwin.render.reference import (
    REFERENCE_FORMAT,
    check_reference_files,
    digest_inputs,
    pose_digest,
    pose_seed,
    reference_files,
    references_store,
    render_reference,
)
from vinetwin.render.sensor import SensorConfig
from vinetwin.twin.model import Twin, check_id

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
    twin: str = ""
    """The twin folder (set when exporting several)."""


@dataclass
class ExportReport:
    results: list[PoseResult] = field(default_factory=list)
    seconds: float = 0.0
    workers: int = 1
    executor: str = "local"

    def count(self, status: Status) -> int:
        return sum(r.status == status for r in self.results)

    @property
    def ok(self) -> bool:
        return self.count("failed") == 0


@dataclass(frozen=True)
class _Job:
    twin: str
    pose_id: str
    T_vine_camera: list[list[float]]
    seed: int
    out_dir: str
    meta: dict[str, Any]
    mesh_path: str
    backend: str
    camera: dict[str, Any]
    perception: dict[str, Any]
    sensor: dict[str, Any]


# ----------------------------------------------------------------------------- workers
def _worker_backend(job: _Job) -> DepthBackend:
    def build() -> DepthBackend:
        V, F = load_mesh_arrays(job.mesh_path)
        cam = CameraModel.from_dict(job.camera)
        kwargs = {"threads": worker_threads()} if job.backend == "open3d" else {}
        return get_backend(job.backend, V, F, cam, **kwargs)

    key = ("render", job.mesh_path, job.meta["mesh_sha256"], job.backend, json.dumps(job.camera))
    return worker_cache(key, build)


def _run_job(job: _Job) -> PoseResult:
    t0 = time.perf_counter()
    key = f"{job.twin}/{job.pose_id}"
    try:
        ref = render_reference(
            _worker_backend(job),
            np.asarray(job.T_vine_camera),
            PerceptionConfig.from_dict(job.perception),
            SensorConfig.from_dict(job.sensor),
            job.seed,
        )
        out = Path(job.out_dir)
        fault_point(key, "render")
        files = reference_files(ref.cloud)
        for ext, data in files.items():  # ply, then pcd
            atomic_write_bytes(out / f"{job.pose_id}.{ext}", data, sync=False)
            fault_point(key, ext)
        warning = "" if len(ref.cloud) else "the view sees nothing: empty reference cloud"
        meta = {
            **job.meta,
            # the hashes of the bytes written (`check_reference_files` checks the files against them)
            "files_sha256": {ext: hashlib.sha256(data).hexdigest() for ext, data in files.items()},
            "points": len(ref.cloud),
            "has_normals": ref.cloud.normals is not None,
            "valid_depth_pixels": int(np.count_nonzero(ref.depth > 0))
            if ref.depth is not None
            else 0,
            "warning": warning,
            "created": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        }
        # the sidecar is written last: a reference is current only once it exists
        references_store(out).put(job.pose_id, meta["inputs_sha256"], meta)
        return PoseResult(
            job.pose_id, "rendered", len(ref.cloud), time.perf_counter() - t0, warning=warning,
            twin=job.twin,
        )  # fmt: skip
    except Exception as exc:  # isolate one pose's failure from the others
        raise_if_interrupt(exc)  # Ctrl-C inside a kernel stops the export
        return PoseResult(
            job.pose_id,
            "failed",
            seconds=time.perf_counter() - t0,
            error=f"{type(exc).__name__}: {exc}",
            twin=job.twin,
        )


# ----------------------------------------------------------------------------- driver
def _is_current(out: Path, pose_id: str, digest: str) -> bool:
    companions = [out / f"{pose_id}.ply", out / f"{pose_id}.pcd"]
    if references_store(out).current(pose_id, digest, companions) is None:
        return False
    problem = check_reference_files(out, pose_id)
    if problem:
        log.warning("%s: rendering it again", problem)
    return not problem


def plan_export(
    twin: Twin,
    pose_ids: Sequence[str] | None = None,
    *,
    backend: str | None = None,
    seed: int = 0,
    sensor: SensorConfig | None = None,
    force: bool = False,
) -> tuple[list[PoseResult], list[_Job]]:
    """The poses already current (skipped) and the jobs that render the others."""
    sensor = sensor or SensorConfig()
    by_id = {p.id: p for p in twin.poses}  # one lookup per pose, not a scan of them all
    poses = (
        [by_id[i] if i in by_id else twin.pose(i) for i in pose_ids]  # TwinError: unknown id
        if pose_ids
        else list(twin.poses)
    )
    backend = resolve_backend(backend, len(poses))
    for p in poses:  # ids name the files written: never a path out of the folder
        check_id(p.id, "pose id")
    load_mesh_arrays(twin.mesh_path)  # refuse a bad mesh once, before any worker starts
    mesh_sha = file_sha256(twin.mesh_path)
    out = twin.references_dir
    references_store(out).open()  # removes what writers killed in an earlier run left
    skipped: list[PoseResult] = []
    jobs: list[_Job] = []
    name = str(twin.root)
    common = digest_inputs(mesh_sha, twin.camera, twin.perception, sensor, backend)
    # shared by every job (each job's meta is its own copy: the workers extend it)
    camera, perception, sensor_d = common["camera"], common["perception"], common["sensor"]
    T_world_vine = np.asarray(twin.T_world_vine)
    mesh_path = str(twin.mesh_path)
    for p in poses:
        s = pose_seed(seed, p.id)
        digest = pose_digest(common, p.T_vine_camera, s)
        if not force and _is_current(out, p.id, digest):
            skipped.append(PoseResult(p.id, "skipped", twin=name))
            continue
        meta = {
            "reference_format": REFERENCE_FORMAT,
            "pose_id": p.id,
            "cut_point": p.cut_point,
            "frame": "reference camera (OpenCV: +x right, +y down, +z forward), metres",
            "T_vine_camera": np.asarray(p.T_vine_camera).tolist(),
            "T_world_camera": (T_world_vine @ p.T_vine_camera).tolist(),
            "icp_variant": p.icp_variant,
            "camera": camera,
            "backend": backend,
            "noise_seed": s,
            "sensor": sensor_d,
            "perception": perception,
            "mesh_sha256": mesh_sha,
            "inputs_sha256": digest,
            "vinetwin_version": vinetwin.__version__,
        }
        jobs.append(
            _Job(
                name, p.id, np.asarray(p.T_vine_camera).tolist(), s, str(out), meta,
                mesh_path, backend, camera, perception, sensor_d,
            )
        )  # fmt: skip
    return skipped, jobs


def export_many(
    twins: Sequence[Twin],
    *,
    backend: str | None = None,
    workers: int = 0,
    seed: int = 0,
    sensor: SensorConfig | None = None,
    force: bool = False,
    executor: ExecutorConfig | None = None,
    progress: Callable[[PoseResult, int, int], None] | None = None,
    broken: Sequence[tuple[Path, str]] = (),
) -> ExportReport:
    """Exports every pose of every twin in one pool of workers (a vineyard: a folder of twin
    folders). See `export_references` for the arguments. A twin that cannot be exported (its
    mesh unreadable, say; `broken`: (folder, why) of those that did not load) fails by name
    and the others are exported."""
    t_start = time.perf_counter()
    backend = resolve_backend(backend, sum(len(t.poses) for t in twins))
    skipped: list[PoseResult] = []
    jobs: list[_Job] = []
    failed = [PoseResult("(all)", "failed", error=why, twin=str(root)) for root, why in broken]
    for twin in twins:
        try:
            sk, js = plan_export(twin, backend=backend, seed=seed, sensor=sensor, force=force)
        except VinetwinError as exc:
            failed.append(PoseResult("(all)", "failed", error=str(exc), twin=str(twin.root)))
            continue
        skipped += sk
        jobs += js
    report = _run_planned(skipped, jobs, workers, executor, progress)
    report.results += failed
    order = {
        (str(t.root), p.id): k for k, (t, p) in enumerate((t, p) for t in twins for p in t.poses)
    }
    report.results.sort(key=lambda r: order.get((r.twin, r.pose_id), 0))
    return _finish(report, t_start, several=len(twins) > 1)


def export_references(
    twin: Twin,
    pose_ids: Sequence[str] | None = None,
    *,
    backend: str | None = None,
    workers: int = 0,
    seed: int = 0,
    sensor: SensorConfig | None = None,
    force: bool = False,
    executor: ExecutorConfig | None = None,
    progress: Callable[[PoseResult, int, int], None] | None = None,
) -> ExportReport:
    """Renders the reference cloud of each selected pose into `twin.references_dir`.

    Args:
        twin: the loaded twin.
        pose_ids: poses to export (default: all).
        backend: depth backend (open3d, pyrender, mujoco); None or "auto": chosen by the
            number of poses (`render.backends.resolve_backend`).
        workers: worker processes; 1 renders in this process; 0 chooses: 1 for open3d (its
            ray caster already uses every core), one per core for pyrender and mujoco.
        seed: base noise seed; each pose derives its own from it and its id.
        sensor: D405 model settings (default SensorConfig()).
        force: re-render even references whose inputs did not change.
        executor: where the jobs run (a local pool by default, or Ray); its `workers`
            replaces the argument.
        progress: called after each pose with (result, done, total).
    """
    t_start = time.perf_counter()
    refs = twin.references_dir
    if refs.is_symlink():  # said, not followed silently; its clean-up is skipped there
        log.warning("%s is a symbolic link: the references are written to %s", refs, refs.resolve())
    skipped, jobs = plan_export(
        twin, pose_ids, backend=backend, seed=seed, sensor=sensor, force=force
    )
    report = _run_planned(skipped, jobs, workers, executor, progress)
    ids = list(pose_ids) if pose_ids else [p.id for p in twin.poses]
    order = {pid: i for i, pid in enumerate(ids)}
    report.results.sort(key=lambda r: order[r.pose_id])
    return _finish(report, t_start, several=False)


def _run_planned(
    skipped: list[PoseResult],
    jobs: list[_Job],
    workers: int,
    executor: ExecutorConfig | None,
    progress: Callable[[PoseResult, int, int], None] | None,
) -> ExportReport:
    report = ExportReport(results=list(skipped))
    total = len(skipped) + len(jobs)
    if progress:
        for k, r in enumerate(report.results):
            progress(r, k + 1, total)
    if executor is None:
        if workers <= 0:  # Open3D's ray caster already uses every core from one process
            open3d = bool(jobs) and jobs[0].backend == "open3d"  # plan_export's choice
            workers = 1 if open3d else max(1, os.cpu_count() or 1)
        executor = ExecutorConfig(workers=workers)
    report.executor = executor.kind
    report.workers = workers_used(executor, len(jobs))
    try:
        for outcome in run_unordered(_run_job, jobs, executor):
            job = jobs[outcome.index]
            r = outcome.value if outcome.ok else PoseResult(
                job.pose_id, "failed", error=outcome.error, twin=job.twin
            )  # fmt: skip
            report.results.append(r)
            if progress:
                progress(r, len(report.results), total)
    finally:
        if executor.kind == "local" and report.workers <= 1:
            clear_worker_cache()  # the renderers built in this process
        for out in sorted({j.out_dir for j in jobs}):  # a broken pool terminates writers mid-file
            references_store(Path(out)).clean()
        if jobs:
            sync_to_disk()  # the references were written without an fsync each
    return report


def _finish(report: ExportReport, t_start: float, several: bool) -> ExportReport:
    report.seconds = time.perf_counter() - t_start
    for r in report.results:
        where = f"{r.twin}: pose {r.pose_id}" if several else f"pose {r.pose_id}"
        if r.status == "failed":
            log.error("%s failed: %s", where, r.error)
        elif r.warning:
            log.warning("%s: %s", where, r.warning)
    return report


def export_twins(
    path: str | Path,
    pose_ids: Sequence[str] = (),
    *,
    backend: str | None = None,
    workers: int = 0,
    seed: int = 0,
    clean: bool = False,
    force: bool = False,
    executor: ExecutorConfig | None = None,
    progress: Callable[[PoseResult, int, int], None] | None = None,
) -> tuple[ExportReport, Path]:
    """`vinetwin export`: the references of one twin folder (`pose_ids`: some of its poses) or
    of every twin of a vineyard folder; `clean` renders without the D405 model. Returns the
    report and the folder the references went to."""
    from vinetwin.twin.model import find_twins, load_twins

    if not 0 <= seed < 2**32 or workers < 0:
        raise InputError(f"seed must lie in [0, 2^32) and workers be >= 0, got {seed}, {workers}")
    roots = find_twins(path)
    sensor = SensorConfig(enabled=not clean)
    if len(roots) == 1:
        twin = Twin.load(roots[0])
        report = export_references(
            twin, pose_ids or None, backend=backend, workers=workers, seed=seed, sensor=sensor,
            force=force, executor=executor, progress=progress,
        )  # fmt: skip
        return report, twin.references_dir
    if pose_ids:
        raise InputError("--poses selects poses of one twin, not of a vineyard")
    twins, broken = load_twins(roots)  # one that does not load fails by name
    report = export_many(
        twins, backend=backend, workers=workers, seed=seed, sensor=sensor, force=force,
        executor=executor, progress=progress, broken=broken,
    )  # fmt: skip
    return report, Path(path)


def check_export_ok(report: ExportReport) -> None:
    """Raises VinetwinError listing the failed poses, if any."""
    failed = [r for r in report.results if r.status == "failed"]
    if failed:
        raise VinetwinError(
            f"{len(failed)} of {len(report.results)} references failed: "
            + "; ".join(
                f"{Path(r.twin).name + ' ' if r.twin else ''}{r.pose_id}: {r.error}" for r in failed
            )
        )


def print_report(report: ExportReport, where: Path) -> None:
    """Prints one row per reference and a line of totals."""
    from rich.console import Console
    from rich.markup import escape
    from rich.table import Table

    several = len({r.twin for r in report.results}) > 1
    table = Table("pose", "status", "points", "seconds", "note")
    for r in report.results:  # ids, paths and messages are printed as text, not markup
        table.add_row(
            escape(f"{Path(r.twin).name}/{r.pose_id}" if several else r.pose_id),
            r.status,
            str(r.points) if r.status == "rendered" else "",
            f"{r.seconds:.2f}",
            escape(r.error or r.warning),
        )
    con = Console()
    con.print(table)
    con.print(
        f"{report.count('rendered')} rendered, {report.count('skipped')} unchanged, "
        f"{report.count('failed')} failed in {report.seconds:.1f} s "
        f"({report.executor}, {report.workers} worker{'s' * (report.workers != 1)}) -> {where}",
        markup=False,
    )


def run_demo(out: Path) -> Path:
    """`vinetwin demo`, the main job headless: the bundled sample copied to `out` (the sample
    itself is never modified), its summary, its references exported and a preview of its first
    pose; returns the copy's folder."""
    from vinetwin.progress import with_progress
    from vinetwin.render.preview import preview_pose
    from vinetwin.twin.model import copy_bundled_sample
    from vinetwin.twin.summary import print_summary

    dst = copy_bundled_sample(out, replace=True)
    twin = Twin.load(dst)  # the export writes its references, not twin.json
    print_summary(twin)
    report, where = with_progress(
        "exporting references", lambda progress: export_twins(dst, progress=progress)
    )
    print_report(report, where)
    check_export_ok(report)
    first = twin.poses[0].id
    preview_pose(twin, first, out / f"preview_{first}.png", overwrite=True)
    log.info("demo done: references and preview in %s", out)
    return dst
