"""The whole pruning job in simulation (`vinetwin prune`): a vine's plan (`plan.job`), then at
each platform stop, for each cut in order: a planned collision-free transit, the ICP-PBVS servo
to the pruning pose (`sim.session.SimSpec`, the one place a simulated servo run is built), the
cut (the tool moves straight in until the robot believes its blade is on the cut point, closes,
and retreats along the same line until the blade is out of the jaw zone and the arm passes the
transit planner's clearance check), then the next cut.

What the robot believes and what is true are kept apart:
- the transit ends where the robot's belief puts the pruning pose; the true camera is off by the
  registration error of the platform's localisation of the vine (the field profile's
  `registration` source, else `SimConfig`'s default 5 mm / 0.02 rad);
- the servo then sees the true vine (and, under the field profile, refers to a reference from a
  reconstructed twin; hand-eye, kinematic, timing, wind and depth errors as `sim.field` draws);
- the straight cut is computed from the servo's last trusted alignment and the robot's hand-eye
  belief, executed by the simulated arm, and judged by the blade's TRUE position against the
  TRUE cut point (swayed by the wind at the moment the blade closes): `blade_error_m`.

Contacts are counted on the actual mesh (Open3D's exact distances to its triangles) for every
collision sphere of the arm, camera and tool (`vinetwin.arm`): along each transit every 20 ms of
its timing, during the servo for the camera, mount and tool at each frame (and the whole arm at
its end), along the cut and the retreat (where the tool may touch the cane within the jaw zone
of its own cut point: the cut). Any other contact is a collision.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np

from vinetwin._config import JsonFields, check_counts
from vinetwin.arm import HOME, STOW
from vinetwin.errors import InputError
from vinetwin.frames import Array, invert, make_pose, so3_exp, so3_log, transform_points
from vinetwin.plan.job import Planner, plan_vine
from vinetwin.plan.job_config import JobConfig
from vinetwin.plan.reach import Collider, CutReach, stop_pose
from vinetwin.plan.sides import far_pose_ids, far_side_twin
from vinetwin.plan.transit import PlanningFailed, plan_transit
from vinetwin.servo.config import ENVELOPE, check_gain
from vinetwin.sim.config import SimConfig, load_profile
from vinetwin.sim.prune_mcap import Track, write_mcap
from vinetwin.sim.prune_sides import merge, summary
from vinetwin.sim.straight import (
    CUT_DT,
    SETTLED_SPEED,
    STRAIGHT_GAIN,
    STRAIGHT_TOLERANCE,
    aimed_cut,
    straight_profile,
)
from vinetwin.twin.model import Twin

SimKind = Literal["kinematic", "mujoco"]
SIM_KINDS: tuple[SimKind, ...] = ("kinematic", "mujoco")
#: Contacts are checked along a transit every this many seconds of its timing.
TRANSIT_CHECK_DT = 0.02
#: The folded arm's clearance is checked every this far (m) along a platform drive.
DRIVE_STEP = 0.05
#: How far (m) a transit's waypoints back the camera off along its optical axis.
BACKOFF = 0.1
#: The retreat ends within this distance (m) of the pruning pose at the latest (earlier once the
#: arm is clear, `_retreat_clear`): the next transit starts from there.
RETREAT_TOLERANCE = 0.005
#: A stow that finds no path is planned again with this many times the planner's time.
STOW_RETRY = 5
#: The arm's rest (s) between the end of the straight move and the blade's closing.
CLOSE_SETTLE = 0.1


@dataclass(frozen=True, kw_only=True)
class PruneConfig(JsonFields):
    """`vinetwin prune`: the simulated arm, the field profile, the servo's time per cut and the
    plan's settings."""

    sim: SimKind = "mujoco"
    """kinematic: a free-flying camera (transits still planned for the arm); mujoco: the D405
    on the MuJoCo Panda."""
    profile: str = "ideal"
    """ideal, field, or a JSON file of `FieldProfile` fields."""
    seed: int = 0
    """Seeds the registration errors, the camera's noise, the field profile's draws, the inverse
    kinematics' random starts and the planner."""
    servo_duration: float = 10.0
    """Longest servo per cut (s, simulated); past it the cut is skipped."""
    servo_settle: float = 0.3
    """The servo must report being at its goal this long (s) before the tool moves in."""
    servo_gain: float = 2.0
    """The servo's lambda at the goal (`ServoConfig.gain`; within the envelope's largest gain).
    Twice the servo's own default: the job starts each servo within a few centimetres of its
    pose and the camera's speed limit bounds the twist, so the faster decay halves the time to
    settle (3.0 to 1.4 s per cut on the VSP vine) with the same blade errors."""
    servo_gain_far: float = 0.8
    """The servo's lambda far from the goal (`ServoConfig.gain_far`), twice its default too."""
    camera_rate: float = 30.0
    """The D405's frame rate; each frame's twist is held one frame period (the servo's compute
    is well under it), so a run's simulated times do not depend on this machine's load."""
    obstacles: Literal["twin", "rebuilt"] = "twin"
    """What the planner keeps the arm clear of: the twin's mesh (the whole vine, as a scan or
    the generator gives it), or, under the field profile's twin source, the reconstructed twin
    its references come from (a capture that may have missed parts of the vine)."""
    job: JobConfig = field(default_factory=JobConfig)

    def __post_init__(self) -> None:
        self._nested_from_dicts()
        if self.obstacles not in ("twin", "rebuilt"):
            raise InputError(f"obstacles must be twin or rebuilt, got {self.obstacles!r}")
        if self.sim not in SIM_KINDS:
            raise InputError(f"unknown sim {self.sim!r}; choose one of: {', '.join(SIM_KINDS)}")
        check_gain(self, ("servo_gain", "servo_gain_far"))
        check_counts(self, ("seed",))
        if not (0.5 <= self.servo_duration <= 120.0) or not (0.0 <= self.servo_settle <= 5.0):
            raise InputError("servo_duration must lie in [0.5, 120] s and servo_settle in [0, 5] s")


@dataclass
class _Contacts:
    """Disallowed contacts: one event per phase and body part that touched."""

    events: list[dict[str, Any]] = field(default_factory=list)

    def check(
        self, collider: Collider, centres: Array, radii: Array, parts: tuple[str, ...],
        phase: str, cut: str, exempt: tuple[Array, float, Array] | None = None,
    ) -> None:  # fmt: skip
        gap, i, what = collider.clearance(centres, radii, exempt, need=0.0)
        if gap < 0:
            key = (phase, cut, parts[i], what)
            if not any(
                (e["phase"], e["cut"], e["part"], e["obstacle"]) == key for e in self.events
            ):
                self.events.append({"phase": phase, "cut": cut, "part": parts[i],
                                    "obstacle": what, "depth_mm": round(-1000 * gap, 2)})  # fmt: skip


class _Job:
    """One vine's job: the twin, the truth and the robot's belief, the arm, the clocks."""

    def __init__(self, twin: Twin, cfg: PruneConfig) -> None:
        from vinetwin.render.backends import raycaster, scene_backend
        from vinetwin.sim.field import (
            field_twin_view_problem,
            reconstructed_twin,
            view_coverages,
        )

        self.twin, self.cfg = twin, cfg
        self.profile = load_profile(cfg.profile)
        top = SimConfig().limits.max_linear
        if cfg.job.cut.approach_speed > top + 1e-12:
            raise InputError(
                f"approach_speed {cfg.job.cut.approach_speed} m/s is above the arm's command "
                f"limit near a vine ({top} m/s, servo.config.Limits.max_linear)"
            )
        true = twin.load_mesh()
        self.V, self.F = np.asarray(true.vertices), np.asarray(true.faces)
        robot_mesh = (self.V, self.F)
        self.reference_backend = None
        self.unshown: dict[str, str] = {}  # pose -> why its reference cannot be made
        if self.profile.on("twin"):
            from vinetwin.mesh import load_mesh

            path, _ = reconstructed_twin(twin, self.profile, cfg.seed, twin.root / "field_twins")
            rm = load_mesh(path)
            robot_mesh = (np.asarray(rm.vertices), np.asarray(rm.faces))
            self.reference_backend = raycaster(rm.vertices, rm.faces, twin.camera)
            # a pose the rebuilt twin missed is skipped by name, as `vinetwin validate` refuses
            # it: its reference would be empty or a fragment, and the servo would lose the vine
            # or settle beside the pose
            views = [p.T_vine_camera for p in twin.poses]
            shares = view_coverages(true, rm, twin.camera, views, twin.perception.max_depth)
            for p, share in zip(twin.poses, shares, strict=True):
                problem = field_twin_view_problem(share, self.profile, p.id)
                if problem:
                    self.unshown[p.id] = problem
        plan_mesh = robot_mesh if cfg.obstacles == "rebuilt" else (self.V, self.F)
        self.planner = Planner.for_twin(twin, cfg.job, mesh=plan_mesh)
        self.truth = Collider(self.V, self.F, cfg.job.platform)
        self.backend = scene_backend(self.V, self.F, twin.camera)
        self.arm = None
        if cfg.sim == "mujoco":
            from vinetwin.sim.panda import PandaArm

            self.arm = PandaArm(T_flange_camera=twin.T_flange_camera, camera=twin.camera,
                                vine=(self.V, self.F))  # fmt: skip
        self.contacts = _Contacts()
        self.track = Track()
        self.transits: list[dict[str, Any]] = []
        #: the joints this stop's transits passed through, in order (`_stow` may retrace them)
        self.trail: list[Array] = []
        self.rng = np.random.default_rng([cfg.seed, 45])
        base = SimConfig()
        from vinetwin.sim.field import registration_error

        self.reg = registration_error(
            self.profile,
            (base.registration_error_translation, base.registration_error_rotation),
        )
        s = self.planner.arm.spheres
        self.tool_mask = np.array([p == "tool" for p in s.part])
        self.flange_fixed = s.frame == 8

    def close(self) -> None:
        self.backend.close()
        if self.reference_backend is not None:
            self.reference_backend.close()

    # --------------------------------------------------------------- bodies
    def _arm_spheres(self, q: Array) -> Array:
        return self.planner.arm.sphere_centres(q)

    def _flange_spheres(self, T_base_camera: Array) -> Array:
        """The flange-fixed spheres (mount, camera, tool) with the camera at T_base_camera."""
        arm = self.planner.arm
        s = arm.spheres
        F = T_base_camera @ invert(arm.T_flange_camera)
        c = s.centre[self.flange_fixed]
        return c @ F[:3, :3].T + F[:3, 3]

    def check_pose(self, q: Array | None, T_base_camera: Array, phase: str, cut: str,
                   exempt_cut: Array | None = None) -> None:  # fmt: skip
        s = self.planner.arm.spheres
        exempt = None
        if q is not None:
            if exempt_cut is not None:
                exempt = (exempt_cut, self.planner.body.jaw_zone, self.tool_mask)
            self.contacts.check(self.truth, self._arm_spheres(q), s.radius, s.part, phase, cut,
                                exempt)  # fmt: skip
        else:
            parts = tuple(p for p, f in zip(s.part, self.flange_fixed, strict=True) if f)
            if exempt_cut is not None:
                exempt = (exempt_cut, self.planner.body.jaw_zone, self.tool_mask[self.flange_fixed])
            self.contacts.check(self.truth, self._flange_spheres(T_base_camera),
                                s.radius[self.flange_fixed], parts, phase, cut, exempt)  # fmt: skip

    # --------------------------------------------------------------- the job
    def run(self) -> dict[str, Any]:
        wall0 = time.perf_counter()
        twin, cfg = self.twin, self.cfg
        plan = plan_vine(twin, self.planner, seed=cfg.seed)
        placed = self.planner.cfg.platform  # its offset and height set from the poses
        planning = plan.planning_s
        cuts: list[dict[str, Any]] = []
        for pid, why in plan.unreachable.items():
            pose = twin.pose(pid)
            cuts.append(_skipped(pose.cut_point, pid, None, why,
                                 twin.cut_point(pose.cut_point).point))  # fmt: skip
        simulated = 0.0
        x_prev: float | None = None
        stopped = ""  # why the job ended early (the arm could not stow for a drive)
        events: list[str] = []
        for x in plan.stops:
            if stopped:
                cuts += [self._skip_all(r, f"the job stopped: {stopped}") for r in plan.order[x]]
                continue
            blocked = self._drive_blocked(x_prev, x, placed)
            if blocked:
                events.append(f"stop {x:+.2f} m skipped: {blocked}")
                cuts += [self._skip_all(r, f"platform: {blocked}") for r in plan.order[x]]
                continue
            drive = 0.0 if x_prev is None else abs(x - x_prev) / placed.drive_speed
            platform = drive + placed.stop_settle
            simulated += platform
            x_prev = x
            B = stop_pose(x, placed)
            self.track.event(f"platform to the stop at {x:+.2f} m")
            self.track.clock += platform
            self.track.pose(self.track.clock, B, B @ self.planner.arm.camera(STOW), STOW)
            self.truth.at_stop(B)
            self.planner.collider.at_stop(B)
            if self.arm is not None:
                self._place_vine(B)
                self.arm.set_q(STOW)
            q = STOW.copy()
            self.trail = []
            for r in plan.order[x]:
                out, q, pl = self._cut(r, B, q)
                out["time_s"] += platform
                out["phases"]["platform"] = platform
                simulated += out["time_s"] - platform
                platform = 0.0
                planning += pl
                cuts.append(out)
            # the arm folds back for the platform's next drive; if it cannot, nothing moves on
            q = np.clip(q, self.planner.arm.lower, self.planner.arm.upper)
            tr, pl = self._stow(q, B)
            planning += pl
            if isinstance(tr, str):
                stopped = f"the arm could not fold back at stop {x:+.2f} m ({tr})"
                events.append(stopped)
                self.track.event(f"stopped: {stopped}", 2)
            else:
                simulated += tr.duration
                self._run_transit(tr, "stow", "")
        wall = time.perf_counter() - wall0
        reached, tol = len(twin.poses) - len(plan.unreachable), cfg.job.cut.max_blade_error
        return {
            "twin": str(twin.root),
            "name": twin.name,
            "config": cfg.to_dict(),
            "plan": plan.to_dict(),
            "cuts": cuts,
            "collisions": len(self.contacts.events),
            "contacts": self.contacts.events,
            "planning_s": planning,
            "reach_planning_s": plan.planning_s,
            "events": events,
            "transits": self.transits,
            "summary": summary(cuts, len(twin.poses), reached, simulated, wall, tol),
        }

    def _skip_all(self, r: CutReach, reason: str) -> dict[str, Any]:
        pose = self.twin.pose(r.pose)
        return _skipped(r.cut, r.pose, r.stop, reason, self.twin.cut_point(pose.cut_point).point)

    def _drive_blocked(self, x0: float | None, x1: float, platform: Any) -> str:
        """Why the platform cannot drive from x0 to x1 with the arm folded (it would touch the
        vine, checked every `DRIVE_STEP` along the way); "" when it can."""
        xs = [x1] if x0 is None else list(np.arange(x0, x1, np.sign(x1 - x0) * DRIVE_STEP)) + [x1]
        for x in xs:
            self.planner.collider.at_stop(stop_pose(float(x), platform))
            if not self.planner.valid(STOW):
                return f"the folded arm would touch the vine at {float(x):+.2f} m along the row"
        return ""

    def _limits(self) -> tuple[Array, Array, Array]:
        a = self.planner.arm
        return a.vmax, a.amax, a.jmax

    def _place_vine(self, T_vine_base: Array) -> None:
        """The MuJoCo scene's vine body where the vine stands in the base at this stop."""
        from vinetwin.conventions import quat_wxyz_from_matrix

        arm = self.arm
        assert arm is not None
        T = invert(T_vine_base)
        arm.T_base_vine = T
        bid = arm.model.body("vine").id
        arm.model.body_pos[bid] = T[:3, 3]
        arm.model.body_quat[bid] = quat_wxyz_from_matrix(T[:3, :3])

    def _stow(self, q: Array, B: Array) -> tuple[Any, float]:
        """The transit that folds the arm for the next drive, and the compute spent planning
        it. Every later stop waits on it, so a planner that finds no path in its time tries
        next the way the arm came (this stop's transits' waypoints backwards, each straight
        segment checked again: among hanging canes a path out is hard to find, the path in is
        known), then searches `STOW_RETRY` times as long, with another seed, before the job
        stops; the reason when it still finds none."""
        cfg, arm = self.cfg, self.planner.arm
        t0 = time.perf_counter()
        why = ""
        once = replace(cfg.job.transit, attempts=1)  # its own retry is the longer search
        for k, transit in enumerate(
            (once, replace(once, timeout=STOW_RETRY * cfg.job.transit.timeout))
        ):
            if k == 0:
                via = self._via(q, STOW, B)
            else:  # the way in, backwards, through the waypoints the planner still passes
                back = [w for w in reversed(self.trail) if self.planner.valid(w)]
                via = [back] if back else []
            try:
                tr = plan_transit(q, STOW, self.planner.valid, arm.lower, arm.upper, self._limits(),
                                  transit, cfg.seed + k, via, self.planner.escape_clear)  # fmt: skip
                return tr, time.perf_counter() - t0
            except PlanningFailed as exc:
                why = str(exc)
                if "configuration collides" in why:
                    break  # no time helps an end that collides
        return why, time.perf_counter() - t0

    def _backed_off(self, q: Array) -> list[Array]:
        """Joints with the camera moved back along its optical axis, BACKOFF and twice that."""
        arm = self.planner.arm
        T = arm.camera(q)
        out = []
        for k in (1, 2):
            Tb = T.copy()
            Tb[:3, 3] -= BACKOFF * k * T[:3, 2]
            qb = arm.solve(Tb, [q])
            if qb is not None:
                out.append(qb)
        return out

    def _via(self, q0: Array, q1: Array, B: Array) -> list[list[Array]]:
        """Waypoint chains a transit tries before the planner: back off from the current pose
        along its optical axis, and into the next along its own; then out, through the arm's
        ready pose (`HOME`) and in."""
        a, b = self._backed_off(q0), self._backed_off(q1)
        chains: list[list[Array]] = []
        for k in range(max(len(a), len(b))):
            chain = ([a[k]] if k < len(a) else []) + ([b[k]] if k < len(b) else [])
            chains.append(chain)
        chains.append([*a[-1:], HOME, *b[-1:]])  # out, through the arm's ready pose, in
        return chains

    def _run_transit(self, tr: Any, phase: str, cut: str) -> None:
        ts, qs = tr.samples(TRANSIT_CHECK_DT)
        arm = self.planner.arm
        B = self.truth.T_vine_base
        self.track.event(f"{phase} {cut}".strip())
        for t, qk in zip(ts, qs, strict=True):
            self.check_pose(qk, arm.camera(qk), phase, cut)
            self.track.pose(self.track.clock + t, B, B @ arm.camera(qk), qk)
        self.track.clock += tr.duration
        if self.arm is not None:
            self.arm.set_q(qs[-1])

    def _cut(self, r: CutReach, B: Array, q: Array) -> tuple[dict[str, Any], Array, float]:
        """Transit, servo, cut, retreat for one pose. Returns (the cut's record, the joints
        after it, planning compute)."""
        twin, cfg = self.twin, self.cfg
        pose = twin.pose(r.pose)
        goal = np.asarray(pose.T_vine_camera, float)
        cut = np.asarray(twin.cut_point(pose.cut_point).point, float)
        arm = self.planner.arm
        phases: dict[str, float] = {}
        if r.pose in self.unshown:
            self.track.event(f"{r.cut} skipped: reference: {self.unshown[r.pose]}", 1)
            return (
                _skipped(r.cut, r.pose, r.stop, f"reference: {self.unshown[r.pose]}", cut),
                q,
                0.0,
            )
        # where the robot's belief takes the camera: the pose, off by the registration error
        E = make_pose(so3_exp(_direction(self.rng) * self.reg[1]),
                      _direction(self.rng) * self.reg[0])  # fmt: skip
        start = goal @ E
        # the arm's IK for where it believes the pose is: near the planned joints, inside the
        # plan's joint margin if it can be, else anywhere inside the limits
        T = invert(B) @ start
        q_goal = arm.solve(T, [r.q_pose], limit_margin=cfg.job.reach.limit_margin)
        if q_goal is None:
            q_goal = arm.solve(T, [r.q_pose], limit_margin=0.0, iterations=400)
        if q_goal is None:
            return _skipped(r.cut, r.pose, r.stop, "the believed pose is out of reach", cut), q, 0.0
        q = np.clip(q, arm.lower, arm.upper)  # a lagging arm may sit a hair past a limit
        via = self._via(q, q_goal, B)
        t0 = time.perf_counter()
        try:
            tr = plan_transit(q, q_goal, self.planner.valid, arm.lower, arm.upper,
                              self._limits(), cfg.job.transit, cfg.seed, via,
                              self.planner.escape_clear)  # fmt: skip
        except PlanningFailed as exc:  # the searches' compute still counts as planning
            self.track.event(f"{r.cut} skipped: transit: {exc}", 1)
            skipped = _skipped(r.cut, r.pose, r.stop, f"transit: {exc}", cut)
            return skipped, q, time.perf_counter() - t0
        phases["planning"] = tr.planning_s
        phases["transit"] = tr.duration
        self.transits.append({"cut": r.cut, "how": tr.how, "planning_s": tr.planning_s,
                              "duration_s": tr.duration, "waypoints": len(tr.waypoints)})  # fmt: skip
        self._run_transit(tr, "transit", r.cut)
        self.trail += tr.waypoints
        out, q_after = self._servo_and_cut(r, pose, goal, start, cut, q_goal, B, phases)
        return out, q_after, tr.planning_s

    def _servo_and_cut(
        self, r: CutReach, pose: Any, goal: Array, start: Array, cut: Array, q: Array,
        B: Array, phases: dict[str, float],
    ) -> tuple[dict[str, Any], Array]:  # fmt: skip
        from vinetwin.render.reference import pose_seed
        from vinetwin.sim.session import SimSpec, SimWorld
        from vinetwin.sim.simulate import simulate

        twin, cfg = self.twin, self.cfg
        sim = SimConfig(variant=pose.icp_variant, duration=cfg.servo_duration,  # type: ignore[arg-type]
                        gain=cfg.servo_gain, gain_far=cfg.servo_gain_far,
                        settle=cfg.servo_settle, seed=int(pose_seed(cfg.seed, pose.id)),
                        profile=self.profile, camera_rate=cfg.camera_rate,
                        fixed_period=1.0 / cfg.camera_rate)  # fmt: skip
        spec = SimSpec(goal, start, sim, pose.id, cut, reference_seed=int(pose_seed(cfg.seed, pose.id)),
                       robot="" if self.arm is not None else None,
                       arm_q=tuple(float(v) for v in q) if self.arm is not None else None)  # fmt: skip
        if self.arm is not None:  # the servo, cut and retreat keep the planned elbow
            self.arm.posture = np.asarray(q, float)
        world = SimWorld(self.backend, twin.perception, self.reference_backend, arm=self.arm,
                         T_flange_camera=twin.T_flange_camera)  # fmt: skip
        self.track.event(f"servo {r.cut}")
        start_clock = self.track.clock  # the session's own clock starts at 0 here
        run = simulate(spec, world, keep=True)
        session = run.session
        for t, T in zip(run.t, run.T, strict=True):
            self.track.pose(start_clock + t, B, T)
        self.track.clock = start_clock + (run.t[-1] if run.t else 0.0)
        try:
            summ = run.summary()
            phases["servo"] = float(run.t[-1]) if run.t else 0.0
            base_from_vine = invert(B)
            for T in run.T[:: max(1, len(run.T) // 60)]:  # camera poses in the vine frame
                self.check_pose(None, base_from_vine @ T, "servo", r.cut)
            if self.arm is not None:
                self.check_pose(self.arm.q, self.arm.pose(), "servo", r.cut)
            # the robot goes on when the servo says it has settled (it cannot see the truth)
            settled = bool(run.t) and run.t[-1] + 1e-6 < cfg.servo_duration
            if run.lost or not settled or session.servo.estimate is None:
                why = run.lost or (
                    f"the servo did not settle in {cfg.servo_duration:g} s "
                    f"({1000 * summ['final_translation']:.1f} mm, "
                    f"{summ['final_rotation']:.3f} rad from the pose)"
                )
                out = _skipped(r.cut, r.pose, r.stop, f"servo: {why}", cut)
                self.track.event(f"{r.cut} skipped: servo: {why}", 1)
                out["time_s"] = _simulated(phases)
                out["phases"] = phases
                return out, self._joints(q, session)
            self.track.event(f"cut {r.cut}")
            blade_error, phases_cut = self._cut_motion(session, run, cut, r.cut, start_clock, B, q)
            phases.update(phases_cut)
            self.track.event(f"{r.cut} done: blade {1000 * blade_error:.2f} mm from the cut")
        finally:
            session.close()
        return {
            "cut": r.cut, "pose": r.pose, "stop": r.stop, "point": cut.tolist(),
            "status": "done", "reason": "",
            "blade_error_m": blade_error, "time_s": _simulated(phases), "phases": phases,
            "servo": {k: summ[k] for k in ("final_translation", "final_rotation", "frames",
                                            "convergence_time")},
        }, self._joints(q, session)  # fmt: skip

    def _joints(self, q: Array, session: Any) -> Array:
        """The arm's joints now: the MuJoCo Panda's, or the IK of the free camera's pose."""
        if self.arm is not None:
            return self.arm.q
        T = session.robot.true_camera()
        B = self.planner.collider.T_vine_base
        qn = self.planner.arm.solve(invert(B) @ T, [q])
        return q if qn is None else qn

    def _cut_motion(
        self, session: Any, run: Any, cut: Array, cut_id: str, clock0: float, B: Array, q: Array
    ) -> tuple[float, dict[str, float]]:
        """Straight in until the robot believes the blade is on the cut (`aimed_cut`), close,
        straight out. Returns the blade's true distance to the true cut point when it closed,
        and the phases' times."""
        robot, source = session.robot, session.source
        arm = self.planner.arm
        cc = self.cfg.job.cut
        aim = aimed_cut(run.believed_cut, cc.aim_window)
        if aim is None:  # (the servo settled, so it trusted frames; kept for safety)
            aim = transform_points(robot.T_base_camera() @ invert(session.servo.estimate),
                                   session.reference.cut[None])[0]  # fmt: skip
        cut_cam = transform_points(invert(robot.T_base_camera()), aim[None])[0]
        # the blade is calibrated in the camera's frame (the D405 sees its tip 7 cm ahead), so
        # the hand-eye error does not enter its offset; it enters the straight move, which the
        # arm executes through its flange
        blade_cam = transform_points(invert(arm.T_flange_camera), arm.blade_flange[None])[0]
        d = cut_cam - blade_cam
        t0 = robot.t
        self._straight(
            robot, d, cc.approach_speed, cut, cut_id, "cut", clock0=clock0, B=B, settle=True
        )
        t_in = robot.t - t0
        robot.stop("closing the shears")
        robot.advance(CLOSE_SETTLE)  # the arm comes to rest as the blades start to close
        T_base_vine = session.T_base_vine
        cam_vine = invert(T_base_vine) @ robot.true_camera()
        blade_true = transform_points(
            cam_vine @ invert(arm.T_flange_camera), arm.blade_flange[None]
        )[0]
        cut_true = transform_points(source.vine_at(robot.t), cut[None])[0]
        error = float(np.linalg.norm(blade_true - cut_true))
        if cc.close_time > CLOSE_SETTLE:
            robot.advance(cc.close_time - CLOSE_SETTLE)
        t1 = robot.t
        # out along the same line, less precisely: the next transit starts wherever it ends
        self.track.event(f"retreat {cut_id}", t=clock0 + robot.t)
        self._straight(robot, -d, cc.approach_speed, cut, cut_id, "retreat", RETREAT_TOLERANCE,
                       clock0, B, until=self._retreat_clear(session, q))  # fmt: skip
        self.track.clock = clock0 + robot.t
        return error, {"cut": t_in, "close": max(cc.close_time, CLOSE_SETTLE),
                       "retreat": robot.t - t1}  # fmt: skip

    def _retreat_clear(self, session: Any, q_pose: Array) -> Callable[[float], bool]:
        """Whether the retreat may end, given how far (m) it has gone: once the blade is past
        the jaw zone and the arm's joints, as the robot reads them, pass the transit planner's
        own check (its clearances on the planning mesh), the next transit takes over from
        there at the arm's speed, planned and checked as every transit is."""
        arm, planner = self.planner.arm, self.planner
        least = planner.body.jaw_zone
        last = [np.asarray(q_pose, float)]  # the free camera's IK seed: the pose's joints

        def clear(moved: float) -> bool:
            if moved < least:
                return False
            if self.arm is not None:
                q = np.asarray(self.arm.q, float)
            else:  # the free camera: the arm's joints for its reported pose
                B = planner.collider.T_vine_base
                q = arm.solve(invert(B) @ session.robot.T_base_camera(), [last[0]])
                if q is None:
                    return False
                last[0] = q
            inside = np.all(q >= arm.lower) and np.all(q <= arm.upper)
            return bool(inside and planner.valid(q))

        return clear

    def _straight(self, robot: Any, d: Array, speed: float, cut: Array, cut_id: str,
                  phase: str, tolerance: float = 0.0, clock0: float = 0.0,
                  B: Array | None = None,
                  until: Callable[[float], bool] | None = None,
                  settle: bool = False) -> None:  # fmt: skip
        """Moves the camera (as the robot believes it) by d in its own frame, as a robot's
        straight move: a trapezoidal profile at `speed` within the command guard's linear
        acceleration (`straight_profile`), its velocity fed forward and the reported pose's
        lag behind it corrected (`STRAIGHT_GAIN`); the orientation held. `until(distance
        moved)` may end it early; with `settle` it ends only once the reported camera is also
        at rest (`SETTLED_SPEED`) on its end."""
        C0 = robot.T_base_camera()
        length = float(np.linalg.norm(d))
        u = d / length if length > 0 else np.zeros(3)
        accel = robot.limits.max_linear_acceleration or ENVELOPE.max_linear_acceleration
        profile, duration = straight_profile(length, speed, accel)
        limit = duration + 2.0
        t0 = robot.t
        # the robot's frame: the base for the Panda, the vine's for the free camera
        to_base = np.eye(4) if self.arm is not None else invert(self.truth.T_vine_base)
        before = None
        while robot.t - t0 < limit:
            M = invert(C0) @ robot.T_base_camera()  # the camera now, in its start frame
            rest = M[:3, :3].T @ (d - M[:3, 3])  # what is left, in the camera frame now
            n = float(np.linalg.norm(rest))
            still = not settle or (
                before is not None and np.linalg.norm(M[:3, 3] - before) < SETTLED_SPEED * CUT_DT
            )
            before = M[:3, 3]
            if n < max(tolerance, STRAIGHT_TOLERANCE) and still:
                break
            if until is not None and until(float(np.linalg.norm(M[:3, 3]))):
                break
            s_des, v_des = profile(robot.t - t0 + CUT_DT)  # where the period ends
            v = v_des * u + STRAIGHT_GAIN * (s_des * u - M[:3, 3])  # start frame
            norm = float(np.linalg.norm(v))
            v = M[:3, :3].T @ (v * min(1.0, speed / norm) if norm > 0 else v)
            w = STRAIGHT_GAIN * so3_log(M[:3, :3].T)  # hold the start's orientation
            robot.command(np.concatenate([v, w]))
            robot.advance(CUT_DT)
            q = self.arm.q if self.arm is not None else None
            T_base_camera = to_base @ robot.true_camera()
            self.check_pose(q, T_base_camera, phase, cut_id, exempt_cut=cut)
            if B is not None:
                self.track.pose(clock0 + robot.t, B, B @ T_base_camera, q)
        robot.stop(f"{phase} done")


def _simulated(phases: dict[str, float]) -> float:
    """A cut's time: its simulated phases (planning is compute, done while the arm works, and
    reported apart as `planning_s`)."""
    return float(sum(v for k, v in phases.items() if k != "planning"))


def _direction(rng: np.random.Generator) -> Array:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def _skipped(
    cut: str, pose: str, stop: float | None, reason: str, point: Any = None
) -> dict[str, Any]:
    return {"cut": cut, "pose": pose, "stop": stop,
            "point": None if point is None else np.asarray(point, float).tolist(),
            "status": "skipped", "reason": reason, "blade_error_m": None, "time_s": 0.0,
            "phases": {}}  # fmt: skip


def prune_twin(
    path: Any, cfg: PruneConfig | None = None, mcap: Path | None = None
) -> dict[str, Any]:
    """One vine's whole job in simulation; its result as plain data (see the module). `mcap`:
    also write the job as a ROS 2 bag with MCAP storage there (`sim.prune_mcap`)."""
    cfg = cfg or PruneConfig()
    twin = Twin.load(path)
    out, track = _pass(twin, cfg)
    far = far_pose_ids(twin) if cfg.job.sides == "both" else []
    far_track = None
    if far:  # the second pass, from the far aisle (`sim.prune_sides`)
        t0 = time.perf_counter()
        far_out, far_track = _pass(far_side_twin(twin, far), cfg)
        far_out["summary"]["wall_s"] = time.perf_counter() - t0  # its twin's making too
        out = merge(out, far_out, twin)
    if mcap is not None:
        write_mcap(Path(mcap), track)
        out["mcap"] = str(mcap)
        if far_track is not None:  # the far pass in its own frame (the vine turned half a turn)
            out["mcap_far_side"] = str(Path(mcap).with_name(Path(mcap).stem + "_far.mcap"))
            write_mcap(Path(out["mcap_far_side"]), far_track)
    return out


def _pass(twin: Twin, cfg: PruneConfig) -> tuple[dict[str, Any], Track]:
    """One pass of the job along the twin's robot side: its result and its track."""
    job = _Job(twin, cfg)
    try:
        return job.run(), job.track
    finally:
        job.close()
