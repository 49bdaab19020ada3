"""A servo session: what one servo run needs (`Session`: the servo, a camera source, a robot,
the loop's settings), and the hardware one built here (`hardware_session`: a live, recorded or
rendered camera with a Franka or no robot). The simulated session is built by
`sim.session.servo_session` from the same `Session`; `servo.runner` (the command) runs either
through `loop.run_loop`. `arrive` is the arrival registration both start with when asked.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from vinetwin.capture.sources import CameraSource
from vinetwin.errors import InputError
from vinetwin.frames import Array, invert
from vinetwin.servo.config import ArrivalConfig, LoopConfig, RunnerConfig
from vinetwin.servo.robot import Robot
from vinetwin.servo.step import Servo, make_servo, wants_dense
from vinetwin.twin.model import PruningPose, Twin

log = logging.getLogger(__name__)


@dataclass
class Session:
    """What one servo run needs: the servo, a camera source, a robot (None: none), the loop's
    settings, and where the goal is in the robot base (for the log)."""

    servo: Servo
    source: CameraSource
    robot: Robot | None
    loop: LoopConfig
    T_base_goal: Array
    true_error: Callable[[], list[float]] | None = None
    """The true camera error now (simulation only), logged with each cycle."""
    check_latency: bool = True
    """False in simulated time: no overrun check."""

    def close(self) -> None:
        if self.robot is not None:
            self.robot.close()
        self.source.close()


def arrive(
    source: CameraSource,
    twin: Twin,
    belief: Array | None,
    mesh: Any = None,
    config: ArrivalConfig | None = None,
) -> Array:
    """Arrival registration (`servo.arrival`) on the source's next frame: the camera's pose in
    the vine frame, from `belief` (T_vine_camera as the robot believes it; None: the frame's
    recorded pose in the twin's world). `mesh`: the twin's mesh (default: loaded). Raises
    ArrivalError, naming why, when the registration refuses: the caller has not moved."""
    from vinetwin.errors import ArrivalError
    from vinetwin.servo.arrival import ArrivalRegistration

    frame = source.read(timeout=5.0)
    if frame is None:
        raise ArrivalError("arrival registration: no frame from the camera in 5 s; nothing moved")
    if belief is None:
        if frame.T_base_camera is None:
            raise ArrivalError(
                "arrival registration needs where the robot believes the camera is: a robot "
                "(franka, sim, mujoco) or a capture folder with recorded poses; nothing moved"
            )
        belief = invert(twin.T_world_vine) @ np.asarray(frame.T_base_camera, float)
    m = mesh if mesh is not None else twin.load_mesh()
    registration = ArrivalRegistration(m.vertices, m.faces, twin.camera, twin.perception, config)
    try:
        depth = frame.counts.astype(np.float32) * np.float32(frame.depth_unit)
        result = registration.register(depth, belief)
    finally:
        registration.close()
    if not result.ok or result.T_vine_camera is None:
        raise ArrivalError(f"arrival registration refused, nothing moved: {result.reason}")
    return result.T_vine_camera


def hardware_session(
    twin: Twin, pose: PruningPose, cfg: RunnerConfig, arrival: ArrivalConfig | None = None
) -> Session:
    """A live, recorded or rendered camera with a Franka or no robot; `arrival`: the arrival
    registration's settings (with `cfg.arrival`; default `ArrivalConfig()`)."""
    from vinetwin.render.reference import reference_for

    robot_kind, _, host = cfg.robot.partition(":")
    reference = reference_for(twin, pose.id, dense=wants_dense(cfg.servo))
    servo = make_servo(reference, twin.camera, twin.perception, cfg.servo, cfg.limits.speeds())
    T_base_ref = twin.T_world_vine @ np.asarray(pose.T_vine_camera, float)
    robot: Robot | None = None
    source: CameraSource | None = None
    try:
        if robot_kind == "franka":
            from vinetwin.servo.robot import FrankaRobot, FrankyTransport

            transport = FrankyTransport(host, cfg.dynamics_factor, cfg.realtime)
            robot = FrankaRobot(transport, twin.T_flange_camera, cfg.limits)
            servo.reset(invert(T_base_ref) @ robot.T_base_camera())
        if cfg.camera == "render":
            from vinetwin.render.backends import raycaster
            from vinetwin.servo.rendered_camera import RenderedCameraSource

            mesh = twin.load_mesh()
            backend = raycaster(mesh.vertices, mesh.faces, twin.camera)
            source = RenderedCameraSource(
                backend, robot, twin.T_world_vine, fps=cfg.fps, seed=cfg.seed
            )
        else:
            from vinetwin.capture.sources import open_source

            source = open_source(
                cfg.camera, camera=twin.camera, width=cfg.width, height=cfg.height,
                fps=cfg.fps, color=cfg.color, rate=cfg.rate,
            )  # fmt: skip
        if robot is None:  # replay: the first frame's recorded pose gives the guess
            first = getattr(source, "capture", None)
            T0 = first.frames[0].T_base_camera if first is not None else None
            if T0 is not None:
                servo.reset(invert(T_base_ref) @ T0)
        _check_camera(twin, source)
        if cfg.arrival:
            belief = None
            if robot is not None:
                belief = invert(twin.T_world_vine) @ robot.T_base_camera()
            T_vine_camera = arrive(source, twin, belief, config=arrival)
            servo.reset(invert(np.asarray(pose.T_vine_camera, float)) @ T_vine_camera)
    except BaseException:
        if robot is not None:
            robot.close()
        if source is not None:
            source.close()
        raise
    return Session(servo, source, robot, cfg.loop, T_base_ref)


def _check_camera(twin: Twin, source: CameraSource) -> None:
    """The live camera must see what the reference was rendered for: same image size and focal
    lengths within 2 %, else the clouds do not compare."""
    a, b = twin.camera, source.camera
    if (a.width, a.height) != (b.width, b.height):
        raise InputError(
            f"the camera streams {b.width}x{b.height} but the twin's references are for "
            f"{a.width}x{a.height}: use --width/--height or re-export with this camera"
        )
    if abs(a.fx - b.fx) > 0.02 * a.fx or abs(a.fy - b.fy) > 0.02 * a.fy:
        log.warning(
            "the camera's focal lengths (%.1f, %.1f) differ from the twin's (%.1f, %.1f) by over "
            "2 %%: set the twin's camera from this device for accurate references",
            b.fx, b.fy, a.fx, a.fy,
        )  # fmt: skip
