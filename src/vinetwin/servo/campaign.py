"""The paper's campaign in simulation: a grid of starts times ICP variants, plus the disturbance
runs (paper Fig. 6) and the runs with and without the initial guess (Fig. 4), written as a report.

`run_campaign(twin, CampaignConfig(...), out_dir)` writes into `out_dir`:
- `campaign.json`: the configuration, one summary per run and its time series;
- `report.md` and `report.html`: the table (with the paper's figures beside ours when the preset
  is one of the paper's) and the plots;
- `fig5_errors.png` (translation and rotation error against time per variant, one column per
  start), `fig5_trajectories.png` (3D camera paths), `fig6_disturbance.png`, `fig4_guess.png`;
- `runs/KEY.json`: each run as it finishes, with the digest of its inputs. A campaign that was
  interrupted or had runs fail keeps these; running it again runs only the missing ones.

Every run's start is a camera pose at the preset's translation and rotation from the pruning
pose that still sees the cut (`sim.start_pose`, seeded by the start's index, so every variant
starts from the same pose). Runs go to `workers` processes, each with its own renderer.
"""

from __future__ import annotations

import hashlib
import json
import logging
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from vinetwin._config import JsonFields, json_default
from vinetwin._faults import fault_point
from vinetwin.cloud import ICP_VARIANTS, PerceptionConfig
from vinetwin.errors import InputError, VinetwinError
from vinetwin.executor import (
    ExecutorConfig,
    clear_worker_cache,
    run_unordered,
    worker_cache,
    worker_threads,
    workers_used,
)
from vinetwin.render.reference import file_sha256, pose_seed
from vinetwin.servo.sim import Disturbance, SimConfig, SimRun, simulate, start_pose
from vinetwin.twin.model import Twin, atomic_write_text, load_mesh, remove_orphan_temp_files

log = logging.getLogger(__name__)

#: Version of the per-run files under a report's `runs/` folder.
CAMPAIGN_FORMAT = 1

#: Initial errors (translation m, rotation rad) of the paper's Tables 1 and 2.
PRESETS: dict[str, tuple[tuple[float, float], ...]] = {
    "table1": (
        (0.184749, 0.351915),
        (0.166275, 0.567889),
        (0.034708, 0.550662),
        (0.316327, 0.12695),
    ),
    "table2": (
        (0.193, 0.35),
        (0.167, 0.566),
        (0.034, 0.55),
        (0.185, 0.22),
        (0.20, 0.168),
        (0.037, 0.47),
    ),
    "quick": ((0.05, 0.15),),
}
#: The paper's names of the variants (data/paper/results.json).
PAPER_NAMES = {
    "point_to_point": "ICP",
    "lm": "LM-ICP",
    "point_to_plane": "PP-ICP",
    "symmetric": "SYMM-ICP",
}
#: The paper's Table 1 (sparse vine, real robot): final static error (m, rad) and convergence
#: time (s) per test and variant; None: did not converge.
PAPER_TABLE1: tuple[dict[str, tuple[float, float, float] | None], ...] = (
    {"ICP": (0.003072, 0.002162, 24.89), "LM-ICP": (0.003333, 0.003612, 33.76), "PP-ICP": None, "SYMM-ICP": (0.002912, 0.004765, 14.27)},
    {"ICP": (0.002969, 0.022047, 18.31), "LM-ICP": (0.002691, 0.021488, 26.53), "PP-ICP": (0.002524, 0.022144, 17.73), "SYMM-ICP": (0.002115, 0.021275, 18.24)},
    {"ICP": (0.002027, 0.02138, 16.85), "LM-ICP": (0.001722, 0.022581, 16.62), "PP-ICP": None, "SYMM-ICP": None},
    {"ICP": (0.002007, 0.019513, 8.83), "LM-ICP": None, "PP-ICP": (0.003296, 0.01839, 6.74), "SYMM-ICP": (0.004129, 0.016704, 7.37)},
)  # fmt: skip


@dataclass(frozen=True, kw_only=True)
class CampaignConfig(JsonFields):
    preset: str = "table1"
    """Starts: table1 (the paper's four), table2 (its six) or quick (one close start)."""
    variants: tuple[str, ...] = ICP_VARIANTS
    pose: str = ""
    """Pruning pose to servo to (default: the twin's first)."""
    sim: str = "kinematic"
    """kinematic (a free-flying camera) or mujoco (the D405 on a Panda's hand)."""
    robot: str = ""
    """With mujoco: the Panda model (a folder holding scene.xml, or an MJCF file); default:
    vinetwin's own."""
    duration: float = 30.0
    """Longest simulated time per run (s)."""
    camera_rate: float = 30.0
    fixed_period: float = 0.0
    """Hold each twist this long (s) instead of the measured processing time; 0: measured."""
    disturbance: bool = True
    """Add the disturbance runs (Fig. 6): one per variant."""
    disturbance_time: float = 10.0
    """When the vine moves in those runs (s)."""
    disturbance_translation: tuple[float, float, float] = (0.03, 0.0, 0.01)
    disturbance_rotation: tuple[float, float, float] = (0.0, 0.0, 0.05)
    guess_comparison: bool = True
    """Add the runs with and without the initial guess (Fig. 4), point-to-plane from start 1."""
    seed: int = 0
    workers: int = 0
    """Processes; 0: one per core."""

    def __post_init__(self) -> None:
        if self.preset not in PRESETS:
            raise InputError(f"unknown preset '{self.preset}'; choose one of: {', '.join(PRESETS)}")
        for v in self.variants:
            if v not in ICP_VARIANTS:
                raise InputError(
                    f"unknown ICP variant '{v}'; choose from: {', '.join(ICP_VARIANTS)}"
                )
        if self.sim not in ("kinematic", "mujoco"):
            raise InputError(f"unknown simulation '{self.sim}'; choose kinematic or mujoco")


@dataclass
class _Job:
    key: str
    group: str
    start_index: int
    goal: list[list[float]]
    start: list[list[float]]
    config: dict[str, Any]
    disturbance: dict[str, Any]
    reference_seed: int
    pose_id: str
    robot: str | None = None
    """None: kinematic camera; "" vinetwin's Panda; else a Panda model path."""
    context: dict[str, Any] = field(default_factory=dict)
    """The twin, for the worker (`twin_context`)."""

    def digest(self) -> str:
        """What this run's result depends on: the job without the mesh's location (its content
        is in the context's `mesh_sha256`)."""
        data = asdict(self)
        data["context"] = {k: v for k, v in self.context.items() if k != "mesh_path"}
        data["format"] = CAMPAIGN_FORMAT
        blob = json.dumps(data, sort_keys=True, default=json_default)
        return hashlib.sha256(blob.encode()).hexdigest()

    @property
    def file_name(self) -> str:
        """The run's file in the report's `runs/` folder."""
        return self.key.replace("/", ".") + ".json"


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
        from vinetwin.render.backends import get_backend

        self.mesh = load_mesh(ctx["mesh_path"])
        cam = CameraModel.from_dict(ctx["camera"])
        self.backend = get_backend(
            "open3d", self.mesh.vertices, self.mesh.faces, cam, threads=worker_threads()
        )
        self.perception = PerceptionConfig.from_dict(ctx["perception"])
        self.arms: dict[tuple[str, bytes], Any] = {}

    def close(self) -> None:
        self.backend.close()


def _worker_twin(ctx: dict[str, Any]) -> _TwinWorker:
    key = ("sim", ctx["mesh_path"], ctx["mesh_sha256"], json.dumps(ctx["camera"]))
    return worker_cache(key, lambda: _TwinWorker(ctx))


def worker_backend(ctx: dict[str, Any]) -> tuple[Any, PerceptionConfig]:
    """The renderer and perception settings of a twin (`twin_context`) in this worker process,
    built on first use."""
    w = _worker_twin(ctx)
    return w.backend, w.perception


def worker_arm(ctx: dict[str, Any], robot: str | None, goal: Any) -> Any:
    """This worker's Panda (None for the kinematic camera), its scene holding the vine placed so
    the goal is comfortably reachable; compiled once per robot and goal (each run starts by
    reaching its start pose from home)."""
    if robot is None:
        return None
    from vinetwin.servo.panda import PandaArm, goal_placement

    w = _worker_twin(ctx)
    key = (robot, np.asarray(goal, float).tobytes())
    if key not in w.arms:
        w.arms[key] = PandaArm(
            robot or None,
            T_flange_camera=np.asarray(ctx["T_flange_camera"]),
            camera=w.backend.camera,
            vine=(w.mesh.vertices, w.mesh.faces),
            T_base_vine=goal_placement(goal),
        )
    return w.arms[key]


def _run_job(job: _Job) -> dict[str, Any]:
    dist = job.disturbance
    backend, perception = worker_backend(job.context)
    run: SimRun = simulate(
        backend,
        np.asarray(job.goal),
        np.asarray(job.start),
        job.reference_seed,
        perception,
        SimConfig.from_dict(job.config),
        disturbance=Disturbance.from_dict(dist) if dist else None,
        pose_id=job.pose_id,
        arm=worker_arm(job.context, job.robot, np.asarray(job.goal)),
    )
    fault_point(job.key, "run")
    return {
        "key": job.key,
        "group": job.group,
        "start_index": job.start_index,
        "summary": run.summary(),
        "series": run.series(step=1),
        "goal": job.goal,
        "disturbance_time": dist.get("time", -1.0) if dist else -1.0,
    }


def plan(twin: Twin, cfg: CampaignConfig) -> list[_Job]:
    """The runs of a campaign (start poses drawn here, so every variant shares them)."""
    pose = twin.pose(cfg.pose) if cfg.pose else twin.poses[0]
    cut = twin.cut_point(pose.cut_point).point
    goal = np.asarray(pose.T_vine_camera)
    ref_seed = pose_seed(cfg.seed, pose.id)
    base = SimConfig(
        duration=cfg.duration,
        camera_rate=cfg.camera_rate,
        fixed_period=cfg.fixed_period,
        seed=cfg.seed,
    )
    robot = None if cfg.sim == "kinematic" else cfg.robot
    starts = []
    for i, (t, r) in enumerate(PRESETS[cfg.preset]):
        rng = np.random.default_rng([cfg.seed, i])
        starts.append(start_pose(goal, cut, t, r, rng, twin.camera, twin.perception.max_depth))

    ctx = twin_context(twin)

    def job(key: str, group: str, i: int, sim: SimConfig, dist: Disturbance | None = None) -> _Job:
        return _Job(key, group, i, goal.tolist(), starts[i].tolist(), sim.to_dict(),
                    dist.to_dict() if dist else {}, ref_seed, pose.id, robot, ctx)  # fmt: skip

    jobs = [
        job(f"grid/{i}/{v}", "grid", i, replace(base, variant=v))
        for i in range(len(starts))
        for v in cfg.variants
    ]
    if cfg.disturbance:
        d = Disturbance(
            time=cfg.disturbance_time,
            translation=cfg.disturbance_translation,
            rotation=cfg.disturbance_rotation,
        )
        long = replace(base, duration=max(cfg.duration, cfg.disturbance_time + 15.0))
        jobs += [
            job(f"disturbance/{v}", "disturbance", 0, replace(long, variant=v), d)
            for v in cfg.variants
        ]
    if cfg.guess_comparison:
        for g in ("kinematic", "identity"):
            jobs.append(
                job(f"guess/{g}", "guess", 0, replace(base, variant="point_to_plane", guess=g))
            )
    return jobs


def run_jobs(
    jobs: list[Any],
    executor: ExecutorConfig,
    progress: Callable[[dict[str, Any], int, int], None] | None = None,
    fn: Callable[[Any], dict[str, Any]] | None = None,
    on_result: Callable[[Any, dict[str, Any]], None] | None = None,
) -> tuple[list[tuple[Any, dict[str, Any]]], list[tuple[Any, str]], int]:
    """Runs simulation jobs (`fn`, default one closed-loop run per job) on the executor (a
    local process pool, one worker per core when `workers` is 0, or Ray), each worker with its
    own renderer. Returns (job, result) in completion order, the failed jobs with their error,
    and the number of workers. `on_result(job, result)` is called as each job finishes (to keep
    it on disk before the others end)."""
    fn = fn or _run_job
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


def run_campaign(
    twin: Twin,
    cfg: CampaignConfig,
    out_dir: Path,
    progress: Callable[[dict[str, Any], int, int], None] | None = None,
    executor: ExecutorConfig | None = None,
    force: bool = False,
) -> dict[str, Any]:
    """Runs the campaign and writes its report into out_dir; returns what campaign.json holds.
    `executor` (default: a local pool of `cfg.workers`) picks where the runs go.

    Each finished run is written at once to `out_dir/runs/KEY.json` with the digest of its
    inputs, so an interrupted or partly failed campaign keeps its finished runs: running it again
    runs only the missing ones (all of them with `force`). The report is written once every run
    is there; when runs fail, the error names them and nothing else is lost."""
    jobs = plan(twin, cfg)
    runs_dir = out_dir / "runs"
    runs_dir.mkdir(parents=True, exist_ok=True)
    for d in (out_dir, runs_dir):  # left by a campaign killed while writing
        remove_orphan_temp_files(d)
    digests = {j.key: j.digest() for j in jobs}
    done: dict[str, dict[str, Any]] = {}
    if not force:
        for j in jobs:
            old = _read_run(runs_dir / j.file_name)
            if old is not None and old.get("digest") == digests[j.key]:
                done[j.key] = old["result"]
    todo = [j for j in jobs if j.key not in done]
    if done:
        log.info(
            "%d of %d runs already done with the same inputs (%s); running %d",
            len(done), len(jobs), runs_dir, len(todo),
        )  # fmt: skip

    def keep(job: _Job, result: dict[str, Any]) -> None:
        record = {"format": CAMPAIGN_FORMAT, "digest": digests[job.key], "result": result}
        text = json.dumps(record, default=json_default)
        atomic_write_text(runs_dir / job.file_name, text + "\n")
        done[job.key] = json.loads(text)["result"]  # as a resumed run reads it

    workers = 0
    failed: list[tuple[Any, str]] = []
    if todo:
        _, failed, workers = run_jobs(
            todo, executor or ExecutorConfig(workers=cfg.workers), progress, on_result=keep
        )
    if failed:
        raise VinetwinError(
            f"{len(failed)} of {len(jobs)} runs failed: "
            + "; ".join(f"{j.key}: {e}" for j, e in failed[:5])
            + f". The {len(done)} finished runs are kept in {runs_dir}; run the same command"
            " again to run only the missing ones."
        )
    results = [done[j.key] for j in jobs]
    data = {
        "twin": twin.name,
        "config": cfg.to_dict(),
        "starts": [list(s) for s in PRESETS[cfg.preset]],
        "workers": workers,
        "resumed": len(jobs) - len(todo),
        "runs": results,
    }
    from vinetwin.servo import report

    atomic_write_text(
        out_dir / "campaign.json", json.dumps(data, indent=1, default=json_default) + "\n"
    )
    report.write_report(data, out_dir)
    return data


def _read_run(path: Path) -> dict[str, Any] | None:
    """A run file, or None when it is missing, unreadable or from another format (run again)."""
    try:
        record = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(record, dict) or record.get("format") != CAMPAIGN_FORMAT:
        return None
    return record if isinstance(record.get("result"), dict) else None
