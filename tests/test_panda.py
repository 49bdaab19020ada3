"""The MuJoCo Panda: kinematics against Franka's DH parameters, the Jacobian control, joint limits,
every scene stepping cleanly, the Menagerie Panda servoing."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tests.conftest import VineViews, shared
from vinetwin import _lazy
from vinetwin import frames as fr
from vinetwin.sim.config import SimConfig
from vinetwin.sim.panda import PANDA_DIR, PandaArm, goal_placement
from vinetwin.sim.session import SimSpec, SimWorld, start_pose
from vinetwin.sim.simulate import simulate

# Franka's published (modified) DH parameters: a, d, alpha per joint, then the flange
DH = [
    (0.0, 0.333, 0.0),
    (0.0, 0.0, -math.pi / 2),
    (0.0, 0.316, math.pi / 2),
    (0.0825, 0.0, math.pi / 2),
    (-0.0825, 0.384, -math.pi / 2),
    (0.0, 0.0, math.pi / 2),
    (0.088, 0.0, math.pi / 2),
]


def dh_flange(q: np.ndarray) -> np.ndarray:
    def link(a: float, d: float, al: float, th: float) -> np.ndarray:
        ca, sa, ct, st = math.cos(al), math.sin(al), math.cos(th), math.sin(th)
        return np.array(
            [
                [ct, -st, 0, a],
                [st * ca, ct * ca, -sa, -d * sa],
                [st * sa, ct * sa, ca, d * ca],
                [0, 0, 0, 1],
            ]
        )

    T = np.eye(4)
    for (a, d, al), th in zip(DH, q, strict=True):
        T = T @ link(a, d, al, th)
    return T @ link(0.0, 0.107, 0.0, 0.0)


def test_forward_kinematics_match_franka_dh() -> None:
    arm = PandaArm()
    m, d = arm.model, arm.data
    flange = m.site("flange").id
    rng = np.random.default_rng(0)
    for _ in range(20):
        q = rng.uniform(arm.lower, arm.upper)
        arm.set_q(q)
        T = dh_flange(q)
        np.testing.assert_allclose(d.site_xpos[flange], T[:3, 3], atol=1e-12)
        np.testing.assert_allclose(d.site_xmat[flange].reshape(3, 3), T[:3, :3], atol=1e-12)
    # the camera sits at T_flange_camera on the flange
    arm.set_q(rng.uniform(arm.lower, arm.upper))
    T_fc = (
        fr.invert(fr.make_pose(d.site_xmat[flange].reshape(3, 3), d.site_xpos[flange])) @ arm.pose()
    )
    from vinetwin.twin.model import DEFAULT_T_FLANGE_CAMERA

    np.testing.assert_allclose(T_fc, DEFAULT_T_FLANGE_CAMERA, atol=1e-12)


def test_joint_velocities_produce_the_camera_twist() -> None:
    """Finite differences: moving the joints by qdot dt moves the camera by twist dt."""
    arm = PandaArm()
    arm.set_q([0.1, -0.3, 0.2, -2.0, 0.1, 1.8, 0.5])
    twist = np.array([0.02, -0.01, 0.015, 0.05, -0.03, 0.04])
    T0 = arm.pose()
    dt = 1e-4
    arm.move(twist, dt)
    measured = fr.se3_log(fr.invert(T0) @ arm.pose()) / dt
    np.testing.assert_allclose(measured, twist, atol=2e-3 * np.linalg.norm(twist))


def test_joint_limits_and_velocity_limits_hold() -> None:
    arm = PandaArm()
    for _ in range(200):  # a long push in one direction drives some joints to their limits
        arm.move([0.5, 0.0, 0.0, 0.0, 0.0, 2.0], 0.05)
        q = arm.q
        assert np.all(q >= arm.lower - 1e-12) and np.all(q <= arm.upper + 1e-12)
    qdot = arm.joint_velocities([10.0, 0, 0, 0, 0, 0])  # far beyond what the joints can do
    assert np.all(np.abs(qdot) <= arm.vmax + 1e-9)


def scenes(views: VineViews) -> dict[str, object]:
    """Every MuJoCo scene of the project, compiled."""
    mj = _lazy.mujoco()
    from vinetwin.render.backends.mujoco_gl import vine_scene_xml

    mesh = views.twin.load_mesh()
    xml, assets = vine_scene_xml(
        np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces, np.uint32), views.twin.camera
    )
    goal = views.twin.poses[0].T_vine_camera
    return {
        "panda.xml": mj.MjModel.from_xml_path(str(PANDA_DIR / "panda.xml")),
        "scene.xml": mj.MjModel.from_xml_path(str(PANDA_DIR / "scene.xml")),
        "render scene": mj.MjModel.from_xml_string(xml, assets),
        "servo scene": PandaArm(
            camera=views.twin.camera,
            vine=(mesh.vertices, mesh.faces),
            T_base_vine=goal_placement(goal),
        ).model,
    }


def test_every_scene_compiles_and_steps_without_warnings(vine_views: VineViews) -> None:
    mj = _lazy.mujoco()
    for name, model in scenes(vine_views).items():
        data = mj.MjData(model)
        if model.nkey:
            mj.mj_resetDataKeyframe(model, data, 0)
        for _ in range(500):
            mj.mj_step(model, data)
        warned = [i for i in range(len(data.warning)) if data.warning[i].number]
        assert warned == [], (name, [str(mj.mjtWarning(i)) for i in warned])
        assert np.all(np.isfinite(data.qpos)), name
    # the arm holds its home pose under its actuators (gravity compensated)
    arm = PandaArm()
    home = arm.q
    assert arm.step_physics(1000) == []
    np.testing.assert_allclose(arm.q, home, atol=2e-3)


@pytest.mark.parametrize("robot", ["vinetwin", "menagerie"])
def test_panda_servos_to_the_pruning_pose(vine_views: VineViews, robot: str) -> None:
    model = None if robot == "vinetwin" else shared("robots", "franka_emika_panda")
    twin = vine_views.twin
    mesh = twin.load_mesh()
    pose = twin.poses[0]
    goal = pose.T_vine_camera
    cut = twin.cut_point(pose.cut_point).point
    arm = PandaArm(
        model,
        T_flange_camera=twin.T_flange_camera,
        camera=twin.camera,
        vine=(mesh.vertices, mesh.faces),
        T_base_vine=goal_placement(goal),
    )
    start = start_pose(goal, cut, (0.05, 0.15), np.random.default_rng(3), twin.camera, 0.4)
    cfg = SimConfig(variant="symmetric", duration=12.0, fixed_period=1 / 30)
    run = simulate(
        SimSpec(goal, start, cfg, reference_seed=1),
        SimWorld(vine_views.backend, twin.perception, arm=arm),
    )
    s = run.summary()
    assert s["converged"], s
    assert s["final_translation"] < 0.002 and s["final_rotation"] < 0.01
    q = arm.q
    assert np.all(q >= arm.lower) and np.all(q <= arm.upper)


def test_redundancy_keeps_joints_off_their_limits() -> None:
    """The seventh joint's freedom pushes a joint near its limit back towards the middle of its
    range without moving the camera: the camera twist is the one commanded, the same with or
    without the push, and joints 1 and 3 (each at 90% of its half-range in turn) are driven
    back towards the middle only with it."""
    twist = np.array([0.02, -0.01, 0.015, 0.05, -0.03, 0.04])
    for j in (0, 2):
        arm = PandaArm()
        q0 = np.array([0.1, -0.3, 0.2, -2.0, 0.1, 1.8, 0.5])
        q0[j] = (arm.upper[j] + arm.lower[j]) / 2 + 0.9 * (arm.upper[j] - arm.lower[j]) / 2
        moved, speed = {}, {}
        for k in (0.0, 1.0):
            arm = PandaArm(limit_avoidance=k)
            arm.set_q(q0)
            T0, dt = arm.pose(), 1e-4
            speed[k] = arm.joint_velocities(twist)[j]
            arm.move(twist, dt)
            moved[k] = fr.se3_log(fr.invert(T0) @ arm.pose()) / dt
            np.testing.assert_allclose(moved[k], twist, atol=1e-2 * np.linalg.norm(twist))  # DLS
        np.testing.assert_allclose(moved[1.0], moved[0.0], atol=1e-4 * np.linalg.norm(twist))
        assert speed[1.0] < speed[0.0] - 0.2, (j, speed)  # away from the upper limit


def test_dynamics_track_the_commanded_twist_through_the_actuators() -> None:
    """With dynamics the joints follow the command through MuJoCo's physics: at rest the arm
    holds (gravity compensated, the D405 included); a 2 cm/s twist held for 1 s moves the
    camera less than the 20 mm an exact integration gives (the references ramp within the
    acceleration limits and the servos lag), and most of the rest arrives after the command
    stops; no joint ever exceeds its velocity limit; an exact arm moves the full 20 mm."""
    q0 = np.array([0.1, -0.3, 0.2, -2.0, 0.1, 1.8, 0.5])
    twist = np.array([0.02, 0.0, 0.0, 0.0, 0.0, 0.0])
    moved = {}
    for dynamics in (False, True):
        arm = PandaArm(dynamics=dynamics)
        arm.set_q(q0)
        T0 = arm.pose()
        for _ in range(15):
            arm.move(np.zeros(6), 1 / 30)
        hold = fr.pose_error(arm.pose(), T0)
        assert hold[0] < 5e-5 and hold[1] < 5e-4, hold
        speeds = []
        for _ in range(30):
            arm.move(twist, 1 / 30)
            speeds.append(np.abs(arm.data.qvel[arm.dadr]) / arm.vmax)
        during = float((fr.invert(T0) @ arm.pose())[0, 3])
        for _ in range(15):
            arm.move(np.zeros(6), 1 / 30)
        moved[dynamics] = (during, float((fr.invert(T0) @ arm.pose())[0, 3]))
        assert max(float(s.max()) for s in speeds) <= 1.0
    np.testing.assert_allclose(moved[False], (0.02, 0.02), atol=2e-4)
    during, after = moved[True]
    assert 0.012 < during < 0.0195, during  # lagging
    assert abs(after - 0.02) < 0.0015, after  # and catching up once the command stops
