"""A simulated servo session, built in one place.

`SimSpec` says what a run is (the goal, the start, the servo and simulation settings with their
field profile and limits, the cut, the disturbance, the reference's noise seed, the arm); its
`setup(world)` builds the session (the servo towards the pose's reference, its first guess off by
the registration error, the simulated arm at the start, the simulated D405 on it) on a `SimWorld`,
the twin's renderers in this process. Every simulated run is built here: `sim.simulate` (the
campaign, the validation, the web app's validate button) and `vinetwin servo --camera sim`
(`servo_session`). `start_pose` draws a start a robot would be given.

The pattern is the one of nerfstudio's `InstantiateConfig`: a frozen, picklable description that
a worker process turns into live objects, so a run is described once and built once.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, replace
from typing import Any

import numpy as np

from vinetwin.camera import CameraModel
from vinetwin.cloud import PerceptionConfig
from vinetwin.errors import InputError
from vinetwin.frames import Array, invert, make_pose, pose_error, so3_exp, transform_points
from vinetwin.render.backends import DepthBackend
from vinetwin.render.reference import Reference, reference_for, render_reference
from vinetwin.render.sensor import SensorConfig
from vinetwin.servo.config import ArrivalConfig, CommandLimits, RunnerConfig
from vinetwin.servo.session import Session, arrive
from vinetwin.servo.step import Servo, make_servo, wants_dense
from vinetwin.sim.camera import SimCameraSource
from vinetwin.sim.config import Disturbance, SimConfig
from vinetwin.sim.robots import KinematicRobot, MujocoRobot, SimulatedRobot
from vinetwin.twin.model import PruningPose, Twin
from vinetwin.twin.poses import DEFAULT_STANDOFF

#: Random directions `start_pose` tries before it settles for the one that sees the cut best.
START_TRIES = 500
#: The nearest depth (m) at which `start_pose` accepts the cut in view; the far end is the
#: perception range less 3 cm.
START_MIN_DEPTH = 0.07


def start_pose(
    goal: Array,
    target: Array,
    offset: tuple[float, float],
    rng: np.random.Generator,
    camera: CameraModel,
    max_depth: float,
) -> Array:
    """A camera pose `offset` = (translation m, rotation rad) away from `goal` that still sees
    `target` (a point in the world, the cut) inside the image and within range: a start a robot
    would be given. Directions are random; the first of `START_TRIES` that sees the target wins
    (else the one that sees it best)."""
    translation, rotation = offset
    best, best_score = None, -math.inf
    for _ in range(START_TRIES):
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
        depth_ok = START_MIN_DEPTH <= p[2] <= max_depth - 0.03
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
class SimWorld:
    """The twin in this process, which a `SimSpec` is built on: the scene's renderer (the true
    vine), the perception settings, and where they apply: the renderer of the reference when it
    is not the scene's (the field profile's reconstructed twin), a reference already at hand (a
    twin's exported one: then nothing is rendered for it), the Panda (`sim.panda.PandaArm`, its
    scene holding the vine at `arm.T_base_vine`; None: the free-flying camera) and the
    hand-eye transform."""

    backend: DepthBackend
    perception: PerceptionConfig
    reference_backend: DepthBackend | None = None
    reference: Reference | None = None
    arm: Any = None
    T_flange_camera: Array | None = None


@dataclass
class SimSession:
    """One simulated run's live pieces, ready for `servo.loop.run_loop`."""

    servo: Servo
    source: SimCameraSource
    robot: SimulatedRobot
    T_base_vine: Array
    """Where the vine stands in the robot base (the identity for the free-flying camera)."""
    reference: Reference

    def close(self) -> None:
        self.source.close()


@dataclass(frozen=True)
class SimSpec:
    """What one simulated run is; `setup(world)` builds it. Poses are camera poses in the vine
    frame."""

    goal: Array
    start: Array
    config: SimConfig = field(default_factory=SimConfig)
    """The servo (variant, law, gains), its limits, the simulated camera and time, the field
    profile, the faults, the seed of the registration error and of the camera's noise."""
    pose_id: str = ""
    cut: Array | None = None
    """The cut point in the vine frame: the view-keeping law's target and the point whose image
    path the run records (None: `DEFAULT_STANDOFF` along the goal camera's axis)."""
    disturbance: Disturbance = field(default_factory=Disturbance)
    reference_seed: int = 0
    """The reference's noise seed (`render.reference.pose_seed`), when it is rendered."""
    robot: str | None = None
    """The arm: None, the free-flying camera; "" vinetwin's Panda; else a Panda model file."""
    watchdog: float | None = None
    """The simulated arm's command watchdog (s; None: the limits' own)."""
    arm_q: tuple[float, ...] | None = None
    """The arm's joints at the start (where a transit left it; `start` must be where they put
    the camera); None: the arm reaches `start` by inverse kinematics."""

    def to_dict(self) -> dict[str, Any]:
        """The run as plain data (its digest's input: a campaign's resumed runs)."""
        out: dict[str, Any] = {}
        for f in fields(self):
            v = getattr(self, f.name)
            if isinstance(v, SimConfig | Disturbance):
                v = v.to_dict()
            elif v is not None and f.name in ("goal", "start", "cut", "arm_q"):
                v = np.asarray(v, float).tolist()
            out[f.name] = v
        return out

    def cut_point(self) -> Array:
        """The cut point (vine frame), or `DEFAULT_STANDOFF` along the goal camera's axis
        without one."""
        if self.cut is not None:
            return np.asarray(self.cut, float)
        goal = np.asarray(self.goal, float)
        return goal[:3, 3] + DEFAULT_STANDOFF * goal[:3, 2]

    def reference_in(self, world: SimWorld) -> Reference:
        """The run's reference: the world's own, else rendered at the goal (with its dense
        cloud when the variant wants one), with the cut in the reference camera frame."""
        goal = np.asarray(self.goal, float)
        cut = transform_points(invert(goal), self.cut_point()[None])[0]
        ref = world.reference
        if ref is None:
            ref = render_reference(
                world.reference_backend or world.backend, goal, world.perception,
                SensorConfig(), self.reference_seed, wants_dense(self.config),
            )  # fmt: skip
        return replace(ref, cut=cut)

    def setup(self, world: SimWorld) -> SimSession:
        """The servo towards the reference, its first guess off by the configured registration
        error, a simulated arm whose camera is at `start`, and the simulated camera on it. With
        the world's arm, the arm first reaches the start (a start it cannot reach raises
        InputError). The run's rng (`config.seed`) draws the registration error, then the
        camera's noise."""
        cfg = self.config
        goal, start = np.asarray(self.goal, float), np.asarray(self.start, float)
        rng = np.random.default_rng(cfg.seed)
        reference = self.reference_in(world)
        servo = make_servo(reference, world.backend.camera, world.perception, cfg, cfg.limits)
        servo.reset(invert(believed_goal(goal, cfg, rng)) @ start)
        watchdog = {} if self.watchdog is None else {"watchdog": self.watchdog}
        limits = CommandLimits.from_dict({**cfg.limits.to_dict(), **watchdog})
        robot: SimulatedRobot
        arm = world.arm
        if arm is None:
            T_base_vine = np.eye(4)
            robot = KinematicRobot(start, world.T_flange_camera, limits)
        else:
            T_base_vine = np.asarray(arm.T_base_vine, float)
            arm.dynamics = cfg.profile.on("dynamics")
            if self.arm_q is not None:
                arm.set_q(self.arm_q)
                ok, dt_, dr_ = True, 0.0, 0.0
            else:
                ok, dt_, dr_ = arm.reach(T_base_vine @ start)
            if not ok:
                raise InputError(
                    f"the arm cannot reach the start pose ({1000 * dt_:.1f} mm, {dr_:.3f} rad "
                    "short)"
                )
            robot = MujocoRobot(arm, limits)
        source = SimCameraSource(
            world.backend, robot, T_base_vine, rng, camera_rate=cfg.camera_rate,
            fixed_period=cfg.fixed_period, disturbance=self.disturbance,
        )  # fmt: skip
        if cfg.profile.sources:
            from vinetwin.sim.field import draw_field

            draw = draw_field(cfg.profile, cfg.seed, world.backend.camera)
            robot.set_field(draw)
            source.set_field(draw)
        return SimSession(servo, source, robot, T_base_vine, reference)


def _random_vector(rng: np.random.Generator, norm: float) -> Array:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v) * norm


def servo_spec(twin: Twin, pose: PruningPose, cfg: RunnerConfig) -> SimSpec:
    """`vinetwin servo --camera sim` as a run: from a start `cfg.start_translation` /
    `start_rotation` away from the pruning pose that still sees the cut (drawn with the run's
    seed), under the command's servo settings, limits, camera rate and field profile."""
    from vinetwin.sim.config import load_profile

    goal = np.asarray(pose.T_vine_camera, float)
    cut = twin.cut_point(pose.cut_point).point
    start = start_pose(
        goal, cut, (cfg.start_translation, cfg.start_rotation), np.random.default_rng(cfg.seed),
        twin.camera, twin.perception.max_depth,
    )  # fmt: skip
    sim = SimConfig(
        **cfg.servo.to_dict(),
        limits=cfg.limits.speeds(),
        camera_rate=cfg.camera_rate,
        duration=max(cfg.loop.duration, 1e-3),
        seed=cfg.seed,
        profile=load_profile(cfg.profile),
    )
    robot = None if cfg.robot == "sim" else cfg.robot_model
    return SimSpec(goal, start, sim, pose.id, cut, robot=robot, watchdog=cfg.limits.watchdog)


def servo_session(
    twin: Twin, pose: PruningPose, cfg: RunnerConfig, arrival: ArrivalConfig | None = None
) -> Session:
    """`vinetwin servo --camera sim`: the simulated D405 on a free-flying camera (`--robot sim`)
    or on the MuJoCo Panda (`--robot mujoco`), servoing to the twin's exported reference (or one
    rendered now; under the field profile's twin source, one rendered from a reconstructed twin
    while the scene stays the true vine); with `cfg.arrival`, the arrival registration first
    (`arrival`: its settings)."""
    from vinetwin.render.backends import scene_backend

    spec = servo_spec(twin, pose, cfg)
    dense = wants_dense(spec.config)
    mesh = twin.load_mesh()  # the true vine: the scene
    robot_mesh = mesh  # the twin the robot has
    if spec.config.profile.on("twin"):  # the reference from a reconstructed twin
        from vinetwin.mesh import load_mesh
        from vinetwin.render.backends import raycaster
        from vinetwin.sim.field import check_field_twin_view, reconstructed_twin

        path, _ = reconstructed_twin(twin, spec.config.profile, cfg.seed, twin.root / "field_twins")
        robot_mesh = load_mesh(path)
        check_field_twin_view(
            mesh, robot_mesh, twin.camera, spec.config.profile, pose.id, spec.goal,
            twin.perception.max_depth,
        )  # fmt: skip
        rebuilt = raycaster(robot_mesh.vertices, robot_mesh.faces, twin.camera)
        try:
            reference = reference_for(
                twin, pose.id, dense=dense, use_exported=False, renderer=rebuilt
            )
        finally:
            rebuilt.close()
    else:
        reference = reference_for(twin, pose.id, dense=dense)
    arm = None
    if spec.robot is not None:
        from vinetwin.sim.panda import PandaArm, goal_placement

        arm = PandaArm(
            spec.robot or None, T_flange_camera=twin.T_flange_camera, camera=twin.camera,
            vine=(mesh.vertices, mesh.faces), T_base_vine=goal_placement(spec.goal),
        )  # fmt: skip
    world = SimWorld(
        scene_backend(mesh.vertices, mesh.faces, twin.camera), twin.perception,
        reference=reference, arm=arm, T_flange_camera=twin.T_flange_camera,
    )  # fmt: skip
    sim = spec.setup(world)
    goal = np.asarray(spec.goal, float)
    if cfg.arrival:  # where the robot believes the camera is: its first guess, in the vine frame
        believed = goal @ sim.servo.initial_guess
        try:
            T_vine_camera = arrive(sim.source, twin, believed, robot_mesh, arrival)
        except BaseException:
            sim.close()
            raise
        sim.servo.reset(invert(goal) @ T_vine_camera)
    source = sim.source
    return Session(
        sim.servo, source, sim.robot, cfg.loop, sim.T_base_vine @ goal,
        lambda: list(pose_error(source.T_rel, goal)), check_latency=False,
    )  # fmt: skip
