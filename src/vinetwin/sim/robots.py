"""The simulated arms, behind the same `Robot` interface, command guard and watchdog as the
hardware (`vinetwin.servo.robot`), in simulated time: `KinematicRobot` (a perfect
velocity-controlled camera) and `MujocoRobot` (the D405 on a MuJoCo Panda, `sim.panda`)."""

from __future__ import annotations

from abc import abstractmethod
from collections import deque
from typing import Any

import numpy as np

from vinetwin.frames import Array, check_pose, invert, make_pose, se3_exp, skew, so3_exp
from vinetwin.servo.robot import CommandLimits, Robot, pose_at


class SimulatedRobot(Robot):
    """A simulated arm in simulated time: `advance(dt)` applies the held twist for dt s (the
    watchdog is checked against simulated time first).

    The field profile's robot errors (`sim.field.FieldDraw`, `set_field`): the pose the robot
    reports (`T_base_camera`, what the servo reads) is the true camera pose (`true_camera`,
    what the simulated camera sees) times the hand-eye error, its motion since the start scaled
    by the kinematic error, with encoder noise on each reading; a commanded twist moves the
    frame the robot believes is the camera. `T_base_camera_at(stamp)` interpolates the reported
    poses of the past second (frames arrive late under the timing source)."""

    def __init__(self, T_flange_camera: Any, limits: CommandLimits | None = None) -> None:
        self.t = 0.0
        self._field: Any = None
        self._origin: Array | None = None
        self._history: deque[tuple[float, Array]] = deque(maxlen=200)
        """(t, true camera pose) after each advance, under a field profile (the reported pose
        is derived from it)."""
        self._held = np.zeros(6)
        self._received = 0.0
        self.lose_next_command = False
        """Fault injection: the next command (twist or stop) never arrives; the arm keeps its
        previous twist until that one expires."""
        self.expire_after: float | None = None
        """A received twist is held at most this long (s), as a Franka's commands are; None:
        until the next command (set with fault injection, where commands can be lost)."""
        super().__init__(T_flange_camera, limits, clock=lambda: self.t, watchdog_thread=False)

    def set_field(self, draw: Any) -> None:
        """Applies a `sim.field.FieldDraw`'s robot errors from now on."""
        self._field = draw
        self._origin = self.true_camera()
        self._history.clear()
        self._remember()

    def true_camera(self) -> Array:
        """T_base_camera as it really is (the simulated camera renders from it)."""
        return self._true_camera()

    def _believed(self, T: Array) -> Array:
        f = self._field
        if f is None:
            return T
        if self._origin is not None and np.any(f.scale):
            T = T.copy()
            o = self._origin[:3, 3]
            T[:3, 3] = o + (1.0 + f.scale) * (T[:3, 3] - o)
        return T @ f.hand_eye

    def _remember(self) -> None:
        self._history.append((self.t, self.true_camera()))

    def true_camera_at(self, t: float) -> Array:
        """The true camera pose at simulated time t (within the kept history; else now)."""
        T = pose_at(self._history, t)
        return self.true_camera() if T is None else T

    def T_base_camera(self) -> Array:
        return self._read(self._believed(self.true_camera()))

    def T_base_camera_at(self, stamp: float) -> Array:
        T = pose_at(self._history, stamp)
        return self.T_base_camera() if T is None else self._read(self._believed(T))

    def _read(self, T: Array) -> Array:
        """A reading of the reported pose: with encoder noise under the kinematics source."""
        f = self._field
        if f is None or not (f.encoder[0] or f.encoder[1]):
            return T
        g = f.rngs["kinematics"]
        return T @ make_pose(so3_exp(g.normal(0, f.encoder[1], 3)), g.normal(0, f.encoder[0], 3))

    def advance(self, dt: float) -> None:
        self.check_watchdog()
        run = dt
        if self.expire_after is not None:
            run = min(dt, max(0.0, self._received + self.expire_after - self.t))
        if run > 0:
            twist = self._held
            if self._field is not None:  # the twist moves the believed camera frame
                twist = adjoint(self._field.hand_eye) @ twist
            self._apply(twist, run)
        if run < dt:
            self._coast(dt - run)
        self.t += dt
        if self._field is not None:
            self._remember()

    def _receive(self, twist: Array) -> None:
        if self.lose_next_command:
            self.lose_next_command = False
            return
        self._held = twist
        self._received = self.t

    def _send(self, twist: Array) -> None:
        self._receive(twist.copy())

    def _halt(self) -> None:
        self._receive(np.zeros(6))

    @abstractmethod
    def _apply(self, twist: Array, dt: float) -> None:
        """Moves the true camera by the body twist for dt s."""

    def _coast(self, dt: float) -> None:  # a kinematic arm stops at once
        """dt s without a command (after the watchdog's expiry)."""

    @abstractmethod
    def _true_camera(self) -> Array: ...


def adjoint(T: Array) -> Array:
    """The 6x6 adjoint of T for twists (v, omega): a body twist of the frame F @ T is the body
    twist adjoint(T) @ xi of F."""
    R, p = T[:3, :3], T[:3, 3]
    A = np.zeros((6, 6))
    A[:3, :3] = A[3:, 3:] = R
    A[:3, 3:] = skew(p) @ R
    return A


class KinematicRobot(SimulatedRobot):
    """A perfect velocity-controlled camera: its pose integrates the twist exactly."""

    name = "kinematic camera"

    def __init__(
        self,
        T_base_camera: Any,
        T_flange_camera: Any = None,
        limits: CommandLimits | None = None,
    ) -> None:
        T_fc = np.eye(4) if T_flange_camera is None else T_flange_camera
        super().__init__(T_fc, limits)
        self._T = check_pose(T_base_camera, "T_base_camera").copy()

    def _pose(self) -> Array:
        return self.T_base_camera() @ invert(self.T_flange_camera)

    def _true_camera(self) -> Array:
        return self._T.copy()

    def _apply(self, twist: Array, dt: float) -> None:
        self._T = self._T @ se3_exp(twist * dt)


class MujocoRobot(SimulatedRobot):
    """The Panda of `sim.panda.PandaArm` (its D405 at the arm's own hand-eye transform)."""

    name = "MuJoCo Panda"

    def __init__(self, arm: Any, limits: CommandLimits | None = None) -> None:
        self.arm = arm
        T_fc = np.asarray(arm.T_flange_camera, float)
        super().__init__(T_fc, limits)

    def _pose(self) -> Array:
        return self.T_base_camera() @ invert(self.T_flange_camera)

    def _true_camera(self) -> Array:
        return self.arm.pose()

    def _apply(self, twist: Array, dt: float) -> None:
        if np.any(twist) or self.arm.dynamics:  # with dynamics a stop takes time too
            self.arm.move(twist, dt)

    def _coast(self, dt: float) -> None:
        if self.arm.dynamics:
            self.arm.move(np.zeros(6), dt)
