"""A Franka Emika Panda in MuJoCo with the D405 on its hand, driven by camera twists.

`PandaArm()` loads vinetwin's own model (`servo/assets/panda/`: `panda.xml` written from Franka's
published kinematics, joint position and velocity limits, primitive collision shapes, a `home`
keyframe and a `flange` site; `scene.xml` adds a floor). `PandaArm("path/to/franka_emika_panda")`
loads the MuJoCo Menagerie's Panda instead (its `scene.xml`, or any MJCF file given). Either way
vinetwin adds, with MjSpec:

- a `flange` site on `link7` (0.107 m along its z axis) when the model has none;
- the camera: a body `d405` at `T_flange_camera` (its frame the OpenCV optical frame) with a
  box for the housing, a site `d405` and a MuJoCo camera `d405` (OpenGL convention);
- the vine mesh as a static body at `T_base_vine`, which can collide with the arm.

Control (`move`): the camera twist, expressed in the camera frame, becomes a world twist at the
camera site; joint velocities come from the site's 6x7 Jacobian through a damped pseudo-inverse,
scaled down as a whole to the joint velocity limits, with joints at a position limit not pushed
further. The joints integrate those velocities exactly (a joint velocity controller that tracks
perfectly, as Franka's own does closely); `step_physics` runs MuJoCo's dynamics with the position
actuators holding the current joints, for checking that a scene steps cleanly.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from vinetwin import _lazy
from vinetwin.arm import ACCELERATION_LIMITS, FLANGE_OFFSET, VELOCITY_LIMITS
from vinetwin.camera import CameraModel
from vinetwin.conventions import mujoco_camera_pos_quat, mujoco_fovy_deg, quat_wxyz_from_matrix
from vinetwin.errors import InputError
from vinetwin.frames import Array, invert, make_pose, pose_error, se3_log
from vinetwin.twin.model import DEFAULT_T_FLANGE_CAMERA

PANDA_DIR = Path(__file__).resolve().parent / "assets" / "panda"
ARM_JOINTS = tuple(f"joint{i}" for i in range(1, 8))


def _wxyz(R: Array) -> list[float]:
    return [float(v) for v in quat_wxyz_from_matrix(R)]


#: How fast (1/s) the null space pulls the joints toward a held posture (`PandaArm.posture`).
POSTURE_GAIN = 0.5


class PandaArm:
    """A Panda (vinetwin's or the Menagerie's) carrying the D405, in a MuJoCo scene with the vine."""

    def __init__(
        self,
        model: str | Path | None = None,
        *,
        T_flange_camera: Any = None,
        camera: CameraModel | None = None,
        vine: tuple[Any, Any] | None = None,
        T_base_vine: Any = None,
        damping: float = 0.02,
        limit_avoidance: float = 1.0,
        dynamics: bool = False,
    ) -> None:
        """`dynamics`: `move` tracks the joint velocities through the model's position
        actuators in MuJoCo's physics (acceleration-limited references, the actuators' gains
        and torque limits) instead of integrating them exactly (see `drive`)."""
        mj = _lazy.mujoco()
        path = Path(model) if model else PANDA_DIR / "scene.xml"
        if path.is_dir():
            path = path / "scene.xml"
        if not path.exists():
            raise InputError(f"robot model not found: {path}")
        spec = mj.MjSpec.from_file(str(path))
        try:
            link7 = spec.body("link7")
        except Exception:
            link7 = None
        if link7 is None:
            raise InputError(f"{path}: no body 'link7' (not a Panda model?)")
        T_fc = np.asarray(
            DEFAULT_T_FLANGE_CAMERA if T_flange_camera is None else T_flange_camera, float
        )
        self.T_flange_camera = T_fc
        if spec.site("flange") is None:
            link7.add_site(name="flange", pos=[0, 0, FLANGE_OFFSET], size=[0.01, 0, 0])
        T7c = make_pose(t=[0, 0, FLANGE_OFFSET]) @ T_fc
        # the D405 body: its frame is the optical frame (OpenCV); housing 42 x 42 x 23 mm behind
        # the lens plane
        cam_body = link7.add_body(name="d405", pos=T7c[:3, 3].tolist(), quat=_wxyz(T7c[:3, :3]))
        cam_body.gravcomp = 1.0  # the payload the robot is told it carries
        cam_body.add_site(name="d405", size=[0.008, 0, 0])
        cam_body.add_geom(
            name="d405_housing", type=mj.mjtGeom.mjGEOM_BOX, size=[0.021, 0.021, 0.0115],
            pos=[0, 0, -0.0115], contype=1, conaffinity=0, mass=0.06, rgba=[0.2, 0.2, 0.2, 1],
        )  # fmt: skip
        if camera is not None:
            pos, quat = mujoco_camera_pos_quat(np.eye(4))
            cam_body.add_camera(
                name="d405", pos=list(pos), quat=list(quat),
                fovy=mujoco_fovy_deg(camera.fy, camera.height),
            )  # fmt: skip
        self.T_base_vine = np.eye(4) if T_base_vine is None else np.asarray(T_base_vine, float)
        if vine is not None:
            V = np.asarray(vine[0], dtype=np.float64)
            F = np.asarray(vine[1], dtype=np.int32)
            spec.add_mesh(name="vine", uservert=V.ravel().tolist(), userface=F.ravel().tolist())
            body = spec.worldbody.add_body(
                name="vine",
                pos=self.T_base_vine[:3, 3].tolist(),
                quat=_wxyz(self.T_base_vine[:3, :3]),
            )
            body.add_geom(
                type=mj.mjtGeom.mjGEOM_MESH, meshname="vine", contype=0, conaffinity=1,
                rgba=[0.45, 0.3, 0.2, 1],
            )  # fmt: skip
        self.model = spec.compile()
        self.data = mj.MjData(self.model)
        self._mj = mj
        m = self.model
        self.joint_ids = [m.joint(n).id for n in ARM_JOINTS]
        self.qadr = np.array([m.jnt_qposadr[j] for j in self.joint_ids])
        self.dadr = np.array([m.jnt_dofadr[j] for j in self.joint_ids])
        self.lower = np.array([m.jnt_range[j][0] for j in self.joint_ids])
        self.upper = np.array([m.jnt_range[j][1] for j in self.joint_ids])
        try:
            self.vmax = np.asarray(m.numeric("velocity_limits").data, float)[:7]
        except KeyError:
            self.vmax = np.asarray(VELOCITY_LIMITS)
        self.site = m.site("d405").id
        self.damping = damping
        self.limit_avoidance = limit_avoidance
        self.posture: Array | None = None
        """Joints the redundant degree of freedom holds instead of avoiding the limits (the
        pruning job's planned configuration at a pose, clear of the vine): a pull toward
        them, `POSTURE_GAIN` per second, in the Jacobian's null space. None: limit avoidance."""
        self.amax = np.asarray(ACCELERATION_LIMITS)
        self._q_ref = np.zeros(7)
        self._qd_ref = np.zeros(7)
        self.dynamics = dynamics
        if dynamics and m.nu < 7:
            raise InputError(f"{path}: no joint actuators, so no dynamics in the loop")
        self.reset()

    # ------------------------------------------------------------------ state
    def reset(self) -> None:
        """Back to the `home` keyframe (or zeros)."""
        mj = self._mj
        if self.model.nkey > 0:
            mj.mj_resetDataKeyframe(self.model, self.data, 0)
        else:
            mj.mj_resetData(self.model, self.data)
        mj.mj_forward(self.model, self.data)
        self._sync()

    def _sync(self) -> None:
        """The actuators' references follow the joints, at rest."""
        self._q_ref = self.q
        self._qd_ref = np.zeros(7)
        self.data.qvel[self.dadr] = 0.0

    @property
    def q(self) -> Array:
        return self.data.qpos[self.qadr].copy()

    def set_q(self, q: Any) -> None:
        self.data.qpos[self.qadr] = np.clip(np.asarray(q, float), self.lower, self.upper)
        self._mj.mj_kinematics(self.model, self.data)
        self._mj.mj_comPos(self.model, self.data)
        self._sync()

    def pose(self) -> Array:
        """T_base_camera: the D405's optical frame (OpenCV) in the robot base."""
        return make_pose(
            self.data.site_xmat[self.site].reshape(3, 3), self.data.site_xpos[self.site]
        )

    # ------------------------------------------------------------------ control
    def joint_velocities(self, twist: Any) -> Array:
        """Joint velocities for a camera twist (v, omega) in the camera frame."""
        mj = self._mj
        R = self.data.site_xmat[self.site].reshape(3, 3)
        xi = np.concatenate([R @ np.asarray(twist, float)[:3], R @ np.asarray(twist, float)[3:]])
        jacp = np.zeros((3, self.model.nv))
        jacr = np.zeros((3, self.model.nv))
        mj.mj_jacSite(self.model, self.data, jacp, jacr, self.site)
        J = np.vstack([jacp, jacr])[:, self.dadr]
        q = self.q
        free = np.ones(7, bool)
        qdot = np.zeros(7)
        for _ in range(3):  # joints at a limit that the solution pushes outward are frozen
            Jf = J[:, free]
            qdot = np.zeros(7)
            qdot[free] = Jf.T @ np.linalg.solve(Jf @ Jf.T + self.damping**2 * np.eye(6), xi)
            blocked = ((q <= self.lower + 1e-4) & (qdot < 0)) | (
                (q >= self.upper - 1e-4) & (qdot > 0)
            )
            if not (blocked & free).any():
                break
            free &= ~blocked
        if (self.limit_avoidance > 0 or self.posture is not None) and free.sum() > 6:
            # the redundant degree of freedom keeps the joints off their limits: a push away from
            # each joint's nearer limit, growing as the cube of its normalised distance from the
            # middle of its range, projected into the Jacobian's null space (no camera motion);
            # or, with a posture, a pull toward it (the elbow stays where a plan put it)
            Jf = J[:, free]
            if self.posture is not None:
                push = -POSTURE_GAIN * (q - self.posture)
            else:
                mid, half = (self.upper + self.lower) / 2, (self.upper - self.lower) / 2
                push = -self.limit_avoidance * ((q - mid) / half) ** 3
            N = np.eye(int(free.sum())) - np.linalg.pinv(Jf) @ Jf
            qdot[free] += N @ push[free]
        scale = float(np.max(np.abs(qdot) / self.vmax))
        return qdot / scale if scale > 1 else qdot

    def move(self, twist: Any, dt: float) -> None:
        """Applies the camera twist for dt seconds through the joints: exactly, or with
        `dynamics` through the actuators (`drive`)."""
        if self.dynamics:
            self.drive(twist, dt)
        else:
            self.set_q(self.q + self.joint_velocities(twist) * dt)

    def drive(self, twist: Any, dt: float) -> None:
        """dt seconds of MuJoCo physics with the joint velocities of `twist` as the command:
        each physics step moves the actuators' position references at a velocity that
        approaches the command within the joints' acceleration limits (and their velocity
        limits); the position servos (their gains, damping and torque limits, gravity
        compensated) make the arm follow, with the lag and overshoot that brings."""
        mj = self._mj
        h = float(self.model.opt.timestep)
        steps = max(1, round(dt / h))
        qdot = self.joint_velocities(twist) if np.any(twist) else np.zeros(7)
        # the vine is there to be seen: MuJoCo collides meshes by their convex hull, which holds
        # the camera at its standoff, so contacts are off while driving (`step_physics` checks
        # the scene with them on)
        flags = self.model.opt.disableflags
        self.model.opt.disableflags = flags | int(mj.mjtDisableBit.mjDSBL_CONTACT)
        try:
            self._drive_steps(qdot, h, steps)
        finally:
            self.model.opt.disableflags = flags
        mj.mj_kinematics(self.model, self.data)
        mj.mj_comPos(self.model, self.data)

    def _drive_steps(self, qdot: Array, h: float, steps: int) -> None:
        mj = self._mj
        for _ in range(steps):
            dv = np.clip(qdot - self._qd_ref, -self.amax * h, self.amax * h)
            self._qd_ref = np.clip(self._qd_ref + dv, -self.vmax, self.vmax)
            q_ref = self._q_ref + self._qd_ref * h
            hit = (q_ref <= self.lower) | (q_ref >= self.upper)
            self._qd_ref[hit] = 0.0
            self._q_ref = np.clip(q_ref, self.lower, self.upper)
            self.data.ctrl[:7] = self._q_ref
            mj.mj_step(self.model, self.data)

    def reach(
        self, T_base_camera: Any, iterations: int = 300, tol: float = 1e-4, seeds: int = 24
    ) -> tuple[bool, float, float]:
        """Sets the joints so the camera is at T_base_camera: damped least squares from home,
        then from seeded random configurations within the limits. Returns (reached within
        1 mm / 0.01 rad, translation error m, rotation error rad) of the best try."""
        target = np.asarray(T_base_camera, float)
        rng = np.random.default_rng(0)
        self.reset()
        starts = [self.q] + [rng.uniform(self.lower, self.upper) for _ in range(seeds)]
        best: tuple[float, Array] = (np.inf, starts[0])
        for q0 in starts:
            self.set_q(q0)
            for _ in range(iterations):
                err = se3_log(invert(self.pose()) @ target)
                nt, nr = float(np.linalg.norm(err[:3])), float(np.linalg.norm(err[3:]))
                if nt < tol and nr < tol:
                    break
                # bounded steps: at most 5 cm and 0.2 rad of camera motion each (kinematic: the
                # arm is placed, not driven)
                step = err * min(1.0, 0.05 / max(nt, 1e-12), 0.2 / max(nr, 1e-12))
                self.set_q(self.q + self.joint_velocities(step))
            dt, dr = pose_error(self.pose(), target)
            if dt + 0.1 * dr < best[0]:
                best = (dt + 0.1 * dr, self.q)
            if dt < 1e-3 and dr < 1e-2:
                break
        self.set_q(best[1])
        dt, dr = pose_error(self.pose(), target)
        return bool(dt < 1e-3 and dr < 1e-2), dt, dr

    # ------------------------------------------------------------------ physics
    def step_physics(self, steps: int) -> list[str]:
        """Runs MuJoCo's dynamics with the actuators holding the current joints; returns the
        warnings MuJoCo raised (empty when clean)."""
        mj = self._mj
        if self.model.nu >= 7:
            self.data.ctrl[:7] = self.q
        for _ in range(steps):
            mj.mj_step(self.model, self.data)
        return [
            str(mj.mjtWarning(i)).split(".")[-1]
            for i in range(len(self.data.warning))
            if self.data.warning[i].number > 0
        ]


def goal_placement(
    goal_vine_camera: Any, position: Any = (0.55, 0.0, 0.5), pitch: float = 0.9
) -> Array:
    """T_base_vine that puts a pruning pose's camera at `position` in the robot base, looking
    forward (+x) and `pitch` rad down, the image's x axis to the robot's right: a pose the arm
    reaches with its joints away from their limits, and with room around it for the starts."""
    z = np.array([np.cos(pitch), 0.0, -np.sin(pitch)])
    x = np.array([0.0, -1.0, 0.0])
    R = np.column_stack([x, np.cross(z, x), z])
    return make_pose(R, position) @ invert(np.asarray(goal_vine_camera, float))
