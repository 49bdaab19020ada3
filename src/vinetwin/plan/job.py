"""A vine's pruning plan (`plan_vine`): for every pruning pose, the platform stops from which the
arm reaches it and its straight approach; the fewest stops that cover them; each pose done from
the chosen stop that reaches it best; the order at each stop; the poses no stop reaches, with
the reason. Transits between the poses are planned when the job runs (`plan.transit`), from
wherever the arm is after the previous cut."""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from vinetwin.arm import DH, STOW, ArmModel
from vinetwin.errors import InputError
from vinetwin.frames import Array
from vinetwin.plan.config import BodyConfig
from vinetwin.plan.job_config import JobConfig, placed
from vinetwin.plan.reach import (
    Collider,
    CutReach,
    VinePlan,
    candidate_stops,
    choose_stops,
    order_cuts,
    reach_cut,
    stop_pose,
)
from vinetwin.twin.model import Twin
from vinetwin.twin.poses import from_far_side

#: Stops tried per pose, nearest first, stop once this many reach it (the set cover rarely
#: needs more choice than that, and the stops beyond cost most: their IK fails).
MAX_STOPS_PER_POSE = 5
#: The clearance (m) a transit keeps, links and hand, where it leaves or reaches an end inside
#: the margins: more than half of what a sphere moves between two of its finer checks.
ESCAPE_CLEARANCE = 0.002


@dataclass
class Planner:
    """What a plan is made with: the arm model, the obstacles and the settings."""

    arm: ArmModel
    collider: Collider
    cfg: JobConfig
    body: BodyConfig

    @classmethod
    def for_twin(
        cls,
        twin: Twin,
        cfg: JobConfig | None = None,
        body: BodyConfig | None = None,
        mesh: Any = None,
    ) -> Planner:
        """The twin's arm (its hand-eye and tool transforms) among its mesh (or `mesh`: the
        vertices and faces the robot believes)."""
        cfg = cfg or JobConfig()
        body = body or BodyConfig()
        if mesh is None:
            m = twin.load_mesh()
            mesh = (m.vertices, m.faces)
        arm = ArmModel(twin.T_flange_camera, twin.T_flange_tool, tool_radius=body.tool_radius)
        return cls(arm, Collider(mesh[0], mesh[1], cfg.platform), cfg, body)

    def valid(self, q: Array) -> bool:
        """Joints q clear of every obstacle at the current stop: the links by
        `reach.clearance`, the hand (mount, camera, tool) by the body's margin."""
        return self.collider.arm_clear(self.arm, q, self.cfg.reach.clearance, self.body.margin)

    def escape_clear(self, q: Array) -> bool:
        """Joints q clear of the vine by `ESCAPE_CLEARANCE` (the same conservative check,
        without the margins): how a transit may leave or reach a configuration inside them
        (`transit.plan_transit`, which then checks its path five times as finely)."""
        return self.collider.arm_clear(self.arm, q, ESCAPE_CLEARANCE, ESCAPE_CLEARANCE)


#: Why a stop is not used: the platform drives with the arm folded (`STOW`), and at this stop
#: the folded arm would touch the vine.
STOW_BLOCKED = "the folded arm would touch the vine at the stop"


def plan_vine(
    twin: Twin, planner: Planner, pose_ids: list[str] | None = None, seed: int = 0
) -> VinePlan:
    """The plan for the twin's pruning poses (or `pose_ids`); `seed` seeds the inverse
    kinematics' random starts. The planner's platform is placed first (`job_config.placed`):
    `planner.cfg` keeps it, for the job that follows."""
    t0 = time.perf_counter()
    cfg = planner.cfg
    poses = twin.poses if pose_ids is None else [twin.pose(p) for p in pose_ids]
    if not poses:
        raise InputError(
            f"{twin.root}: the twin has no pruning poses; add some with `vinetwin propose`, "
            "`vinetwin poses` or the web app"
        )
    rng = np.random.default_rng(seed)
    plan = VinePlan()
    near = [p for p in poses if not from_far_side(p.T_vine_camera)]
    for p in poses:
        if p not in near:
            plan.unreachable[p.id] = (
                "the pose looks at the row from its other side (+Y): prune it from there "
                "(`vinetwin prune --sides both`)"
            )
    poses = near
    cfg = replace(cfg, platform=placed(
        cfg.platform, [tuple(np.asarray(p.T_vine_camera, float)[:3, 3]) for p in poses]))  # fmt: skip
    planner.cfg = cfg
    plan.platform = cfg.platform.to_dict()
    poses = _within_reach(poses, cfg, planner.arm, plan)
    reach: dict[str, dict[float, CutReach]] = {}
    reasons: dict[str, dict[str, int]] = {}
    where: dict[str, tuple[Array, Array]] = {}
    stowed: dict[float, bool] = {}  # whether the folded arm is clear of the vine at a stop
    for pose in poses:
        cut = twin.cut_point(pose.cut_point).point
        T = np.asarray(pose.T_vine_camera, float)
        where[pose.id] = (T, cut)
        stops = candidate_stops([float(cut[0])], cfg)
        stops.sort(key=lambda s: abs(s - float(T[0, 3])))
        found: dict[float, CutReach] = {}
        why: dict[str, int] = {}
        warm: list[Array] = []
        for s in stops:
            if len(found) >= MAX_STOPS_PER_POSE:
                break
            T_vine_base = stop_pose(s, cfg.platform)
            planner.collider.at_stop(T_vine_base)
            plan.tried += 1
            if s not in stowed:
                stowed[s] = planner.valid(STOW)
            if not stowed[s]:  # the platform arrives, and leaves, with the arm folded
                why[STOW_BLOCKED] = why.get(STOW_BLOCKED, 0) + 1
                continue
            r = reach_cut(
                planner.arm, planner.collider, T, cut, T_vine_base, cfg, planner.body.margin,
                planner.body.jaw_zone, warm, rng, approach=False,
            )  # fmt: skip
            if isinstance(r, str):
                why[r] = why.get(r, 0) + 1
                continue
            warm = [r[0]]
            found[s] = CutReach(pose.cut_point, pose.id, s, *r)
        reach[pose.id] = found
        reasons[pose.id] = why
    # the straight approach is checked only where the cover uses a stop (the pose's own checks
    # decide nearly every stop): one that fails drops that stop for the pose, and the cover is
    # made again
    checked: set[tuple[str, float]] = set()
    while True:
        plan.stops = choose_stops(reach)
        dropped = False
        for pid, by_stop in reach.items():
            here = [s for s in plan.stops if s in by_stop]
            if not here:
                continue
            best = max(here, key=lambda s: by_stop[s].manipulability)
            if (pid, best) in checked:
                continue
            checked.add((pid, best))
            T_vine_base = stop_pose(best, cfg.platform)
            planner.collider.at_stop(T_vine_base)
            r = reach_cut(
                planner.arm, planner.collider, *where[pid], T_vine_base, cfg,
                planner.body.margin, planner.body.jaw_zone, [by_stop[best].q_pose], rng,
            )  # fmt: skip
            if isinstance(r, str):
                reasons[pid][r] = reasons[pid].get(r, 0) + 1
                del by_stop[best]
                dropped = True
            else:
                by_stop[best] = CutReach(by_stop[best].cut, pid, best, *r)
        if not dropped:
            break
    for pid, found in reach.items():
        if not found:
            why = reasons[pid]
            common = max(why, key=lambda k: why[k]) if why else "no stop within reach"
            plan.unreachable[pid] = f"no platform stop reaches it ({common})"
    for s in plan.stops:
        plan.order[s] = []
    for by_stop in reach.values():
        here = [s for s in plan.stops if s in by_stop]
        if here:
            best = max(here, key=lambda s: by_stop[s].manipulability)
            plan.order[best].append(by_stop[best])
    for s in plan.stops:
        plan.order[s] = order_cuts(STOW, plan.order[s], planner.arm.vmax)
        _follow_on(twin, planner, s, plan.order[s], rng)
    plan.planning_s = time.perf_counter() - t0
    return plan


def _within_reach(poses: list[Any], cfg: JobConfig, arm: ArmModel, plan: VinePlan) -> list[Any]:
    """The poses the arm's camera could reach from some stop on the robot's side; the others
    are named unreachable with how far across the row they lie (a bound, not a search: the
    camera is farther from the shoulder than the arm, end to end, is long)."""
    base = stop_pose(0.0, cfg.platform)[:3, 3]
    shoulder_y, shoulder_z = float(base[1]), float(base[2]) + float(DH[0, 1])
    reach = arm.camera_reach
    kept = []
    for p in poses:
        c = np.asarray(p.T_vine_camera, float)[:3, 3]
        far = float(np.hypot(c[1] - shoulder_y, c[2] - shoulder_z))
        if far > reach:
            plan.unreachable[p.id] = (
                f"out of the arm's reach from this side of the row (the camera's pose lies "
                f"{far:.2f} m from the arm's shoulder across the row; the arm reaches at most "
                f"{reach:.2f} m): prune it from the row's other side (`vinetwin propose "
                "--side far` or auto approaches it from there)"
            )
        else:
            kept.append(p)
    return kept


def _follow_on(
    twin: Twin, planner: Planner, stop: float, items: list[CutReach], rng: np.random.Generator
) -> None:
    """Each pose's joints re-solved from the previous pose's in the order (from `STOW`), kept
    when they are nearer in time: consecutive poses then share an arm configuration family
    instead of whichever branch the search met first, and the transits stay short."""
    from vinetwin.plan.reach import joint_time

    cfg = planner.cfg
    T_vine_base = stop_pose(stop, cfg.platform)
    planner.collider.at_stop(T_vine_base)
    arm = planner.arm
    prev = STOW
    for k, r in enumerate(items):
        pose = twin.pose(r.pose)
        cut = twin.cut_point(pose.cut_point).point
        got = reach_cut(
            arm, planner.collider, np.asarray(pose.T_vine_camera, float), cut, T_vine_base,
            cfg, planner.body.margin, planner.body.jaw_zone, [prev], rng,
        )  # fmt: skip
        if not isinstance(got, str) and joint_time(prev, got[0], arm.vmax) < joint_time(
            prev, r.q_pose, arm.vmax
        ):
            items[k] = CutReach(r.cut, r.pose, r.stop, got[0], got[1], got[2], got[3])
        prev = items[k].q_pose
