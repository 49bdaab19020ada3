"""The simulation rig, built in one place: where the run starts (`start_pose`), where the robot
believes the goal is (`believed_goal`), and the servo, the simulated arm (a free-flying camera or
the MuJoCo Panda) and the simulated camera that close the loop (`build_rig`). The closed-loop run
(`sim.simulate`), the campaign, the validation, `vinetwin servo --camera sim` and the web app's
validate button all build their runs here."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from vinetwin.camera import CameraModel
from vinetwin.cloud import Cloud, PerceptionConfig
from vinetwin.errors import InputError
from vinetwin.frames import Array, invert, make_pose, so3_exp, transform_points
from vinetwin.render.backends import DepthBackend
from vinetwin.render.sensor import SensorConfig
from vinetwin.servo.config import CommandLimits, RunnerConfig, SafetyConfig
from vinetwin.servo.runner import Session
from vinetwin.servo.step import Servo, make_servo
from vinetwin.sim.camera import SimCameraSource
from vinetwin.sim.config import Disturbance, SimConfig
from vinetwin.sim.robots import KinematicRobot, MujocoRobot, SimulatedRobot
from vinetwin.twin.model import PruningPose, Twin


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


def believed_goal(goal: Array, config: SimConfig, rng: np.random.Generator) -> Array:
    """Where the robot believes the reference camera is: the goal, off by the configured
    registration error, or the platform's under the field profile's registration source (the
    first frame's guess comes from it)."""
    from vinetwin.sim.field import registration_error

    t, r = registration_error(
        config.profile,
        (config.registration_error_translation, config.registration_error_rotation),
    )
    return goal @ make_pose(so3_exp(_random_vector(rng, r)), _random_vector(rng, t))


@dataclass
class Rig:
    """One simulated run's pieces, ready for `servo.loop.run_loop`."""

    servo: Servo
    source: SimCameraSource
    robot: SimulatedRobot
    T_base_vine: Array
    """Where the vine stands in the robot base (the identity for the free-flying camera)."""


def build_rig(
    backend: DepthBackend,
    goal: Array,
    start: Array,
    reference: Cloud,
    perception: PerceptionConfig,
    config: SimConfig,
    rng: np.random.Generator,
    *,
    arm: Any = None,
    T_flange_camera: Array | None = None,
    disturbance: Disturbance | None = None,
    sensor: SensorConfig | None = None,
    safety: SafetyConfig | None = None,
    watchdog: float | None = None,
    cut: Array | None = None,
    dense_reference: Cloud | None = None,
) -> Rig:
    """The servo towards `reference` (rendered at `goal`, a camera pose in the vine frame), its
    first guess off by the configured registration error, a simulated arm whose camera is at
    `start`, and the simulated camera on it.

    With `arm` (a `sim.panda.PandaArm` whose scene holds the vine at `arm.T_base_vine`) the arm
    first reaches the start pose (a start it cannot reach raises InputError); without it the
    camera flies freely. `rng` draws the registration error, then the camera's noise. `cut`
    (the cut point in the vine frame) is the target of the view-keeping law (`--law target`;
    None: the reference cloud's median point)."""
    cfg = config
    target = None if cut is None else transform_points(invert(goal), np.asarray(cut)[None])[0]
    servo = make_servo(
        reference, backend.camera, perception, cfg, cfg.limits, safety, target, dense_reference
    )
    servo.reset(invert(believed_goal(goal, cfg, rng)) @ start)
    limits = CommandLimits.from_dict(
        {**cfg.limits.to_dict(), **({} if watchdog is None else {"watchdog": watchdog})}
    )
    robot: SimulatedRobot
    if arm is None:
        T_base_vine = np.eye(4)
        robot = KinematicRobot(start, T_flange_camera, limits)
    else:
        T_base_vine = np.asarray(arm.T_base_vine, float)
        arm.dynamics = cfg.profile.on("dynamics")
        ok, dt_, dr_ = arm.reach(T_base_vine @ start)
        if not ok:
            raise InputError(
                f"the arm cannot reach the start pose ({1000 * dt_:.1f} mm, {dr_:.3f} rad short)"
            )
        robot = MujocoRobot(arm, limits)
    source = SimCameraSource(
        backend, robot, T_base_vine, rng, sensor=sensor, camera_rate=cfg.camera_rate,
        fixed_period=cfg.fixed_period, disturbance=disturbance,
    )  # fmt: skip
    if cfg.profile.sources:
        from vinetwin.sim.field import draw_field

        draw = draw_field(cfg.profile, cfg.seed, backend.camera)
        robot.set_field(draw)
        source.set_field(draw)
    return Rig(servo, source, robot, T_base_vine)


def _random_vector(rng: np.random.Generator, norm: float) -> Array:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v) * norm


def simulated_session(twin: Twin, pose: PruningPose, cfg: RunnerConfig) -> Session:
    """`vinetwin servo --camera sim`: the simulated D405 on a free-flying camera (`--robot sim`)
    or on the MuJoCo Panda (`--robot mujoco`), from a start `cfg.start_translation` /
    `start_rotation` away from the pruning pose that still sees the cut."""
    from vinetwin.render.backends import get_backend, scene_backend
    from vinetwin.servo.runner import dense_reference_for, reference_cloud, true_error_of
    from vinetwin.sim.config import load_profile

    goal = np.asarray(pose.T_vine_camera, float)
    sim = SimConfig(
        **cfg.servo.to_dict(),
        limits=cfg.limits.speeds(),
        camera_rate=cfg.camera_rate,
        duration=max(cfg.loop.duration, 1e-3),
        seed=cfg.seed,
        profile=load_profile(cfg.profile),
    )
    reference = reference_cloud(twin, pose.id)
    dense = dense_reference_for(twin, pose.id, cfg.servo)
    robot_mesh = None  # the twin the robot has, when it is not the true vine
    mesh = twin.load_mesh()  # the true vine: the scene
    if sim.profile.on("twin"):  # the reference from a reconstructed twin; the scene stays true
        from vinetwin.mesh import load_mesh
        from vinetwin.render.reference import pose_seed, render_reference
        from vinetwin.render.sensor import SensorConfig
        from vinetwin.sim.field import check_field_twin_view, reconstructed_twin

        path, _ = reconstructed_twin(twin, sim.profile, cfg.seed, twin.root / "field_twins")
        rebuilt = load_mesh(path)
        check_field_twin_view(mesh, rebuilt, twin.camera, sim.profile, pose.id, goal)
        robot_mesh = rebuilt
        ref_backend = get_backend("open3d", rebuilt.vertices, rebuilt.faces, twin.camera)
        rendered = render_reference(
            ref_backend, goal, twin.perception, SensorConfig(), pose_seed(0, pose.id)
        )
        reference = rendered.cloud
        if dense is not None:
            from vinetwin.render.reference import dense_cloud
            from vinetwin.servo.config import DENSE_FACTOR

            dense = dense_cloud(rendered.depth, twin.camera, twin.perception, DENSE_FACTOR)
    backend = scene_backend(mesh.vertices, mesh.faces, twin.camera)
    rng = np.random.default_rng(cfg.seed)
    cut = twin.cut_point(pose.cut_point).point
    start = start_pose(
        goal, cut, cfg.start_translation, cfg.start_rotation, rng, twin.camera,
        twin.perception.max_depth,
    )  # fmt: skip
    arm = None
    if cfg.robot == "mujoco":
        from vinetwin.sim.panda import PandaArm, goal_placement

        arm = PandaArm(
            cfg.robot_model or None, T_flange_camera=twin.T_flange_camera, camera=twin.camera,
            vine=(mesh.vertices, mesh.faces), T_base_vine=goal_placement(goal),
        )  # fmt: skip
    rig = build_rig(
        backend, goal, start, reference, twin.perception, sim, rng,
        arm=arm, T_flange_camera=twin.T_flange_camera, watchdog=cfg.limits.watchdog, cut=cut,
        dense_reference=dense,
    )  # fmt: skip
    if cfg.arrival:  # where the robot believes the camera is: its first guess, in the vine frame
        from vinetwin.servo.runner import arrive

        believed = goal @ rig.servo.initial_guess
        try:
            T_vine_camera = arrive(rig.source, twin, believed, robot_mesh or mesh)
        except BaseException:
            rig.source.close()
            raise
        rig.servo.reset(invert(goal) @ T_vine_camera)
    return Session(
        rig.servo,
        rig.source,
        rig.robot,
        cfg.loop,
        rig.T_base_vine @ goal,
        true_error_of(rig.source, goal),
        check_latency=False,
    )
