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
from typing import Any

import numpy as np

from vinetwin._config import JsonFields
from vinetwin.camera import CameraModel
from vinetwin.cloud import PerceptionConfig
from vinetwin.errors import InputError
from vinetwin.frames import (
    Array,
    invert,
    make_pose,
    pose_error,
    se3_exp,
    so3_exp,
    transform_points,
)
from vinetwin.render.backends import DepthBackend
from vinetwin.render.reference import render_reference
from vinetwin.render.sensor import SensorConfig, apply_d405_model
from vinetwin.servo.icp import ICPConfig
from vinetwin.servo.pbvs import Gain, Limits
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
) -> SimRun:
    """One closed-loop run from `start` to `goal` (camera poses in the vine frame).

    With `arm` (a `servo.panda.PandaArm` whose scene holds the vine at `arm.T_base_vine`), the
    camera is the D405 on the Panda's hand: the arm first reaches the start pose (a start it
    cannot reach raises InputError), then each twist drives its joints. Without it the camera
    flies freely."""
    cfg = config
    camera = backend.camera
    sensor = sensor or SensorConfig()
    dist = disturbance or Disturbance()
    rng = np.random.default_rng(cfg.seed)
    ref = render_reference(backend, goal, perception, sensor, reference_seed).cloud
    servo = Servo(
        ref,
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
    # where the robot believes the reference camera is: the goal, off by the registration error
    believed = goal @ make_pose(
        so3_exp(_random_vector(rng, cfg.registration_error_rotation)),
        _random_vector(rng, cfg.registration_error_translation),
    )
    servo.reset(invert(believed) @ start)
    run = SimRun(cfg, pose_id, np.asarray(goal, float), np.asarray(start, float), dist)
    period = 1.0 / cfg.camera_rate
    T_base_vine = np.eye(4) if arm is None else np.asarray(arm.T_base_vine, float)
    if arm is not None:
        ok, dt_, dr_ = arm.reach(T_base_vine @ start)
        if not ok:
            raise InputError(
                f"the arm cannot reach the start pose ({1000 * dt_:.1f} mm, {dr_:.3f} rad short)"
            )
    T = np.asarray(start, dtype=np.float64).copy()  # camera in the vine's original frame
    t = 0.0
    at_goal_since: float | None = None
    wall0 = time.perf_counter()
    while t <= cfg.duration:
        if arm is not None:
            T = invert(T_base_vine) @ arm.pose()
        M = dist.vine_motion(t)
        T_rel = invert(M) @ T  # the camera relative to the (moved) vine
        depth = apply_d405_model(backend.render(T_rel), camera, rng, sensor)
        r = servo.step_depth(depth, stamp=t, T_base_camera=T_base_vine @ T)
        compute = sum(r.timings.values())
        et, er = pose_error(T_rel, goal)
        run.t.append(t)
        run.T.append(T.copy())
        run.error_t.append(et)
        run.error_r.append(er)
        run.trusted.append(r.trusted)
        run.compute.append(compute)
        if not r.trusted:
            key = r.reason.split(":")[0]
            run.reasons[key] = run.reasons.get(key, 0) + 1
        if cfg.settle > 0:
            if r.trusted and r.at_goal:
                at_goal_since = t if at_goal_since is None else at_goal_since
                if t - at_goal_since >= cfg.settle and (
                    dist.time < 0 or t > dist.time + cfg.settle
                ):
                    break
            elif r.trusted or at_goal_since is None:
                at_goal_since = None
        hold = (
            cfg.fixed_period
            if cfg.fixed_period > 0
            else period * max(1, math.ceil(compute / period))
        )
        if arm is None:
            T = T @ se3_exp(r.twist * hold)
        else:
            arm.move(r.twist, hold)
        t += hold
    run.wall = time.perf_counter() - wall0
    return run


def _random_vector(rng: np.random.Generator, norm: float) -> Array:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v) * norm
