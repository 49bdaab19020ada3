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
  (2 mm / 0.01 rad);
- convergence time: the first time after which the true error stays within those tolerances to
  the end of the run (None when it never does);
- loop rate: frames processed per simulated second, and the median compute time per frame.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from vinetwin._config import JsonFields
from vinetwin.camera import CameraModel
from vinetwin.cloud import Cloud, PerceptionConfig
from vinetwin.errors import InputError
from vinetwin.frames import (
    Array,
    invert,
    make_pose,
    pose_error,
    so3_exp,
    transform_points,
)
from vinetwin.reconstruct.capture import CaptureWriter
from vinetwin.render.backends import DepthBackend
from vinetwin.render.reference import render_reference
from vinetwin.render.sensor import SensorConfig, apply_d405_model
from vinetwin.servo.icp import ICPConfig
from vinetwin.servo.loop import Cycle, CycleLog, LoopConfig, run_loop
from vinetwin.servo.pbvs import Gain, Limits
from vinetwin.servo.robot import CommandLimits, KinematicRobot, MujocoRobot, SimulatedRobot
from vinetwin.servo.sources import CameraFrame, CameraSource, quantize_depth
from vinetwin.servo.step import GUESSES, SafetyConfig, Servo


@dataclass(frozen=True, kw_only=True)
class Disturbance(JsonFields):
    """The vine moves rigidly by (translation, rotation vector) at `time`, in the vine frame
    (paper Fig. 6), and optionally vibrates sinusoidally along `vibration_axis`."""

    time: float = -1.0
    """When the vine moves (s); negative: never."""
    translation: tuple[float, float, float] = (0.03, 0.0, 0.0)
    """m."""
    rotation: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Rotation vector, rad."""
    vibration_amplitude: float = 0.0
    """m; 0: no vibration."""
    vibration_frequency: float = 2.0
    """Hz."""
    vibration_axis: tuple[float, float, float] = (1.0, 0.0, 0.0)

    def vine_motion(self, t: float) -> Array:
        """The vine's pose at time t in its original frame."""
        M = np.eye(4)
        if self.time >= 0 and t >= self.time:
            M = make_pose(so3_exp(self.rotation), self.translation)
        if self.vibration_amplitude > 0:
            axis = np.asarray(self.vibration_axis, dtype=np.float64)
            axis = axis / (np.linalg.norm(axis) or 1.0)
            s = self.vibration_amplitude * math.sin(2 * math.pi * self.vibration_frequency * t)
            M = make_pose(t=s * axis) @ M
        return M


@dataclass(frozen=True, kw_only=True)
class SimConfig(JsonFields):
    """One closed-loop run."""

    variant: str = "point_to_plane"
    """ICP variant."""
    camera_rate: float = 30.0
    """Frames per second of the camera (the D405 gives 30-90)."""
    fixed_period: float = 0.0
    """Hold each twist this long (s) instead of the measured processing time; 0: measured."""
    duration: float = 20.0
    """Longest simulated time (s)."""
    settle: float = 2.0
    """End the run once the servo has reported being at its goal for this long (s); 0: run the
    whole duration."""
    gain: float = 1.0
    """lambda at the goal (adaptive gain, ViSP's law)."""
    gain_far: float = 0.4
    """lambda far from the goal."""
    max_linear: float = 0.10
    """m/s."""
    max_angular: float = 0.5
    """rad/s."""
    guess: str = "kinematic"
    """Where ICP starts each frame: kinematic (eq. 11), previous or identity."""
    registration_error_translation: float = 0.005
    """Error (m) of where the robot believes the reference camera is (the twin's registration
    to the robot), which sets the first frame's guess."""
    registration_error_rotation: float = 0.02
    """rad."""
    converged_translation: float = 0.002
    """m."""
    converged_rotation: float = 0.01
    """rad."""
    seed: int = 0
    """Noise and registration-error seed."""

    def __post_init__(self) -> None:
        ICPConfig(variant=self.variant)  # validates the name
        if self.guess not in GUESSES:
            raise InputError(f"unknown guess '{self.guess}'; choose one of: {', '.join(GUESSES)}")
        if self.camera_rate <= 0 or self.duration <= 0:
            raise InputError("camera_rate and duration must be positive")


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

    def summary(self) -> dict[str, Any]:
        cfg = self.config
        t = np.asarray(self.t)
        et = np.asarray(self.error_t)
        er = np.asarray(self.error_r)
        last = t >= (t[-1] - 0.5) if len(t) else np.zeros(0, bool)
        final_t = float(np.median(et[last])) if last.any() else math.nan
        final_r = float(np.median(er[last])) if last.any() else math.nan
        inside = (et <= cfg.converged_translation) & (er <= cfg.converged_rotation)
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
            "converged": bool(
                final_t <= cfg.converged_translation and final_r <= cfg.converged_rotation
            ),
            "convergence_time": conv_time,
            "frames": len(t),
            "refused": int(len(self.trusted) - sum(self.trusted)),
            "refusal_reasons": dict(self.reasons),
            "simulated_s": sim_time,
            "loop_rate_hz": (len(t) - 1) / sim_time if sim_time > 0 else math.nan,
            "compute_ms": 1000 * float(np.median(self.compute)) if self.compute else math.nan,
            "wall_s": self.wall,
            "realtime_factor": sim_time / self.wall if self.wall > 0 else math.nan,
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
        }


def start_pose(
    goal: Array,
    target: Array,
    translation: float,
    rotation: float,
    rng: np.random.Generator,
    camera: CameraModel,
    max_depth: float,
    tries: int = 500,
) -> Array:
    """A camera pose `translation` (m) and `rotation` (rad) away from `goal` that still sees
    `target` (a point in the world, the cut) inside the image and within range: a start a robot
    would be given. Directions are random; the first of `tries` that sees the target wins (else
    the one that sees it best)."""
    best, best_score = None, -math.inf
    for _ in range(tries):
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        a = rng.normal(size=3)
        a /= np.linalg.norm(a)
        T = make_pose(goal[:3, :3] @ so3_exp(rotation * a), goal[:3, 3] + translation * d)
        p = transform_points(invert(T), target[None])[0]
        if p[2] <= 0:
            continue
        u = camera.fx * p[0] / p[2] + camera.cx
        v = camera.fy * p[1] / p[2] + camera.cy
        margin = min(u, camera.width - u, v, camera.height - v) / max(camera.width, camera.height)
        depth_ok = 0.07 <= p[2] <= max_depth - 0.03
        score = margin if depth_ok else margin - 1.0
        if score > 0.1:
            return T
        if score > best_score:
            best, best_score = T, score
    assert best is not None
    return best


class _MeshCamera(CameraSource):
    """A D405 rendered from the twin's mesh (placed at `T_base_vine` in the robot base) at a
    robot's camera pose, through the D405 model, streamed as 16-bit counts like the real one."""

    def __init__(
        self,
        backend: DepthBackend,
        robot: Any,
        T_base_vine: Array,
        rng: np.random.Generator,
        sensor: SensorConfig | None,
        rate: float,
    ) -> None:
        self.backend = backend
        self.camera = backend.camera
        self.depth_unit = backend.camera.depth_unit
        self.robot = robot
        self.T_base_vine = np.asarray(T_base_vine, float)
        self.rng = rng
        self.sensor = sensor or SensorConfig()
        self.period = 1.0 / rate
        self.number = 0

    def _frame(self, T_vine_camera: Array, stamp: float) -> CameraFrame:
        depth = apply_d405_model(
            self.backend.render(T_vine_camera), self.camera, self.rng, self.sensor
        )
        frame = CameraFrame(
            quantize_depth(depth, self.depth_unit), self.depth_unit, stamp, self.number
        )
        self.number += 1
        return frame


class SimCameraSource(_MeshCamera):
    """The simulator's camera, in simulated time: a frame is taken at once; the next one after
    the loop's processing time (measured from this frame's delivery to the next `read`, or
    `fixed_period`), rounded up to whole camera periods, during which the robot applies the
    twist it was last sent. A disturbance moves the vine."""

    def __init__(
        self,
        backend: DepthBackend,
        robot: SimulatedRobot,
        T_base_vine: Array,
        rng: np.random.Generator,
        *,
        sensor: SensorConfig | None = None,
        camera_rate: float = 30.0,
        fixed_period: float = 0.0,
        disturbance: Disturbance | None = None,
    ) -> None:
        super().__init__(backend, robot, T_base_vine, rng, sensor, camera_rate)
        self.sim_robot = robot
        self.fixed_period = fixed_period
        self.disturbance = disturbance or Disturbance()
        self.description = f"simulated D405 at {camera_rate:g} fps ({robot.name})"
        self._delivered: float | None = None
        self.T = np.eye(4)
        """The camera in the vine's original frame at the last frame."""
        self.T_rel = np.eye(4)
        """The camera relative to the (possibly moved) vine at the last frame."""

    def read(self, timeout: float = 1.0) -> CameraFrame | None:
        if self._delivered is not None:
            compute = time.perf_counter() - self._delivered
            hold = (
                self.fixed_period
                if self.fixed_period > 0
                else self.period * max(1, math.ceil(compute / self.period))
            )
            self.sim_robot.advance(hold)
        t = self.sim_robot.t
        self.T = invert(self.T_base_vine) @ self.robot.T_base_camera()
        self.T_rel = invert(self.disturbance.vine_motion(t)) @ self.T
        frame = self._frame(self.T_rel, t)
        self._delivered = time.perf_counter()
        return frame

    def now(self) -> float:
        return self.sim_robot.t


class RenderedCameraSource(_MeshCamera):
    """A stand-in camera for a real robot: the D405 rendered at the pose the robot reports, in
    real time at `fps`. It closes the loop through a real robot link (a Franka, or franky-sim)
    without a camera: bring-up and bench tests. `T_base_vine` is the twin's `T_world_vine`."""

    def __init__(
        self,
        backend: DepthBackend,
        robot: Any,
        T_base_vine: Array,
        *,
        fps: float = 30.0,
        sensor: SensorConfig | None = None,
        seed: int = 0,
    ) -> None:
        super().__init__(backend, robot, T_base_vine, np.random.default_rng(seed), sensor, fps)
        self._next: float | None = None
        self.description = f"D405 rendered at the robot's pose, {fps:g} fps"

    def read(self, timeout: float = 1.0) -> CameraFrame | None:
        now = time.monotonic()
        if self._next is None:
            self._next = now
        wait = self._next - now
        if wait > timeout:
            time.sleep(timeout)
            return None
        if wait > 0:
            time.sleep(wait)
        self._next = max(self._next + self.period, time.monotonic())  # drop missed ticks
        stamp = time.monotonic()
        return self._frame(invert(self.T_base_vine) @ self.robot.T_base_camera(), stamp)


def make_servo(
    reference: Cloud,
    camera: CameraModel,
    perception: PerceptionConfig,
    config: SimConfig,
    safety: SafetyConfig | None = None,
) -> Servo:
    """The servo a `SimConfig` describes (the same one `vinetwin servo` builds)."""
    cfg = config
    return Servo(
        reference,
        icp=ICPConfig(variant=cfg.variant),
        gain=Gain(l0=cfg.gain, l_inf=cfg.gain_far, adaptive=True),
        limits=Limits(max_linear=cfg.max_linear, max_angular=cfg.max_angular),
        safety=safety,
        camera=camera,
        perception=perception,
        goal_translation=cfg.converged_translation,
        goal_rotation=cfg.converged_rotation,
        guess=cfg.guess,
    )


def believed_goal(goal: Array, config: SimConfig, rng: np.random.Generator) -> Array:
    """Where the robot believes the reference camera is: the goal, off by the configured
    registration error (the first frame's guess comes from it)."""
    return goal @ make_pose(
        so3_exp(_random_vector(rng, config.registration_error_rotation)),
        _random_vector(rng, config.registration_error_translation),
    )


def simulate(
    backend: DepthBackend,
    goal: Array,
    start: Array,
    reference_seed: int,
    perception: PerceptionConfig,
    config: SimConfig,
    *,
    disturbance: Disturbance | None = None,
    sensor: SensorConfig | None = None,
    pose_id: str = "",
    safety: SafetyConfig | None = None,
    arm: Any = None,
    log: CycleLog | None = None,
    record: str | Path | None = None,
) -> SimRun:
    """One closed-loop run from `start` to `goal` (camera poses in the vine frame), through
    `loop.run_loop`, the loop that drives hardware.

    With `arm` (a `servo.panda.PandaArm` whose scene holds the vine at `arm.T_base_vine`), the
    camera is the D405 on the Panda's hand: the arm first reaches the start pose (a start it
    cannot reach raises InputError), then each twist drives its joints. Without it the camera
    flies freely. `log` receives every cycle (with the true error); `record` writes the frames,
    with their stamps and robot poses, as a capture folder that `FolderSource` replays."""
    cfg = config
    camera = backend.camera
    sensor = sensor or SensorConfig()
    dist = disturbance or Disturbance()
    rng = np.random.default_rng(cfg.seed)
    ref = render_reference(backend, goal, perception, sensor, reference_seed).cloud
    servo = make_servo(ref, camera, perception, cfg, safety)
    servo.reset(invert(believed_goal(goal, cfg, rng)) @ start)
    run = SimRun(cfg, pose_id, np.asarray(goal, float), np.asarray(start, float), dist)
    limits = CommandLimits(max_linear=cfg.max_linear, max_angular=cfg.max_angular)
    robot: SimulatedRobot
    if arm is None:
        T_base_vine = np.eye(4)
        robot = KinematicRobot(start, limits=limits)
    else:
        T_base_vine = np.asarray(arm.T_base_vine, float)
        ok, dt_, dr_ = arm.reach(T_base_vine @ start)
        if not ok:
            raise InputError(
                f"the arm cannot reach the start pose ({1000 * dt_:.1f} mm, {dr_:.3f} rad short)"
            )
        robot = MujocoRobot(arm, limits=limits)
    source = SimCameraSource(
        backend, robot, T_base_vine, rng, sensor=sensor, camera_rate=cfg.camera_rate,
        fixed_period=cfg.fixed_period, disturbance=dist,
    )  # fmt: skip
    writer = None
    if record is not None:
        writer = CaptureWriter(
            record, camera, camera.depth_unit, extra={"provenance": {"simulation": cfg.to_dict()}}
        )
    at_goal_since: list[float | None] = [None]

    def on_cycle(c: Cycle) -> dict[str, Any]:
        r, t = c.result, c.frame.stamp
        et, er = pose_error(source.T_rel, goal)
        run.t.append(t)
        run.T.append(source.T.copy())
        run.error_t.append(et)
        run.error_r.append(er)
        run.trusted.append(r.trusted)
        run.compute.append(sum(r.timings.values()))
        if not r.trusted:
            key = r.reason.split(":")[0]
            run.reasons[key] = run.reasons.get(key, 0) + 1
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
        run_loop(
            servo, source, robot, LoopConfig(settle=0.0, max_cycle=0.0), log=log,
            on_cycle=on_cycle,
        )  # fmt: skip
    finally:
        if writer is not None:
            writer.close()
    run.wall = time.perf_counter() - wall0
    return run


def _random_vector(rng: np.random.Generator, norm: float) -> Array:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v) * norm
