"""Collision-free transits between two arm configurations: a joint-space path planned by OMPL
(RRT-Connect by default, then OMPL's path simplifier) against a validity check the caller gives
(`plan.reach.Collider.arm_clear`), each straight segment then timed by ruckig within the Panda's
joint velocity, acceleration and jerk limits. Segments are timed rest to rest by ruckig on
each segment's path parameter, so the arm follows the checked straight segments exactly. A path is
searched at the planner's resolution and kept once checked three times as finely (the hand's
margin is less than a coarse step can move the tool); an OMPL path that fails that is planned
again at the fine resolution."""

from __future__ import annotations

import itertools
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from vinetwin import _lazy
from vinetwin.frames import Array
from vinetwin.plan.job_config import TransitConfig


@dataclass
class Transit:
    """A timed joint-space path: straight segments between `waypoints`, each rest to rest."""

    waypoints: list[Array]
    durations: list[float] = field(default_factory=list)
    planning_s: float = 0.0
    """Compute spent planning and timing it (s)."""
    checks: int = 0
    """Collision checks made in this process (the planner's own, in its child, not counted)."""
    how: str = ""
    """straight, via (backing off along the optical axes) or the OMPL planner's name."""
    _trajectories: list[tuple[Any, Array, Array]] = field(default_factory=list, repr=False)

    @property
    def duration(self) -> float:
        return float(sum(self.durations))

    def at(self, t: float) -> Array:
        """Joints at time t (s) from the start (clamped to the ends)."""
        if not self._trajectories:
            return np.asarray(self.waypoints[-1], float)
        for (traj, a, d), dur in zip(self._trajectories, self.durations, strict=True):
            if t <= dur:
                s = float(traj.at_time(max(t, 0.0))[0][0])  # type: ignore[attr-defined]
                return a + s * d
            t -= dur
        return np.asarray(self.waypoints[-1], float)

    def samples(self, dt: float) -> tuple[Array, Array]:
        """(times, joints) every dt s, both ends included."""
        n = max(2, math.ceil(self.duration / dt) + 1)
        ts = np.linspace(0.0, self.duration, n)
        return ts, np.array([self.at(t) for t in ts])


#: Joint-space distance (rad) from a transit's end within which, when that end lies inside the
#: clearance margins, the path is judged by the contact check alone (`plan_transit`'s escape).
ESCAPE = 0.2
#: Within `ESCAPE` the path is checked this many times as finely: the escape's clearance
#: (`plan.job.ESCAPE_CLEARANCE`) must cover what a sphere moves between two checks (a joint
#: step of 0.002 rad moves the Panda's farthest sphere at most about 2.6 mm).
ESCAPE_STEPS = 5
#: A path found at the planner's resolution is kept once checked this many times as finely
#: (a joint step of 0.0033 rad moves the tool at most about 4.3 mm, within the hand's margin).
FINE_STEPS = 3


class PlanningFailed(Exception):
    """No collision-free path within the planner's time."""


def _segment_ok(q0: Array, q1: Array, valid: Callable[[Array], bool], step: float) -> bool:
    """Whether the straight joint-space segment passes `valid` at every `step` (rad, the
    largest joint's), checked coarse to fine (every 2^j-th point, halving j): a blocked segment
    fails after a few checks; a free one costs one check per point, as in order."""
    n = max(1, math.ceil(float(np.max(np.abs(q1 - q0))) / step))
    seen = np.zeros(n + 1, bool)
    stride = 1 << (n.bit_length() - 1)
    while stride >= 1:
        for k in range(stride, n + 1, stride):
            if not seen[k]:
                seen[k] = True
                if not valid(q0 + (q1 - q0) * k / n):
                    return False
        stride //= 2
    return True


def time_path(waypoints: list[Array], vmax: Array, amax: Array, jmax: Array) -> Transit:
    """Each segment timed rest to rest by ruckig on its path parameter (0 to 1 along the
    straight joint-space line, within each joint's velocity, acceleration and jerk limits
    scaled to the segment), so the arm follows the checked straight segment exactly: ruckig's
    own phase synchronisation of seven joints falls back to time synchronisation, off the
    line, where a segment's profiles cannot be made alike (measured: 4 cm off, into a cane)."""
    ruckig = _lazy.module("ruckig", "the transit timing (pip install ruckig)")
    out = Transit([np.asarray(w, float) for w in waypoints])
    otg = ruckig.Ruckig(1)
    for a, b in itertools.pairwise(out.waypoints):
        d = b - a
        moving = np.abs(d) > 1e-12
        if not moving.any():
            continue
        scale = np.abs(d[moving])
        inp = ruckig.InputParameter(1)
        inp.current_position = [0.0]
        inp.target_position = [1.0]
        inp.max_velocity = [float(np.min(np.asarray(vmax)[moving] / scale))]
        inp.max_acceleration = [float(np.min(np.asarray(amax)[moving] / scale))]
        inp.max_jerk = [float(np.min(np.asarray(jmax)[moving] / scale))]
        traj = ruckig.Trajectory(1)
        result = otg.calculate(inp, traj)
        if result not in (ruckig.Result.Working, ruckig.Result.Finished):
            raise PlanningFailed(f"ruckig could not time a segment ({result})")
        out._trajectories.append((traj, a, d))
        out.durations.append(float(traj.duration))
    return out


def plan_transit(
    q0: Array,
    q1: Array,
    valid: Callable[[Array], bool],
    lower: Array,
    upper: Array,
    limits: tuple[Array, Array, Array],
    cfg: TransitConfig,
    seed: int = 0,
    via: list[list[Array]] | None = None,
    escape: Callable[[Array], bool] | None = None,
) -> Transit:
    """A timed collision-free path from q0 to q1 (both must be valid). The straight segment is
    kept when it is free, else the first chain of `via` waypoints (backing off along the
    approach, for instance; each chain's waypoints alone tried before the whole chain) whose
    straight segments are free; else OMPL's `cfg.planner`
    searches for `cfg.timeout` s (up to `cfg.attempts` times, each with its own seed) and its
    path is simplified. An end that fails `valid` (an arm
    the servo's correction brought within a margin of a cane) is refused unless it passes
    `escape` (a check with a small clearance instead of the margins); then the path may stay
    under the margins, never closer than that, within `ESCAPE` of that end, to leave it or to
    arrive, checked `ESCAPE_STEPS` times as finely. Raises
    PlanningFailed with the reason."""
    t0 = time.perf_counter()
    q0, q1 = np.asarray(q0, float), np.asarray(q1, float)
    checks = [0]

    near: list[Array] = []  # ends inside the margins but clear of contact

    def counted(q: Array) -> bool:
        checks[0] += 1
        if valid(q):
            return True
        return (
            bool(near)
            and escape is not None
            and any(float(np.linalg.norm(q - e)) <= ESCAPE for e in near)
            and escape(q)
        )

    for name, q in (("start", q0), ("goal", q1)):
        if not valid(q):
            if escape is None or not escape(q):
                raise PlanningFailed(f"the transit's {name} configuration collides")
            near.append(q)
    if near:  # under the margins the steps between checks must be short: a fifth of them
        cfg = replace(cfg, resolution=cfg.resolution / ESCAPE_STEPS)
    # a path is searched at the resolution, and kept only once checked FINE_STEPS times as
    # finely: the hand's 5 mm margin is less than a 0.01 rad step can move the tool
    fine = cfg.resolution if near else cfg.resolution / FINE_STEPS

    def path_ok(cand: list[Array], resolution: float) -> bool:
        return all(_segment_ok(a, b, counted, resolution) for a, b in itertools.pairwise(cand))

    path: list[Array] | None = None
    how = cfg.planner
    # each chain's single waypoints first: a path that stops once instead of twice is quicker
    chains: list[list[Array]] = [[]]
    for chain in via or []:
        chains += [[w] for w in chain] if len(chain) > 1 else []
        chains.append(chain)
    for k, chain in enumerate(chains):
        cand = [q0, *[np.asarray(w, float) for w in chain], q1]
        if all(counted(w) for w in cand[1:-1]) and path_ok(cand, fine):
            path, how = cand, "via" if k else "straight"
            break
    if path is None:
        used = seed
        for attempt in range(cfg.attempts):
            used = seed + attempt
            try:
                path = _ompl_path(q0, q1, counted, lower, upper, cfg, used)
                break
            except PlanningFailed as exc:
                if attempt + 1 == cfg.attempts:
                    raise PlanningFailed(f"{exc} ({cfg.attempts} searches)") from None
        assert path is not None
        if not path_ok(path, fine):  # planned again, checking as finely as it is judged
            path = _ompl_path(q0, q1, counted, lower, upper, replace(cfg, resolution=fine), used)
            if not path_ok(path, fine):
                raise PlanningFailed("the planned path collides between its checks")
    scale = cfg.speed_scale
    vmax, amax, jmax = limits
    transit = time_path(path, vmax * scale, amax * scale, jmax * scale)
    transit.checks = checks[0]
    transit.how = how
    transit.planning_s = time.perf_counter() - t0
    return transit


def _ompl_path(
    q0: Array,
    q1: Array,
    valid: Callable[[Array], bool],
    lower: Array,
    upper: Array,
    cfg: TransitConfig,
    seed: int,
) -> list[Array]:
    """OMPL's path, planned in a forked child process: OMPL's random numbers can be seeded only
    before their first use in a process, so each plan gets a fresh process whose first use is
    seeded with `seed`, and a vine's transits are the same whichever worker (a local pool's or
    Ray's) plans them and whatever it planned before. The child shares the parent's collision
    model by the fork (no copy); it sends the waypoints back through a pipe."""
    import multiprocessing as mp
    import pickle

    _lazy.module("ompl", "transit planning (pip install ompl)")  # imported once, here
    ctx = mp.get_context("fork")
    recv, send = ctx.Pipe(duplex=False)

    def child() -> None:
        try:
            out: Any = _ompl_plan(q0, q1, valid, lower, upper, cfg, seed)
        except PlanningFailed as exc:
            out = str(exc)
        except BaseException as exc:
            out = f"the planner failed: {type(exc).__name__}: {exc}"
        send.send_bytes(pickle.dumps(out))
        send.close()

    proc = ctx.Process(target=child, daemon=True)
    proc.start()
    send.close()
    try:
        if not recv.poll(cfg.timeout + 30.0):
            raise PlanningFailed(f"the planner did not answer in {cfg.timeout + 30.0:g} s")
        out = pickle.loads(recv.recv_bytes())
    except EOFError:
        raise PlanningFailed("the planner's process died") from None
    finally:
        recv.close()
        proc.join(timeout=5.0)
        if proc.is_alive():
            proc.kill()
    if isinstance(out, str):
        raise PlanningFailed(out)
    return [np.asarray(w, float) for w in out]


def _ompl_plan(
    q0: Array,
    q1: Array,
    valid: Callable[[Array], bool],
    lower: Array,
    upper: Array,
    cfg: TransitConfig,
    seed: int,
) -> list[Array]:
    ompl = _lazy.module("ompl", "transit planning (pip install ompl)")
    ob, og, ou = ompl.base, ompl.geometric, ompl.util
    ou.setLogLevel(ou.LogLevel.LOG_WARN)
    ou.RNG.setSeed(int(seed) + 1)
    space = ob.RealVectorStateSpace(7)
    bounds = ob.RealVectorBounds(7)
    for i in range(7):
        bounds.setLow(i, float(lower[i]))
        bounds.setHigh(i, float(upper[i]))
    space.setBounds(bounds)
    ss = og.SimpleSetup(space)
    q = np.empty(7)

    def check(s: Any) -> bool:
        for i in range(7):
            q[i] = s[i]
        return valid(q.copy())

    ss.setStateValidityChecker(check)
    si = ss.getSpaceInformation()
    # OMPL's resolution is a share of the space's extent; ours is a joint step
    si.setStateValidityCheckingResolution(cfg.resolution / si.getMaximumExtent())
    start, goal = space.allocState(), space.allocState()
    for i in range(7):
        start[i], goal[i] = float(q0[i]), float(q1[i])
    ss.setStartAndGoalStates(start, goal)
    ss.setPlanner(getattr(og, cfg.planner)(si))
    solved = ss.solve(cfg.timeout)
    if not ss.haveExactSolutionPath():
        raise PlanningFailed(f"{cfg.planner} found no collision-free path in {cfg.timeout} s "
                             f"({solved})")  # fmt: skip
    # OMPL's rope shortcuts, then fewer vertices: as short a transit as its full `simplify`
    # (shortcuts, B-spline smoothing and more) in under half the checks (measured on the
    # field benchmark's OMPL transits, docs/prune.md), and each vertex left is a stop fewer
    p = ss.getSolutionPath()
    ps = og.PathSimplifier(si)
    ps.ropeShortcutPath(p)
    ps.reduceVertices(p)
    ps.collapseCloseVertices(p)
    return [np.array([p.getState(k)[i] for i in range(7)]) for k in range(p.getStateCount())]
