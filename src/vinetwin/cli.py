"""The `vinetwin` command. Each subcommand is a frozen dataclass parsed by tyro; its `run()`
imports what it needs, so `vinetwin --help` stays fast."""

from __future__ import annotations

import logging
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import tyro

from vinetwin.errors import VinetwinError

log = logging.getLogger("vinetwin")


@dataclass(frozen=True, kw_only=True)
class Sample:
    """Grow a procedural dormant grapevine and write it as a twin folder."""

    out: Path
    """Twin folder to create (e.g. vine7.twin)."""
    seed: int = 0
    """Random seed: the same seed gives the same vine."""
    cordons: Literal[1, 2] = 2
    """One cordon arm (unilateral) or two (bilateral)."""
    edge: float = 0.002
    """Target triangle edge length of the tube mesh, metres (smaller: denser mesh)."""
    cut_points: int = 4
    """How many cut-point candidates become cut points with a default pruning pose."""
    overwrite: bool = False
    """Replace a twin already in OUT."""

    def run(self) -> None:
        from vinetwin.twin.generator import VineParams, generate_vine
        from vinetwin.twin.model import twin_from_skeleton

        sk = generate_vine(self.seed, VineParams(cordons=self.cordons))
        twin = twin_from_skeleton(
            self.out,
            sk,
            edge=self.edge,
            source={
                "generator": "vinetwin.twin.generator",
                "seed": self.seed,
                "cordons": self.cordons,
            },
            cut_points=self.cut_points,
            overwrite=self.overwrite,
        )
        _summary(twin)


@dataclass(frozen=True, kw_only=True)
class ImportVine:
    """Import a digitised plant skeleton (hydroshoot digit.input or a cylinder list) as a twin."""

    file: Annotated[Path, tyro.conf.Positional]
    """Skeleton file to import."""
    out: Path
    """Twin folder to create."""
    format: Literal["auto", "hydroshoot", "cylinders"] = "auto"
    """File format; auto detects it from the first lines."""
    edge: float = 0.003
    """Target triangle edge length of the tube mesh, metres."""
    cut_points: int = 0
    """How many cut-point candidates (hydroshoot shoots) become cut points with a pose."""
    overwrite: bool = False
    """Replace a twin already in OUT."""

    def run(self) -> None:
        from vinetwin.twin.importers import detect_format, load_skeleton
        from vinetwin.twin.model import twin_from_skeleton

        fmt = detect_format(self.file) if self.format == "auto" else self.format
        sk = load_skeleton(self.file, fmt)
        twin = twin_from_skeleton(
            self.out,
            sk,
            edge=self.edge,
            caps="round" if fmt == "hydroshoot" else "flat",
            source={"importer": fmt, "file": str(self.file)},
            cut_points=self.cut_points,
            overwrite=self.overwrite,
        )
        _summary(twin)


@dataclass(frozen=True, kw_only=True)
class Info:
    """Validate a twin folder and print what it holds."""

    twin: Annotated[Path, tyro.conf.Positional]
    """Twin folder."""
    check_mesh: bool = True
    """Also read and check the mesh."""

    def run(self) -> None:
        from vinetwin.twin.model import Twin

        twin = Twin.load(self.twin)
        _summary(twin, mesh=self.check_mesh)


BackendChoice = Literal["open3d", "pyrender", "mujoco"]


@dataclass(frozen=True, kw_only=True)
class Export:
    """Render each pruning pose's reference cloud into TWIN/references (PLY, PCD, JSON), for one
    twin or every twin of a vineyard folder; resumable."""

    twin: Annotated[Path, tyro.conf.Positional]
    """Twin folder, or a folder of twin folders (a vineyard)."""
    poses: tuple[str, ...] = ()
    """Pose ids to export (default: all; one twin only)."""
    backend: BackendChoice = "open3d"
    """Depth renderer: open3d (ray casting, no OpenGL), pyrender or mujoco (EGL)."""
    workers: int = 0
    """Worker processes; 0 chooses (1 for open3d, whose ray caster already uses every core; one
    per core for pyrender and mujoco). With --ray: the local Ray's CPUs (0: all)."""
    ray: bool = False
    """Run the jobs on a local Ray started on this machine (pip install 'vinetwin[ray]')."""
    ray_address: str = ""
    """Run the jobs on this Ray cluster (e.g. HOST:6379 or auto); the twin folders must be at the
    same path on every node."""
    seed: int = 0
    """Base seed of the D405 noise; each pose derives its own."""
    force: bool = False
    """Re-render references whose inputs did not change."""
    clean: bool = False
    """Render without the D405 sensor model (exact depth)."""

    def run(self) -> None:
        from vinetwin.render.export import check_export_ok, export_many, export_references
        from vinetwin.render.sensor import SensorConfig
        from vinetwin.twin.model import Twin, find_twins

        roots = find_twins(self.twin)
        executor = _executor(self.ray, self.ray_address, self.workers)
        sensor = SensorConfig(enabled=not self.clean)
        if len(roots) == 1:
            twin = Twin.load(roots[0])
            report = _with_progress(
                "exporting references",
                lambda progress: export_references(
                    twin, self.poses or None, backend=self.backend, workers=self.workers,
                    seed=self.seed, sensor=sensor, force=self.force, executor=executor,
                    progress=progress,
                ),
            )  # fmt: skip
            where = twin.references_dir
        else:
            if self.poses:
                raise VinetwinError("--poses selects poses of one twin, not of a vineyard")
            twins = [Twin.load(r) for r in roots]
            report = _with_progress(
                f"exporting references of {len(twins)} twins",
                lambda progress: export_many(
                    twins, backend=self.backend, workers=self.workers, seed=self.seed,
                    sensor=sensor, force=self.force, executor=executor, progress=progress,
                ),
            )  # fmt: skip
            where = self.twin
        _print_export(report, where)
        check_export_ok(report)


def _executor(ray: bool, address: str, workers: int):  # type: ignore[no-untyped-def]
    """The executor the flags ask for (None: the command's default local pool)."""
    from vinetwin.executor import ExecutorConfig

    if address:
        return ExecutorConfig(kind="ray", address=address)
    if ray:
        return ExecutorConfig(kind="ray", workers=workers)
    return None


@dataclass(frozen=True, kw_only=True)
class Preview:
    """Render one pose's D405 depth image and reference cloud into a PNG to look at."""

    twin: Annotated[Path, tyro.conf.Positional]
    """Twin folder."""
    pose: str
    """Pose id."""
    out: Path = Path("preview.png")
    """PNG to write."""
    backend: BackendChoice = "open3d"
    """Depth renderer."""
    seed: int = 0
    """Base seed of the D405 noise."""

    def run(self) -> None:
        from vinetwin.render.backends import get_backend
        from vinetwin.render.preview import save_preview
        from vinetwin.render.reference import pose_seed, render_reference
        from vinetwin.render.sensor import SensorConfig
        from vinetwin.twin.model import Twin

        twin = Twin.load(self.twin)
        pose = twin.pose(self.pose)
        mesh = twin.load_mesh()
        backend = get_backend(self.backend, mesh.vertices, mesh.faces, twin.camera)
        ref = render_reference(
            backend,
            pose.T_vine_camera,
            twin.perception,
            SensorConfig(),
            pose_seed(self.seed, pose.id),
        )
        backend.close()
        save_preview(ref, self.out, f"{twin.name} / {pose.id} ({self.backend})")
        if ref.cloud.empty:
            log.warning(
                "pose %s sees nothing within %.2f m: empty reference cloud",
                pose.id,
                twin.perception.max_depth,
            )
        log.info("wrote %s (%d points)", self.out, len(ref.cloud))


def _with_progress(label: str, work):  # type: ignore[no-untyped-def]
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    with Progress(
        TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn()
    ) as bar:
        task = bar.add_task(label, total=None)

        def progress(result: object, done: int, total: int) -> None:
            bar.update(task, completed=done, total=total)

        return work(progress)


def _print_export(report: object, where: Path) -> None:
    from rich.console import Console
    from rich.table import Table

    from vinetwin.render.export import ExportReport

    assert isinstance(report, ExportReport)
    several = len({r.twin for r in report.results}) > 1
    table = Table("pose", "status", "points", "seconds", "note")
    for r in report.results:
        table.add_row(
            f"{Path(r.twin).name}/{r.pose_id}" if several else r.pose_id,
            r.status,
            str(r.points) if r.status == "rendered" else "",
            f"{r.seconds:.2f}",
            r.error or r.warning,
        )
    con = Console()
    con.print(table)
    con.print(
        f"{report.count('rendered')} rendered, {report.count('skipped')} unchanged, "
        f"{report.count('failed')} failed in {report.seconds:.1f} s "
        f"({report.executor}, {report.workers} worker{'s' * (report.workers != 1)}) -> {where}"
    )


VariantChoice = Literal["point_to_point", "lm", "point_to_plane", "symmetric"]


@dataclass(frozen=True, kw_only=True)
class Campaign:
    """Servo in simulation from the paper's starts with each ICP variant, plus a disturbance run
    per variant and runs with and without the initial guess; write a report (Markdown, HTML,
    PNG plots, JSON)."""

    twin: Annotated[Path, tyro.conf.Positional]
    """Twin folder."""
    preset: Literal["table1", "table2", "quick"] = "table1"
    """Starts: the paper's Table 1 (4), Table 2 (6), or one close start (quick)."""
    sim: Literal["kinematic", "mujoco"] = "kinematic"
    """Simulation: a free-flying camera (kinematic) or the D405 on a MuJoCo Panda (mujoco)."""
    robot: str = ""
    """With --sim mujoco: a Panda model folder (holding scene.xml, e.g. MuJoCo Menagerie's
    franka_emika_panda) or MJCF file; default: vinetwin's own Panda."""
    variants: tuple[VariantChoice, ...] = ("point_to_point", "lm", "point_to_plane", "symmetric")
    """ICP variants to run."""
    pose: str = ""
    """Pruning pose to servo to (default: the twin's first)."""
    out: Path | None = None
    """Report folder (default: TWIN/campaign/PRESET)."""
    json: Path | None = None
    """Also write the figures (campaign.json) here."""
    duration: float = 30.0
    """Longest simulated time per run (s)."""
    camera_rate: float = 30.0
    """Camera frames per second."""
    fixed_period: float = 0.0
    """Hold each twist this long (s) instead of the measured processing time; 0: measured."""
    disturbance: bool = True
    """Add a disturbance run per variant (the vine moves 3 cm and 0.05 rad at 10 s)."""
    guess_comparison: bool = True
    """Add point-to-plane runs with and without the kinematic initial guess."""
    workers: int = 0
    """Processes; 0: one per core. With --ray: the local Ray's CPUs (0: all)."""
    ray: bool = False
    """Run the runs on a local Ray started on this machine (pip install 'vinetwin[ray]')."""
    ray_address: str = ""
    """Run the runs on this Ray cluster (HOST:6379, auto)."""
    seed: int = 0
    """Seed of the starts, the noise and the registration error."""
    force: bool = False
    """Run every run again, even those already in OUT/runs with the same inputs (an earlier
    campaign that was interrupted or had runs fail keeps its finished runs there)."""

    def run(self) -> None:
        import shutil

        from vinetwin.servo.campaign import CampaignConfig, run_campaign
        from vinetwin.twin.model import Twin

        twin = Twin.load(self.twin)
        cfg = CampaignConfig(
            preset=self.preset,
            variants=tuple(self.variants),
            pose=self.pose,
            sim=self.sim,
            robot=self.robot,
            duration=self.duration,
            camera_rate=self.camera_rate,
            fixed_period=self.fixed_period,
            disturbance=self.disturbance,
            guess_comparison=self.guess_comparison,
            workers=self.workers,
            seed=self.seed,
        )
        out = self.out or (self.twin / "campaign" / self.preset)
        executor = _executor(self.ray, self.ray_address, self.workers)
        data = _with_progress(
            "simulating",
            lambda progress: run_campaign(twin, cfg, out, progress, executor, self.force),
        )
        _print_campaign(data)
        log.info("report: %s", out / "report.html")
        if self.json:
            self.json.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(out / "campaign.json", self.json)


@dataclass(frozen=True, kw_only=True)
class Validate:
    """Check every pruning pose can be reached: closed-loop runs from stratified starts per pose
    and ICP variant; success rate and convergence basin into TWIN/validation and twin.json."""

    twin: Annotated[Path, tyro.conf.Positional]
    """Twin folder, or a folder of twin folders (a vineyard)."""
    poses: tuple[str, ...] = ()
    """Pose ids (default: all)."""
    variants: tuple[VariantChoice, ...] = ("point_to_point", "lm", "point_to_plane", "symmetric")
    """ICP variants to try."""
    starts: int = 6
    """Runs per pose and variant, from 1/N to N/N of the radii away."""
    radius_translation: float = 0.10
    """Farthest start (m)."""
    radius_rotation: float = 0.30
    """Farthest start (rad)."""
    duration: float = 20.0
    """Longest simulated time per run (s)."""
    workers: int = 0
    """Processes; 0: one per core. With --ray: the local Ray's CPUs (0: all)."""
    ray: bool = False
    """Run on a local Ray started on this machine (pip install 'vinetwin[ray]')."""
    ray_address: str = ""
    """Run on this Ray cluster (HOST:6379, auto); twin folders at the same path on every node."""
    seed: int = 0
    """Seed of the starts and the noise."""
    force: bool = False
    """Run again what is already validated with the same inputs."""
    json: Path | None = None
    """Also write the summary here."""

    def run(self) -> None:
        import json

        from vinetwin.servo.validate import ValidateConfig, validate_many
        from vinetwin.twin.model import Twin, find_twins

        twins = [Twin.load(r) for r in find_twins(self.twin)]
        cfg = ValidateConfig(
            variants=tuple(self.variants),
            poses=self.poses,
            starts=self.starts,
            radius_translation=self.radius_translation,
            radius_rotation=self.radius_rotation,
            duration=self.duration,
            seed=self.seed,
            workers=self.workers,
            force=self.force,
        )
        executor = _executor(self.ray, self.ray_address, self.workers)
        summaries = _with_progress(
            "validating", lambda progress: validate_many(twins, cfg, progress, executor)
        )
        for twin in twins:
            print((twin.root / "validation" / "summary.md").read_text())
        if self.json:
            self.json.parent.mkdir(parents=True, exist_ok=True)
            data = summaries[0] if len(summaries) == 1 else summaries
            self.json.write_text(json.dumps(data, indent=1))
        failed = [f for s in summaries for f in s.get("failed", [])]
        if failed:
            raise VinetwinError(
                f"{len(failed)} pose/variant validations failed (run again to complete them): "
                + "; ".join(f"{f['pose']}.{f['variant']}: {f['error']}" for f in failed[:5])
            )


@dataclass(frozen=True, kw_only=True)
class ServoCmd:
    """Servo the camera to one pruning pose: camera frames -> perception -> ICP (kinematic guess)
    -> PBVS -> guarded robot command, every cycle logged. In simulation (--camera sim --robot
    sim|mujoco), replayed without a robot (--camera folder:DIR|bag:FILE --robot none) or on
    hardware (--camera realsense --robot franka:HOST); see docs/hardware.md."""

    twin: Path
    """Twin folder."""
    pose: str = ""
    """Pruning pose id (default: the twin's first)."""
    camera: str = "sim"
    """realsense[:SERIAL] (a live D405), bag:FILE (a RealSense recording), folder:DIR (a capture
    folder), sim (rendered from the twin, simulated time), or render (rendered from the twin at
    a real robot's pose, in real time: the robot link without a camera)."""
    robot: str = "sim"
    """franka:HOST (franky-control), sim (a free-flying camera), mujoco (the MuJoCo Panda) or
    none (compute and log only)."""
    variant: VariantChoice = "point_to_plane"
    """ICP variant."""
    dry_run: bool = False
    """Compute and log twists; send none (the robot is only read)."""
    log: Path | None = None
    """Cycle log (JSON Lines; default TWIN/servo/POSE-DATE.jsonl)."""
    record: Path | None = None
    """Also write the frames, with stamps and robot poses, as a capture folder (replayable with
    --camera folder:DIR --robot none)."""
    duration: float = 30.0
    """End after this many seconds; 0: no limit."""
    settle: float = 2.0
    """End once at the goal (2 mm, 0.01 rad) for this long (s); 0: never."""
    max_linear: float = 0.05
    """Camera speed limit (m/s) of the servo and of the robot adapter."""
    max_angular: float = 0.25
    """rad/s."""
    watchdog: float = 0.2
    """Stop the robot when no command came for this long (s)."""
    max_cycle: float = 0.1
    """Send zero when a frame took longer than this from capture to command (s)."""
    width: int = 848
    """Live camera: depth width (848 or 1280 for the twin's D405 presets)."""
    height: int = 480
    fps: int = 30
    """Live camera: frames per second (30, 60 or 90)."""
    rate: float | None = None
    """Playback pacing in frames per second. folder: default as fast as read; bag: default the
    recorded rate, 0 as fast as read."""
    color: bool = False
    """Also stream colour aligned to depth (live or bag; kept by --record)."""
    camera_rate: float = 30.0
    """Simulation: camera frames per second."""
    robot_model: str = ""
    """With --robot mujoco: a Panda model folder or MJCF file (default: vinetwin's own)."""
    start_translation: float = 0.04
    """Simulation: start this far from the pruning pose (m)."""
    start_rotation: float = 0.1
    """Simulation: and this angle (rad)."""
    dynamics_factor: float = 0.2
    """franka: fraction of the robot's velocity, acceleration and jerk limits."""
    no_realtime: bool = False
    """franka: do not demand a real-time kernel (a simulated Franka, bench tests)."""
    seed: int = 0

    def run(self) -> None:
        from vinetwin.servo.loop import LoopConfig
        from vinetwin.servo.robot import CommandLimits
        from vinetwin.servo.runner import RunnerConfig, run_pose
        from vinetwin.servo.sim import SimConfig
        from vinetwin.twin.model import Twin

        twin = Twin.load(self.twin)
        cfg = RunnerConfig(
            pose=self.pose,
            camera=self.camera,
            robot=self.robot,
            robot_model=self.robot_model,
            servo=SimConfig(
                variant=self.variant,
                max_linear=self.max_linear,
                max_angular=self.max_angular,
                camera_rate=self.camera_rate,
                duration=max(self.duration, 1e-3),
                seed=self.seed,
            ),
            limits=CommandLimits(
                max_linear=self.max_linear, max_angular=self.max_angular, watchdog=self.watchdog
            ),
            loop=LoopConfig(
                dry_run=self.dry_run,
                duration=self.duration,
                settle=self.settle,
                max_cycle=self.max_cycle,
            ),
            start_translation=self.start_translation,
            start_rotation=self.start_rotation,
            width=self.width,
            height=self.height,
            fps=self.fps,
            color=self.color,
            rate=self.rate,
            realtime=not self.no_realtime,
            dynamics_factor=self.dynamics_factor,
        )
        summary, path = run_pose(twin, cfg, log_path=self.log, record=self.record)
        err = summary.final_error
        print(
            f"{summary.frames} frames, {summary.trusted} trusted, {summary.sent} commands sent; "
            f"ended: {summary.ended}; at goal: {summary.at_goal}"
        )
        if err is not None:
            print(f"last estimated error: {1000 * err[0]:.2f} mm, {err[1]:.4f} rad")
        if summary.reasons:
            print("refused: " + ", ".join(f"{k} x{v}" for k, v in summary.reasons.items()))
        print(
            f"median cycle {summary.median_cycle_ms:.1f} ms, {summary.loop_rate_hz:.1f} Hz; "
            f"overruns {summary.overruns}, camera timeouts {summary.camera_timeouts}"
        )
        print(f"log: {path}")


@dataclass(frozen=True, kw_only=True)
class ServoPlot:
    """Plot servo logs (vinetwin servo --log) with the campaign report's figures: error against
    time and the camera's path."""

    logs: Annotated[tuple[Path, ...], tyro.conf.Positional]
    """One or more .jsonl logs."""
    out: Path = Path("servo-plots")
    """Folder for errors.png and trajectories.png."""

    def run(self) -> None:
        from vinetwin.servo.loop import log_as_campaign
        from vinetwin.servo.report import plot_errors, plot_trajectories

        data = log_as_campaign(list(self.logs))
        self.out.mkdir(parents=True, exist_ok=True)
        plot_errors(data, self.out / "errors.png")
        plot_trajectories(data, self.out / "trajectories.png")
        print(f"wrote {self.out / 'errors.png'} and {self.out / 'trajectories.png'}")


@dataclass(frozen=True, kw_only=True)
class CaptureSynthetic:
    """Render a synthetic RGB-D capture of a twin's mesh (D405 depth with its noise, textured
    colour, ground-truth poses) into a capture folder."""

    twin: Annotated[Path, tyro.conf.Positional]
    """Twin folder whose mesh is captured."""
    out: Path
    """Capture folder to write."""
    frames: int = 120
    """Number of frames."""
    distance: float = 0.3
    """Camera distance to the vine (m)."""
    pose_noise: tuple[float, float] = (0.0, 0.0)
    """Standard deviation of the error added to the recorded poses (m, rad)."""
    trajectory: Literal["grid", "path"] = "grid"
    """grid: viewpoints spread over the vine; path: a continuous sweep with small steps (video)."""
    seed: int = 0

    def run(self) -> None:
        from vinetwin.reconstruct.synthetic import synthetic_capture
        from vinetwin.twin.model import Twin

        twin = Twin.load(self.twin)
        path = _with_progress(
            "rendering frames",
            lambda progress: synthetic_capture(
                twin,
                self.out,
                self.frames,
                self.distance,
                self.seed,
                self.pose_noise,
                progress,
                self.trajectory,
            ),
        )
        log.info("capture: %s (%d frames)", path, self.frames)


@dataclass(frozen=True, kw_only=True)
class ImportRecording:
    """Turn a RealSense recording (.db3 from librealsense 2.59, or .bag where the installed
    librealsense reads it) into a capture folder (colour aligned to depth; no robot poses)."""

    recording: Annotated[Path, tyro.conf.Positional]
    """Recording file."""
    out: Path
    """Capture folder to write."""
    max_frames: int = 0
    """Stop after this many frames (0: all)."""

    def run(self) -> None:
        from vinetwin.reconstruct.realsense import read_recording

        path = read_recording(self.recording, self.out, self.max_frames)
        log.info("capture: %s", path)


@dataclass(frozen=True, kw_only=True)
class Reconstruct:
    """Fuse a capture folder into a vine mesh (TSDF) and write it into a twin; optionally
    evaluate it against a ground-truth mesh (Chamfer distance, F-score at 2 and 5 mm)."""

    capture: Annotated[Path, tyro.conf.Positional]
    """Capture folder (capture.json, color/, depth/)."""
    twin: Path
    """Twin folder to create (or update with --overwrite)."""
    poses: Literal["kinematics", "colmap", "odometry"] = "kinematics"
    """Pose source: the capture's robot kinematics, pycolmap structure-from-motion on the colour
    frames (metric scale from the depth), or depth odometry (frame-to-frame ICP; needs a
    video-like capture)."""
    voxel: float = 0.0015
    """TSDF voxel size (m)."""
    depth_max: float = 0.5
    """Farthest depth fused (m)."""
    target_triangles: int = 0
    """Decimate the mesh to at most this many triangles (0: keep)."""
    overwrite: bool = False
    """Replace the mesh of an existing twin (its cut points and poses are kept)."""
    ground_truth: Path | None = None
    """A twin folder or mesh file to evaluate against."""
    json: Path | None = None
    """Write the fusion report and the evaluation here."""

    def run(self) -> None:
        import json as _json

        import numpy as np

        from vinetwin.reconstruct.capture import read_capture
        from vinetwin.reconstruct.fusion import (
            FusionConfig,
            evaluate,
            fuse,
            kinematic_poses,
            observed,
        )
        from vinetwin.twin.model import TWIN_FILE, Twin, load_mesh

        cap = read_capture(self.capture)
        sfm_report: dict[str, object] = {}
        if self.poses == "odometry":
            from vinetwin.reconstruct.odometry import odometry_poses
            from vinetwin.reconstruct.sfm import align_to

            odo = odometry_poses(cap)
            poses = align_to(odo.poses, kinematic_poses(cap)) if cap.has_poses else odo.poses
            sfm_report = {"failed_pairs": odo.failed, "seconds": odo.seconds}
            log.info(
                "odometry over %d frames in %.1f s%s", len(cap.frames), odo.seconds,
                f"; pairs that did not align: {', '.join(odo.failed)}" if odo.failed else "",
            )  # fmt: skip
        elif self.poses == "colmap":
            from vinetwin.reconstruct.sfm import align_to, colmap_poses

            sfm = colmap_poses(cap)
            poses = sfm.poses
            if cap.has_poses:  # express the mesh in the robot base, as kinematics would
                poses = align_to(poses, kinematic_poses(cap))
            sfm_report = {
                "registered": len(sfm.poses),
                "unregistered": sfm.unregistered,
                "scale_m_per_unit": sfm.scale,
                "seconds": sfm.seconds,
                "points": sfm.points,
            }
            log.info(
                "structure-from-motion registered %d of %d frames in %.1f s%s",
                len(sfm.poses), len(cap.frames), sfm.seconds,
                f"; not registered: {', '.join(sfm.unregistered)}" if sfm.unregistered else "",
            )  # fmt: skip
        else:
            poses = kinematic_poses(cap)
        cfg = FusionConfig(
            voxel=self.voxel,
            truncation=4 * self.voxel,
            depth_max=self.depth_max,
            target_triangles=self.target_triangles,
        )
        res = _with_progress("fusing frames", lambda progress: fuse(cap, poses, cfg, progress))
        source = {"reconstructed_from": str(self.capture), "poses": self.poses, "voxel": self.voxel}
        if (self.twin / TWIN_FILE).exists() and self.overwrite:
            twin = Twin.load(self.twin)
            twin.write_mesh(res.vertices, res.faces)
            twin.extra["provenance_reconstruction"] = source
            twin.save()
        else:
            Twin.create(self.twin, res.vertices, res.faces, camera=cap.camera, source=source)
        report: dict[str, object] = {
            "frames_fused": len(res.frames_used),
            "frames_skipped": res.frames_skipped,
            "seconds": res.seconds,
            "triangles": len(res.faces),
            "removed_components": res.removed_components,
            "poses": self.poses,
            **({f"{self.poses}_report": sfm_report} if sfm_report else {}),
        }
        log.info(
            "fused %d frames in %.1f s: %d triangles -> %s",
            len(res.frames_used), res.seconds, len(res.faces), self.twin,
        )  # fmt: skip
        if self.ground_truth is not None:
            gt_path = self.ground_truth
            gt = (
                Twin.load(gt_path).load_mesh()
                if (gt_path / TWIN_FILE).exists()
                else load_mesh(gt_path)
            )
            Vg, Fg = np.asarray(gt.vertices), np.asarray(gt.faces)
            gt_poses = kinematic_poses(cap) if cap.has_poses else poses
            ev = evaluate(
                res.vertices, res.faces, Vg, Fg,
                gt_mask_fn=lambda p, n: observed(p, n, cap, gt_poses, Vg, Fg),
            )  # fmt: skip
            report["evaluation"] = ev
            print(
                f"Chamfer {ev['chamfer_mm']:.2f} mm, F-score@2mm {ev['fscore@2mm']:.3f}, "
                f"F-score@5mm {ev['fscore@5mm']:.3f}"
            )
        if self.json:
            self.json.parent.mkdir(parents=True, exist_ok=True)
            self.json.write_text(_json.dumps(report, indent=1))


@dataclass(frozen=True, kw_only=True)
class Web:
    """Serve the authoring app: click canes, adjust pruning poses, preview what the D405 sees,
    save, export."""

    twin: Annotated[Path | None, tyro.conf.Positional] = None
    """Twin folder (default: a copy of the bundled sample in out/web)."""
    host: str = "127.0.0.1"
    """Address to listen on."""
    port: int = 8080
    """Port to listen on."""

    def run(self) -> None:
        import shutil
        import time

        from vinetwin.web.app import serve

        root = self.twin
        if root is None:
            root = Path("out") / "web" / "vine_bilateral.twin"
            if not root.exists():
                shutil.copytree(_bundled_sample(), root)
            log.info("no twin given: editing a copy of the bundled sample in %s", root)
        serve(root, self.host, self.port)
        print(f"vinetwin web: open http://{self.host}:{self.port} (Ctrl-C stops)", flush=True)
        while True:
            time.sleep(3600)


def _print_campaign(data: dict[str, object]) -> None:
    from rich.console import Console
    from rich.table import Table

    from vinetwin.servo.report import other_rows, table_rows

    con = Console()
    for rows, title in (
        (table_rows(data), "starts x variants"),
        (other_rows(data, "disturbance"), "disturbance"),
        (other_rows(data, "guess"), "initial guess"),
    ):
        if not rows:
            continue
        keys = [k for k in rows[0] if k != "refusals"]
        if all(r.get("paper (real robot)", "") == "-" for r in rows):
            keys = [k for k in keys if k != "paper (real robot)"]
        table = Table(*keys, title=title)
        for r in rows:
            table.add_row(*(r[k].split(":")[0] if k == "start" else r[k] for k in keys))
        con.print(table)


def _bundled_sample() -> Path:
    """The bundled sample twin: `samples/vine_bilateral.twin` of the source checkout."""
    here = Path(__file__).resolve()
    for parent in here.parents:
        cand = parent / "samples" / "vine_bilateral.twin"
        if (cand / "twin.json").exists():
            return cand
    raise VinetwinError(
        "the bundled sample twin was not found (it ships in the source checkout under samples/); "
        "make one with: vinetwin sample --out vine.twin"
    )


@dataclass(frozen=True, kw_only=True)
class Demo:
    """The main job, headless: copy the bundled sample twin to OUT, export its reference clouds
    and write a preview of the first pose."""

    out: Path = Path("out/demo")
    """Folder for the demo's outputs (the bundled sample itself is never modified)."""

    def run(self) -> None:
        import shutil

        from vinetwin.twin.model import Twin

        src = _bundled_sample()
        dst = self.out / src.name
        if dst.exists():
            shutil.rmtree(dst)
        self.out.mkdir(parents=True, exist_ok=True)
        shutil.copytree(src, dst)
        twin = Twin.load(dst)
        _summary(twin)
        Export(twin=dst).run()
        first = twin.poses[0].id
        Preview(twin=dst, pose=first, out=self.out / f"preview_{first}.png").run()
        log.info(
            "demo done: references in %s, preview in %s",
            twin.references_dir,
            self.out / f"preview_{first}.png",
        )


def _summary(twin: object, mesh: bool = True) -> None:
    from rich.console import Console
    from rich.table import Table

    from vinetwin.twin.model import Twin

    assert isinstance(twin, Twin)
    con = Console()
    con.print(f"[bold]{twin.name}[/] at {twin.root}")
    if mesh:
        m = twin.load_mesh()
        ext = m.bounds[1] - m.bounds[0]
        con.print(
            f"mesh {twin.mesh_file}: {len(m.vertices)} vertices, {len(m.faces)} triangles, "
            f"extent {ext[0]:.3f} x {ext[1]:.3f} x {ext[2]:.3f} m"
        )
    con.print(f"camera {twin.camera.name}: {twin.camera.width}x{twin.camera.height}")
    table = Table(
        "pose", "cut point", "standoff (m)", "ICP variant", "camera position (m)", "servo-ability"
    )
    for p in twin.poses:
        t = p.T_vine_camera[:3, 3]
        table.add_row(
            p.id,
            p.cut_point,
            f"{p.standoff:.3f}",
            p.icp_variant,
            f"{t[0]:+.3f} {t[1]:+.3f} {t[2]:+.3f}",
            _servo_ability(p.extra.get("validation"), p.icp_variant),
        )
    con.print(f"{len(twin.cut_points)} cut points, {len(twin.poses)} pruning poses")
    if twin.poses:
        con.print(table)


def _servo_ability(validation: object, variant: str) -> str:
    """One pose's validation summary for its own ICP variant ('not validated' without one)."""
    if not isinstance(validation, dict):
        return "not validated"
    cell = validation.get("variants", {}).get(variant)
    if not isinstance(cell, dict):
        return f"not validated with {variant}"
    return (
        f"{100 * cell.get('success_rate', 0):.0f}% of {cell.get('starts', '?')} starts; basin "
        f"{1000 * cell.get('basin_translation', 0):.0f} mm / {cell.get('basin_rotation', 0):.2f} rad"
    )


COMMANDS: dict[str, type] = {
    "sample": Sample,
    "import-vine": ImportVine,
    "info": Info,
    "export": Export,
    "preview": Preview,
    "demo": Demo,
    "campaign": Campaign,
    "validate": Validate,
    "web": Web,
    "capture-synthetic": CaptureSynthetic,
    "import-recording": ImportRecording,
    "servo": ServoCmd,
    "servo-plot": ServoPlot,
    "reconstruct": Reconstruct,
}


def main(argv: list[str] | None = None) -> int:
    """Entry point of the `vinetwin` command; returns the exit status."""
    args = sys.argv[1:] if argv is None else argv
    cmd = tyro.extras.subcommand_cli_from_dict(
        {name: cls for name, cls in COMMANDS.items()},
        args=args,
        description="vinetwin: reference clouds and digital twins for robotic vine pruning.",
    )
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    try:
        cmd.run()
    except VinetwinError as exc:
        log.error("%s", exc)
        return 2
    except KeyboardInterrupt:
        log.error("interrupted")
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
