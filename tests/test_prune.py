"""The whole pruning job (`vinetwin prune`): the arm model against MuJoCo's, inverse kinematics,
exact distances against Open3D, the planner's conservative check, a transit around a cane, reach
and its named refusals, the blade judged against the true cut, resuming a killed row, one result
whichever executor ran it."""

from __future__ import annotations

import itertools
import json
import re
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from vinetwin.arm import DH, HOME, LOWER, STOW, UPPER, ArmModel, _frames, _jacobian
from vinetwin.errors import InputError
from vinetwin.frames import make_pose
from vinetwin.plan.job import Planner, plan_vine
from vinetwin.plan.job_config import CutConfig, JobConfig, PlatformConfig, TransitConfig
from vinetwin.plan.reach import Collider
from vinetwin.plan.transit import PlanningFailed, plan_transit
from vinetwin.twin.model import DEFAULT_T_FLANGE_CAMERA, DEFAULT_T_FLANGE_TOOL, Twin


def _arm() -> ArmModel:
    return ArmModel(DEFAULT_T_FLANGE_CAMERA, DEFAULT_T_FLANGE_TOOL)


def _tube(p0: list[float], p1: list[float], r: float, n: int = 24, rings: int = 80):
    """A closed cylinder mesh (a cane) from p0 to p1."""
    import trimesh

    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    axis = p1 - p0
    T = trimesh.geometry.align_vectors([0, 0, 1], axis / np.linalg.norm(axis))
    m = trimesh.creation.cylinder(radius=r, height=float(np.linalg.norm(axis)), sections=n)
    m = m.subdivide_to_size(0.01)
    T[:3, 3] = (p0 + p1) / 2
    m.apply_transform(T)
    return np.asarray(m.vertices), np.asarray(m.faces)


def test_arm_kinematics_match_the_mujoco_panda() -> None:
    """vinetwin.arm's forward kinematics equal sim.panda's MuJoCo model (the same chain written
    twice, numpy for planning, MJCF for simulation) to 1e-9 at random joints."""
    pytest.importorskip("mujoco")
    from vinetwin.sim.panda import PandaArm

    arm, sim = _arm(), PandaArm()
    rng = np.random.default_rng(0)
    for _ in range(25):
        q = rng.uniform(LOWER, UPPER)
        sim.set_q(q)
        assert np.allclose(arm.camera(q), sim.pose(), atol=1e-9)


def test_jacobian_matches_finite_differences() -> None:
    arm = _arm()
    q = np.array([0.3, -0.5, 0.4, -2.0, 0.2, 1.8, 0.6])
    F = np.empty((9, 4, 4))
    _frames(q, F)
    p = (F[8] @ arm.T_flange_camera)[:3, 3]
    J = _jacobian(F, p)
    h = 1e-6
    for i in range(7):
        dq = np.zeros(7)
        dq[i] = h
        Tp, Tm = arm.camera(q + dq), arm.camera(q - dq)
        assert np.allclose(J[:3, i], (Tp[:3, 3] - Tm[:3, 3]) / (2 * h), atol=1e-6)
        dR = Tp[:3, :3] @ Tm[:3, :3].T  # a small rotation: its axis-angle over 2h
        w = np.array([dR[2, 1] - dR[1, 2], dR[0, 2] - dR[2, 0], dR[1, 0] - dR[0, 1]]) / 2
        assert np.allclose(J[3:, i], w / (2 * h), atol=1e-6)


def test_inverse_kinematics_recovers_known_poses() -> None:
    """Poses made by forward kinematics at random joints are reached within 0.5 mm / 0.005 rad
    (the solver's tolerance), from the home seed and random ones."""
    arm = _arm()
    rng = np.random.default_rng(3)
    solved = 0
    for _ in range(20):
        q_true = rng.uniform(LOWER + 0.3, UPPER - 0.3)
        T = arm.camera(q_true)
        seeds = [HOME] + [rng.uniform(LOWER, UPPER) for _ in range(20)]
        q = arm.solve(T, seeds)
        if q is None:
            continue
        solved += 1
        E = np.linalg.inv(arm.camera(q)) @ T
        assert np.linalg.norm(E[:3, 3]) < 5e-4
        assert np.arccos(np.clip((np.trace(E[:3, :3]) - 1) / 2, -1, 1)) < 5e-3
        assert np.all(q >= LOWER - 1e-9) and np.all(q <= UPPER + 1e-9)
    assert solved >= 18


def test_exact_distances_match_open3d_and_the_fast_check_is_conservative() -> None:
    """The compiled point-to-triangle distances equal Open3D's on the sample vine; the planner's
    check never calls a configuration clear that the exact distances say is not."""
    o3d = pytest.importorskip("open3d")
    twin = Twin.load(Path(__file__).resolve().parents[1] / "samples" / "vine_bilateral.twin")
    m = twin.load_mesh()
    c = Collider(m.vertices, m.faces, PlatformConfig())
    rng = np.random.default_rng(1)
    P = m.vertices[rng.choice(len(m.vertices), 400)] + rng.normal(0, 0.01, (400, 3))
    d, cp = c.closest(P, 0.05)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(m.vertices.astype(np.float32)),
                        o3d.core.Tensor(m.faces.astype(np.uint32)))  # fmt: skip
    ref = scene.compute_distance(o3d.core.Tensor(P.astype(np.float32))).numpy()
    ok = np.isfinite(d)
    assert ok.sum() > 300 and np.all(ref[~ok] > 0.05 - 1e-6)
    assert np.abs(d[ok] - ref[ok]).max() < 1e-5
    assert np.allclose(np.linalg.norm(cp[ok] - P[ok], axis=1), d[ok], atol=1e-9)
    # the conservative check against the exact one, at configurations near the vine
    arm = _arm()
    from vinetwin.plan.reach import stop_pose

    c.at_stop(stop_pose(0.0, PlatformConfig(offset=0.55, height=0.45)))
    said_clear = 0
    for _ in range(300):
        q = rng.uniform(LOWER, UPPER)
        if c.arm_clear(arm, q, 0.01, 0.01):
            said_clear += 1
            gap, _, _ = c.clearance(arm.sphere_centres(q), arm.spheres.radius, need=0.05)
            assert gap >= 0.01 - 1e-9
    assert said_clear > 20
    # the free-space grid that spares the search is a lower bound of the distance to a vertex
    from scipy.spatial import cKDTree

    from vinetwin.plan.reach import FREE_CELL

    lo, hi = c.origin, c.origin + np.asarray(c.free.shape) * FREE_CELL
    Q = rng.uniform(lo, hi, (20000, 3))
    near, _ = cKDTree(m.vertices).query(Q)
    cells = np.floor((Q - lo) / FREE_CELL).astype(int)
    free = c.free[cells[:, 0], cells[:, 1], cells[:, 2]]
    assert np.all(free <= near) and (free > 0.03).mean() > 0.2


def test_a_transit_goes_around_a_cane_in_the_way() -> None:
    """A cane stands between two arm configurations: the straight joint-space move hits it;
    the planned transit goes around, and its timed trajectory, checked every 5 ms with exact
    distances, keeps every sphere clear; it stays within the joint limits and ends at rest."""
    pytest.importorskip("ompl")
    pytest.importorskip("ruckig")
    arm = _arm()
    q0 = np.array([-0.9, 0.3, 0.0, -1.8, 0.0, 2.1, 0.785])
    q1 = np.array([0.9, 0.3, 0.0, -1.8, 0.0, 2.1, 0.785])
    mid = arm.camera((q0 + q1) / 2)[:3, 3]  # the straight move sweeps the camera through here
    V, F = _tube([mid[0], mid[1], 0.1], [mid[0], mid[1], 1.2], 0.01)
    c = Collider(V, F, PlatformConfig(offset=0.55, height=0.45))
    c.at_stop(np.eye(4) @ make_pose(np.eye(3), [0, 0, 0.0]))
    cfg = TransitConfig()

    def valid(q: np.ndarray) -> bool:
        return c.arm_clear(arm, q, 0.02, 0.005)

    assert valid(q0) and valid(q1)
    assert not all(valid(q0 + (q1 - q0) * k / 50) for k in range(51))
    tr = plan_transit(q0, q1, valid, arm.lower, arm.upper, (arm.vmax, arm.amax, arm.jmax), cfg,
                      seed=1)  # fmt: skip
    assert len(tr.waypoints) > 2
    _, qs = tr.samples(0.005)
    assert np.allclose(qs[0], q0) and np.allclose(qs[-1], q1, atol=1e-9)
    for q in qs:
        gap, _, _ = c.clearance(arm.sphere_centres(q), arm.spheres.radius, need=0.0)
        assert gap >= 0.0
        assert np.all(q >= arm.lower - 1e-9) and np.all(q <= arm.upper + 1e-9)
    v = np.diff(qs, axis=0) / 0.005
    assert np.all(np.abs(v) <= arm.vmax * cfg.speed_scale * 1.02)
    # the arm follows the checked straight segments: every sample on the planned polyline
    W = np.array(tr.waypoints)

    def off(q: np.ndarray) -> float:
        d = W[1:] - W[:-1]
        t = np.clip(np.einsum("ij,ij->i", q - W[:-1], d) / np.einsum("ij,ij->i", d, d), 0, 1)
        return float(np.min(np.linalg.norm(q - (W[:-1] + t[:, None] * d), axis=1)))

    assert max(off(q) for q in qs) < 1e-9
    # the same seed plans the same path (a row's results do not depend on the worker)
    again = plan_transit(q0, q1, valid, arm.lower, arm.upper, (arm.vmax, arm.amax, arm.jmax),
                         cfg, seed=1)  # fmt: skip
    assert np.allclose(np.array(again.waypoints), np.array(tr.waypoints))
    # nowhere to go: a goal inside the cane is refused by name
    with pytest.raises(PlanningFailed, match="goal configuration collides"):
        plan_transit(q0, (q0 + q1) / 2, valid, arm.lower, arm.upper,
                     (arm.vmax, arm.amax, arm.jmax), cfg)  # fmt: skip


def test_a_transit_search_that_times_out_is_tried_again_with_another_seed(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A search that finds nothing is repeated `attempts` times, each with its own seed; the
    reason names how many searches failed, and one that succeeds is the transit's path."""
    from vinetwin.plan import transit as T

    arm = _arm()
    q0 = np.array([-0.9, 0.3, 0.0, -1.8, 0.0, 2.1, 0.785])
    q1 = np.array([0.9, 0.3, 0.0, -1.8, 0.0, 2.1, 0.785])
    mid = (q0 + q1) / 2 + np.array([0, -0.4, 0, 0, 0, 0, 0])

    def valid(q: np.ndarray) -> bool:  # the straight move is blocked half way
        return float(np.linalg.norm(q - (q0 + q1) / 2)) > 0.2

    seeds: list[int] = []

    def search(a: Any, b: Any, check: Any, lo: Any, hi: Any, cfg: TransitConfig,
               seed: int) -> list[Any]:  # fmt: skip
        seeds.append(seed)
        if len(seeds) < cfg.attempts + 1 and seed < 12:
            raise T.PlanningFailed(f"RRTConnect found no collision-free path in {cfg.timeout} s")
        return [a, mid, b]

    monkeypatch.setattr(T, "_ompl_path", search)
    limits = (arm.vmax, arm.amax, arm.jmax)
    with pytest.raises(PlanningFailed, match=r"in 1.0 s \(2 searches\)"):
        plan_transit(q0, q1, valid, arm.lower, arm.upper, limits, TransitConfig(), seed=10)
    assert seeds == [10, 11]
    seeds.clear()  # the second search of three finds it
    tr = plan_transit(q0, q1, valid, arm.lower, arm.upper, limits, TransitConfig(attempts=3),
                      seed=11)  # fmt: skip
    assert seeds == [11, 12] and np.allclose(tr.waypoints[1], mid)
    for bad in (0, 11, 1.5, True):
        with pytest.raises(InputError, match="attempts"):
            TransitConfig(attempts=bad)  # type: ignore[arg-type]


def test_a_transit_leaves_a_start_inside_the_margin_without_contact() -> None:
    """An arm the servo brought within the links' 2 cm margin of a cane (8-12 mm off): the
    transit is refused with the plain check, and with the contact check as its escape it leaves
    the cane, every state on the way clear of contact and, past the escape's 0.2 rad, of the
    margin too."""
    pytest.importorskip("ompl")
    pytest.importorskip("ruckig")
    from vinetwin.plan.transit import ESCAPE

    arm = _arm()
    q0 = np.array([-0.9, 0.3, 0.0, -1.8, 0.0, 2.1, 0.785])
    q1 = np.array([0.9, 0.3, 0.0, -1.8, 0.0, 2.1, 0.785])
    s = arm.spheres
    centre = arm.frames(q0)[4][:3, 3]  # a short upright cane beside the elbow, moved out
    for dx in np.arange(0.05, 0.3, 0.002):  # until the nearest sphere is 8-12 mm from it
        V, F = _tube([centre[0] + dx, centre[1], centre[2] - 0.15],
                     [centre[0] + dx, centre[1], centre[2] + 0.15], 0.01)  # fmt: skip
        c = Collider(V, F, PlatformConfig(offset=0.55, height=0.45))
        gap, _, _ = c.clearance(arm.sphere_centres(q0), s.radius, need=0.05)
        if gap > 0.008:
            break
    assert 0.008 < gap < 0.012
    cfg = TransitConfig()

    def valid(q: np.ndarray) -> bool:
        return c.arm_clear(arm, q, 0.02, 0.005)

    def contact_free(q: np.ndarray) -> bool:
        return c.arm_clear(arm, q, 0.0, 0.0)

    limits = (arm.vmax, arm.amax, arm.jmax)
    assert not valid(q0) and contact_free(q0) and valid(q1)
    with pytest.raises(PlanningFailed, match="start configuration collides"):
        plan_transit(q0, q1, valid, arm.lower, arm.upper, limits, cfg)
    tr = plan_transit(q0, q1, valid, arm.lower, arm.upper, limits, cfg, escape=contact_free)
    _, qs = tr.samples(0.005)
    assert np.allclose(qs[0], q0) and np.allclose(qs[-1], q1, atol=1e-9)
    for q in qs:
        gap, _, _ = c.clearance(arm.sphere_centres(q), s.radius, need=0.0)
        assert gap >= 0.0
        if np.linalg.norm(q - q0) > ESCAPE + 0.02:
            assert valid(q)


def _twin_with(tmp_path: Path, sample_twin_dir: Path, keep: list[str], name: str = "v.twin"):
    dst = tmp_path / name
    shutil.copytree(sample_twin_dir, dst,
                    ignore=shutil.ignore_patterns("references", "validation", "prune"))  # fmt: skip
    twin = Twin.load(dst)
    for p in [p.id for p in twin.poses if p.id not in keep]:
        twin.delete_pose(p)
    twin.save()
    return Twin.load(dst)


def test_unreachable_cuts_are_named(tmp_path: Path, sample_twin_dir: Path) -> None:
    """A pose 2.5 m up, one 1 m across the row from the shoulder (inside the reach's bound, but
    past what the joint limits let the arm stretch to) and one looking from the far side of the
    row are named, with the reason; the others get a stop."""
    twin = _twin_with(tmp_path, sample_twin_dir, ["p1", "p2"])
    high = twin.add_pose(twin.add_cut_point([0.1, 0.0, 2.5], [0, 0, 1]).id).id
    back = twin.add_pose(twin.add_cut_point([0.2, 0.0, 0.75], [0, 0, 1]).id).id
    looking_back = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])  # optical axis -Y
    twin.set_pose(back, make_pose(looking_back, [0.2, 0.15, 0.75]))
    # the base at y -0.55, its shoulder 0.45 + 0.333 m up: a camera 1.0 m across the row
    across = twin.add_pose(twin.add_cut_point([0.1, 0.6, 0.783], [0, 0, 1]).id).id
    looking_on = np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]])  # optical axis +Y
    twin.set_pose(across, make_pose(looking_on, [0.1, 0.45, 0.783]))
    twin.save()
    twin = Twin.load(twin.root)
    assert np.asarray(twin.pose(back).T_vine_camera)[1, 2] < -0.5
    planner = Planner.for_twin(twin, JobConfig(platform=PlatformConfig(offset=0.55, height=0.45)))
    plan = plan_vine(twin, planner)
    why = plan.unreachable[high]
    assert why.startswith("out of the arm's reach from this side of the row"), why
    far = float(why.split("lies ")[1].split(" m")[0])
    cam = np.asarray(twin.pose(high).T_vine_camera)[:3, 3]
    assert far == pytest.approx(np.hypot(cam[1] + 0.55, cam[2] - 0.783), abs=0.006)
    assert f"at most {planner.arm.camera_reach:.2f} m" in why
    assert "no platform stop reaches it" in plan.unreachable[across]
    assert "other side" in plan.unreachable[back]
    done = {r.pose for rs in plan.order.values() for r in rs}
    assert done == {"p1", "p2"}
    assert plan.stops


def test_no_stop_is_chosen_where_the_folded_arm_would_touch_the_vine(
    tmp_path: Path, sample_twin_dir: Path
) -> None:
    """The platform arrives and leaves with the arm folded: where the folded arm would touch
    the vine at the stop the plan chose (a hanging cane there, as the planner's check says),
    that stop is ruled out and the plan takes others (before, the job chose it and then skipped
    its cuts when it drove there)."""
    from vinetwin.arm import STOW

    twin = _twin_with(tmp_path, sample_twin_dir, ["p1", "p2", "p3"])
    cfg = JobConfig(platform=PlatformConfig(offset=0.55, height=0.45))
    plan = plan_vine(twin, Planner.for_twin(twin, cfg))
    assert plan.stops and not plan.unreachable
    s0 = plan.stops[0]
    planner = Planner.for_twin(twin, cfg)
    clear = planner.valid
    folded_at: list[float] = []

    def valid(q: np.ndarray) -> bool:  # the folded arm meets a cane at s0, and only there
        x = float(planner.collider.T_vine_base[0, 3])
        if np.allclose(q, STOW):
            folded_at.append(x)
            if abs(x - s0) < 1e-9:
                return False
        return clear(q)

    planner.valid = valid  # type: ignore[method-assign]
    plan2 = plan_vine(twin, planner)
    assert s0 in folded_at and s0 not in plan2.stops
    assert set(plan2.stops) <= set(folded_at)  # every stop chosen had its folded arm checked
    done = {r.pose for rs in plan2.order.values() for r in rs}
    assert done | set(plan2.unreachable) == {"p1", "p2", "p3"} and done


def test_no_poses_and_bad_settings_are_refused(tmp_path: Path, sample_twin_dir: Path) -> None:
    from vinetwin.sim.prune import PruneConfig, prune_twin

    twin = _twin_with(tmp_path, sample_twin_dir, [])
    with pytest.raises(InputError, match=r"no pruning poses.*propose"):
        prune_twin(twin.root, PruneConfig(sim="kinematic"))
    with pytest.raises(InputError, match="unknown profile"):
        prune_twin(sample_twin_dir, PruneConfig(sim="kinematic", profile="feild"))
    with pytest.raises(InputError, match="approach_speed"):
        prune_twin(sample_twin_dir, PruneConfig(
            sim="kinematic", job=JobConfig(cut=CutConfig(approach_speed=0.2))))  # fmt: skip
    for bad in (dict(offset=5.0), dict(drive_speed=3.0), dict(height=-1.0)):
        with pytest.raises(InputError):
            PlatformConfig(**bad)
    with pytest.raises(InputError, match="unknown planner"):
        TransitConfig(planner="Teleport")  # type: ignore[arg-type]
    with pytest.raises(InputError, match="unknown sim"):
        PruneConfig(sim="gazebo")  # type: ignore[arg-type]
    with pytest.raises(InputError, match="servo_gain"):
        PruneConfig(servo_gain=50.0)  # past the envelope's largest gain
    with pytest.raises(InputError, match="aim_window"):
        CutConfig(aim_window=-0.1)


def test_the_straight_profile_and_the_aim() -> None:
    """The straight cut's trapezoid: it covers exactly its length, never passes the speed or the
    acceleration, and its distance is the integral of its speed; a move too short for the speed
    is a triangle. The aim is the mean of the window's believed cut points."""
    from vinetwin.sim.straight import aimed_cut, straight_profile

    for length, speed, accel in ((0.08, 0.05, 0.5), (0.002, 0.05, 0.5), (0.3, 0.05, 0.25)):
        at, total = straight_profile(length, speed, accel)
        assert total == pytest.approx(
            length / speed + speed / accel if length >= speed**2 / accel
            else 2 * np.sqrt(length / accel), rel=1e-9)  # fmt: skip
        t = np.linspace(0.0, total + 0.1, 4001)
        s, v = np.array([at(x) for x in t]).T
        assert s[-1] == pytest.approx(length) and at(total + 1.0) == (pytest.approx(length), 0.0)
        assert v.max() <= speed + 1e-12 and np.all(
            np.abs(np.diff(v)) <= accel * (t[1] - t[0]) + 1e-9
        )
        assert np.allclose(np.diff(s), 0.5 * (v[1:] + v[:-1]) * np.diff(t), atol=1e-7)
    assert straight_profile(0.0, 0.05, 0.5)[1] == 0.0
    pts = [(0.1 * k, np.array([k, 0.0, 0.0])) for k in range(10)]
    assert np.allclose(aimed_cut(pts, 0.35), [7.5, 0, 0])  # the last four frames: 6 to 9
    assert np.allclose(aimed_cut(pts, 0.0), [9, 0, 0]) and aimed_cut([], 0.3) is None


def test_a_pose_its_field_twin_does_not_show_is_skipped_by_name(
    tmp_path: Path, sample_twin_dir: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Under the field profile the references come from a rebuilt twin; where it missed the
    pose's part of the vine the cut is skipped before any motion, with the remedy named (as
    `vinetwin validate` refuses it), instead of a servo that loses the vine."""
    pytest.importorskip("ompl")
    import trimesh

    import vinetwin.sim.field as field_mod
    from vinetwin.sim.prune import PruneConfig, prune_twin

    twin = _twin_with(tmp_path, sample_twin_dir, ["p3"])
    far = tmp_path / "far.ply"
    trimesh.creation.box((0.2, 0.2, 0.01), make_pose(t=[5.0, 5.0, 5.0])).export(far)
    monkeypatch.setattr(field_mod, "reconstructed_twin", lambda *a, **k: (far, {}))
    out = prune_twin(twin.root, PruneConfig(sim="kinematic", profile="field"))
    (c,) = out["cuts"]
    assert c["status"] == "skipped"
    assert re.search(r"reference: the field twin rebuilt .* 0% .* pose 'p3'.*twin_trajectory",
                     c["reason"]), c["reason"]  # fmt: skip
    assert out["summary"]["simulated_s"] < 20  # no servo ran: the drive, the stow


def test_the_blade_is_judged_against_the_true_cut(tmp_path: Path, sample_twin_dir: Path) -> None:
    """The robot's reference comes from a twin 4 mm off the true vine (a bad reconstruction):
    the servo lands where that reference says, the blade closes about 4 mm from the TRUE cut
    point, and the result says so; with the true twin's reference it closes within 1 mm."""
    pytest.importorskip("ompl")
    from vinetwin.render.backends import raycaster
    from vinetwin.sim.prune import PruneConfig, _Job

    twin = _twin_with(tmp_path, sample_twin_dir, ["p3"])
    cfg = PruneConfig(sim="kinematic")
    errors = {}
    for shift in (0.0, 0.004):
        job = _Job(Twin.load(twin.root), cfg)
        m = twin.load_mesh()
        job.reference_backend = raycaster(m.vertices + [shift, 0.0, 0.0], m.faces, twin.camera)
        try:
            out = job.run()
        finally:
            job.close()
        (c,) = out["cuts"]
        assert c["status"] == "done", c["reason"]
        errors[shift] = c["blade_error_m"]
    assert errors[0.0] < 0.001
    assert 0.003 < errors[0.004] < 0.005


def _row(tmp_path: Path, sample_twin_dir: Path) -> Path:
    row = tmp_path / "row"
    row.mkdir()
    _twin_with(row, sample_twin_dir, ["p3"], "a.twin")
    _twin_with(row, sample_twin_dir, ["p2"], "b.twin")
    return row


def test_a_killed_row_resumes_and_every_executor_agrees(
    tmp_path: Path, sample_twin_dir: Path
) -> None:
    """A row of two vines: a run killed after the first vine keeps it and a rerun prunes only
    the second; the in-process run, the local pool and Ray give the same per-vine results."""
    pytest.importorskip("ompl")
    from vinetwin.executor import ExecutorConfig
    from vinetwin.sim.prune import PruneConfig
    from vinetwin.sim.prune_row import comparable, prune_row

    row = _row(tmp_path, sample_twin_dir)
    cfg = PruneConfig(sim="kinematic")
    out = tmp_path / "out"
    first = prune_row(row, cfg, out, ExecutorConfig(workers=1))
    assert set(first["vines"]) == {"a.twin", "b.twin"}
    assert first["summary"]["done"] == 2 and first["summary"]["collisions"] == 0
    kept = out / "vines" / "a.twin.json"
    before = kept.stat().st_mtime_ns
    (out / "vines" / "b.twin.json").unlink()  # killed before b's result was written
    again = prune_row(row, cfg, out, ExecutorConfig(workers=1))
    assert kept.stat().st_mtime_ns == before  # a: kept, not run again
    assert comparable(again["vines"]["b.twin"]) == comparable(first["vines"]["b.twin"])
    # a changed input runs again
    data = json.loads(kept.read_text())
    data["digest"] = "stale"
    kept.write_text(json.dumps(data))
    prune_row(row, cfg, out, ExecutorConfig(workers=1))
    assert kept.stat().st_mtime_ns != before
    pool = prune_row(row, cfg, tmp_path / "pool", ExecutorConfig(workers=2))
    for name in ("a.twin", "b.twin"):
        assert comparable(pool["vines"][name]) == comparable(first["vines"][name])
    pytest.importorskip("ray")
    ray = prune_row(row, cfg, tmp_path / "ray", ExecutorConfig(kind="ray", workers=2))
    for name in ("a.twin", "b.twin"):
        assert comparable(ray["vines"][name]) == comparable(first["vines"][name])


def test_a_vine_that_fails_is_named_and_an_earlier_report_is_kept(
    tmp_path: Path, sample_twin_dir: Path
) -> None:
    """`vinetwin prune ROW`: a vine whose mesh is corrupt fails by name with a non-zero exit
    status, the report holding the other; a row where every vine fails writes nothing over the
    earlier report; a profile that cannot be read and a negative seed are refused before any
    vine runs."""
    pytest.importorskip("ompl")
    from vinetwin.cli import main

    row = _row(tmp_path, sample_twin_dir)
    out = tmp_path / "out"
    assert main(["prune", str(row), "--sim", "kinematic", "--out", str(out)]) == 0
    report = (out / "report.html").read_bytes()
    bad = Twin.load(row / "b.twin")
    bad.mesh_path.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 3\n")
    torn = row / "c.twin"
    shutil.copytree(row / "a.twin", torn)
    (torn / "twin.json").write_text("{torn")
    args = ["prune", str(row), "--sim", "kinematic", "--out", str(out), "--force"]
    assert main(args) == 2
    data = json.loads((out / "prune.json").read_text())
    assert set(data["vines"]) == {"a.twin"} and set(data["failed"]) == {"b.twin", "c.twin"}
    assert "not valid JSON" in data["failed"]["c.twin"]
    shutil.rmtree(torn)
    Twin.load(row / "a.twin").mesh_path.write_bytes(b"not a mesh")
    before = (out / "prune.json").read_bytes()
    assert main(args) == 2
    assert (out / "prune.json").read_bytes() == before  # nothing written over it
    assert (out / "report.html").read_bytes() != report  # the one with a.twin alone, kept
    fresh = tmp_path / "fresh"
    assert main(["prune", str(row), "--profile", "nope.json", "--out", str(fresh)]) == 2
    assert main(["prune", str(row), "--seed", "-1", "--out", str(fresh)]) == 2
    assert not fresh.exists()


@pytest.mark.slow
def test_the_sample_is_pruned_on_the_mujoco_panda(tmp_path: Path, sample_twin_dir: Path) -> None:
    """The bundled sample, MuJoCo Panda, ideal profile: every pose reached and cut with the
    blade within 2 mm of the true cut point, no collision, the report written."""
    pytest.importorskip("mujoco")
    pytest.importorskip("ompl")
    from vinetwin.sim.prune import PruneConfig
    from vinetwin.sim.prune_report import write_report
    from vinetwin.sim.prune_row import prune_row

    twin = _twin_with(tmp_path, sample_twin_dir, ["p1", "p2", "p3", "p4", "p5"])
    data = prune_row(twin.root, PruneConfig(sim="mujoco"), tmp_path / "out", mcap=True)
    s = data["summary"]
    assert s["done"] == 5 and s["collisions"] == 0, data["vines"]
    (v,) = data["vines"].values()
    assert all(c["blade_error_m"] < 0.002 for c in v["cuts"])
    assert all(set(c["phases"]) >= {"transit", "servo", "cut", "close", "retreat"}
               for c in v["cuts"])  # fmt: skip
    assert v["plan"]["stops"] and s["realtime_factor"] > 1.0
    from mcap.reader import make_reader

    (bag,) = (tmp_path / "out" / "vines").glob("*.mcap/*.mcap")
    with bag.open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None and summary.statistics is not None
    counts = {c.topic: summary.statistics.channel_message_counts[c.id]
              for c in summary.channels.values()}  # fmt: skip
    assert counts["/tf"] > 500 and counts["/joint_states"] > 500 and counts["/vinetwin/events"] > 20
    # the bag's clock is the job's: it ends when the vine's simulated time does
    assert abs(summary.statistics.message_end_time / 1e9 - v["summary"]["simulated_s"]) < 0.05
    write_report(data, tmp_path / "out")
    assert (tmp_path / "out" / "report.html").exists()
    assert (tmp_path / "out" / "v.twin_vine.png").stat().st_size > 10_000


def test_stow_and_home_are_within_limits() -> None:
    assert np.all(STOW >= LOWER) and np.all(STOW <= UPPER)
    arm = _arm()
    # the folded arm reaches no more than 0.25 m ahead of its base
    c = arm.sphere_centres(STOW)
    assert float((c[:, 0] + arm.spheres.radius).max()) < 0.25


def test_an_arm_that_finds_no_way_out_retraces_the_way_it_came(
    tmp_path: Path, sample_twin_dir: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Among hanging canes the planner may find no path from the last cut back to the folded
    arm (on hydroshoot's gdc_can1_grapevine this stopped the job). The way in is known: the
    stow then follows this stop's transits' waypoints backwards, each straight segment checked
    again; with no way in recorded, the job stops with the planner's reason."""
    from vinetwin.plan import transit as T
    from vinetwin.sim.prune import PruneConfig, _Job

    twin = _twin_with(tmp_path, sample_twin_dir, ["p1"])
    job = _Job(twin, PruneConfig(sim="kinematic"))
    try:
        e0, e2 = np.eye(7)[0], np.eye(7)[2]
        w1, w2, q = STOW + 0.5 * e2, STOW + e0 + 0.5 * e2, STOW + e0
        path = [STOW, w1, w2, q]  # the way in, bent: the straight way back is blocked

        def valid(x: np.ndarray) -> bool:  # free within 0.05 rad of the way in, nowhere else
            for a, b in itertools.pairwise(path):
                s = np.clip(np.dot(x - a, b - a) / np.dot(b - a, b - a), 0.0, 1.0)
                if np.linalg.norm(x - (a + s * (b - a))) < 0.05:
                    return True
            return False

        def search(*args: Any, **kwargs: Any) -> list[Any]:
            raise T.PlanningFailed("RRTConnect found no collision-free path in 1.0 s")

        job.planner.valid = valid  # type: ignore[method-assign]
        monkeypatch.setattr(T, "_ompl_path", search)
        B = np.eye(4)
        job.trail = []  # nothing recorded: the planner's reason
        why, _ = job._stow(q, B)
        assert isinstance(why, str) and "no collision-free path" in why
        job.trail = [STOW, w1, w2]  # the transit's waypoints, start to end
        tr, _ = job._stow(q, B)
        assert not isinstance(tr, str) and tr.how == "via"
        assert np.allclose(np.array(tr.waypoints), [q, w2, w1, STOW, STOW])
    finally:
        job.close()


def test_the_camera_reach_bounds_every_configuration() -> None:
    """`ArmModel.camera_reach` is an upper bound on the camera's distance from the shoulder
    (20000 random joint vectors within the limits, and the arm stretched out), and not a loose
    one: the farthest of them lies within 15% of it."""
    arm = _arm()
    rng = np.random.default_rng(0)
    shoulder = np.array([0.0, 0.0, DH[0, 1]])
    qs = list(rng.uniform(LOWER, UPPER, (20000, 7))) + [np.array([0, 0, 0, -0.0698, 0, 0, 0])]
    far = max(float(np.linalg.norm(arm.camera(q)[:3, 3] - shoulder)) for q in qs)
    assert far <= arm.camera_reach
    assert far >= 0.85 * arm.camera_reach
