"""`vinetwin servo`: one pruning pose of a twin, servoed with a camera source and a robot, in
simulation or on hardware, through `loop.run_loop`.

The pieces, by name (`RunnerConfig.camera` / `.robot`):
- camera `realsense[:SERIAL]`, `bag:PATH`, `folder:PATH` (`capture.sources`), `render` (the
  D405 rendered in real time at the pose a real robot reports: the robot link without a
  camera, `servo.rendered_camera`), or `sim` (the simulator's D405 in simulated time, built by
  `sim.session.servo_session`, which the caller passes as `simulator`);
- robot `franka:HOST` (a Franka through franky-control), `none` (no robot: twists are computed
  and logged, and frames that carry a recorded robot pose give the kinematic guess), or, with
  the simulated camera, `sim` (a free-flying camera) and `mujoco` (the MuJoCo Panda).

The session is built by `servo.session.hardware_session` or the simulator; this module only
checks the command, opens its outputs and runs the loop. The reference is the twin's exported
`references/POSE.ply` (rendered now, with the twin's settings, when it was never exported:
`render.reference.reference_for`). On hardware the twin's `T_world_vine` is taken as the
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

from vinetwin.errors import InputError
from vinetwin.files import refuse_existing
from vinetwin.frames import invert
from vinetwin.servo.config import ArrivalConfig, RunnerConfig
from vinetwin.servo.loop import Cycle, CycleLog, LoopSummary, run_loop
from vinetwin.servo.session import Session, hardware_session
from vinetwin.twin.model import PruningPose, Twin

log = logging.getLogger(__name__)

__all__ = ["RunOutputs", "RunnerConfig", "run_pose"]


@dataclass(frozen=True)
class RunOutputs:
    """Where a servo run writes: its cycle log (None: `default_log_path`), a capture folder of
    its frames (`record`), a ROS 2 bag with MCAP storage (`mcap`, `servo.mcap_log`); an existing
    log file or non-empty record folder is refused unless `overwrite`."""

    log: str | Path | None = None
    record: str | Path | None = None
    mcap: str | Path | None = None
    overwrite: bool = False


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


def run_pose(
    twin: Twin,
    cfg: RunnerConfig,
    outputs: RunOutputs | None = None,
    simulator: Callable[[Twin, PruningPose, RunnerConfig, ArrivalConfig | None], Session]
    | None = None,
    arrival: ArrivalConfig | None = None,
) -> tuple[LoopSummary, Path]:
    """Servos to one pruning pose; returns the loop's summary and the log's path. The simulated
    camera (`cfg.camera == "sim"`) needs `simulator`: `vinetwin.sim.session.servo_session`.
    `arrival`: the arrival registration's settings (with `cfg.arrival`)."""
    out = outputs or RunOutputs()
    log_path, record, mcap, overwrite = out.log, out.record, out.mcap, out.overwrite
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
                "simulator=vinetwin.sim.session.servo_session"
            )
        session = simulator(twin, pose, cfg, arrival)
    else:
        session = hardware_session(twin, pose, cfg, arrival)
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
