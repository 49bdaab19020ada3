"""Benchmark: the four ICP variants side by side with Open3D and small_gicp, and the servo cycle.

Clouds: a twin's pruning poses (`--twin`, default the bundled sample) rendered at 848x480 with Open3D ray casting
through the D405 sensor model and the perception chain (reference at the pose, current at a
known offset from it, each with its own noise), at 4 mm and 2 mm voxels. Starts: warm
(2 cm / 3 deg from the truth) and identity (5 cm / 10 deg).

Every method runs the levels of our variant of its objective (`ICPConfig`'s defaults): warm,
reach 3 cm (on 4 mm copies of the clouds for point-to-plane, symmetric and GICP; on the clouds
as given for point-to-point), 1 cm, then 5 mm on the clouds as given; identity,
`ICPConfig.coarse_to_fine()` (16 mm and 8 mm voxels, then 12 mm and 5 mm reach). Our
point-to-plane and symmetric pair points by projection into the reference view at the levels of
1 cm reach or less, our point-to-point and LM by the exact tree (`ICPConfig.association`'s
per-variant default), the peers by their k-d trees. Each
peer gets what it would keep between frames of a servo built once: the reference's downsampled
copies, normals and (small_gicp) k-d tree; the current cloud's downsampling, conversion and (for
GICP) covariances are timed. Open3D's legacy API rebuilds the target's tree on every call; that is
the library's behaviour and is timed. Convergence: ours 1e-5 m / 1e-5 rad per update,
small_gicp the same epsilons, Open3D relative fitness and RMSE 1e-6; at most 40 iterations a
level for all. Timing: per case, each library's methods are warmed up, then timed in rounds,
each round every method once in an order rotated by one (a drift of the machine's speed lands
on them alike); one library after another (interleaved with small_gicp, whose OpenMP threads
spin after each call, ours ran 1.5-3.4x slower: `measure`). The servo cycles interleave the
four variants the same way.

Printed per method: median time (ms), median iterations, translation and rotation error against
the true transform (median and 90th percentile), the fraction within 1 mm / 0.1 deg, and the
time ratio to the fastest peer implementing the same objective (LM and symmetric also to our
point-to-plane). Then the full servo cycle at each voxel: perception chain + ICP + PBVS control
(`Servo.step_depth` with the servo's own ICP settings), in ms and Hz (the JSON's `cycles`), from
two starts: tracking (the servo's steady state: the frame after a trusted one, its kinematic
prediction 2 mm / 0.5 deg off, a frame's motion at the speed limits; the servo then tries ICP's
final level alone, and the JSON's `tracked` is the share of frames it kept) and warm (a first
frame 2 cm / 3 deg off, after a disturbance: the full schedule). `--decimation N` runs every
cloud through the chain with `PerceptionConfig.decimation` N (default: the twin's).

    .venv/bin/python benchmarks/icp.py [--twin TWIN] [--trials 4] [--quick] [--json out.json]
        [--association tree] [--decimation N]
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import statistics
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numba
import numpy as np
from results_file import write_json

import vinetwin
from vinetwin import _lazy
from vinetwin import frames as fr
from vinetwin.cloud import Cloud, perceive, voxel_downsample
from vinetwin.registration.icp import ASSOCIATIONS, ICP, ICPConfig
from vinetwin.render.backends import get_backend
from vinetwin.render.sensor import SensorConfig, apply_d405_model
from vinetwin.servo.config import Limits
from vinetwin.servo.step import Servo
from vinetwin.twin import Twin

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "samples" / "vine_bilateral.twin"
VARIANTS = ("point_to_point", "lm", "point_to_plane", "symmetric")
STARTS = {"warm": (0.02, 3.0), "identity": (0.05, 10.0)}
#: the servo cycle's starts: tracking (a frame's motion at the hardware speed limits, 0.05 m/s
#: and 0.25 rad/s at 30 Hz, unpredicted: the kinematic guess normally removes most of it) and
#: warm (a disturbance, as in the tables)
CYCLE_STARTS = {"tracking": (0.002, 0.5), "warm": STARTS["warm"]}
# which peers implement each of our objectives
PEERS = {
    "point_to_point": ("open3d point_to_point", "small_gicp ICP"),
    "point_to_plane": ("open3d point_to_plane", "small_gicp PLANE_ICP"),
    "symmetric": ("open3d symmetric",),
    "lm": (),
}
MAX_ITER = 40
TOL = 1e-5


def config_for(start: str, variant: str, association: str | None = None) -> ICPConfig:
    """Our settings for a start; `association` None: `ICPConfig`'s default."""
    if start == "identity":
        cfg = ICPConfig.coarse_to_fine(variant, max_iterations=MAX_ITER)
    else:
        cfg = ICPConfig(variant=variant, max_iterations=MAX_ITER)
    return with_association(cfg, association)


def with_association(cfg: ICPConfig, association: str | None) -> ICPConfig:
    """`cfg` with `association` (None: as it is)."""
    return cfg if association is None else dataclasses.replace(cfg, association=association)


@dataclasses.dataclass
class Case:
    pose: str
    reference: Cloud
    current: Cloud
    depth: np.ndarray
    T_true: np.ndarray
    T_init: np.ndarray


def make_cases(
    twin: Twin, voxel: float, trials: int, start: str, rng: np.random.Generator
) -> list[Case]:
    """The twin's poses, `trials` offsets each of the size `start` names (in `STARTS` or
    `CYCLE_STARTS`)."""
    mesh = twin.load_mesh()
    backend = get_backend("open3d", mesh.vertices, mesh.faces, twin.camera)
    per = dataclasses.replace(twin.perception, voxel_size=voxel)
    sensor = SensorConfig()
    cases = []
    dt, dr = {**STARTS, **CYCLE_STARTS}[start]
    for pose in twin.poses:
        Tg = pose.T_vine_camera
        clean = backend.render(Tg)
        ref_depth = apply_d405_model(clean, twin.camera, np.random.default_rng(1), sensor)
        ref = perceive(ref_depth, twin.camera, per)
        for k in range(trials):
            D = fr.random_pose(rng, dt, np.radians(dr))
            depth = apply_d405_model(
                backend.render(Tg @ D), twin.camera, np.random.default_rng(100 + k), sensor
            )
            cur = perceive(depth, twin.camera, per)
            # the truth is D; every method starts from the identity
            cases.append(Case(pose.id, ref, cur, depth, D, np.eye(4)))
    backend.close()
    return cases


# ----------------------------------------------------------------------------- peers
#: the objective (our variant) of each peer method, whose levels it runs
OBJECTIVE = {
    "point_to_point": "point_to_point", "point_to_plane": "point_to_plane",
    "symmetric": "symmetric", "ICP": "point_to_point", "PLANE_ICP": "point_to_plane",
    "GICP": "point_to_plane",
}  # fmt: skip


def _levels(start: str, kind: str) -> list[tuple[float, float]]:
    """The levels our variant of the same objective runs (`ICPConfig`'s defaults)."""
    return config_for(start, OBJECTIVE[kind]).levels()


def _down(cloud: Cloud, voxel: float) -> tuple[np.ndarray, np.ndarray | None]:
    """The same level copy every method gets (unit normals; the cloud as is at voxel 0)."""
    return voxel_downsample(cloud.points, voxel, cloud.normals)


def open3d_method(kind: str, start: str) -> Callable[[Case], Callable[[], tuple[Any, int]]]:
    o3d = _lazy.open3d()
    reg = o3d.pipelines.registration
    crit = reg.ICPConvergenceCriteria(1e-6, 1e-6, MAX_ITER)
    levels = _levels(start, kind)

    def prepare(case: Case) -> Callable[[], tuple[Any, int]]:
        targets = []
        for voxel, dmax in levels:
            pts, nrm = _down(case.reference, voxel)
            pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
            pc.normals = o3d.utility.Vector3dVector(nrm)
            targets.append((voxel, dmax, pc))

        def run() -> tuple[Any, int]:
            T = case.T_init
            for voxel, dmax, tgt in targets:
                pts, nrm = _down(case.current, voxel)
                src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
                if kind == "symmetric":
                    src.normals = o3d.utility.Vector3dVector(nrm)
                    r = reg.registration_symmetric_icp(
                        src, tgt, dmax, T, reg.TransformationEstimationSymmetric(), crit
                    )
                else:
                    est = (
                        reg.TransformationEstimationPointToPoint()
                        if kind == "point_to_point"
                        else reg.TransformationEstimationPointToPlane()
                    )
                    r = reg.registration_icp(src, tgt, dmax, T, est, crit)
                T = np.asarray(r.transformation)
            return T, -1

        return run

    return prepare


def import_small_gicp_with_its_defaults() -> None:
    """Imports small_gicp with the environment a user of small_gicp alone would have: it bundles
    its own libgomp, which reads `GOMP_SPINCOUNT` when it loads, and `import vinetwin` sets that
    variable for numba's libgomp (`vinetwin.GOMP_SPINCOUNT`, `docs/render.md`). Run before any
    of our parallel kernels (numba's libgomp loads at the first, and reads it then)."""
    ours = os.environ.get("GOMP_SPINCOUNT") == vinetwin.GOMP_SPINCOUNT
    if ours:
        del os.environ["GOMP_SPINCOUNT"]
    try:
        import small_gicp  # noqa: F401
    finally:
        if ours:
            os.environ["GOMP_SPINCOUNT"] = vinetwin.GOMP_SPINCOUNT


def small_gicp_method(
    kind: str, start: str, threads: int
) -> Callable[[Case], Callable[[], tuple[Any, int]]]:
    import small_gicp

    levels = _levels(start, kind)

    def prepare(case: Case) -> Callable[[], tuple[Any, int]]:
        targets = []
        for voxel, dmax in levels:
            pts, _ = _down(case.reference, voxel)
            pc = small_gicp.PointCloud(pts)
            tree = small_gicp.KdTree(pc, num_threads=threads)
            small_gicp.estimate_normals_covariances(pc, tree, 20, threads)
            targets.append((voxel, dmax, pc, tree))

        def run() -> tuple[Any, int]:
            T = case.T_init
            iters = 0
            for voxel, dmax, tgt, tree in targets:
                pts, _ = _down(case.current, voxel)
                src = small_gicp.PointCloud(pts)
                if kind == "GICP":
                    small_gicp.estimate_covariances(src, num_neighbors=20, num_threads=threads)
                r = small_gicp.align(
                    tgt,
                    src,
                    tree,
                    T,
                    registration_type=kind,
                    max_correspondence_distance=dmax,
                    num_threads=threads,
                    max_iterations=MAX_ITER,
                    rotation_epsilon=TOL,
                    translation_epsilon=TOL,
                )
                T = np.asarray(r.T_target_source)
                iters += int(r.iterations)
            return T, iters

        return run

    return prepare


def ours_method(
    variant: str, start: str, twin: Twin, association: str | None = None
) -> Callable[[Case], Callable[[], tuple[Any, int]]]:
    def prepare(case: Case) -> Callable[[], tuple[Any, int]]:
        icp = ICP(
            case.reference,
            config_for(start, variant, association),
            camera=twin.camera,
            max_depth=twin.perception.max_depth,
        )

        def run() -> tuple[Any, int]:
            r = icp.align(case.current, case.T_init)
            return r.T_ref_cur, r.iterations

        return run

    return prepare


# ----------------------------------------------------------------------------- measuring
def rotated(items: Sequence[str], k: int) -> list[str]:
    """`items` in the order of round k of an interleaved timing: started k places on."""
    k %= len(items)
    return [*items[k:], *items[:k]]


def measure(
    methods: dict[str, Callable[[Case], Callable[[], tuple[Any, int]]]],
    cases: list[Case],
    repeats: int,
) -> list[dict[str, Any]]:
    """The methods of one library on each case, interleaved: per case every method is prepared
    and warmed up, then each of the `repeats` rounds times every method once, the round's order
    rotated by one, so that a drift of the machine's speed (up to 1.4x within an hour here)
    lands on the methods alike. A method's time on a case is the median of its rounds; its row,
    the median over the cases. Call it once per library (`main`): interleaved with small_gicp,
    ours took 1.5-3.4x their time alone, since small_gicp's bundled libgomp keeps its threads
    spinning after each call (its default, which a user of small_gicp alone has), taking a core
    from whatever runs next; with `OMP_WAIT_POLICY=passive` the difference went away
    (docs/results/speed.md)."""
    names = list(methods)
    times: dict[str, list[float]] = {n: [] for n in names}
    iters: dict[str, list[int]] = {n: [] for n in names}
    et: dict[str, list[float]] = {n: [] for n in names}
    er: dict[str, list[float]] = {n: [] for n in names}
    for case in cases:
        runs = {n: methods[n](case) for n in names}
        last = {n: run() for n, run in runs.items()}  # warm-up (compilation, caches)
        ts: dict[str, list[float]] = {n: [] for n in names}
        for k in range(repeats):
            for n in rotated(names, k):
                t0 = time.perf_counter()
                last[n] = runs[n]()
                ts[n].append(time.perf_counter() - t0)
        for n in names:
            T, it = last[n]
            times[n].append(statistics.median(ts[n]))
            iters[n].append(it)
            dt, dr = fr.pose_error(T, case.T_true)
            et[n].append(1000 * dt)
            er[n].append(float(np.degrees(dr)))
    rows = []
    for n in names:
        a_t, a_r = np.array(et[n]), np.array(er[n])
        rows.append(
            {
                "method": n,
                "ms": 1000 * statistics.median(times[n]),
                "iterations": float(np.median(iters[n])) if min(iters[n]) >= 0 else None,
                "t_mm_median": float(np.median(a_t)),
                "t_mm_p90": float(np.percentile(a_t, 90)),
                "r_deg_median": float(np.median(a_r)),
                "r_deg_p90": float(np.percentile(a_r, 90)),
                "within_1mm_0.1deg": float(np.mean((a_t < 1.0) & (a_r < 0.1))),
                "within_5mm_1deg": float(np.mean((a_t < 5.0) & (a_r < 1.0))),
                "t_mm_cases": [round(float(x), 4) for x in a_t],  # per case, in `cases` order
            }
        )
    return rows


#: a difference of median errors this small (mm) counts as equal accuracy
ACCURACY_TOLERANCE_MM = 0.05


def paired_accuracy(ours: list[float], peer: list[float], seed: int = 0) -> dict[str, Any]:
    """Our translation errors against a peer's on the same cases (mm): the median of the per-case
    differences (ours - peer's), its 95% bootstrap interval (2000 resamples of the cases), the
    share of cases where ours is within `ACCURACY_TOLERANCE_MM` of the peer's or better, and a
    verdict: "worse" when the whole interval lies above the tolerance, "better" when it lies
    below minus the tolerance, else "equal" (the cases cannot tell them apart)."""
    d = np.asarray(ours, float) - np.asarray(peer, float)
    rng = np.random.default_rng(seed)
    boot = np.median(d[rng.integers(0, len(d), (2000, len(d)))], axis=1)
    lo, hi = (float(x) for x in np.percentile(boot, [2.5, 97.5]))
    tol = ACCURACY_TOLERANCE_MM
    verdict = "worse" if lo > tol else "better" if hi < -tol else "equal"
    return {
        "median_diff_mm": float(np.median(d)),
        "ci95_mm": [lo, hi],
        "within_tolerance_or_better": float(np.mean(d <= tol)),
        "verdict": verdict,
    }


def add_ratios(rows: list[dict[str, Any]]) -> None:
    by = {r["method"]: r for r in rows}
    for v in VARIANTS:
        row = by[f"vinetwin {v}"]
        peers = [by[p] for p in PEERS[v] if p in by]
        if peers:
            fastest = min(peers, key=lambda r: r["ms"])
            row["fastest_peer"] = fastest["method"]
            row["ratio_to_fastest_peer"] = row["ms"] / fastest["ms"]
            row["ratios"] = {p["method"]: row["ms"] / p["ms"] for p in peers}
            if "t_mm_cases" in row and "t_mm_cases" in fastest:
                row["accuracy_vs_fastest_peer"] = paired_accuracy(
                    row["t_mm_cases"], fastest["t_mm_cases"]
                )
        if v in ("lm", "symmetric"):
            row["ratio_to_our_point_to_plane"] = row["ms"] / by["vinetwin point_to_plane"]["ms"]


def cycle(
    twin: Twin,
    cases: list[Case],
    repeats: int,
    voxel: float,
    start: str,
    association: str | None = None,
) -> list[dict[str, Any]]:
    """Perception + ICP + control per frame (`Servo.step_depth`, the servo's own ICP settings)
    at `voxel`, from the offsets of `cases` (`start`): for tracking, the frame after a trusted
    one, whose kinematic prediction is the start's offset from the truth (the steady state;
    `tracked`: the share of frames the final ICP level alone aligned); for warm, a first
    frame (the full schedule)."""
    per = dataclasses.replace(twin.perception, voxel_size=voxel)
    times: dict[str, list[float]] = {v: [] for v in VARIANTS}
    parts: dict[str, dict[str, list[float]]] = {
        v: {"perception": [], "icp": [], "control": []} for v in VARIANTS
    }
    tracked: dict[str, list[int]] = {v: [] for v in VARIANTS}
    for case in cases:
        servos = {
            v: Servo(
                case.reference,
                icp=with_association(ICPConfig(variant=v), association),
                camera=twin.camera,
                perception=per,
                limits=Limits(max_linear_acceleration=0, max_angular_acceleration=0),
            )
            for v in VARIANTS
        }
        # the variants interleaved, as `measure` does: round k times each once, rotated by k
        for k in range(repeats + 1):
            for v in rotated(VARIANTS, k):
                servo = servos[v]
                stamp = float(k)
                if start == "tracking":
                    # the steady state: a trusted frame at the truth, then the frame whose
                    # kinematic prediction is the case's start (the robot reports a motion of
                    # inv(T_true) that the camera did not make)
                    servo.reset(case.T_true)
                    servo.step_depth(case.depth, stamp=stamp, T_base_camera=np.eye(4))
                    base, stamp = fr.invert(case.T_true) @ case.T_init, stamp + 1 / 30
                else:  # a first frame (after a disturbance): the full schedule
                    servo.reset(case.T_init)
                    base = None
                before = servo.tracked_frames
                t0 = time.perf_counter()
                r = servo.step_depth(case.depth, stamp=stamp, T_base_camera=base)
                el = time.perf_counter() - t0
                if k == 0:
                    continue  # warm-up
                times[v].append(el)
                tracked[v].append(servo.tracked_frames - before)
                for key in parts[v]:
                    parts[v][key].append(r.timings.get(key, 0.0))
    out = []
    for v in VARIANTS:
        ms = 1000 * statistics.median(times[v])
        out.append(
            {
                "voxel": voxel,
                "start": start,
                "variant": v,
                "cycle_ms": ms,
                "hz": 1000 / ms,
                "tracked": float(np.mean(tracked[v])),
                **{f"{k}_ms": 1000 * statistics.median(x) for k, x in parts[v].items()},
            }
        )
    return out


def print_table(title: str, rows: list[dict[str, Any]]) -> None:
    print(f"\n{title}")
    print(
        f"{'method':30} {'ms':>7} {'iter':>5} {'t mm med':>9} {'p90':>6} {'r deg med':>9} {'p90':>6}"
        f" {'<=1mm/.1deg':>11} {'ratio to fastest peer':>28} {'/ our p2plane':>13}"
    )
    for r in rows:
        it = "-" if r["iterations"] is None else f"{r['iterations']:.0f}"
        ratio = (
            f"{r['ratio_to_fastest_peer']:.2f} ({r['fastest_peer']})"
            if "ratio_to_fastest_peer" in r
            else ""
        )
        own = (
            f"{r['ratio_to_our_point_to_plane']:.2f}" if "ratio_to_our_point_to_plane" in r else ""
        )
        print(
            f"{r['method']:30} {r['ms']:7.2f} {it:>5} {r['t_mm_median']:9.2f} {r['t_mm_p90']:6.2f}"
            f" {r['r_deg_median']:9.3f} {r['r_deg_p90']:6.3f} {r['within_1mm_0.1deg']:11.2f}"
            f" {ratio:>28} {own:>13}"
        )


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--trials", type=int, default=4, help="offsets per pruning pose")
    ap.add_argument("--repeats", type=int, default=3, help="timed runs per case (median)")
    ap.add_argument("--threads", type=int, default=2, help="small_gicp threads")
    ap.add_argument("--quick", action="store_true", help="1 trial, 1 repeat, 4 mm only")
    ap.add_argument("--json", type=Path, help="write the figures here")
    ap.add_argument("--twin", type=Path, default=SAMPLE, help="twin folder (default: the sample)")
    ap.add_argument(
        "--decimation", type=int, default=None,
        help="the perception chain's decimation for every cloud of the run (default: the twin's)",
    )  # fmt: skip
    ap.add_argument(
        "--association", choices=ASSOCIATIONS, default=None,
        help="our ICP's association for every variant (default: each variant's, "
        "ICPConfig.association_in_use); tree: the exact k-d tree at every level, to compare",
    )  # fmt: skip
    args = ap.parse_args()
    import_small_gicp_with_its_defaults()
    if args.quick:
        args.trials, args.repeats = 1, 1
    twin = Twin.load(args.twin)
    if args.decimation is not None:
        twin.perception = dataclasses.replace(twin.perception, decimation=args.decimation)
    rng = np.random.default_rng(7)
    voxels = (0.004,) if args.quick else (0.004, 0.002)
    print(
        f"sample {twin.name}, {twin.camera.width}x{twin.camera.height}, {len(twin.poses)} poses x "
        f"{args.trials} offsets, {os.cpu_count()} CPUs; small_gicp {args.threads} threads, Open3D "
        f"its OpenMP default, vinetwin {numba.get_num_threads()} numba threads"
    )
    results: dict[str, Any] = {
        "twin": twin.name,
        "trials": args.trials,
        "association": args.association or "per variant (ICPConfig.association_in_use)",
        "decimation": twin.perception.decimation,
        "tables": [],
        "cycles": [],
    }
    for voxel in voxels:
        for start in STARTS:
            cases = make_cases(twin, voxel, args.trials, start, rng)
            npts = int(np.median([len(c.current) for c in cases]))
            methods: dict[str, Callable[[Case], Callable[[], tuple[Any, int]]]] = {}
            for v in VARIANTS:
                methods[f"vinetwin {v}"] = ours_method(v, start, twin, args.association)
            for k in ("point_to_point", "point_to_plane", "symmetric"):
                methods[f"open3d {k}"] = open3d_method(k, start)
            for k in ("ICP", "PLANE_ICP", "GICP"):
                methods[f"small_gicp {k}"] = small_gicp_method(k, start, args.threads)
            # each library's methods interleaved among themselves, one library after another
            rows = [
                row
                for lib in dict.fromkeys(n.split()[0] for n in methods)
                for row in measure(
                    {n: m for n, m in methods.items() if n.split()[0] == lib}, cases, args.repeats
                )
            ]
            add_ratios(rows)
            title = (
                f"voxel {1000 * voxel:.0f} mm, start {start} ({STARTS[start][0] * 100:.0f} cm / "
                f"{STARTS[start][1]:.0f} deg), {len(cases)} cases, median {npts} current points"
            )
            print_table(title, rows)
            results["tables"].append(
                {"voxel": voxel, "start": start, "cases": len(cases), "points": npts, "rows": rows}
            )
            if start == "warm":
                results["cycles"] += cycle(
                    twin, cases, args.repeats, voxel, start, args.association
                )
        tracking = make_cases(twin, voxel, args.trials, "tracking", rng)
        results["cycles"] += cycle(
            twin, tracking, args.repeats, voxel, "tracking", args.association
        )
    print("\nservo cycle (perception + ICP + control, Servo.step_depth; starts: tracking "
          f"{CYCLE_STARTS['tracking'][0] * 1000:.0f} mm / {CYCLE_STARTS['tracking'][1]} deg, "
          "warm as above)")  # fmt: skip
    print(f"{'voxel':>5} {'start':9} {'variant':16} {'cycle ms':>9} {'Hz':>6} {'perception':>11} "
          f"{'icp':>6} {'control':>8} {'tracked':>7}")  # fmt: skip
    key = lambda c: (-c["voxel"], c["start"] != "tracking")  # noqa: E731
    for c in sorted(results["cycles"], key=key):
        print(
            f"{1000 * c['voxel']:4.0f}mm {c['start']:9} {c['variant']:16} {c['cycle_ms']:9.2f} "
            f"{c['hz']:6.0f} "
            f"{c['perception_ms']:11.2f} {c['icp_ms']:6.2f} {c['control_ms']:8.3f} "
            f"{c['tracked']:7.2f}"
        )
    write_json(args.json, results)


if __name__ == "__main__":
    main()
