"""Closed-loop simulation with a kinematic camera: render -> D405 model -> perception -> ICP ->
PBVS -> integrate the twist -> render again.

The camera is a free-flying rigid body whose pose integrates the commanded twist (a perfect
velocity-controlled arm). Each frame is rendered from the twin's mesh at the camera's pose
relative to the vine, through the D405 sensor model with fresh noise, and goes through
`Servo.step_depth`, the same perception chain and safety rules as live frames.

Timing. The outer loop is free-running, as in the paper: a frame is taken, processed, and its
twist held (zero-order hold) until the next frame is taken, at the next camera tick after the
processing ended. With processing faster than the camera that is one frame period; slower
processing holds each twist longer, and the trajectory degrades as the paper describes.
`SimConfig.fixed_period` replaces the measured time by a fixed one (reproducible runs).

Frames. The world is the vine's original frame and also the robot base: `T_base_camera` (the
robot's kinematics, exact here) is the camera pose in it. A disturbance moves the vine rigidly,
so the goal moves with it and the kinematic guess is wrong by the disturbance until the servo
re-acquires (see `SafetyConfig.reacquire_frames`).

Metrics (`SimRun.summary`):
- final static error: the median true translation / rotation error over the last 0.5 s;
- converged: the final static error is within `converged_translation` / `converged_rotation`
  (2 mm / 0.01 rad); under a field profile within its `settled_translation` /
  `settled_rotation` (5 mm / 0.05 rad, the real robot's range in the paper), since a wrong twin
  or calibration moves the camera's resting point by design;
- convergence time: the first time after which the true error stays within those tolerances to
  the end of the run (None when it never does);
- final cut error: the median, over the last 0.5 s, of how far the cut point is in the camera
  (tool) frame from where it is at the goal;
- loop rate: frames processed per simulated second, and the median compute time per frame.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from vinetwin.capture.folder import CaptureWriter
from vinetwin.frames import Array, invert, pose_error, transform_points
from vinetwin.servo.config import LoopConfig
from vinetwin.servo.loop import Cycle, CycleLog, run_loop
from vinetwin.sim.config import Disturbance, SimConfig
from vinetwin.sim.session import SimSpec, SimWorld


@dataclass
class SimRun:
    """Time series and outcome of one run (poses are camera poses in the world frame)."""

    config: SimConfig
    pose_id: str
    goal: Array
    start: Array
    disturbance: Disturbance = field(default_factory=Disturbance)
    t: list[float] = field(default_factory=list)
    T: list[Array] = field(default_factory=list)
    error_t: list[float] = field(default_factory=list)
    error_r: list[float] = field(default_factory=list)
    trusted: list[bool] = field(default_factory=list)
    compute: list[float] = field(default_factory=list)
    reasons: dict[str, int] = field(default_factory=dict)
    wall: float = 0.0
    cut_uv: list[list[float]] = field(default_factory=list)
    """The cut point's pixel (u, v) in each frame (NaN behind the camera)."""
    cut_outside: int = 0
    """Frames whose image did not hold the cut point."""
    cut_error: list[float] = field(default_factory=list)
    """Per frame: how far the cut point is, in the camera (the tool) frame, from where it is at
    the goal (m): what the pruning tool would miss it by."""
    believed_cut: list[tuple[float, Array]] = field(default_factory=list)
    """Per trusted frame: its stamp and where the robot believes the cut point is in its own
    base frame (the frame's reported pose and the servo's alignment; what a cut is aimed by)."""
    reacquisitions: int = 0
    """Frames trusted by the wide search after a streak of refusals."""
    lost: str = ""
    """The named stop that ended the run, with its reason: the servo's "lost the vine" or the
    loop's "the arm does not follow" (`LoopConfig.follow_window`); "" when none did."""
    longest_refusal_s: float = 0.0
    """The longest streak of refused frames (s, first to last refused stamp)."""
    faults: dict[str, Any] | None = None
    """With fault injection: what was injected and how the servo coped (`faults.fault_summary`)."""
    session: Any = field(default=None, repr=False)
    """The run's live `SimSession` when `simulate(keep=True)` (the caller goes on driving its
    arm and closes it)."""

    def summary(self) -> dict[str, Any]:
        cfg = self.config
        t = np.asarray(self.t)
        et = np.asarray(self.error_t)
        er = np.asarray(self.error_r)
        last = t >= (t[-1] - 0.5) if len(t) else np.zeros(0, bool)
        final_t = float(np.median(et[last])) if last.any() else math.nan
        final_r = float(np.median(er[last])) if last.any() else math.nan
        ec = np.asarray(self.cut_error)
        final_cut = float(np.median(ec[last])) if last.any() and len(ec) == len(t) else math.nan
        tol_t, tol_r = cfg.tolerances()
        inside = (et <= tol_t) & (er <= tol_r)
        conv_time = None
        if inside.size and inside[-1]:
            outside = np.nonzero(~inside)[0]
            k = int(outside[-1]) + 1 if outside.size else 0
            conv_time = float(t[k]) if k < len(t) else None
        sim_time = float(t[-1]) if len(t) else 0.0
        start_t, start_r = pose_error(self.start, self.goal)
        return {
            "pose": self.pose_id,
            "variant": cfg.variant,
            "guess": cfg.guess,
            "start_translation": start_t,
            "start_rotation": start_r,
            "final_translation": final_t,
            "final_rotation": final_r,
            "final_cut_error": final_cut,
            "converged": bool(final_t <= tol_t and final_r <= tol_r),
            "convergence_time": conv_time,
            "frames": len(t),
            "refused": int(len(self.trusted) - sum(self.trusted)),
            "refusal_reasons": dict(self.reasons),
            "reacquisitions": self.reacquisitions,
            "cut_outside_frames": self.cut_outside,
            "lost": self.lost,
            "longest_refusal_s": self.longest_refusal_s,
            "simulated_s": sim_time,
            "loop_rate_hz": (len(t) - 1) / sim_time if sim_time > 0 else math.nan,
            "compute_ms": 1000 * float(np.median(self.compute)) if self.compute else math.nan,
            "wall_s": self.wall,
            "realtime_factor": sim_time / self.wall if self.wall > 0 else math.nan,
            **({"faults": self.faults} if self.faults is not None else {}),
        }

    def series(self, step: int = 1) -> dict[str, Any]:
        """The time series as plain lists (every `step`-th frame)."""
        sl = slice(None, None, step)
        return {
            "t": self.t[sl],
            "error_t": self.error_t[sl],
            "error_r": self.error_r[sl],
            "trusted": self.trusted[sl],
            "position": [T[:3, 3].tolist() for T in self.T[sl]],
            "cut_uv": self.cut_uv[sl],
        }


def simulate(
    spec: SimSpec,
    world: SimWorld,
    *,
    log: CycleLog | None = None,
    record: str | Path | None = None,
    keep: bool = False,
) -> SimRun:
    """One closed-loop run (`spec`, built on `world` by `SimSpec.setup`) through
    `loop.run_loop`, the loop that drives hardware.

    With the world's arm the camera is the D405 on the Panda's hand: the arm first reaches the
    start pose (a start it cannot reach raises InputError), then each twist drives its joints.
    Without it the camera flies freely. `log` receives every cycle (with the true error);
    `record` writes the frames, with their stamps and robot poses, as a capture folder that
    `FolderSource` replays. `keep` leaves the session in `SimRun.session` (the whole job goes on
    to cut with the same arm and field draw)."""
    cfg = spec.config
    camera = world.backend.camera
    goal = np.asarray(spec.goal, float)
    dist = spec.disturbance
    run = SimRun(cfg, spec.pose_id, goal, np.asarray(spec.start, float), dist)
    cut = spec.cut_point()
    rig = spec.setup(world)
    servo, robot = rig.servo, rig.robot
    if rig.reference.depth is not None:  # compile before the first frame, whose time is measured
        servo.warm_up(rig.reference.depth)
    source: Any = rig.source
    faulty = None
    if cfg.faults.classes:
        from vinetwin.sim.faults import FaultySource

        source = faulty = FaultySource(rig.source, cfg.faults, cut)
        robot.expire_after = robot.limits.watchdog  # commands expire, as a Franka's do
    cycles: list[dict[str, Any]] = []
    writer = None
    if record is not None:
        writer = CaptureWriter(
            record, camera, camera.depth_unit, extra={"provenance": {"simulation": cfg.to_dict()}}
        )
    at_goal_since: list[float | None] = [None]
    cut_at_goal = rig.reference.cut  # the cut in the goal camera's frame

    def on_cycle(c: Cycle) -> dict[str, Any]:
        r, t = c.result, source.now()  # the frame's stamp, unless a fault made it late
        et, er = pose_error(source.T_rel, goal)
        run.t.append(t)
        run.T.append(source.T.copy())
        run.error_t.append(et)
        run.error_r.append(er)
        p = transform_points(invert(source.T_rel), cut[None])[0]  # the cut in the camera
        run.cut_error.append(float(np.linalg.norm(p - cut_at_goal)))
        run.cut_uv.append(
            [float(camera.fx * p[0] / p[2] + camera.cx), float(camera.fy * p[1] / p[2] + camera.cy)]
            if p[2] > 1e-6
            else [math.nan, math.nan]
        )
        u, v = run.cut_uv[-1]
        run.cut_outside += int(not (0 <= u < camera.width and 0 <= v < camera.height))
        run.trusted.append(r.trusted)
        if (
            r.trusted
            and r.T_ref_cur is not None
            and c.T_base_camera is not None
            and cut_at_goal is not None
        ):
            seen = transform_points(invert(r.T_ref_cur), cut_at_goal[None])[0]
            run.believed_cut.append((t, transform_points(c.T_base_camera, seen[None])[0]))
        run.compute.append(sum(r.timings.values()))
        if not r.trusted:
            key = r.reason.split(":")[0]
            run.reasons[key] = run.reasons.get(key, 0) + 1
        if faulty is not None:
            cycles.append(
                {"t": t, "trusted": r.trusted, "overrun": c.overrun, "sent": c.sent.tolist()}
            )
        if writer is not None:
            writer.add(c.frame.counts, None, c.T_base_camera, t)
        end = t + 1e-9 >= cfg.duration
        if cfg.settle > 0:  # settled at the goal (and past the disturbance)
            if r.trusted and r.at_goal:
                since = at_goal_since[0] = t if at_goal_since[0] is None else at_goal_since[0]
                if t - since >= cfg.settle and (dist.time < 0 or t > dist.time + cfg.settle):
                    end = True
            elif r.trusted or at_goal_since[0] is None:
                at_goal_since[0] = None
        return {"true_error": [et, er], "end_run": end}

    wall0 = time.perf_counter()
    try:
        summary = run_loop(
            servo, source, robot, LoopConfig(settle=0.0), log=log, check_latency=False,
            on_cycle=on_cycle,
        )  # fmt: skip
    finally:
        if writer is not None:
            writer.close()
    run.wall = time.perf_counter() - wall0
    run.reacquisitions = summary.reacquisitions
    run.lost = summary.lost or summary.stalled
    run.longest_refusal_s = longest_refusal(run.t, run.trusted)
    if keep:
        run.session = rig
    if faulty is not None:
        from vinetwin.sim.faults import fault_summary

        run.faults = fault_summary(faulty.log, cycles, robot.limits, run.t[-1] if run.t else 0.0)
    return run


def longest_refusal(t: list[float], trusted: list[bool]) -> float:
    """The longest streak of refused frames (s, from its first refused stamp to the first
    trusted one after it, or to the run's last frame)."""
    best, since = 0.0, None
    for ti, ok in zip(t, trusted, strict=True):
        if ok:
            if since is not None:
                best = max(best, ti - since)
            since = None
        elif since is None:
            since = ti
    if since is not None and t:
        best = max(best, t[-1] - since)
    return float(best)
