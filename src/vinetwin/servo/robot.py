"""The robot velocity interface: read the flange pose, send a camera twist, stop. Every command
passes one guard, the same for every robot, before it leaves the adapter:

- a twist with a NaN or infinite component is not sent: the robot is stopped;
- linear and angular speeds are scaled down (direction kept) to `CommandLimits.max_linear` /
  `max_angular`;
- speed increases are ramped by `max_linear_acceleration` / `max_angular_acceleration` from the
  last command sent (stops are not ramped; the robot's own controller brakes smoothly);
- a watchdog stops the robot when no command has come for `CommandLimits.watchdog` seconds
  (the loop hung, the camera stopped): a thread on hardware, a check of simulated time in the
  simulation. Franka commands also carry their own expiry: each velocity is held for at most
  `watchdog` seconds by the robot's controller, which then brakes to a stop by itself.

Twists are the camera's (v, omega), expressed in the camera frame, as `Servo.step` gives them;
`T_flange_camera` (the twin's hand-eye transform) relates the camera to the flange.

Implementations: `FrankaRobot` here (a real Panda or FR3 through the `franky-control` library,
imported only when used; its `FrankaTransport` is the one seam a test replaces), and the
simulated arms of `vinetwin.sim.robots` (`KinematicRobot`, a free-flying camera; `MujocoRobot`,
vinetwin's or the Menagerie's Panda in MuJoCo).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from abc import ABC, abstractmethod
from collections import deque
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from vinetwin.errors import VinetwinError
from vinetwin.frames import Array, check_pose, invert, se3_exp, se3_log
from vinetwin.servo.config import CommandLimits

log = logging.getLogger(__name__)


class RobotError(VinetwinError):
    """The robot cannot be reached or refused a command (a reflex, a lost connection)."""


class PlannerRefusal(RobotError):
    """The robot's own trajectory generator failed to plan one velocity command (franky's
    "Motion planner failed", a numerical failure of its online planner, not a reflex): that
    command was not executed and the arm is braking. `FrankaRobot` sends it once more and
    raises a plain `RobotError` when the second try is refused too."""


def guard_twist(twist: Any, previous: Array, dt: float, limits: CommandLimits) -> tuple[Array, str]:
    """The twist that may be sent after `previous` (sent `dt` s ago): limited and ramped; with
    the reason it was changed ("" when sent as asked). A non-finite twist becomes zero."""
    try:
        w = np.array(twist, dtype=np.float64).reshape(6)
    except (TypeError, ValueError):
        return np.zeros(6), "malformed twist: stopped"
    if not np.all(np.isfinite(w)):
        return np.zeros(6), "non-finite twist: stopped"
    notes = []
    for sl, vmax, amax, what in (
        (slice(0, 3), limits.max_linear, limits.max_linear_acceleration, "linear"),
        (slice(3, 6), limits.max_angular, limits.max_angular_acceleration, "angular"),
    ):
        n = float(np.linalg.norm(w[sl]))
        if n > vmax:
            w[sl] *= vmax / n
            notes.append(f"{what} speed {n:.3g} capped to {vmax}")
        if amax > 0 and math.isfinite(dt):
            prev = previous[sl]
            delta = w[sl] - prev
            nd = float(np.linalg.norm(delta))
            cap = amax * max(dt, 0.0)
            growing = float(np.linalg.norm(w[sl])) > float(np.linalg.norm(prev)) + 1e-12
            if nd > cap and growing:
                w[sl] = prev + delta * (cap / nd)
                notes.append(f"{what} acceleration ramped")
    return w, "; ".join(notes)


def pose_at(history: Sequence[tuple[float, Array]], stamp: float) -> Array | None:
    """The pose at `stamp` interpolated (on the screw) between the two samples of `history`
    ((time, pose), oldest first) around it; None when `stamp` lies outside them."""
    if len(history) < 2 or not history[0][0] <= stamp <= history[-1][0]:
        return None
    k = next(i for i in range(1, len(history)) if history[i][0] >= stamp)
    (t0, A), (t1, B) = history[k - 1], history[k]
    a = 0.0 if t1 <= t0 else (stamp - t0) / (t1 - t0)
    return A @ se3_exp(a * se3_log(invert(A) @ B))


class Robot(ABC):
    """A velocity-controlled arm carrying the camera. Subclasses give `_pose` (T_base_flange),
    `_send` (a guarded camera twist) and `_halt`."""

    name = "robot"

    def __init__(
        self,
        T_flange_camera: Any,
        limits: CommandLimits | None = None,
        clock: Callable[[], float] = time.monotonic,
        watchdog_thread: bool = True,
    ) -> None:
        self.T_flange_camera = check_pose(T_flange_camera, "T_flange_camera")
        self.limits = limits or CommandLimits()
        self.clock = clock
        self.last_sent = np.zeros(6)
        self.last_command_time = -math.inf
        self.moving = False
        self.events: deque[tuple[float, str]] = deque(maxlen=1000)
        """(time, what) of the latest stops and guarded changes."""
        self._lock = threading.RLock()
        self._closed = threading.Event()
        self._thread: threading.Thread | None = None
        if watchdog_thread:
            self._thread = threading.Thread(target=self._watch, daemon=True, name="watchdog")
            self._thread.start()

    # ------------------------------------------------------------------ interface
    def T_base_flange(self) -> Array:
        return self._pose()

    def T_base_camera(self) -> Array:
        return self._pose() @ self.T_flange_camera

    def T_base_camera_at(self, stamp: float) -> Array:
        """The camera pose when a frame stamped `stamp` (on `clock`) was taken: the pose now,
        unless the robot keeps a pose history (`FrankaRobot`), which is interpolated."""
        return self.T_base_camera()

    def command(self, twist: Any) -> Array:
        """Sends the camera twist, guarded; returns what was sent."""
        with self._lock:
            if self._closed.is_set():
                raise RobotError(f"{self.name}: closed")
            now = self.clock()
            # growth is allowed for the time since the last command, at most the watchdog's
            # (after longer the robot has been stopped); none before the first command
            dt = now - self.last_command_time
            dt = min(dt, self.limits.watchdog) if math.isfinite(dt) else 0.0
            w, note = guard_twist(twist, self.last_sent, dt, self.limits)
            if note:
                self.events.append((now, note))
                if "stopped" in note:
                    log.warning("%s: %s", self.name, note)
            self.last_command_time = now
            if not np.any(w):
                # a refused (non-finite) twist is an explicit stop; a zero twist brakes a moving
                # robot and sends nothing to one at rest
                self._stop_locked(note or "zero twist", force="stopped" in note)
                return w
            self._send(w)
            self.last_sent = w
            self.moving = True
            return w

    def stop(self, reason: str = "stop") -> None:
        with self._lock:
            self._stop_locked(reason)

    def check_watchdog(self) -> bool:
        """Stops the robot when commands stopped coming; True when it did."""
        with self._lock:
            idle = self.clock() - self.last_command_time
            if self.moving and idle > self.limits.watchdog:
                self._stop_locked(f"watchdog: no command for {idle:.3f} s")
                return True
        return False

    def close(self) -> None:
        """Stops the robot and the watchdog."""
        with self._lock:
            if not self._closed.is_set():
                self._stop_locked("close", force=False)
                self._closed.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=1.0)

    def __enter__(self) -> Robot:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ internals
    def _stop_locked(self, reason: str, force: bool = True) -> None:
        """Brakes; a robot that was not moving is sent nothing unless `force` (an explicit
        stop), so a dry run sends no command at all."""
        was_moving = self.moving
        self.last_sent = np.zeros(6)
        self.moving = False
        if was_moving or force:
            self.events.append((self.clock(), f"stop: {reason}"))
            self._halt()

    def _watch(self) -> None:
        period = self.limits.watchdog / 4
        while not self._closed.wait(period):
            try:
                self.check_watchdog()
            except Exception as exc:  # the watchdog must outlive a failing transport
                log.error("%s: watchdog could not stop the robot: %s", self.name, exc)

    @abstractmethod
    def _pose(self) -> Array: ...

    @abstractmethod
    def _send(self, twist: Array) -> None: ...

    @abstractmethod
    def _halt(self) -> None: ...


# ----------------------------------------------------------------------------- Franka
class FrankaTransport(ABC):
    """What `FrankaRobot` needs from a Franka control library."""

    @abstractmethod
    def T_base_flange(self) -> Array:
        """The flange (F) in the robot base (O)."""

    @abstractmethod
    def send_velocity(
        self, linear: Array, angular: Array, T_flange_point: Array, duration: float
    ) -> None:
        """Commands the velocity (base-frame coordinates) of the point `T_flange_point` of the
        hand, held for at most `duration` s, then braked to a stop by the robot."""

    @abstractmethod
    def stop(self) -> None:
        """Brakes to a stop."""

    def close(self) -> None:  # noqa: B027 - optional
        """Releases the connection."""


class FrankyTransport(FrankaTransport):
    """A Franka Panda or FR3 through `franky-control` (libfranka inside; needs the FCI
    activated and, on a real robot, a real-time kernel unless `realtime=False`)."""

    def __init__(self, host: str, dynamics_factor: float = 0.2, realtime: bool = True) -> None:
        try:
            import franky
        except ImportError as exc:
            raise RobotError(
                f"the Franka adapter needs franky-control: pip install 'vinetwin[franka]' ({exc})"
            ) from exc
        self._fr = franky
        cfg = franky.RealtimeConfig.Enforce if realtime else franky.RealtimeConfig.Ignore
        try:
            self.robot = franky.Robot(host, realtime_config=cfg)
            self.robot.relative_dynamics_factor = dynamics_factor
            self.robot.recover_from_errors()
        except Exception as exc:  # franky raises its own exception types
            raise RobotError(f"cannot connect to the Franka at {host}: {exc}") from exc

    def _F_T_EE(self) -> Array:
        return np.asarray(self.robot.state.F_T_EE.matrix, float)

    def T_base_flange(self) -> Array:
        O_T_EE = np.asarray(self.robot.current_cartesian_state.pose.end_effector_pose.matrix)
        return O_T_EE @ invert(self._F_T_EE())

    def send_velocity(
        self, linear: Array, angular: Array, T_flange_point: Array, duration: float
    ) -> None:
        fr = self._fr
        ee_frame = fr.Affine(invert(self._F_T_EE()) @ T_flange_point)
        motion = fr.CartesianVelocityMotion(
            fr.RobotVelocity(fr.Twist(linear, angular)),
            duration=fr.Duration(max(int(duration * 1000), 1)),
            ee_frame=ee_frame,
        )
        try:
            self.robot.move(motion, asynchronous=True)
        except Exception as exc:
            what = f"the Franka refused the velocity command: {exc}"
            if "motion planner failed" in str(exc).lower():
                raise PlannerRefusal(what) from exc
            raise RobotError(what) from exc

    def stop(self) -> None:
        fr = self._fr
        try:
            self.robot.move(fr.CartesianVelocityStopMotion(), asynchronous=True)
        except Exception:
            self.robot.stop()

    def close(self) -> None:
        try:
            self.robot.join_motion()
        except Exception:
            pass


class FrankaRobot(Robot):
    """A Franka arm with the camera on its flange at the twin's `T_flange_camera`. The camera
    twist is sent as the velocity of the camera frame in base coordinates; each command expires
    after `limits.watchdog` s on the robot itself."""

    name = "Franka"

    def __init__(
        self,
        transport: FrankaTransport,
        T_flange_camera: Any,
        limits: CommandLimits | None = None,
        pose_rate: float = 250.0,
    ) -> None:
        self.transport = transport
        self._history: deque[tuple[float, Array]] = deque(maxlen=max(int(pose_rate), 2))
        super().__init__(T_flange_camera, limits)
        self._pose_period = 1.0 / pose_rate if pose_rate > 0 else 0.0
        if self._pose_period:
            self._sampler = threading.Thread(target=self._sample, daemon=True, name="poses")
            self._sampler.start()

    def _sample(self) -> None:
        """Samples the flange pose at `pose_rate` (the last second kept), so each frame gets the
        pose of its capture time, not of its processing time."""
        while not self._closed.wait(self._pose_period):
            try:
                T = self._pose()
            except Exception:  # a failing link is reported by the loop's own reads
                continue
            self._history.append((self.clock(), T))

    def T_base_camera_at(self, stamp: float) -> Array:
        T = pose_at(list(self._history), stamp)
        return self.T_base_camera() if T is None else T @ self.T_flange_camera

    def _pose(self) -> Array:
        T = np.asarray(self.transport.T_base_flange(), float)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise RobotError("the robot reported a non-finite flange pose")
        return T

    def _send(self, twist: Array) -> None:
        for attempt in (1, 2):
            R = (self._pose() @ self.T_flange_camera)[:3, :3]
            try:
                self.transport.send_velocity(
                    R @ twist[:3], R @ twist[3:], self.T_flange_camera, self.limits.watchdog
                )
                return
            except PlannerRefusal as exc:
                # measured on franky-sim: about 1 command in 1000 is refused this way and the
                # next is accepted; two refusals in a row end the run (stop and say why)
                note = f"planner refused a command ({exc}); " + (
                    "sent again" if attempt == 1 else "refused twice: stopping"
                )
                self.events.append((self.clock(), note))
                log.warning("%s: %s", self.name, note)
                if attempt == 2:
                    raise RobotError(f"{self.name}: {note}") from exc

    def _halt(self) -> None:
        self.transport.stop()

    def close(self) -> None:
        super().close()
        self.transport.close()


ROBOTS = ("franka:HOST", "sim", "mujoco", "none")
