"""`vinetwin servo`: one pruning pose of a twin, servoed with a camera source and a robot, in
simulation or on hardware, through `loop.run_loop`.

The pieces, by name (`RunnerConfig.camera` / `.robot`):
- camera `realsense[:SERIAL]`, `bag:PATH`, `folder:PATH` (`servo.sources`), `sim` (the
  simulator's D405, rendered from the twin's mesh in simulated time), or `render` (the D405
  rendered in real time at the pose a real robot reports: the robot link without a camera);
- robot `franka:HOST` (a Franka through franky-control), `sim` (a free-flying camera),
  `mujoco` (the MuJoCo Panda; `robot_model` picks another Panda model), or `none` (no robot:
  twists are computed and logged, and frames that carry a recorded robot pose give the
  kinematic guess).

The reference is the twin's exported `references/POSE.ply` (rendered now, with the twin's
settings, when it was never exported). On hardware the twin's `T_world_vine` is taken as the
vine in the robot base and `T_flange_camera` as the hand-eye transform: the first frame's guess
is where they put the reference camera relative to the camera now. In simulation that belief is
off by the registration error of `SimConfig`.
"""

from __future__ import annotations

import datetime as _dt
import logging
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from vinetwin._config import JsonFields
from vinetwin.errors import InputError
from vinetwin.frames import invert, pose_error
from vinetwin.servo.loop import Cycle, CycleLog, LoopConfig, LoopSummary, run_loop
from vinetwin.servo.robot import CommandLimits, Robot
from vinetwin.servo.sim import SimConfig
from vinetwin.servo.sources import CameraSource
from vinetwin.twin.model import Twin

log = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class RunnerConfig(JsonFields):
    pose: str = ""
    """Pruning pose id (default: the twin's first)."""
    camera: str = "sim"
    robot: str = "sim"
    robot_model: str = ""
    """With robot mujoco: a Panda model folder or MJCF file (default: vinetwin's own)."""
    servo: SimConfig = field(default_factory=SimConfig)
    """ICP variant, gains, speed limits, guess mode; in simulation also the camera rate, the
    registration error, the seed."""
    limits: CommandLimits = field(default_factory=CommandLimits)
    loop: LoopConfig = field(default_factory=LoopConfig)
    start_translation: float = 0.04
    """Simulation: the start's distance from the pruning pose (m)."""
    start_rotation: float = 0.1
    """Simulation: the start's angle from the pruning pose (rad)."""
    width: int = 848
    height: int = 480
    fps: int = 30
    color: bool = False
    rate: float | None = None
    """Playback pacing: frames per second for folder:, 0 for bag: as fast as possible."""
    realtime: bool = True
    """franka: demand a real-time kernel (libfranka's default); off for a simulated Franka."""
    dynamics_factor: float = 0.2
    """franka: fraction of the robot's velocity, acceleration and jerk limits."""


def _reference(twin: Twin, pose_id: str) -> Any:
    from vinetwin.render.reference import read_reference_cloud

    path = twin.references_dir / f"{pose_id}.ply"
    if path.exists():
        return read_reference_cloud(path)
    log.warning("%s: not exported; rendering the reference with the twin's settings", path)
    from vinetwin.render.backends import get_backend
    from vinetwin.render.reference import pose_seed, render_reference
    from vinetwin.render.sensor import SensorConfig

    mesh = twin.load_mesh()
    backend = get_backend("open3d", mesh.vertices, mesh.faces, twin.camera)
    pose = twin.pose(pose_id)
    return render_reference(
        backend, pose.T_vine_camera, twin.perception, SensorConfig(), pose_seed(0, pose_id)
    ).cloud


def default_log_path(twin: Twin, pose_id: str) -> Path:
    stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    return twin.root / "servo" / f"{pose_id}-{stamp}.jsonl"


def run_pose(
    twin: Twin,
    cfg: RunnerConfig,
    *,
    log_path: str | Path | None = None,
    record: str | Path | None = None,
) -> tuple[LoopSummary, Path]:
    """Servos to one pruning pose; returns the loop's summary and the log's path."""
    from vinetwin.servo.sim import believed_goal, make_servo, start_pose

    pose = twin.pose(cfg.pose) if cfg.pose else twin.poses[0]
    goal = np.asarray(pose.T_vine_camera, float)
    sim_camera = cfg.camera == "sim"
    robot_kind, _, host = cfg.robot.partition(":")
    if robot_kind not in ("franka", "sim", "mujoco", "none") or (robot_kind == "franka") != bool(
        host
    ):
        raise InputError(f"unknown robot '{cfg.robot}'; choose franka:HOST, sim, mujoco or none")
    if sim_camera and robot_kind not in ("sim", "mujoco"):
        raise InputError("the simulated camera needs a simulated robot: --robot sim or mujoco")
    if cfg.camera == "render" and robot_kind != "franka":
        raise InputError("the rendered camera follows a real robot's pose: use --robot franka:HOST")
    if not sim_camera and robot_kind in ("sim", "mujoco"):
        raise InputError(
            f"a simulated robot cannot move the camera '{cfg.camera}': use --robot none (replay) "
            "or franka:HOST"
        )

    reference = _reference(twin, pose.id)
    servo = make_servo(reference, twin.camera, twin.perception, cfg.servo)
    rng = np.random.default_rng(cfg.servo.seed)
    robot: Robot | None = None
    header: dict[str, Any] = {
        "twin": str(twin.root),
        "pose": pose.id,
        "variant": cfg.servo.variant,
        "camera": cfg.camera,
        "robot": cfg.robot,
        "dry_run": cfg.loop.dry_run or robot_kind == "none",
        "config": cfg.to_dict(),
        "T_flange_camera": twin.T_flange_camera.tolist(),
    }
    writer = None
    source: CameraSource | None = None
    try:
        if sim_camera:
            from vinetwin.render.backends import get_backend
            from vinetwin.servo.robot import KinematicRobot, MujocoRobot
            from vinetwin.servo.sim import SimCameraSource

            mesh = twin.load_mesh()
            backend = get_backend("open3d", mesh.vertices, mesh.faces, twin.camera)
            cut = twin.cut_point(pose.cut_point).point
            start = start_pose(
                goal, cut, cfg.start_translation, cfg.start_rotation, rng, twin.camera,
                twin.perception.max_depth,
            )  # fmt: skip
            servo.reset(invert(believed_goal(goal, cfg.servo, rng)) @ start)
            if robot_kind == "sim":
                T_base_vine = np.eye(4)
                robot = KinematicRobot(start, twin.T_flange_camera, cfg.limits)
            else:
                from vinetwin.servo.panda import PandaArm, goal_placement

                T_base_vine = goal_placement(goal)
                arm = PandaArm(
                    cfg.robot_model or None, T_flange_camera=twin.T_flange_camera,
                    camera=twin.camera, vine=(mesh.vertices, mesh.faces), T_base_vine=T_base_vine,
                )  # fmt: skip
                ok, dt_, _ = arm.reach(T_base_vine @ start)
                if not ok:
                    raise InputError(
                        f"the arm cannot reach the start pose ({1000 * dt_:.1f} mm short)"
                    )
                robot = MujocoRobot(arm, cfg.limits)
            source = SimCameraSource(
                backend, robot, T_base_vine, rng, camera_rate=cfg.servo.camera_rate,
                fixed_period=cfg.servo.fixed_period,
            )  # fmt: skip
            loop_cfg = replace(cfg.loop, max_cycle=0.0)
            header["T_base_goal"] = (T_base_vine @ goal).tolist()
        else:
            from vinetwin.servo.sources import open_source

            loop_cfg = cfg.loop
            T_base_ref = twin.T_world_vine @ goal
            header["T_base_goal"] = T_base_ref.tolist()
            if robot_kind == "franka":
                from vinetwin.servo.robot import FrankaRobot, FrankyTransport

                transport = FrankyTransport(host, cfg.dynamics_factor, cfg.realtime)
                robot = FrankaRobot(transport, twin.T_flange_camera, cfg.limits)
                servo.reset(invert(T_base_ref) @ robot.T_base_camera())
            if cfg.camera == "render":
                from vinetwin.render.backends import get_backend
                from vinetwin.servo.sim import RenderedCameraSource

                mesh = twin.load_mesh()
                backend = get_backend("open3d", mesh.vertices, mesh.faces, twin.camera)
                source = RenderedCameraSource(
                    backend, robot, twin.T_world_vine, fps=cfg.fps, seed=cfg.servo.seed
                )
            else:
                source = open_source(
                    cfg.camera, camera=twin.camera, width=cfg.width, height=cfg.height,
                    fps=cfg.fps, color=cfg.color, rate=cfg.rate,
                )  # fmt: skip
            if robot is None:  # replay: the first frame's recorded pose gives the guess
                first = getattr(source, "capture", None)
                T0 = first.frames[0].T_base_camera if first is not None else None
                if T0 is not None:
                    servo.reset(invert(T_base_ref) @ T0)
            _check_camera(twin, source)
        header["source"] = source.description
        if record is not None:
            from vinetwin.reconstruct.capture import CaptureWriter

            writer = CaptureWriter(
                record, source.camera, source.depth_unit,
                extra={"provenance": {"servo": header}, "T_flange_camera": header["T_flange_camera"]},
            )  # fmt: skip
        path = Path(log_path) if log_path else default_log_path(twin, pose.id)
        cycle_log = CycleLog(path, **header)
        truth = getattr(source, "T_rel", None) is not None

        def on_cycle(c: Cycle) -> dict[str, Any] | None:
            if writer is not None:
                writer.add(c.frame.counts, c.frame.color, c.T_base_camera, c.frame.stamp)
            if truth:
                return {"true_error": list(pose_error(source.T_rel, goal))}  # type: ignore[attr-defined]
            return None

        try:
            summary = run_loop(
                servo, source, robot if robot_kind != "none" else None, loop_cfg,
                log=cycle_log, on_cycle=on_cycle,
            )  # fmt: skip
        finally:
            cycle_log.close()
        return summary, path
    finally:
        if writer is not None:
            writer.close()
        if robot is not None:
            robot.close()
        if source is not None:
            source.close()


def _check_camera(twin: Twin, source: CameraSource) -> None:
    """The live camera must see what the reference was rendered for: same image size and focal
    lengths within 2 %, else the clouds do not compare."""
    a, b = twin.camera, source.camera
    if (a.width, a.height) != (b.width, b.height):
        raise InputError(
            f"the camera streams {b.width}x{b.height} but the twin's references are for "
            f"{a.width}x{a.height}: use --width/--height or re-export with this camera"
        )
    if abs(a.fx - b.fx) > 0.02 * a.fx or abs(a.fy - b.fy) > 0.02 * a.fy:
        log.warning(
            "the camera's focal lengths (%.1f, %.1f) differ from the twin's (%.1f, %.1f) by over "
            "2 %%: set the twin's camera from this device for accurate references",
            b.fx, b.fy, a.fx, a.fy,
        )  # fmt: skip
