"""The servo step: one call per camera frame, from a cloud (or a depth image) to a camera twist,
with the safety rules of a servo that stops when it cannot trust its alignment.

`Servo(reference, ...)` is built once per pruning pose (it builds the reference's ICP search
structures). `Servo.step(cloud, stamp, T_base_camera)` then, per frame:

1. refuses a stale frame (its stamp not newer than the last one, or older than `max_frame_age`
   when the caller gives `now`) and an empty one;
2. predicts the pose: the kinematic guess of paper eq. 11 when the robot's `T_base_camera` is
   given with this frame and the last trusted one, otherwise the last trusted estimate moved by
   the twist commanded since (zero after a refusal), otherwise the caller's `initial_guess`;
3. aligns the frame with ICP from that prediction. In steady tracking (the last frame trusted)
   it first runs ICP's final level alone and keeps that answer when it is trusted (step 4),
   moved the prediction less than `track_translation` / `track_rotation` and pairs at least
   `track_overlap` of the last frame's overlap: the wider levels, which pull in a prediction
   centimetres off, would end in the same basin and cost 1.3-2x the time on 2 mm clouds.
   Otherwise the full schedule runs on the same frame;
4. trusts the alignment only if ICP converged, its overlap, correspondence count and inlier RMSE
   pass the thresholds, and the estimate lies within what the motion since the last trusted
   frame can explain (a pose jump means ICP slipped to another cane), unless the same jump is
   seen in `reacquire_frames` consecutive frames (the vine itself moved: the servo re-acquires);
   before the first trusted frame, the estimate must lie within `max_guess_translation` /
   `max_guess_rotation` of the believed pose;
   a trusted estimate pairing under `doubt_overlap` of the frame is looked at again by the
   wide search (step 5) around it: a pose elsewhere pairing clearly more ("ambiguous
   alignment") refuses the frame until `reacquire_frames` frames find that pose;
5. after refusals for `search_after` s, also runs the wide search (`registration.search`:
   coarse-to-fine from several hypotheses around the prediction) and trusts its pose once
   `reacquire_frames` consecutive frames agree on it and no other hypothesis fits as well;
6. after refusals for `lost_after` s, stops for good: "lost the vine" (`StepResult.lost`), a
   named end instead of zeros forever;
7. returns the PBVS twist (eq. 8, saturated, its increase ramped by the acceleration limits), or
   a zero twist and the reason.

A refused frame never moves the arm: the twist is exactly zero and `trusted` is False.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from vinetwin.camera import CameraModel
from vinetwin.cloud import Cloud, PerceptionConfig, perceive
from vinetwin.errors import raise_if_interrupt
from vinetwin.frames import Array, check_pose, invert, pose_error, se3_exp, so3_log
from vinetwin.registration.icp import ICP, ICPConfig, ICPResult
from vinetwin.registration.search import SearchResult, WideSearch
from vinetwin.render.reference import Reference
from vinetwin.servo.config import DENSE_VARIANTS, GUESSES, LAWS, Limits, SafetyConfig, ServoConfig
from vinetwin.servo.pbvs import Gain, kinematic_guess, pbvs_error, pbvs_twist, target_twist


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
    reacquired: bool = False
    """Trusted by the wide search after a streak of refusals (not by tracking)."""
    tracked: bool = False
    """Aligned by ICP's final level alone (steady tracking), not the full schedule."""
    lost: bool = False
    """The servo lost the vine (refusals for `SafetyConfig.lost_after`) and stopped for good;
    the loop ends."""


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
        law: str = "eq8",
        target: Any = None,
        dense_reference: Cloud | None = None,
        dither: bool = True,
    ) -> None:
        """`camera` and `perception` are the twin's: they describe the reference's view (for the
        edge-of-view rejection of ICP) and run the perception chain of `step_depth`. `guess` is
        where each frame's ICP starts: "kinematic" (eq. 11, the default), "previous" (the last
        trusted estimate, ignoring the robot's motion) or "identity" (no initial guess, as plain
        ICP; the pose-jump rule is then off, having no prediction to compare with). `law` is
        eq8 or target (`pbvs.target_twist`), towards `target`, the cut point in the reference
        camera frame (None: the median of the reference cloud). `dense_reference`: the same view
        sampled more densely, for ICP's final level (`ICP(final_reference=...)`)."""
        if guess not in GUESSES:
            raise ValueError(f"unknown guess '{guess}'; choose one of: {', '.join(GUESSES)}")
        self.guess = guess
        if law not in LAWS:
            raise ValueError(f"unknown law '{law}'; choose one of: {', '.join(LAWS)}")
        self.law = law
        if target is not None:
            self.target = np.asarray(target, dtype=np.float64).reshape(3)
        elif len(reference.points):
            self.target = np.median(reference.points, axis=0)
        else:
            self.target = np.zeros(3)
        self.icp_config = icp or ICPConfig()
        self.perception = perception or PerceptionConfig()
        self.camera = camera
        max_depth = self.perception.max_depth if camera is not None else math.inf
        self.reference = reference
        self.icp = ICP(
            reference, self.icp_config, camera=camera, max_depth=max_depth,
            final_reference=dense_reference,
        )  # fmt: skip
        self.gain = gain
        self.limits = limits or Limits()
        self.safety = safety or SafetyConfig()
        self.goal_translation = goal_translation
        self.goal_rotation = goal_rotation
        self._max_depth = max_depth
        self._dense = dense_reference
        self.dither = dither
        self._search: WideSearch | None = None
        self._tight: ICP | None = None
        self.reset()

    def reset(self, initial_guess: Any = None) -> None:
        """Forgets the trajectory; the next frame starts from `initial_guess` (T_ref_cur, the
        identity when None)."""
        self._guess = None if initial_guess is None else check_pose(initial_guess, "initial_guess")
        self._last_stamp = -math.inf
        self._trusted_T: Array | None = None
        self._trusted_stamp = -math.inf
        self._trusted_base: Array | None = None
        self._trusted_overlap = 0.0
        self._twist = np.zeros(6)
        self._twist_stamp = -math.inf
        self.refusals = 0
        """Consecutive refused frames."""
        self.reacquisitions = 0
        """Poses trusted by the wide search since the reset."""
        self.tracked_frames = 0
        """Frames trusted on the final ICP level alone (steady tracking) since the reset."""
        self.lost = ""
        """Why the servo lost the vine (empty while it has not)."""
        self._streak_since: float | None = None
        self._jumps: list[Array] = []
        self._found: list[Array] = []
        self._doubt_stamp = -math.inf
        self._doubts: list[Array] = []

    @property
    def initial_guess(self) -> Array:
        """Where the next frame's ICP starts while nothing is trusted yet (T_ref_cur given to
        `reset`; the identity if none)."""
        return np.eye(4) if self._guess is None else self._guess.copy()

    @property
    def estimate(self) -> Array | None:
        """T_ref_cur of the last trusted frame: where the servo believes the camera is relative
        to the reference camera (None before the first)."""
        return None if self._trusted_T is None else self._trusted_T.copy()

    def warm_up(self, depth: Any) -> None:
        """Compiles what a frame will run (perception, the ICP levels, the tight ICP and the wide
        search: numba kernels compile on their first call, 10-30 s on a fresh install) on a depth
        image, from the identity, once per process and variant; the servo's state is untouched.
        The simulation calls it before its first frame, whose measured processing time would
        otherwise hold the first twist for as long as the compilation took."""
        key = (self.icp_config.variant, self._dense is not None)
        if key in _WARMED or self.camera is None:
            return
        cloud = perceive(
            depth, self.camera, self.perception,
            normals=self.icp_config.variant == "symmetric", grid_origin=self._dither(0.0),
        )  # fmt: skip
        if cloud.points.size:
            self.icp.align(cloud, np.eye(4))
            self._tight_icp().align(cloud, np.eye(4))
            self._searcher().align(
                cloud, np.eye(4), translation=0.01, rotation=0.02, accept=self._untrusted
            )
        _WARMED.add(key)

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
            cloud = perceive(
                depth, self.camera, self.perception, normals=normals,
                grid_origin=self._dither(stamp),
            )  # fmt: skip
        except Exception as exc:  # a malformed image is a refused frame, not a crash
            raise_if_interrupt(exc)
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
        if self.lost:
            return StepResult(np.zeros(6), False, self.lost, lost=True)
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
        tight: ICPResult | None = None
        tracked = False
        if self._tracking():
            # steady tracking: the final level alone from the prediction, kept when it is
            # trusted and barely moved the prediction (the wider levels would end in the same
            # basin); else the full schedule on the same frame
            tight = self._tight_icp().align(cloud, guess)
            tracked = not self._judge(
                tight, guess, kinematic, stamp, base, track_jumps=False
            ) and self._settled(tight, guess)
        if tracked and tight is not None:
            r, reason = tight, ""
            timings = {"icp": time.perf_counter() - t0}
        else:
            r = self.icp.align(cloud, guess)
            timings = {"icp": time.perf_counter() - t0}
            reason = self._judge(r, guess, kinematic, stamp, base, track_jumps=True)
        if reason and self._trusted_T is not None and self.guess != "identity":
            # a second opinion from the same prediction without the wide first level: a good
            # prediction (eq. 11) that the 3 cm level let slide off along the canes
            if tight is None:
                t0 = time.perf_counter()
                tight = self._tight_icp().align(cloud, guess)
                timings["icp_tight"] = time.perf_counter() - t0
            if not self._judge(tight, guess, kinematic, stamp, base, track_jumps=False):
                r, reason = tight, ""
        reacquired = False
        if reason:
            if not reason.startswith("pose jump"):
                self._jumps.clear()
            since = stamp if self._streak_since is None else self._streak_since
            if stamp - since >= s.search_after and not self._lost_now(stamp):
                t0 = time.perf_counter()
                found, why = self._wide_search(cloud, guess, base)
                timings["search"] = time.perf_counter() - t0
                if found is None:
                    reason = f"{reason}; wide search: {why}"
                else:
                    r, reason, reacquired = found, "", True
        if not reason and not reacquired:
            t0 = time.perf_counter()
            found, reason = self._doubt(r, cloud, base, stamp)
            if self._doubt_stamp == stamp:  # the wide search looked
                timings["doubt"] = time.perf_counter() - t0
            if found is not None and found is not r:
                r, reacquired = found, True
        if reason:
            out = self._refuse(reason, stamp)
            if not out.lost:
                out.T_ref_cur, out.icp = r.T_ref_cur, r
            out.timings = timings
            return out
        self._jumps.clear()
        self._found.clear()
        self._streak_since = None
        self.reacquisitions += int(reacquired)

        t0 = time.perf_counter()
        T = r.T_ref_cur
        e = pbvs_error(T)
        if self.law == "target":
            twist = target_twist(T, self.target, self.gain, self.limits)
        else:
            twist = pbvs_twist(T, self.gain, self.limits)
        twist = self._ramp(twist, stamp)
        timings["control"] = time.perf_counter() - t0
        self._trusted_T, self._trusted_stamp, self._trusted_base = T, stamp, base
        self._trusted_overlap = r.overlap
        self.tracked_frames += int(tracked)
        self._twist, self._twist_stamp = twist, stamp
        self.refusals = 0
        at_goal = (
            float(np.linalg.norm(e[:3])) <= self.goal_translation
            and float(np.linalg.norm(e[3:])) <= self.goal_rotation
        )
        return StepResult(
            twist, True, "", T, e, at_goal, r, timings, reacquired=reacquired, tracked=tracked
        )

    # ------------------------------------------------------------------ helpers
    def _judge(
        self,
        r: ICPResult,
        guess: Array,
        kinematic: bool,
        stamp: float,
        base: Array | None,
        track_jumps: bool,
    ) -> str:
        """Why an alignment is not trusted ("" when it is): ICP's failure, the thresholds, an
        implausible first estimate, or a pose jump (which, with `track_jumps`, counts towards
        the consistent-jump rule)."""
        s = self.safety
        if not r.converged:
            return f"ICP failed: {r.reason}"
        why = self._untrusted(r)
        if why or self.guess == "identity":
            return why
        jt, jr = pose_error(r.T_ref_cur, guess)
        if self._trusted_T is None:
            if self._guess is not None and (
                jt > s.max_guess_translation or jr > s.max_guess_rotation
            ):
                return (
                    f"implausible first estimate: {1000 * jt:.1f} mm / {math.degrees(jr):.2f} deg "
                    f"from the believed pose (allowed {1000 * s.max_guess_translation:.0f} mm / "
                    f"{math.degrees(s.max_guess_rotation):.1f} deg)"
                )
            return ""
        allow_t = s.max_jump_translation + s.jump_fraction * float(np.linalg.norm(guess[:3, 3]))
        allow_r = s.max_jump_rotation + s.jump_fraction * float(
            np.linalg.norm(so3_log(guess[:3, :3]))
        )
        if not kinematic:
            since = max(stamp - self._trusted_stamp, 0.0)
            allow_t += self.limits.max_linear * since
            allow_r += self.limits.max_angular * since
        if jt <= allow_t and jr <= allow_r:
            return ""
        if track_jumps and self._consistent_jump(r.T_ref_cur, base):
            return ""
        return (
            f"pose jump: the estimate is {1000 * jt:.1f} mm / {math.degrees(jr):.2f} deg "
            f"from its prediction (allowed {1000 * allow_t:.1f} mm / "
            f"{math.degrees(allow_r):.2f} deg)"
        )

    def _searcher(self) -> WideSearch:
        """The wide search over this servo's reference, built on first use."""
        if self._search is None:
            self._search = WideSearch(
                self.reference, variant=self.icp_config.variant, camera=self.camera,
                max_depth=self._max_depth,
            )  # fmt: skip
        return self._search

    def _tracking(self) -> bool:
        """Steady tracking: the last frame was trusted and this one has a prediction."""
        s = self.safety
        return (
            s.track_translation > 0
            and self._trusted_T is not None
            and self.refusals == 0
            and self.guess != "identity"
        )

    def _settled(self, r: ICPResult, guess: Array) -> bool:
        """A trusted final-level answer that may stand for the full schedule's: it moved the
        prediction less than the tracking limits and pairs about as much as the last frame."""
        s = self.safety
        jt, jr = pose_error(r.T_ref_cur, guess)
        return (
            jt <= s.track_translation
            and jr <= s.track_rotation
            and r.overlap >= s.track_overlap * self._trusted_overlap
        )

    def _tight_icp(self) -> ICP:
        """Tracking ICP without the wide levels: the final level only, from the prediction."""
        if self._tight is None:
            cfg, tol = self.icp_config, self.safety.track_tolerance
            tight = replace(
                cfg, schedule=(), tolerance_translation=max(cfg.tolerance_translation, tol),
                tolerance_rotation=max(cfg.tolerance_rotation, tol),
            )  # fmt: skip
            self._tight = ICP(
                self.reference, tight, camera=self.camera, max_depth=self._max_depth,
                final_reference=self._dense,
            )  # fmt: skip
        return self._tight

    def _dither(self, stamp: float) -> Array | None:
        """A voxel-grid origin for this frame, uniform within one voxel and seeded by the frame's
        stamp (None when `dither` is off). The reference's grid is anchored at its camera's
        origin; a live grid anchored the same way in its own camera makes the two lattices
        coincide exactly when the camera is at the goal, and point-to-point (and, less, the
        other variants) is drawn to that coincidence: its estimate reads zero up to a voxel
        before the goal (the "lattice floor", 1-2 mm at 4 mm voxels). A grid moved at random
        every frame turns that pull into noise, which the loop averages out (dithering)."""
        if not self.dither or not math.isfinite(stamp):
            return None
        seed = int.from_bytes(np.float64(stamp).tobytes(), "little")
        return np.random.default_rng(seed).uniform(0.0, self.perception.voxel_size, 3)

    def _untrusted(self, r: ICPResult) -> str:
        """Why a converged alignment is not trusted by the thresholds ("" when it is)."""
        s = self.safety
        if r.overlap < s.min_overlap:
            return f"low overlap: {r.overlap:.2f} < {s.min_overlap}"
        if r.correspondences < s.min_correspondences:
            return f"too few correspondences: {r.correspondences} < {s.min_correspondences}"
        if not r.inlier_rmse <= s.max_rmse:
            return f"high RMSE: {1000 * r.inlier_rmse:.2f} mm > {1000 * s.max_rmse:.2f} mm"
        return ""

    def _wide_search(
        self, cloud: Cloud, prediction: Array, base: Array | None
    ) -> tuple[ICPResult | None, str]:
        """The wide search on this frame; its pose is returned once `reacquire_frames`
        consecutive frames found the same one (compared as the reference camera in the robot
        base, or as they are without kinematics)."""
        res = self._search_around(cloud, prediction)
        if res.best is None:
            self._found.clear()
            return None, res.reason
        found, need = self._agreeing(self._found, res.best.T_ref_cur, base)
        if found < need:
            return None, f"found a pose in {found} of the {need} frames it needs"
        return res.best, ""

    def _search_around(self, cloud: Cloud, T_ref_cur: Array) -> SearchResult:
        """The wide search's `SearchResult` on this frame, its hypotheses around `T_ref_cur`."""
        s = self.safety
        return self._searcher().align(
            cloud, T_ref_cur, translation=s.search_translation, rotation=s.search_rotation,
            accept=self._untrusted,
        )  # fmt: skip

    def _agreeing(
        self, streak: list[Array], T_ref_cur: Array, base: Array | None
    ) -> tuple[int, int]:
        """Adds this frame's pose to `streak` (as the reference camera in the robot base, or as
        it is without kinematics), which restarts when it differs from the last one by more
        than `reacquire_translation` / `reacquire_rotation`: the consecutive frames that agree,
        and the `reacquire_frames` needed."""
        s = self.safety
        implied = T_ref_cur if base is None else base @ invert(T_ref_cur)
        if streak:
            jt, jr = pose_error(streak[-1], implied)
            if jt > s.reacquire_translation or jr > s.reacquire_rotation:
                streak.clear()
        streak.append(implied)
        return len(streak), max(s.reacquire_frames, 1)

    def _doubt(
        self, r: ICPResult, cloud: Cloud, base: Array | None, stamp: float
    ) -> tuple[ICPResult | None, str]:
        """A trusted alignment that pairs little of the frame, looked at again (`doubt_overlap`):
        the wide search around it, then, once it found a pose elsewhere pairing clearly more,
        the final ICP level from that pose on each frame. Returns `r` and "" when nothing fits
        clearly better; None and the reason while the better pose waits for its
        `reacquire_frames` agreeing frames; that pose once they agree."""
        s = self.safety
        if s.doubt_overlap <= 0 or r.overlap >= s.doubt_overlap:
            self._doubts.clear()
            return r, ""
        if not (self._trusted_T is None or self._doubts) and stamp - self._doubt_stamp < (
            s.doubt_every
        ):
            return r, ""
        self._doubt_stamp = stamp
        better: ICPResult | None
        if self._doubts:  # the better pose, where the robot's motion since puts it
            last = self._doubts[-1]
            better = self._tight_icp().align(cloud, last if base is None else invert(last) @ base)
            why = "" if better.converged else "lost"
        else:
            res = self._search_around(cloud, r.T_ref_cur)
            better, why = res.best, res.reason
        if better is None or why or self._untrusted(better):
            self._doubts.clear()
            return r, ""
        dt, dr = pose_error(better.T_ref_cur, r.T_ref_cur)
        if better.overlap < r.overlap + s.doubt_margin or (
            dt <= s.max_jump_translation and dr <= s.max_jump_rotation
        ):
            self._doubts.clear()
            return r, ""
        found, need = self._agreeing(self._doubts, better.T_ref_cur, base)
        if found >= need:
            self._doubts.clear()
            return better, ""
        return None, (
            f"ambiguous alignment: a pose {1000 * dt:.1f} mm / {math.degrees(dr):.2f} deg from "
            f"the estimate pairs {100 * better.overlap:.0f}% of the frame, the estimate "
            f"{100 * r.overlap:.0f}% (found in {found} of the {need} frames it needs)"
        )

    def _lost_now(self, stamp: float) -> bool:
        """True when this refusal ends a streak of `lost_after` s."""
        lim = self.safety.lost_after
        since = self._streak_since
        return lim > 0 and since is not None and stamp - since >= lim

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
            if self._streak_since is None:
                self._streak_since = stamp
            if self._lost_now(stamp):
                self.lost = (
                    f"lost the vine: no trusted alignment for {stamp - self._streak_since:.2f} s "
                    f"(limit {self.safety.lost_after} s; last refusal: {reason})"
                )
                return StepResult(np.zeros(6), False, self.lost, lost=True)
        return StepResult(np.zeros(6), False, reason)


#: (variant, dense reference) pairs whose kernels this process has compiled (`Servo.warm_up`).
_WARMED: set[tuple[str, bool]] = set()


def make_servo(
    reference: Reference | Cloud,
    camera: CameraModel,
    perception: PerceptionConfig,
    config: ServoConfig,
    limits: Limits | None = None,
    safety: SafetyConfig | None = None,
) -> Servo:
    """The servo a `ServoConfig` describes, for a twin's camera and perception settings: the one
    the simulation, `vinetwin servo` and the web app build. `reference`: the pose's
    (`render.reference.reference_for`), whose cut point is the view-keeping law's target and
    whose dense cloud the dense variants pair against; a bare cloud has neither."""
    ref = reference if isinstance(reference, Reference) else Reference(reference, None, 0)
    return Servo(
        ref.cloud,
        icp=ICPConfig(variant=config.variant),
        gain=Gain(l0=config.gain, l_inf=config.gain_far, adaptive=True),
        limits=limits or Limits(),
        safety=safety,
        camera=camera,
        perception=perception,
        goal_translation=config.converged_translation,
        goal_rotation=config.converged_rotation,
        guess=config.guess,
        law=config.law,
        target=ref.cut,
        dense_reference=ref.dense if wants_dense(config) else None,
    )


def wants_dense(config: ServoConfig) -> bool:
    """Whether this servo pairs its final ICP level against a dense reference."""
    return config.dense_reference and config.variant in DENSE_VARIANTS


def _non_finite_share(depth: Any) -> float:
    """The share of a float depth image's pixels that are NaN or infinite (0 for integers and
    for what is not an array of numbers: perception names those)."""
    d = np.asarray(depth)
    if d.dtype.kind != "f" or d.size == 0:
        return 0.0
    finite = np.isfinite(d)
    return 0.0 if finite.all() else float(1.0 - finite.mean())
