"""The simulated arms, behind the same `Robot` interface, command guard and watchdog as the
hardware (`vinetwin.servo.robot`), in simulated time: `KinematicRobot` (a perfect
velocity-controlled camera) and `MujocoRobot` (the D405 on a MuJoCo Panda, `sim.panda`)."""

from __future__ import annotations

from abc import abstractmethod
from typing import Any

import numpy as np

from vinetwin.frames import Array, check_pose, invert, se3_exp
from vinetwin.servo.robot import CommandLimits, Robot


class SimulatedRobot(Robot):
    """A simulated arm in simulated time: `advance(dt)` applies the held twist for dt s (the
    watchdog is checked against simulated time first)."""

    def __init__(self, T_flange_camera: Any, limits: CommandLimits | None = None) -> None:
        self.t = 0.0
        self._held = np.zeros(6)
        self._received = 0.0
        self.lose_next_command = False
        """Fault injection: the next command (twist or stop) never arrives; the arm keeps its
        previous twist until that one expires."""
        self.expire_after: float | None = None
        """A received twist is held at most this long (s), as a Franka's commands are; None:
        until the next command (set with fault injection, where commands can be lost)."""
        super().__init__(T_flange_camera, limits, clock=lambda: self.t, watchdog_thread=False)

    def advance(self, dt: float) -> None:
        self.check_watchdog()
        run = dt
        if self.expire_after is not None:
            run = min(dt, max(0.0, self._received + self.expire_after - self.t))
        if run > 0:
            self._apply(self._held, run)
        self.t += dt

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
    def _apply(self, twist: Array, dt: float) -> None: ...


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
        return self._T @ invert(self.T_flange_camera)

    def T_base_camera(self) -> Array:
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
        return self.arm.pose() @ invert(self.T_flange_camera)

    def T_base_camera(self) -> Array:
        return self.arm.pose()

    def _apply(self, twist: Array, dt: float) -> None:
        if np.any(twist):
            self.arm.move(twist, dt)
