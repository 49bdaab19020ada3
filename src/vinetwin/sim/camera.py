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
from vinetwin.sim.field import FieldDraw
from vinetwin.sim.robots import SimulatedRobot


class SimCameraSource(MeshCamera):
    """The simulator's camera, in simulated time: a frame is taken at once; the next one after
        the loop's processing time (measured from this frame's delivery to the next `read`, or
        `fixed_period`), rounded up to whole camera periods, during which the robot applies the
        twist it was last sent. A disturbance moves the vine. `T` and `T_rel` are the camera's true pose
    now (the run's error is measured on them); under the timing source the frame shows the pose of
    `latency` earlier."""

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
        self.field: FieldDraw | None = None

    def set_field(self, draw: FieldDraw) -> None:
        """The field profile's camera errors (`sim.field.FieldDraw`): timing (latency, stamp
        jitter, dropped frames), wind (the vine sways) and depth (the D405 model's scale error,
        outdoor noise and dropout)."""
        self.field = draw
        if draw.sensor is not None:
            self.sensor = draw.sensor

    def vine_at(self, t: float) -> Array:
        """Where the vine is at simulated time t (its disturbance and wind) in its own frame."""
        return self._vine(t)

    def _vine(self, t: float) -> Array:
        M = self.vine_offset @ self.disturbance.vine_motion(t)
        return M if self.field is None else M @ self.field.vine_wind(t)

    def read(self, timeout: float = 1.0) -> CameraFrame | None:
        robot, f = self.sim_robot, self.field
        if self._delivered is not None:
            compute = time.perf_counter() - self._delivered
            hold = (
                self.fixed_period
                if self.fixed_period > 0
                else self.period * max(1, math.ceil(compute / self.period))
            )
            robot.advance(hold)
            if f is not None and f.drop > 0:  # lost frames: the robot holds its twist meanwhile
                while f.rngs["timing"].random() < f.drop:
                    robot.advance(self.period)
        t = robot.t
        self.T = invert(self.T_base_vine) @ robot.true_camera()
        self.T_rel = invert(self._vine(t)) @ self.T
        stamp, view = t, self.T_rel
        if f is not None and (f.latency > 0 or f.jitter > 0):
            # the frame was exposed `latency` ago and arrives now, its stamp a little off
            exposed = max(t - f.latency, 0.0)
            T_then = invert(self.T_base_vine) @ robot.true_camera_at(exposed)
            view = invert(self._vine(exposed)) @ T_then
            stamp = exposed + (f.rngs["timing"].normal(0, f.jitter) if f.jitter > 0 else 0.0)
        frame = self._frame(view, stamp)
        self._delivered = time.perf_counter()
        return frame

    def now(self) -> float:
        return self.sim_robot.t
