"""The simulator's camera: the D405 rendered from the twin's mesh at the simulated robot's
camera pose, in simulated time, with the vine moved by a `Disturbance`."""

from __future__ import annotations

import math
import time

import numpy as np

from vinetwin.capture.sources import CameraFrame
from vinetwin.frames import Array, invert
from vinetwin.render.backends import DepthBackend
from vinetwin.render.sensor import SensorConfig
from vinetwin.servo.rendered_camera import MeshCamera
from vinetwin.sim.config import Disturbance
from vinetwin.sim.robots import SimulatedRobot


class SimCameraSource(MeshCamera):
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
        self.vine_offset = np.eye(4)
        """A rigid jump of the vine on top of the disturbance (fault injection's jerks)."""

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
        self.T_rel = invert(self.vine_offset @ self.disturbance.vine_motion(t)) @ self.T
        frame = self._frame(self.T_rel, t)
        self._delivered = time.perf_counter()
        return frame

    def now(self) -> float:
        return self.sim_robot.t
