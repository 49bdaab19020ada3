"""`vinetwin servo`: one pruning pose of a twin, servoed with a camera source and a robot, in
simulation or on hardware, through `loop.run_loop`.

The pieces, by name (`RunnerConfig.camera` / `.robot`):
- camera `realsense[:SERIAL]`, `bag:PATH`, `folder:PATH` (`capture.sources`), `render` (the
  D405 rendered in real time at the pose a real robot reports: the robot link without a
  camera, `servo.rendered_camera`), or `sim` (the simulator's D405 in simulated time, built by
  `sim.rig.simulated_session`, which the caller passes as `simulator`);
- robot `franka:HOST` (a Franka through franky-control), `none` (no robot: twists are computed
  and logged, and frames that carry a recorded robot pose give the kinematic guess), or, with
  the simulated camera, `sim` (a free-flying camera) and `mujoco` (the MuJoCo Panda).

The reference is the twin's exported `references/POSE.ply` (rendered now, with the twin's
settings, when it was never exported). On hardware the twin's `T_world_vine` is taken as the
vine in the robot base and `T_flange_camera` as the hand-eye transform: the first frame's guess
is where they put the reference camera relative to the camera now. In simulation that belief is
off by the registration error of `SimConfig`.
"""

from __future__ import annotations

import datetime as _dt
import logging
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from vinetwin.capture.sources import CameraSource
from vinetwin.cloud import Cloud
from vinetwin.errors import InputError
from vinetwin.files import refuse_existing
from vinetwin.frames import Array, invert, pose_error, transform_points
from vinetwin.servo.config import LoopConfig, RunnerConfig, ServoConfig
from vinetwin.servo.loop import Cycle, CycleLog, LoopSummary, run_loop
from vinetwin.servo.robot import Robot
from vinetwin.servo.step import Servo, make_servo
from vinetwin.twin.model import PruningPose, Twin

log = logging.getLogger(__name__)

__all__ = ["RunnerConfig", "Session", "hardware_session", "reference_cloud", "run_pose"]


@dataclass
class Session:
    """What one servo run needs: the servo, a camera source, a robot (None: none), the loop's
    settings, and where the goal is in the robot base (for the log)."""

    servo: Servo
    source: CameraSource
    robot: Robot | None
    loop: LoopConfig
    T_base_goal: Array
    true_error: Callable[[], list[float]] | None = None
    """The true camera error now (simulation only), logged with each cycle."""
    check_latency: bool = True
    """False in simulated time: no overrun check."""

    def close(self) -> None:
        if self.robot is not None:
            self.robot.close()
        self.source.close()


def reference_cloud(twin: Twin, pose_id: str) -> Cloud:
    """The pose's exported reference cloud, or one rendered now with the twin's settings."""
    from vinetwin.render.export import check_reference_files
    from vinetwin.render.reference import read_reference_cloud

    path = twin.references_dir / f"{pose_id}.ply"
    if path.exists():
        problem = check_reference_files(twin.references_dir, pose_id)
        if problem:
            raise InputError(f"refusing reference {path}: {problem}; run `vinetwin export` again")
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


def dense_reference_for(twin: Twin, pose_id: str, config: ServoConfig) -> Cloud | None:
    """The dense reference of point-to-point and LM (`ServoConfig.dense_reference`): the pose's
    view rendered from the twin's mesh with its D405 model, through the perception chain at a
    quarter of its voxel. None for the other variants, or when switched off."""
    from vinetwin.servo.step import wants_dense

    if not wants_dense(config):
        return None
    from vinetwin.render.backends import get_backend
    from vinetwin.render.reference import dense_cloud, pose_seed, render_reference
    from vinetwin.render.sensor import SensorConfig
    from vinetwin.servo.config import DENSE_FACTOR

    mesh = twin.load_mesh()
    backend = get_backend("open3d", mesh.vertices, mesh.faces, twin.camera)
    pose = twin.pose(pose_id)
    rendered = render_reference(
        backend, pose.T_vine_camera, twin.perception, SensorConfig(), pose_seed(0, pose_id)
    )
    return dense_cloud(rendered.depth, twin.camera, twin.perception, DENSE_FACTOR)


def default_log_path(twin: Twin, pose_id: str) -> Path:
    """TWIN/servo/POSE-DATE.jsonl, with a counter when a run in the same second has it."""
    stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    path = twin.root / "servo" / f"{pose_id}-{stamp}.jsonl"
    k = 1
    while path.exists():
        k += 1
        path = twin.root / "servo" / f"{pose_id}-{stamp}-{k}.jsonl"
    return path


def _check_combination(cfg: RunnerConfig) -> str:
    """The robot kind, once camera and robot are known to fit together."""
    robot_kind, _, host = cfg.robot.partition(":")
    if robot_kind not in ("franka", "sim", "mujoco", "none") or (robot_kind == "franka") != bool(
        host
    ):
        raise InputError(f"unknown robot '{cfg.robot}'; choose franka:HOST, sim, mujoco or none")
    sim_camera = cfg.camera == "sim"
    if sim_camera and robot_kind not in ("sim", "mujoco"):
        raise InputError("the simulated camera needs a simulated robot: --robot sim or mujoco")
    if cfg.camera == "render" and robot_kind != "franka":
        raise InputError("the rendered camera follows a real robot's pose: use --robot franka:HOST")
    if not sim_camera and robot_kind in ("sim", "mujoco"):
        raise InputError(
            f"a simulated robot cannot move the camera '{cfg.camera}': use --robot none (replay) "
            "or franka:HOST"
        )
    return robot_kind


def cut_in_camera(twin: Twin, pose: PruningPose) -> Array:
    """The pose's cut point in its (reference) camera frame: the target of the view-keeping law."""
    cut = twin.cut_point(pose.cut_point).point
    return transform_points(invert(np.asarray(pose.T_vine_camera, float)), cut[None])[0]


def arrive(source: CameraSource, twin: Twin, belief: Array | None, mesh: Any = None) -> Array:
    """Arrival registration (`servo.arrival`) on the source's next frame: the camera's pose in
    the vine frame, from `belief` (T_vine_camera as the robot believes it; None: the frame's
    recorded pose in the twin's world). `mesh`: the twin's mesh (default: loaded). Raises
    ArrivalError, naming why, when the registration refuses: the caller has not moved."""
    from vinetwin.errors import ArrivalError
    from vinetwin.servo.arrival import ArrivalRegistration

    frame = source.read(timeout=5.0)
    if frame is None:
        raise ArrivalError("arrival registration: no frame from the camera in 5 s; nothing moved")
    if belief is None:
        if frame.T_base_camera is None:
            raise ArrivalError(
                "arrival registration needs where the robot believes the camera is: a robot "
                "(franka, sim, mujoco) or a capture folder with recorded poses; nothing moved"
            )
        belief = invert(twin.T_world_vine) @ np.asarray(frame.T_base_camera, float)
    m = mesh if mesh is not None else twin.load_mesh()
    registration = ArrivalRegistration(m.vertices, m.faces, twin.camera, twin.perception)
    try:
        depth = frame.counts.astype(np.float32) * np.float32(frame.depth_unit)
        result = registration.register(depth, belief)
    finally:
        registration.close()
    if not result.ok or result.T_vine_camera is None:
        raise ArrivalError(f"arrival registration refused, nothing moved: {result.reason}")
    return result.T_vine_camera


def hardware_session(twin: Twin, pose: PruningPose, cfg: RunnerConfig) -> Session:
    """A live, recorded or rendered camera with a Franka or no robot."""
    robot_kind, _, host = cfg.robot.partition(":")
    servo = make_servo(
        reference_cloud(twin, pose.id), twin.camera, twin.perception, cfg.servo,
        cfg.limits.speeds(), target=cut_in_camera(twin, pose),
        dense_reference=dense_reference_for(twin, pose.id, cfg.servo),
    )  # fmt: skip
    T_base_ref = twin.T_world_vine @ np.asarray(pose.T_vine_camera, float)
    robot: Robot | None = None
    source: CameraSource | None = None
    try:
        if robot_kind == "franka":
            from vinetwin.servo.robot import FrankaRobot, FrankyTransport

            transport = FrankyTransport(host, cfg.dynamics_factor, cfg.realtime)
            robot = FrankaRobot(transport, twin.T_flange_camera, cfg.limits)
            servo.reset(invert(T_base_ref) @ robot.T_base_camera())
        if cfg.camera == "render":
            from vinetwin.render.backends import get_backend
            from vinetwin.servo.rendered_camera import RenderedCameraSource

            mesh = twin.load_mesh()
            backend = get_backend("open3d", mesh.vertices, mesh.faces, twin.camera)
            source = RenderedCameraSource(
                backend, robot, twin.T_world_vine, fps=cfg.fps, seed=cfg.seed
            )
        else:
            from vinetwin.capture.sources import open_source

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
        if cfg.arrival:
            belief = None
            if robot is not None:
                belief = invert(twin.T_world_vine) @ robot.T_base_camera()
            T_vine_camera = arrive(source, twin, belief)
            servo.reset(invert(np.asarray(pose.T_vine_camera, float)) @ T_vine_camera)
    except BaseException:
        if robot is not None:
            robot.close()
        if source is not None:
            source.close()
        raise
    return Session(servo, source, robot, cfg.loop, T_base_ref)


def run_pose(
    twin: Twin,
    cfg: RunnerConfig,
    *,
    log_path: str | Path | None = None,
    record: str | Path | None = None,
    simulator: Callable[[Twin, PruningPose, RunnerConfig], Session] | None = None,
    mcap: str | Path | None = None,
    overwrite: bool = False,
) -> tuple[LoopSummary, Path]:
    """Servos to one pruning pose; returns the loop's summary and the log's path. The simulated
    camera (`cfg.camera == "sim"`) needs `simulator`: `vinetwin.sim.rig.simulated_session`.
    `mcap`: also write the run as a ROS 2 bag with MCAP storage (`servo.mcap_log`). An
    existing `log_path` file or non-empty `record` folder is refused unless `overwrite`."""
    pose = twin.pose(cfg.pose) if cfg.pose else twin.poses[0]
    robot_kind = _check_combination(cfg)
    path = Path(log_path) if log_path else default_log_path(twin, pose.id)
    refuse_existing(path, "--log", overwrite)  # before any robot or camera is opened
    _check_writable(path, "--log", folder=False)
    if record is not None:
        refuse_existing(record, "--record", overwrite)
        _check_writable(Path(record), "--record", folder=True)
    if mcap is not None and Path(mcap).exists():
        raise InputError(f"--mcap {mcap} exists; choose a new name (a folder is made)")
    if cfg.camera == "sim":
        if simulator is None:
            raise InputError(
                "the simulated camera needs the simulator: pass "
                "simulator=vinetwin.sim.rig.simulated_session"
            )
        session = simulator(twin, pose, cfg)
    else:
        session = hardware_session(twin, pose, cfg)
    header: dict[str, Any] = {
        "twin": str(twin.root),
        "pose": pose.id,
        "variant": cfg.servo.variant,
        "camera": cfg.camera,
        "robot": cfg.robot,
        "dry_run": cfg.loop.dry_run or robot_kind == "none",
        "config": cfg.to_dict(),
        "T_flange_camera": twin.T_flange_camera.tolist(),
        "T_base_goal": np.asarray(session.T_base_goal).tolist(),
        "source": session.source.description,
    }
    writer = None
    viewer = None
    try:
        if mcap is not None:
            from vinetwin.servo.mcap_log import McapLog

            T_base_vine = session.T_base_goal @ invert(np.asarray(pose.T_vine_camera, float))
            T_cut = np.eye(4)
            T_cut[:3, 3] = twin.cut_point(pose.cut_point).point
            viewer = McapLog(
                mcap, session.servo.reference, session.T_base_goal, T_base_vine @ T_cut
            )
        if record is not None:
            from vinetwin.capture.folder import CaptureWriter

            writer = CaptureWriter(
                record, session.source.camera, session.source.depth_unit,
                extra={"provenance": {"servo": header}, "T_flange_camera": header["T_flange_camera"]},
            )  # fmt: skip
        cycle_log = CycleLog(path, **header)
        truth = session.true_error

        def on_cycle(c: Cycle) -> dict[str, Any] | None:
            if writer is not None:
                writer.add(c.frame.counts, c.frame.color, c.T_base_camera, c.frame.stamp)
            if viewer is not None:
                viewer.cycle(c)
            return {"true_error": truth()} if truth is not None else None

        try:
            summary = run_loop(
                session.servo, session.source, session.robot if robot_kind != "none" else None,
                session.loop, log=cycle_log, on_cycle=on_cycle,
                check_latency=session.check_latency,
            )  # fmt: skip
        finally:
            cycle_log.close()
        return summary, path
    finally:
        if writer is not None:
            writer.close()
        if viewer is not None:
            viewer.close()
        session.close()


def true_error_of(source: Any, goal: Array) -> Callable[[], list[float]]:
    """The true error of a simulated camera (its `T_rel`, the camera relative to the possibly
    moved vine) against `goal`."""
    return lambda: list(pose_error(source.T_rel, goal))


def _check_writable(path: Path, flag: str, folder: bool) -> None:
    """Raises InputError naming `flag` unless `path` (a file, or a folder with `folder`) can be
    written: its folder made and writable, and not a file where a folder goes or vice versa."""
    target = path if folder else path.parent
    try:
        target.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"{flag} {path}: cannot create {target}: {exc.strerror or exc}") from exc
    if not os.access(target, os.W_OK):
        raise InputError(f"{flag} {path}: {target} is not writable")
    if not folder and path.is_dir():
        raise InputError(f"{flag} {path} is a folder; name a file")


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
