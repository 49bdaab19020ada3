"""The whole pruning job (`vinetwin prune`) on the bundled sample, a dense generated vine and two
hydroshoot vines with the spur rule's proposals: cuts done and done right (blade within 5 mm of
the true cut point), skipped with their reasons, collisions, time per cut, planning per vine and
per transit, and how much faster than real time the simulation runs; then, side by side on the
same transits, the planner's collision check against the one a user would otherwise write
(Open3D's exact distances) inside the same OMPL planner, and our inverse kinematics against
mink's (when installed).

    .venv/bin/python benchmarks/prune.py [--plants sample dense gdc_can1 vsp_ww]
        [--seeds 0 1 2] [--profile field] [--sim mujoco] [--keep DIR] [--json FILE]
    .venv/bin/python benchmarks/prune.py --quick     # the sample, one seed, kinematic
"""

from __future__ import annotations

import argparse
import itertools
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from propose import make_twin
from results_file import write_json

from vinetwin.plan.config import ProposeConfig, RuleConfig
from vinetwin.plan.proposer import propose
from vinetwin.twin.model import Twin, bundled_sample

PLANTS = ("sample", "dense", "gdc_can1", "vsp_ww")
#: Vines whose field twin is captured around the pruning poses (`"twin_trajectory": "poses"`):
#: the field profile's grid sweep at the D405's 30 cm misses the GDC's two curtains, 1.2 m apart
#: (40 of its 60 frames see nothing within range), and every pose would be skipped by name.
AROUND_POSES = ("gdc_can1",)


def plant_profile(name: str, profile: str, work: Path) -> str:
    """The profile a plant runs under: `profile`, or for a field run of a vine in
    `AROUND_POSES` the same field profile with its twin captured around the poses."""
    import json

    from vinetwin.sim.config import load_profile

    p = load_profile(profile)
    if name not in AROUND_POSES or not p.on("twin") or p.twin_trajectory == "poses":
        return profile
    path = work / f"{Path(profile).stem}_around_poses.json"
    path.write_text(json.dumps({**p.to_dict(), "twin_trajectory": "poses"}, indent=1))
    return str(path)


def plant_twin(name: str, work: Path) -> Path:
    """The sample as bundled (its five cuts and poses), or the plant with the spur rule's
    proposals."""
    import shutil

    root = work / f"{name}.twin"
    if root.exists():
        return root
    if name == "sample":
        shutil.copytree(bundled_sample(), root)
        return root
    twin = make_twin(name, root)
    propose(twin, ProposeConfig(rule=RuleConfig(rule="spur")))
    return root


def run_vines(plants: list[str], seeds: list[int], sim: str, profile: str, work: Path) -> list:
    from vinetwin.sim.prune import PruneConfig, prune_twin

    rows = []
    print("| plant | seed | poses | reachable | done | done right | skipped | collisions | "
          "median blade mm (max) | median s per cut | s per vine | planning s | x real time |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for name in plants:
        root = plant_twin(name, work)
        for seed in seeds:
            cfg = PruneConfig(sim=sim, profile=plant_profile(name, profile, work), seed=seed)  # type: ignore[arg-type]
            r = prune_twin(root, cfg)
            s = r["summary"]
            done = [c for c in r["cuts"] if c["status"] == "done"]
            errs = [1000 * c["blade_error_m"] for c in done]
            transits = [c["phases"]["planning"] for c in r["cuts"] if "planning" in c["phases"]]
            reasons: dict[str, int] = {}
            for c in r["cuts"]:
                if c["status"] != "done":
                    key = c["reason"].split(" (")[0]
                    reasons[key] = reasons.get(key, 0) + 1
            row = {
                "plant": name, "seed": seed, **{k: s[k] for k in (
                    "poses", "reachable", "done", "done_right", "skipped",
                    "median_time_per_cut_s", "simulated_s", "realtime_factor")},
                "collisions": r["collisions"], "contacts": r["contacts"],
                "median_blade_error_mm": float(np.median(errs)) if errs else None,
                "max_blade_error_mm": max(errs) if errs else None,
                "planning_s": r["planning_s"], "reach_planning_s": r["reach_planning_s"],
                "transit_planning_s": transits, "skip_reasons": reasons,
                "times_per_cut_s": [c["time_s"] for c in done],
            }  # fmt: skip
            rows.append(row)
            med = (
                f"{row['median_blade_error_mm']:.2f} ({row['max_blade_error_mm']:.2f})"
                if errs
                else "-"
            )
            print(f"| {name} | {seed} | {s['poses']} | {s['reachable']} | {s['done']} | "
                  f"{s['done_right']} | {s['skipped']} | {r['collisions']} | {med} | "
                  f"{s['median_time_per_cut_s']:.1f} | {s['simulated_s']:.0f} | "
                  f"{r['planning_s']:.2f} | {s['realtime_factor']:.1f} |", flush=True)  # fmt: skip
    return rows


def collision_checks(root: Path, n: int = 12) -> dict[str, Any]:
    """The same OMPL planner (RRT-Connect, same seeds, each in its forked process as the job
    plans) on the same transits between the plan's consecutive poses, its validity check ours
    (compiled, on a vertex hash) or Open3D's (`compute_distance` on the mesh: what a user would
    otherwise write): median planning time per transit (a transit past the planner's 1 s is
    failed), and the time per check at 500 random configurations (ours is conservative by at
    most the surface between vertices: it may call a few more of them blocked)."""
    from vinetwin.arm import STOW
    from vinetwin.plan.job import Planner, plan_vine
    from vinetwin.plan.reach import stop_pose
    from vinetwin.plan.transit import PlanningFailed, _ompl_path

    twin = Twin.load(root)
    planner = Planner.for_twin(twin)
    plan = plan_vine(twin, planner)
    arm, col = planner.arm, planner.collider
    from vinetwin import _lazy

    o3d = _lazy.open3d()
    m = twin.load_mesh()
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(m.vertices.astype(np.float32)),
                        o3d.core.Tensor(m.faces.astype(np.uint32)))  # fmt: skip
    hand = arm.spheres.frame == 8
    need = np.where(hand, planner.body.margin, planner.cfg.reach.clearance) + arm.spheres.radius

    def open3d_valid(q: np.ndarray) -> bool:
        P = arm.sphere_centres(q) @ col.T_vine_base[:3, :3].T + col.T_vine_base[:3, 3]
        d = scene.compute_distance(o3d.core.Tensor(P.astype(np.float32))).numpy()
        if np.any(d < need):
            return False
        g = col.gaps(P, arm.spheres.radius, 0.0)  # the deck and the ground, as ours
        return bool(np.all(g[:, 1:] >= need[:, None] - arm.spheres.radius[:, None]))

    pairs = []
    for s in plan.stops:
        qs = [STOW] + [r.q_pose for r in plan.order[s]]
        pairs += [(s, a, b) for a, b in itertools.pairwise(qs)]
    pairs = pairs[:n]
    out: dict[str, Any] = {"transits": len(pairs)}
    rng = np.random.default_rng(0)
    probes = [rng.uniform(arm.lower, arm.upper) for _ in range(500)]
    for name, fn in (("vinetwin", planner.valid), ("open3d", open3d_valid)):
        times, failed = [], 0
        for k, (s, a, b) in enumerate(pairs):
            col.at_stop(stop_pose(s, planner.cfg.platform))
            t0 = time.perf_counter()
            try:
                _ompl_path(a, b, fn, arm.lower, arm.upper, planner.cfg.transit, k)
            except PlanningFailed:
                failed += 1
            times.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        verdicts = [fn(q) for q in probes]
        per_check = (time.perf_counter() - t0) / len(probes)
        out[name] = {
            "median_transit_s": statistics.median(times),
            "check_us": 1e6 * per_check,
            "clear_of_500_random": int(sum(verdicts)),
            "failed": failed,
        }
    out["ratio_open3d_to_ours"] = out["open3d"]["median_transit_s"] / max(
        out["vinetwin"]["median_transit_s"], 1e-9
    )
    return out


def inverse_kinematics(n: int = 200) -> dict[str, Any]:
    """Our compiled damped least squares against mink (a QP per step on MuJoCo's model) on the
    same reachable camera poses from the same start: median time per solve and how many solve."""
    from vinetwin.arm import HOME, LOWER, UPPER, ArmModel
    from vinetwin.twin.model import DEFAULT_T_FLANGE_CAMERA, DEFAULT_T_FLANGE_TOOL

    arm = ArmModel(DEFAULT_T_FLANGE_CAMERA, DEFAULT_T_FLANGE_TOOL)
    rng = np.random.default_rng(0)
    targets = [arm.camera(rng.uniform(LOWER + 0.3, UPPER - 0.3)) for _ in range(n)]
    arm.solve(targets[0], [HOME])  # compiled before timing
    t0 = time.perf_counter()
    ours = sum(arm.solve(T, [HOME], iterations=300) is not None for T in targets)
    out: dict[str, Any] = {"poses": n, "vinetwin": {
        "median_ms": 1000 * (time.perf_counter() - t0) / n, "solved": ours}}  # fmt: skip
    try:
        import mink
        import mujoco

        from vinetwin.sim.panda import PandaArm
    except ImportError:
        out["mink"] = "not installed"
        return out
    panda = PandaArm()
    model = panda.model
    cfg = mink.Configuration(model)
    task = mink.FrameTask("d405", "site", position_cost=1.0, orientation_cost=1.0)
    solved, t0 = 0, time.perf_counter()
    for T in targets:
        q0 = model.key_qpos[0].copy() if model.nkey else np.zeros(model.nq)
        cfg.update(q0)
        task.set_target(mink.SE3.from_matrix(T))
        for _ in range(300):
            v = mink.solve_ik(cfg, [task], 0.05, "daqp", 1e-3)
            cfg.integrate_inplace(v, 0.05)
            e = task.compute_error(cfg)
            if np.linalg.norm(e[:3]) < 5e-4 and np.linalg.norm(e[3:]) < 5e-3:
                solved += 1
                break
    out["mink"] = {"median_ms": 1000 * (time.perf_counter() - t0) / n, "solved": solved}
    del mujoco
    return out


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--plants", nargs="*", default=list(PLANTS))
    ap.add_argument("--seeds", nargs="*", type=int, default=[0, 1, 2])
    ap.add_argument("--profile", default="field")
    ap.add_argument("--sim", default="mujoco", choices=["kinematic", "mujoco"])
    ap.add_argument("--quick", action="store_true", help="the sample, one seed, kinematic")
    ap.add_argument("--keep", type=Path, help="keep the plants' twins in this folder")
    ap.add_argument("--json", type=Path)
    a = ap.parse_args()
    if a.quick:
        a.plants, a.seeds, a.sim, a.profile = ["sample"], [0], "kinematic", "ideal"
    work = Path(a.keep) if a.keep else Path(tempfile.mkdtemp(prefix="prune-"))
    work.mkdir(parents=True, exist_ok=True)
    rows = run_vines(a.plants, a.seeds, a.sim, a.profile, work)
    done = sum(r["done_right"] for r in rows)
    reach = sum(r["reachable"] for r in rows)
    times = [t for r in rows for t in r["times_per_cut_s"]]
    transits = [t for r in rows for t in r["transit_planning_s"]]
    total = {
        "done_right_of_reachable": done / reach if reach else None,
        "collisions": sum(r["collisions"] for r in rows),
        "median_time_per_cut_s": statistics.median(times) if times else None,
        "max_planning_per_vine_s": max(r["planning_s"] for r in rows),
        "median_planning_per_transit_s": statistics.median(transits) if transits else None,
        # of the runs that cut: one that cut nothing simulated no servo, nothing to time
        "min_realtime_factor": min((r["realtime_factor"] for r in rows if r["done"]),
                                   default=None),
    }  # fmt: skip
    print(f"\nall: {done}/{reach} reachable cuts done right; {total['collisions']} collisions; "
          f"median {total['median_time_per_cut_s']:.1f} s per cut; planning per vine at most "
          f"{total['max_planning_per_vine_s']:.2f} s, per transit median "
          f"{total['median_planning_per_transit_s']:.3f} s; at least "
          f"{total['min_realtime_factor'] or 0:.1f}x real time on the runs that cut")  # fmt: skip
    checks = collision_checks(plant_twin(a.plants[-1] if a.quick else "dense", work),
                              4 if a.quick else 12)  # fmt: skip
    print("\n| collision check in OMPL's RRT-Connect | median s per transit | failed | us per "
          "check | clear of 500 random |\n|---|---|---|---|---|")  # fmt: skip
    for name in ("vinetwin", "open3d"):
        c = checks[name]
        print(f"| {name} | {c['median_transit_s']:.3f} | {c['failed']} | {c['check_us']:.0f} | "
              f"{c['clear_of_500_random']} |")  # fmt: skip
    print(f"Open3D's check takes {checks['ratio_open3d_to_ours']:.1f}x as long per transit")
    ik = inverse_kinematics(50 if a.quick else 200)
    print("\n| inverse kinematics | ms per solve | solved |\n|---|---|---|")
    print(
        f"| vinetwin | {ik['vinetwin']['median_ms']:.2f} | {ik['vinetwin']['solved']}/{ik['poses']} |"
    )
    if isinstance(ik.get("mink"), dict):
        print(f"| mink | {ik['mink']['median_ms']:.2f} | {ik['mink']['solved']}/{ik['poses']} |")
    write_json(a.json, {"sim": a.sim, "profile": a.profile, "seeds": a.seeds, "rows": rows,
                        "total": total, "collision_checks": checks, "inverse_kinematics": ik})  # fmt: skip


if __name__ == "__main__":
    main()
