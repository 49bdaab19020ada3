"""A D405 rendered from a twin's mesh at a robot's camera pose, streamed like the real camera
(16-bit depth counts through the D405 model): the base of the simulator's camera
(`sim.camera.SimCameraSource`) and, in real time, `RenderedCameraSource`, a stand-in camera for
bringing up a real robot link without a camera (`vinetwin servo --camera render`)."""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from vinetwin.capture.sources import CameraFrame, CameraSource, quantize_depth
from vinetwin.frames import Array, invert
from vinetwin.render.backends import DepthBackend
from vinetwin.render.sensor import SensorConfig, apply_d405_model


class MeshCamera(CameraSource):
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


class RenderedCameraSource(MeshCamera):
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
