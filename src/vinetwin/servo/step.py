"""The servo step: one call per camera frame, from a cloud (or a depth image) to a camera twist,
with the safety rules of a servo that stops when it cannot trust its alignment.

`Servo(reference, ...)` is built once per pruning pose (it builds the reference's ICP search
structures). `Servo.step(cloud, stamp, T_base_camera)` then, per frame:

1. refuses a stale frame (its stamp not newer than the last one, or older than `max_frame_age`
   when the caller gives `now`) and an empty one;
2. predicts the pose: the kinematic guess of paper eq. 11 when the robot's `T_base_camera` is
   given with this frame and the last trusted one, otherwise the last trusted estimate moved by
   the twist commanded since (zero after a refusal), otherwise the caller's `initial_guess`;
3. aligns the frame with ICP from that prediction;
4. trusts the alignment only if ICP converged, its overlap, correspondence count and inlier RMSE
   pass the thresholds, and the estimate lies within what the motion since the last trusted
   frame can explain (a pose jump means ICP slipped to another cane), unless the same jump is
   seen in `reacquire_frames` consecutive frames (the vine itself moved: the servo re-acquires);
5. returns the PBVS twist (eq. 8, saturated, its increase ramped by the acceleration limits), or
   a zero twist and the reason.

A refused frame never moves the arm: the twist is exactly zero and `trusted` is False.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from vinetwin.camera import CameraModel
from vinetwin.cloud import Cloud, PerceptionConfig, perceive
from vinetwin.frames import Array, check_pose, invert, pose_error, se3_exp
from vinetwin.registration.icp import ICP, ICPConfig, ICPResult
from vinetwin.servo.config import GUESSES, Limits, SafetyConfig, ServoConfig
from vinetwin.servo.pbvs import Gain, kinematic_guess, pbvs_error, pbvs_twist


@dataclass
class StepResult:
    """What one servo step decided."""

    twist: Array
    """Camera twist (v, omega) in the current camera frame, m/s and rad/s; zeros when not
    trusted."""
    trusted: bool
    reason: str = ""
    """Why the frame was refused (empty when trusted)."""
    T_ref_cur: Array | None = None
    """The alignment's estimate (also when refused for a threshold, None when not aligned)."""
    error: Array | None = None
    """PBVS error (c*t_c, theta*u) of a trusted estimate."""
    at_goal: bool = False
    """The trusted error is within the goal tolerance."""
    icp: ICPResult | None = None
    timings: dict[str, float] = field(default_factory=dict)
    """Seconds spent in perception, icp and control."""
    cloud: Cloud | None = None
    """The frame's cloud after perception (`step_depth`), camera frame."""


class Servo:
    """ICP-PBVS towards one reference cloud, one `step` per frame."""

    def __init__(
        self,
        reference: Cloud,
        *,
        icp: ICPConfig | None = None,
        gain: Gain | float = 0.8,
        limits: Limits | None = None,
        safety: SafetyConfig | None = None,
        camera: CameraModel | None = None,
        perception: PerceptionConfig | None = None,
        goal_translation: float = 0.002,
        goal_rotation: float = 0.01,
        guess: str = "kinematic",
    ) -> None:
        """`camera` and `perception` are the twin's: they describe the reference's view (for the
        edge-of-view rejection of ICP) and run the perception chain of `step_depth`. `guess` is
        where each frame's ICP starts: "kinematic" (eq. 11, the default), "previous" (the last
        trusted estimate, ignoring the robot's motion) or "identity" (no initial guess, as plain
        ICP; the pose-jump rule is then off, having no prediction to compare with)."""
        if guess not in GUESSES:
            raise ValueError(f"unknown guess '{guess}'; choose one of: {', '.join(GUESSES)}")
        self.guess = guess
        self.icp_config = icp or ICPConfig()
        self.perception = perception or PerceptionConfig()
        self.camera = camera
        max_depth = self.perception.max_depth if camera is not None else math.inf
        self.reference = reference
        self.icp = ICP(reference, self.icp_config, camera=camera, max_depth=max_depth)
        self.gain = gain
        self.limits = limits or Limits()
        self.safety = safety or SafetyConfig()
        self.goal_translation = goal_translation
        self.goal_rotation = goal_rotation
        self.reset()

    def reset(self, initial_guess: Any = None) -> None:
        """Forgets the trajectory; the next frame starts from `initial_guess` (T_ref_cur, the
        identity when None)."""
        self._guess = None if initial_guess is None else check_pose(initial_guess, "initial_guess")
        self._last_stamp = -math.inf
        self._trusted_T: Array | None = None
        self._trusted_stamp = -math.inf
        self._trusted_base: Array | None = None
        self._twist = np.zeros(6)
        self._twist_stamp = -math.inf
        self.refusals = 0
        """Consecutive refused frames."""
        self._jumps: list[Array] = []

    # ------------------------------------------------------------------ per frame
    def step_depth(
        self, depth: Any, stamp: float, T_base_camera: Any = None, now: float | None = None
    ) -> StepResult:
        """`step` on a depth image (metres) run through the twin's perception chain."""
        if self.camera is None:
            raise ValueError("step_depth needs the camera given to Servo(camera=...)")
        t0 = time.perf_counter()
        normals = self.icp_config.variant == "symmetric"
        bad = _non_finite_share(depth)
        if 0.0 < bad < 1.0:  # all non-finite: nothing survives perception, an empty frame
            return self._refuse(
                f"corrupt depth image: {100 * bad:.1f}% of its pixels are NaN or infinite (a "
                "sensor reports no data as 0): the whole frame is refused",
                stamp,
            )
        try:
            cloud = perceive(depth, self.camera, self.perception, normals=normals)
        except Exception as exc:  # a malformed image is a refused frame, not a crash
            return self._refuse(f"bad depth image: {exc}", stamp)
        t_perception = time.perf_counter() - t0
        result = self.step(cloud, stamp, T_base_camera, now)
        result.cloud = cloud
        result.timings["perception"] = t_perception
        return result

    def step(
        self, cloud: Cloud, stamp: float, T_base_camera: Any = None, now: float | None = None
    ) -> StepResult:
        """One frame: the camera twist to command until the next frame, or zero and the reason."""
        s = self.safety
        if not math.isfinite(stamp) or stamp <= self._last_stamp:
            return self._refuse(
                f"stale frame: stamp {stamp} is not newer than the last one ({self._last_stamp})",
                stamp,
                keep_stamp=True,
            )
        self._last_stamp = stamp
        if now is not None and now - stamp > s.max_frame_age:
            return self._refuse(
                f"stale frame: {now - stamp:.3f} s old (limit {s.max_frame_age} s)", stamp
            )
        if cloud.points.size == 0:
            return self._refuse("empty frame: no points survived perception", stamp)
        base = None if T_base_camera is None else np.asarray(T_base_camera, dtype=np.float64)
        if base is not None and (base.shape != (4, 4) or not np.all(np.isfinite(base))):
            return self._refuse("T_base_camera is not a finite 4x4 pose", stamp)

        # prediction
        kinematic = False
        if self.guess == "identity":
            guess = np.eye(4)
        elif self._trusted_T is None:
            guess = np.eye(4) if self._guess is None else self._guess
        elif self.guess == "previous":
            guess = self._trusted_T
        elif base is not None and self._trusted_base is not None:
            guess = kinematic_guess(self._trusted_T, self._trusted_base, base)
            kinematic = True
        else:
            dt = max(stamp - max(self._twist_stamp, self._trusted_stamp), 0.0)
            guess = self._trusted_T @ se3_exp(self._twist * dt)

        t0 = time.perf_counter()
        r = self.icp.align(cloud, guess)
        t_icp = time.perf_counter() - t0
        timings = {"icp": t_icp}

        reason = ""
        if not r.converged:
            reason = f"ICP failed: {r.reason}"
        elif r.overlap < s.min_overlap:
            reason = f"low overlap: {r.overlap:.2f} < {s.min_overlap}"
        elif r.correspondences < s.min_correspondences:
            reason = f"too few correspondences: {r.correspondences} < {s.min_correspondences}"
        elif not r.inlier_rmse <= s.max_rmse:
            reason = f"high RMSE: {1000 * r.inlier_rmse:.2f} mm > {1000 * s.max_rmse:.2f} mm"
        elif self._trusted_T is not None and self.guess != "identity":
            jt, jr = pose_error(r.T_ref_cur, guess)
            allow_t, allow_r = s.max_jump_translation, s.max_jump_rotation
            if not kinematic:
                since = max(stamp - self._trusted_stamp, 0.0)
                allow_t += self.limits.max_linear * since
                allow_r += self.limits.max_angular * since
            if (jt > allow_t or jr > allow_r) and not self._consistent_jump(r.T_ref_cur, base):
                reason = (
                    f"pose jump: the estimate is {1000 * jt:.1f} mm / {math.degrees(jr):.2f} deg "
                    f"from its prediction (allowed {1000 * allow_t:.1f} mm / "
                    f"{math.degrees(allow_r):.2f} deg)"
                )
        if reason:
            if not reason.startswith("pose jump"):
                self._jumps.clear()
            out = self._refuse(reason, stamp)
            out.T_ref_cur, out.icp, out.timings = r.T_ref_cur, r, timings
            return out
        self._jumps.clear()

        t0 = time.perf_counter()
        T = r.T_ref_cur
        e = pbvs_error(T)
        twist = self._ramp(pbvs_twist(T, self.gain, self.limits), stamp)
        timings["control"] = time.perf_counter() - t0
        self._trusted_T, self._trusted_stamp, self._trusted_base = T, stamp, base
        self._twist, self._twist_stamp = twist, stamp
        self.refusals = 0
        at_goal = (
            float(np.linalg.norm(e[:3])) <= self.goal_translation
            and float(np.linalg.norm(e[3:])) <= self.goal_rotation
        )
        return StepResult(twist, True, "", T, e, at_goal, r, timings)

    # ------------------------------------------------------------------ helpers
    def _consistent_jump(self, T_ref_cur: Array, base: Array | None) -> bool:
        """A jump seen the same way in `reacquire_frames` consecutive frames is the scene moving
        (the vine was pushed), not ICP slipping: the servo re-acquires it. Estimates are
        compared as the reference camera's pose in the robot base (or as they are, the arm being
        stopped after a refusal, without kinematics)."""
        s = self.safety
        if s.reacquire_frames <= 0:
            return False
        implied = T_ref_cur if base is None else base @ invert(T_ref_cur)
        self._jumps.append(implied)
        if len(self._jumps) < s.reacquire_frames:
            return False
        recent = self._jumps[-s.reacquire_frames :]
        for other in recent[:-1]:
            jt, jr = pose_error(other, implied)
            if jt > s.reacquire_translation or jr > s.reacquire_rotation:
                return False
        return True

    def _ramp(self, twist: Array, stamp: float) -> Array:
        """Limits how fast the commanded speeds grow (from the last commanded twist)."""
        s = self.limits
        dt = stamp - self._twist_stamp
        if not math.isfinite(dt) or dt <= 0:
            dt = 0.0
        out = twist.copy()
        for sl, acc in (
            (slice(0, 3), s.max_linear_acceleration),
            (slice(3, 6), s.max_angular_acceleration),
        ):
            if acc <= 0:
                continue
            prev = self._twist[sl]
            delta = out[sl] - prev
            n = float(np.linalg.norm(delta))
            cap = acc * dt
            if n > cap and float(np.linalg.norm(out[sl])) > float(np.linalg.norm(prev)) - 1e-12:
                out[sl] = prev + delta * (cap / n)
        return out

    def _refuse(self, reason: str, stamp: float, keep_stamp: bool = False) -> StepResult:
        self.refusals += 1
        self._twist = np.zeros(6)
        if not keep_stamp and math.isfinite(stamp):
            self._twist_stamp = max(self._twist_stamp, stamp)
        return StepResult(np.zeros(6), False, reason)


def make_servo(
    reference: Cloud,
    camera: CameraModel,
    perception: PerceptionConfig,
    config: ServoConfig,
    limits: Limits | None = None,
    safety: SafetyConfig | None = None,
) -> Servo:
    """The servo a `ServoConfig` describes, for a twin's camera and perception settings: the one
    the simulation, `vinetwin servo` and the web app build."""
    from vinetwin.registration.icp import ICPConfig

    return Servo(
        reference,
        icp=ICPConfig(variant=config.variant),
        gain=Gain(l0=config.gain, l_inf=config.gain_far, adaptive=True),
        limits=limits or Limits(),
        safety=safety,
        camera=camera,
        perception=perception,
        goal_translation=config.converged_translation,
        goal_rotation=config.converged_rotation,
        guess=config.guess,
    )


def _non_finite_share(depth: Any) -> float:
    """The share of a float depth image's pixels that are NaN or infinite (0 for integers and
    for what is not an array of numbers: perception names those)."""
    d = np.asarray(depth)
    if d.dtype.kind != "f" or d.size == 0:
        return 0.0
    finite = np.isfinite(d)
    return 0.0 if finite.all() else float(1.0 - finite.mean())
