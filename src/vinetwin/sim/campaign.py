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

import logging
import shutil
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from vinetwin._faults import fault_point
from vinetwin.errors import VinetwinError
from vinetwin.executor import ExecutorConfig
from vinetwin.files import atomic_write_json, json_sha256, remove_orphan_temp_files
from vinetwin.jobstore import JobStore
from vinetwin.render.reference import pose_seed
from vinetwin.sim import report
from vinetwin.sim.config import (
    CampaignConfig,
    Disturbance,
    FaultConfig,
    FieldProfile,
    SimConfig,
    servo_settings,
)
from vinetwin.sim.paper import PRESETS
from vinetwin.sim.session import SimSpec, start_pose
from vinetwin.sim.simulate import SimRun, simulate
from vinetwin.sim.workers import run_jobs, twin_context, worker_world
from vinetwin.twin.model import Twin

log = logging.getLogger(__name__)

#: Version of the per-run files under a report's `runs/` folder.
CAMPAIGN_FORMAT = 3
#: The variant of the control-law comparison (its runs under the grid's law are the grid's).
LAW_VARIANT = "point_to_plane"


@dataclass
class _Job:
    key: str
    group: str
    start_index: int
    spec: SimSpec
    context: dict[str, Any] = field(default_factory=dict)
    """The twin, for the worker (`twin_context`)."""
    reference: dict[str, Any] = field(default_factory=dict)
    """Under the field profile's twin source: the reconstructed twin's mesh (`mesh_path`,
    `mesh_sha256`), which renders the reference while the scene stays the true vine."""

    def digest(self) -> str:
        """What this run's result depends on: the run, and the twin and reference meshes by
        their content (`mesh_sha256`), not their location."""
        data = {
            "key": self.key,
            "group": self.group,
            "start_index": self.start_index,
            "spec": self.spec.to_dict(),
            "context": {k: v for k, v in self.context.items() if k != "mesh_path"},
            "reference": {k: v for k, v in self.reference.items() if k != "mesh_path"},
            "servo": servo_settings(self.spec.config.variant),
            "format": CAMPAIGN_FORMAT,
        }
        return json_sha256(data)

    @property
    def run_name(self) -> str:
        """The run's file in the report's `runs/` folder, without `.json`."""
        return self.key.replace("/", ".")


def _run_job(job: _Job) -> dict[str, Any]:
    spec = job.spec
    run: SimRun = simulate(spec, worker_world(job.context, job.reference, spec))
    fault_point(job.key, "run")
    return {
        "key": job.key,
        "group": job.group,
        "start_index": job.start_index,
        "summary": run.summary(),
        "series": run.series(step=1),
        "goal": np.asarray(spec.goal, float).tolist(),
        "disturbance_time": spec.disturbance.time,
    }


def plan(twin: Twin, cfg: CampaignConfig, cache: Path | None = None) -> list[_Job]:
    """The runs of a campaign (start poses drawn here, so every variant shares them). Under the
    field profile's twin source the reconstructed twin is built here (cached in `cache`)."""
    pose = twin.pose(cfg.pose) if cfg.pose else twin.poses[0]
    cut = twin.cut_point(pose.cut_point).point
    goal = np.asarray(pose.T_vine_camera)
    ref_seed = pose_seed(cfg.seed, pose.id)
    profile = cfg.field_profile()
    base = SimConfig(
        law=cfg.law,
        duration=cfg.duration,
        camera_rate=cfg.camera_rate,
        fixed_period=cfg.fixed_period,
        limits=cfg.limits,
        seed=cfg.seed,
        profile=profile,
    )
    rebuilt: dict[str, Any] = {}
    if profile.on("twin"):
        from vinetwin.files import file_sha256
        from vinetwin.mesh import load_mesh
        from vinetwin.sim.field import check_field_twin_view, reconstructed_twin

        mesh, _ = reconstructed_twin(twin, profile, cfg.seed, cache or twin.root / "field_twins")
        check_field_twin_view(
            twin.load_mesh(), load_mesh(mesh), twin.camera, profile, pose.id, goal,
            twin.perception.max_depth,
        )  # fmt: skip
        rebuilt = {"mesh_path": str(mesh), "mesh_sha256": file_sha256(mesh)}
    robot = None if cfg.sim == "kinematic" else cfg.robot
    starts = []
    for i, (t, r) in enumerate(PRESETS[cfg.preset]):
        rng = np.random.default_rng([cfg.seed, i])
        starts.append(start_pose(goal, cut, (t, r), rng, twin.camera, twin.perception.max_depth))

    ctx = twin_context(twin)

    def job(key: str, group: str, i: int, sim: SimConfig, dist: Disturbance | None = None) -> _Job:
        spec = SimSpec(goal, starts[i], sim, pose.id, np.asarray(cut, float),
                       dist or Disturbance(), ref_seed, robot)  # fmt: skip
        return _Job(key, group, i, spec, ctx, rebuilt if sim.profile.on("twin") else {})

    jobs = [
        job(f"grid/{i}/{v}", "grid", i, replace(base, variant=v))
        for i in range(len(starts))
        for v in cfg.variants
    ]
    if profile.sources and cfg.profile_comparison:  # the same grid, ideal
        jobs += [
            job(f"ideal/{i}/{v}", "ideal", i, replace(base, variant=v, profile=FieldProfile()))
            for i in range(len(starts))
            for v in cfg.variants
        ]
    if profile.sources and cfg.ablation:  # each source alone, from the first start
        jobs += [
            job(f"ablation/{src}/{v}", "ablation", 0,
                replace(base, variant=v, profile=replace(profile, sources=(src,))))
            for src in profile.sources
            if src != "dynamics" or robot is not None  # no arm: nothing to simulate
            for v in cfg.variants
        ]  # fmt: skip
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
    for c in cfg.faults:  # one run per fault class and variant, from the first start
        faults = FaultConfig(classes=(c,), rate=cfg.fault_rate, seed=cfg.seed)
        jobs += [
            job(f"faults/{c}/{v}", "faults", 0, replace(base, variant=v, faults=faults))
            for v in cfg.variants
        ]
    if cfg.law_comparison:  # the grid's variant under the other law, from every start
        other = "target" if cfg.law == "eq8" else "eq8"
        jobs += [
            job(f"law/{i}/{other}", "law", i, replace(base, variant=LAW_VARIANT, law=other))
            for i in range(len(starts))
        ]
    if cfg.guess_comparison:
        for g in ("kinematic", "identity"):
            jobs.append(
                job(f"guess/{g}", "guess", 0, replace(base, variant="point_to_plane", guess=g))
            )
    return jobs


def run_campaign(
    twin: Twin,
    cfg: CampaignConfig,
    out_dir: Path,
    progress: Callable[[dict[str, Any], int, int], None] | None = None,
    executor: ExecutorConfig | None = None,
    force: bool = False,
    copy_json: Path | None = None,
) -> dict[str, Any]:
    """Runs the campaign and writes its report into out_dir; returns what campaign.json holds.
    `executor` (default: a local pool of `cfg.workers`) picks where the runs go.

    Each finished run is written at once to `out_dir/runs/KEY.json` with the digest of its
    inputs, so an interrupted or partly failed campaign keeps its finished runs: running it again
    runs only the missing ones (all of them with `force`). The report is written once every run
    is there; when runs fail, the error names them and nothing else is lost. `copy_json`: also
    copy campaign.json there."""
    jobs = plan(twin, cfg, out_dir / "field_twins")
    profile = cfg.field_profile()
    field_twin: dict[str, Any] = {}
    if profile.on("twin"):  # built by plan (cached there); its score, for the report
        from vinetwin.sim.field import reconstructed_twin

        field_twin = reconstructed_twin(twin, profile, cfg.seed, out_dir / "field_twins")[1]
    runs_dir = out_dir / "runs"
    store = JobStore(runs_dir, CAMPAIGN_FORMAT, indent=None).open()
    remove_orphan_temp_files(out_dir)  # left by a campaign killed while writing its report
    digests = {j.key: j.digest() for j in jobs}
    done: dict[str, dict[str, Any]] = {}
    if not force:
        for j in jobs:
            old = store.current(j.run_name, digests[j.key])
            if old is not None and isinstance(old.get("result"), dict):
                done[j.key] = old["result"]
    todo = [j for j in jobs if j.key not in done]
    if done:
        log.info(
            "%d of %d runs already done with the same inputs (%s); running %d",
            len(done), len(jobs), runs_dir, len(todo),
        )  # fmt: skip

    def keep(job: _Job, result: dict[str, Any]) -> None:
        # as a resumed run reads it
        done[job.key] = store.put(job.run_name, digests[job.key], {"result": result})["result"]

    workers = 0
    failed: list[tuple[Any, str]] = []
    if todo:
        _, failed, workers = run_jobs(
            todo, executor or ExecutorConfig(workers=cfg.workers), _run_job, progress, keep
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
        "image_size": [twin.camera.width, twin.camera.height],
        "workers": workers,
        "resumed": len(jobs) - len(todo),
        "field_sources": list(profile.sources),
        "field_tolerances": list(SimConfig(profile=profile).tolerances()),
        "field_twin": field_twin,
        "runs": results,
    }
    atomic_write_json(out_dir / "campaign.json", data)
    report.write_report(data, out_dir)
    if copy_json is not None:  # the figures, also where the caller wants them
        copy_json.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(out_dir / "campaign.json", copy_json)
    return data
