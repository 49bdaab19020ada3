"""Cut proposals (`vinetwin propose`) on the bundled sample, a dense generated vine, two hydroshoot
vines and a Tree-Models-Library tree (`../shared/data`): per plant and rule, the cuts proposed,
poses found, median clearance, reference points per pose (rendered by `reference_for`, the
export's chain), the time to propose, and:

- **collisions**, checked apart from the search: points on the body's surfaces (`BodyConfig`:
  the swept camera box, the tool's capsule outside the jaw zone) against the mesh with Open3D's
  distance query, at every proposed pose and at the same cuts' default approaches; and the
  arm's wrist (the planner's spheres on link 7, the mount and the housing, `arm.camera_fixed_spheres`,
  along the approach) against the clearance the planner asks of each (`wrist_short`);
- **agreement under real-scan conditions** (`--agreement`): each vine scanned by the simulated
  scanner at the realistic quality, imported with `import_scan`, proposals on it against
  proposals on the true twin (moved into the scan's vine frame): the share of the true cuts with
  one of ours within 1 cm, missing, extra; once with the same stated internode on both
  (the skeleton's share of the error), once with the true twin's own nodes (the whole chain);
  and why each true cut missed (`miss_classes`, same internode). `--agreement-json FILE`
  writes the agreement apart (the three-seed run: `benchmarks/results/propose_agreement.json`);
- **the rule's own stability** (`--stability`): the spur rule on each vine's true skeleton against
  the same skeleton resampled and moved by a smooth axis error of 0-2 mm (`jitter`,
  `STABILITY_SIGMAS`): what the scanned agreement could reach with every cane routed right.
  `--stability-json FILE` writes it (`benchmarks/results/propose_stability.json`).

    .venv/bin/python benchmarks/propose.py [--plants sample dense ...] [--rules spur cane]
        [--agreement [--agreement-seeds 3] [--agreement-json F]] [--stability [--stability-json F]]
        [--keep DIR] [--check-profile PROFILE]
        [--json benchmarks/results/propose.json]
        [--picture docs/results/proposals_dense.png]

`--keep DIR` leaves the proposed twins there (for `vinetwin validate DIR --profile field`).
`--check-profile PROFILE` checks each pose by the servo while proposing (`ServoCheckConfig`).
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from vinetwin import _lazy
from vinetwin.arm import camera_fixed_spheres
from vinetwin.plan.config import (
    BodyConfig,
    ProposeConfig,
    RuleConfig,
    SearchConfig,
    ServoCheckConfig,
)
from vinetwin.plan.job_config import ReachConfig
from vinetwin.plan.proposer import propose
from vinetwin.sim.servo_check import propose_checked
from vinetwin.twin.model import Twin
from vinetwin.twin.poses import pruning_pose

sys.path.insert(0, str(Path(__file__).resolve().parent))
from results_file import machine

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
PLANTS = {
    "sample": None,
    "dense": None,
    "gdc_can1": DATA / "vines/hydroshoot/gdc_can1_grapevine/digit.input",
    "vsp_ww": DATA / "vines/hydroshoot/vsp_ww_grapevine/digit.input",
    "apple_spindle": DATA / "trees/tree-models-library/Apple_1_TallSpindle.txt",
}


def make_twin(name: str, out: Path) -> Twin:
    from vinetwin.twin.generator import sample_twin
    from vinetwin.twin.importers import import_twin

    if name == "sample":  # the bundled sample's vine (seed 3), without its cut points
        return sample_twin(out, 3, cut_points=0, overwrite=True)
    if name == "dense":
        return sample_twin(out, 5, dense=True, cut_points=0, overwrite=True)
    path = PLANTS[name]
    assert path is not None
    return import_twin(path, out, edge=0.003, overwrite=True)


def body_points(standoff: float, body: BodyConfig) -> np.ndarray:
    """Points on the body's surfaces in the camera frame at the pruning pose (3 mm apart), the
    tool's within the jaw zone of the cut left out."""
    w, h, d = body.camera_size
    travel = standoff - body.tool_reach
    pts = []
    for z in np.arange(-d, travel + 1e-9, 0.003):
        for x in np.arange(-w / 2, w / 2 + 1e-9, 0.003):
            pts += [[x, -h / 2, z], [x, h / 2, z]]
        for y in np.arange(-h / 2, h / 2 + 1e-9, 0.003):
            pts += [[-w / 2, y, z], [w / 2, y, z]]
    for x in np.arange(-w / 2, w / 2 + 1e-9, 0.003):
        for y in np.arange(-h / 2, h / 2 + 1e-9, 0.003):
            pts += [[x, y, -d], [x, y, travel]]
    ring = np.linspace(0, 2 * math.pi, 24, endpoint=False)
    r = body.tool_radius
    for z in np.arange(0, standoff + 1e-9, 0.003):
        if standoff - z < body.jaw_zone + r:
            continue
        pts += [[r * math.cos(a), r * math.sin(a), z] for a in ring]
    return np.array(pts)


class Checker:
    """The body's distance to the mesh (Open3D), independent of the search's vertex test."""

    def __init__(self, twin: Twin, cfg: SearchConfig) -> None:
        o3d = _lazy.open3d()
        m = twin.load_mesh()
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(o3d.core.Tensor(np.asarray(m.vertices, np.float32)),
                                 o3d.core.Tensor(np.asarray(m.faces, np.uint32)))  # fmt: skip
        self.B = body_points(cfg.standoff, cfg.body)
        self.tensor = o3d.core.Tensor
        # the planner's own spheres for the arm's parts fixed to the camera (link 7, mount,
        # housing), each with the clearance the planner asks of it, along the approach
        cam, radius, part = camera_fixed_spheres(twin.T_flange_camera)
        steps = np.linspace(0.0, cfg.standoff - cfg.body.tool_reach, 17)
        self.W = (cam[None] + steps[:, None, None] * [0.0, 0.0, 1.0]).reshape(-1, 3)
        keep = np.where(np.asarray(part) == "link7", ReachConfig().clearance, cfg.body.margin)
        self.W_need = np.tile(radius + keep, len(steps))

    def distance(self, T: np.ndarray) -> float:
        W = (self.B @ T[:3, :3].T + T[:3, 3]).astype(np.float32)
        d = self.scene.compute_distance(self.tensor(W)).numpy()
        inside = self.scene.compute_occupancy(self.tensor(W)).numpy() > 0.5
        return float(np.where(inside, -d, d).min())

    def wrist(self, T: np.ndarray) -> float:
        """How far (m) the wrist's spheres stay beyond the clearance each must keep (negative:
        short of it), the mesh's exact surface."""
        W = (self.W @ T[:3, :3].T + T[:3, 3]).astype(np.float32)
        d = self.scene.compute_distance(self.tensor(W)).numpy()
        return float((d - self.W_need).min())


def reference_points(twin: Twin, pose_ids: list[str]) -> list[int]:
    from vinetwin.render.backends import scene_backend
    from vinetwin.render.reference import reference_for

    m = twin.load_mesh()
    backend = scene_backend(np.asarray(m.vertices), np.asarray(m.faces), twin.camera)
    try:
        return [len(reference_for(twin, pid, use_exported=False, renderer=backend).cloud)
                for pid in pose_ids]  # fmt: skip
    finally:
        backend.close()


def run_plant(name: str, rule: str, work: Path, check_profile: str = "") -> dict[str, Any]:
    root = work / f"{name}_{rule}.twin"
    twin = make_twin(name, root)
    servo = ServoCheckConfig(check_profile=check_profile)
    cfg = ProposeConfig(rule=RuleConfig(rule=rule), servo=servo)  # type: ignore[arg-type]
    t0 = time.perf_counter()
    try:
        result = propose_checked(twin, cfg) if check_profile else propose(twin, cfg)
    except Exception as exc:  # a rule that refuses a plant is a result
        return {"plant": name, "rule": rule, "error": str(exc)[:200]}
    secs = time.perf_counter() - t0
    twin = Twin.load(root)
    check = Checker(twin, cfg.search)
    dists, dflt_dists, posed, wrists = [], [], [], []
    default_bad = fixed = 0
    for r in result.rows:
        cut = twin.cut_point(r["id"])
        Td = pruning_pose(cut.point, cut.cane_axis, None)
        dd = check.distance(Td)
        dflt_dists.append(dd)
        d = r["default"]
        bad = dd <= 0 or not d["cut_seen"] or d["visible"] < cfg.search.min_visible
        default_bad += bad
        if "pose_id" in r:
            posed.append(r["pose_id"])
            Tp = np.asarray(twin.pose(r["pose_id"]).T_vine_camera)
            dists.append(check.distance(Tp))
            wrists.append(check.wrist(Tp))
            fixed += bad
    refs = reference_points(twin, posed)
    clear = [r["search"]["clearance_m"] for r in result.rows if "search" in r]
    return {
        "plant": name, "rule": rule, "seconds": round(secs, 2), **result.counts(),
        "shorten": sum(r["action"] == "shorten" for r in result.rows),
        "remove": sum(r["action"] == "remove" for r in result.rows),
        "no_pose_reasons": [r["pose"] for r in result.rows if r["pose"] != "found"],
        "median_clearance_mm": round(1000 * float(np.median(clear)), 2) if clear else None,
        "collisions": int(sum(d <= 0 for d in dists)),
        "min_body_distance_mm": round(1000 * min(dists), 2) if dists else None,
        "wrist_short": int(sum(w < 0 for w in wrists)),
        "wrist_min_spare_mm": round(1000 * min(wrists), 2) if wrists else None,
        "median_reference_points": int(np.median(refs)) if refs else 0,
        "min_reference_points": int(min(refs)) if refs else 0,
        "default_colliding": int(sum(d <= 0 for d in dflt_dists)),
        "default_bad": int(default_bad), "default_bad_fixed": int(fixed),
        **({"servo_check": {r["pose_id"]: r["servo_check"] for r in result.rows
                            if "servo_check" in r}} if check_profile else {}),
    }  # fmt: skip


def agreement(name: str, work: Path, seed: int = 0) -> dict[str, Any]:
    """Proposals on a twin imported from a simulated scan (its draw: `seed`) against those on
    the true twin."""
    from scan_accuracy import truth_skeleton, write_ply

    from vinetwin.scan.config import ScanImportConfig
    from vinetwin.scan.importer import import_scan
    from vinetwin.scan.synthetic import QUALITY_LADDER, scanner_frame, simulate_scan
    from vinetwin.twin.skeleton import DEFAULT_INTERNODE, transform_skeleton, tube_mesh

    truth = _sample3() if name == "sample" else truth_skeleton(name)
    V, F = tube_mesh(truth, edge=0.003, caps="round")
    wire = float(truth.branches[0].points[-1][2])
    P, _ = simulate_scan(V, F, QUALITY_LADDER["realistic"], seed, wire_height=wire)
    T_scan_vine = scanner_frame(seed)
    f = work / f"{name}_scan.ply"
    write_ply(f, (P @ T_scan_vine[:3, :3].T + T_scan_vine[:3, 3]) * 1000.0)
    twin_s, scan = import_scan(f, work / f"{name}_scan.twin", ScanImportConfig(), overwrite=True)
    T = scan.T_vine_scan @ T_scan_vine  # the truth's vine frame -> the scan twin's
    true_twin = make_twin(name, work / f"{name}_true.twin")
    out: dict[str, Any] = {"plant": name, "seed": seed}
    for label, internode in (("same_internode", DEFAULT_INTERNODE), ("true_nodes", 0.0)):
        for tw in (twin_s, true_twin):
            for c in list(tw.cut_points):
                tw.delete_cut_point(c.id)
        cfg_s = ProposeConfig(rule=RuleConfig(internode=DEFAULT_INTERNODE), replace=True)
        cfg_t = ProposeConfig(rule=RuleConfig(internode=internode), replace=True)
        ours = propose(twin_s, cfg_s)
        theirs = propose(true_twin, cfg_t)
        p_ours = np.array([twin_s.cut_point(r["id"]).point for r in ours.rows]).reshape(-1, 3)
        p_true = np.array([true_twin.cut_point(r["id"]).point for r in theirs.rows]).reshape(-1, 3)
        p_true = p_true @ T[:3, :3].T + T[:3, 3]
        used = _matched(p_true, p_ours)
        matched = len(used)
        out[label] = {"true": len(p_true), "ours": len(p_ours), "matched": matched,
                      "share": round(matched / max(len(p_true), 1), 3),
                      "missing": len(p_true) - matched, "extra": len(p_ours) - len(used)}  # fmt: skip
    sk_t, sk_s = true_twin.load_skeleton(), twin_s.load_skeleton()
    assert sk_t is not None and sk_s is not None  # both twins were made with one
    out["misses"] = miss_classes(
        sk_s, transform_skeleton(sk_t, T), RuleConfig(internode=DEFAULT_INTERNODE)
    )
    return out


def _matched(p_true: np.ndarray, p_ours: np.ndarray, tol: float = 0.01) -> set[int]:
    """Which of `p_ours` are matched one to one, nearest first, to a point of `p_true` within
    `tol` (their indices)."""
    used: set[int] = set()
    for p in p_true:
        d = np.linalg.norm(p_ours - p, axis=1) if len(p_ours) else np.zeros(0)
        for j in np.argsort(d):
            if d[j] > tol:
                break
            if int(j) not in used:
                used.add(int(j))
                break
    return used


def jitter(
    sk: Any, sigma: float, rng: np.random.Generator, step: float = 0.002, corr: float = 0.02
) -> Any:
    """A copy of the skeleton with each branch resampled every `step` and its axis moved by a
    smooth error: independent normal offsets (`sigma` per coordinate) every `corr` along it,
    interpolated between (a scan's skeleton errs by a slowly varying offset, not point by
    point). Nodes are dropped (a scan knows none)."""
    import copy

    from vinetwin.twin.skeleton import arc_length, resample

    out = copy.deepcopy(sk)
    for b in out.branches:
        P, R = resample(b.points, b.radii, step)
        s = arc_length(P)
        knots = np.arange(0.0, s[-1] + corr, corr)
        E = rng.normal(0.0, sigma, (len(knots), 3))
        b.points = P + np.column_stack([np.interp(s, knots, E[:, k]) for k in range(3)])
        b.radii, b.nodes = R, np.zeros(0)
    return out


#: Axis errors (m, `jitter`'s sigma) of the rule's own stability (`stability`): 0 resamples
#: only; 1-2 mm is how far the scanned skeletons' axes are off (median 1.0-1.6 mm on the four
#: vines' realistic scans).
STABILITY_SIGMAS = (0.0, 0.0005, 0.001, 0.002)


def stability(name: str, reps: int = 3) -> dict[str, Any]:
    """The rule's own stability: the spur rule on the true skeleton against the same rule on
    that skeleton moved by `jitter` (each sigma of `STABILITY_SIGMAS`, `reps` draws), the same
    internode on both: the share of the true cuts with one within 1 cm, and why the others
    missed (`miss_classes`). Every cane is routed right here: what is lost is the rule's
    discrete decisions (which spur, which cane is kept, cane or side shoot) flipping under a
    small error, a ceiling for the scanned agreement."""
    from scan_accuracy import truth_skeleton
    from scipy.spatial import cKDTree

    from vinetwin.plan.rules import propose_cuts
    from vinetwin.twin.skeleton import DEFAULT_INTERNODE, resample

    truth = _sample3() if name == "sample" else truth_skeleton(name)
    cfg = RuleConfig(internode=DEFAULT_INTERNODE)
    p_true = np.array([p.point for p in propose_cuts(truth, cfg)]).reshape(-1, 3)
    axis = cKDTree(np.vstack([resample(b.points, b.radii, 0.002)[0] for b in truth.branches]))
    rows = []
    for sigma in STABILITY_SIGMAS:
        matched, offsets = 0, []
        misses = dict.fromkeys(MISS_CLASSES, 0)
        for rep in range(reps):
            sk = jitter(truth, sigma, np.random.default_rng(rep))
            p_ours = np.array([p.point for p in propose_cuts(sk, cfg)]).reshape(-1, 3)
            matched += len(_matched(p_true, p_ours))
            moved = np.vstack([b.points for b in sk.branches])
            offsets.append(float(np.median(axis.query(moved)[0])))
            for k, v in miss_classes(sk, truth, cfg).items():
                misses[k] += v
        n = reps * len(p_true)
        rows.append({"sigma_mm": sigma * 1000, "median_offset_mm": round(1000 * float(np.mean(offsets)), 2),
                     "matched": matched, "true": n, "share": round(matched / max(n, 1), 3),
                     "misses": misses})  # fmt: skip
    return {"plant": name, "reps": reps, "rows": rows}


#: Why a true cut has none of ours within 1 cm (`miss_classes`), judged where the true cut is.
MISS_CLASSES = {
    "displaced": "our cut on that cane, the same action, 1-2 cm away (where it parts, its buds)",
    "displaced_far": "our cut on that cane, the same action, more than 2 cm away",
    "choice": "our cane there gets the other action; our spur holds as many canes as the true one",
    "spur_differs": "our cane there gets the other action; our spur holds more or fewer canes",
    "no_cut": "our cane there gets no cut",
    "no_axis": "no axis of ours within 6 mm of the cut (touching canes run as one axis, or lost)",
}


def miss_classes(ours: Any, truth: Any, cfg: RuleConfig) -> dict[str, int]:
    """For each true cut (the rule on `truth`) with none of ours (the rule on `ours`) within
    1 cm: why (`MISS_CLASSES`), counted, from what our skeleton has at the true cut: the shoots
    whose axis passes within 6 mm of it and the cuts the rule gives them. The two skeletons in
    one frame."""
    from scipy.spatial import cKDTree

    from vinetwin.plan.rules import analyse, propose_cuts

    s_t, g_t = analyse(truth, cfg)
    s_o, g_o = analyse(ours, cfg)
    p_t, p_o = propose_cuts(truth, cfg), propose_cuts(ours, cfg)
    pts_o = np.array([p.point for p in p_o]).reshape(-1, 3)
    trees = [cKDTree(s.points) for s in s_o]
    by_label = {s.label: s for s in s_t}

    def n_canes(ss: list[Any], g: list[int]) -> int:
        return sum(1 for i in g if ss[i].side_of < 0)

    out = dict.fromkeys(MISS_CLASSES, 0)
    for p in p_t:
        if len(pts_o) and float(np.min(np.linalg.norm(pts_o - p.point, axis=1))) <= 0.01:
            continue
        near = [j for j, t in enumerate(trees) if t.query(p.point)[0] <= 0.006]
        if not near:
            out["no_axis"] += 1
            continue
        labels = {s_o[j].label for j in near}
        mine = [q for q in p_o if q.label in labels]
        same = [float(np.linalg.norm(q.point - p.point)) for q in mine if q.action == p.action]
        if same:
            out["displaced" if min(same) <= 0.02 else "displaced_far"] += 1
        elif mine:
            n_t = n_canes(s_t, g_t[by_label[p.label].spur])
            n_o = {n_canes(s_o, g_o[s_o[j].spur]) for j in near}
            out["choice" if n_t in n_o else "spur_differs"] += 1
        else:
            out["no_cut"] += 1
    return out


def _sample3() -> Any:
    from vinetwin.twin.generator import generate_vine

    return generate_vine(3)


def picture(twin_dir: Path, rule: str, out: Path) -> None:
    """The skeleton with its proposed cuts (green: shortened, red: removed, magenta x: no pose)
    and each pose's camera and straight approach, from the robot's side and obliquely."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tw = Twin.load(twin_dir)
    sk = tw.load_skeleton()
    assert sk is not None
    P = np.concatenate([b.points for b in sk.branches])
    lo, hi = P.min(0), P.max(0)
    mid, half = (lo + hi) / 2, (hi - lo).max() / 2
    fig = plt.figure(figsize=(13, 7.5))
    views = [(8, -90, "from the robot's side (-Y)"), (25, -55, "oblique")]
    for k, (elev, azim, title) in enumerate(views):
        ax: Any = fig.add_subplot(1, 2, k + 1, projection="3d")
        for b in sk.branches:
            lw = {"trunk": 4, "cordon": 3, "spur": 2}.get(b.kind, 1)
            ax.plot(*b.points.T, color=(0.45, 0.3, 0.2), lw=lw)
        for c in tw.cut_points:
            rec = c.extra.get("proposal", {})
            col = {"shorten": "tab:green", "remove": "tab:red"}.get(rec.get("action"), "k")
            ax.scatter(*c.point, color=col, s=30, depthshade=False)
            if rec.get("pose") not in (None, "found"):
                ax.scatter(*c.point, color="magenta", s=80, marker="x")
        for p in tw.poses:
            cut = tw.cut_point(p.cut_point).point
            o = np.asarray(p.T_vine_camera)[:3, 3]
            ax.plot(*np.stack([o, cut]).T, color="tab:blue", lw=0.8)
            ax.scatter(*o, color="tab:blue", s=8, marker="s", depthshade=False)
        ax.set_xlim(mid[0] - half, mid[0] + half)
        ax.set_ylim(mid[1] - half, mid[1] + half)
        ax.set_zlim(max(mid[2] - half, 0.4), mid[2] + 0.8 * half)
        ax.view_init(elev, azim)
        ax.set_title(title)
        ax.set_xlabel("x (m)")
    fig.suptitle(f"{tw.name}, {rule} rule: {len(tw.cut_points)} cuts (green: shortened, red: "
                 "removed), blue: the camera at each searched pose and its straight approach")  # fmt: skip
    fig.tight_layout()
    fig.savefig(out, dpi=90)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--plants", nargs="*", default=list(PLANTS))
    ap.add_argument("--rules", nargs="*", default=["spur", "cane"])
    ap.add_argument("--agreement", action="store_true", help="also the scanned-twin agreement")
    ap.add_argument("--agreement-seeds", type=int, default=1, help="scans per plant (seeds 0..N-1)")
    ap.add_argument("--agreement-json", type=Path, help="write the agreement here (apart)")
    ap.add_argument(
        "--stability",
        action="store_true",
        help="also the rule's own stability on each vine's true skeleton (`stability`)",
    )
    ap.add_argument("--stability-json", type=Path, help="write the stability here")
    ap.add_argument("--keep", type=Path, help="leave the proposed twins in this folder")
    ap.add_argument(
        "--check-profile",
        default="",
        help="check each pose by the servo under "
        "this profile (`propose --check-profile`); the large vines and the tree want a "
        'profile with "twin_trajectory": "poses"',
    )
    ap.add_argument("--json", type=Path)
    ap.add_argument("--picture", type=Path, help="draw the dense vine's spur proposals here")
    a = ap.parse_args()
    rows, agree, stab = [], [], []
    work = Path(a.keep) if a.keep else Path(tempfile.mkdtemp(prefix="propose-"))
    work.mkdir(parents=True, exist_ok=True)
    try:
        if a.rules:
            print("| plant | rule | cuts (shorten/remove) | posed | no pose | s | median clearance mm "
                  "| collisions (min mm) | wrist short of its clearance (min spare mm) "
                  "| ref points median (min) | default poses colliding / bad | bad fixed |")  # fmt: skip
            print("|---|---|---|---|---|---|---|---|---|---|---|---|")
        for name in a.plants:
            for rule in a.rules:
                r = run_plant(name, rule, work, a.check_profile)
                rows.append(r)
                if "error" in r:
                    print(f"| {name} | {rule} | refused: {r['error']} |", flush=True)
                    continue
                print(f"| {name} | {rule} | {r['proposed']} ({r['shorten']}/{r['remove']}) "
                      f"| {r['with_pose']} | {r['without_pose']} | {r['seconds']:.1f} "
                      f"| {r['median_clearance_mm']} | {r['collisions']} ({r['min_body_distance_mm']}) "
                      f"| {r['wrist_short']} ({r['wrist_min_spare_mm']}) "
                      f"| {r['median_reference_points']} ({r['min_reference_points']}) "
                      f"| {r['default_colliding']} / {r['default_bad']} | {r['default_bad_fixed']} |",
                      flush=True)  # fmt: skip
        if a.picture and (work / "dense_spur.twin").exists():
            picture(work / "dense_spur.twin", "spur", a.picture)
        if a.agreement:
            print("\n| plant | seed | same internode: matched / true (missing, extra) | true "
                  "nodes: matched / true (missing, extra) | misses (same internode) |\n"
                  "|---|---|---|---|---|")  # fmt: skip
            for name, seed in [(p, k) for p in a.plants if p != "apple_spindle"
                               for k in range(a.agreement_seeds)]:  # fmt: skip
                g = agreement(name, work, seed)
                agree.append(g)
                s, t = g["same_internode"], g["true_nodes"]
                m = ", ".join(f"{k} {v}" for k, v in g["misses"].items() if v)
                print(f"| {name} | {seed} | {s['matched']}/{s['true']} = {s['share']:.0%} ({s['missing']}, "
                      f"{s['extra']}) | {t['matched']}/{t['true']} = {t['share']:.0%} "
                      f"({t['missing']}, {t['extra']}) | {m} |", flush=True)  # fmt: skip
            misses = {k: sum(g["misses"][k] for g in agree) for k in MISS_CLASSES}
            print("\nwhy the true cuts were missed (same internode, all runs):")
            for k, v in misses.items():
                print(f"- {k}: {v} ({MISS_CLASSES[k]})")
        if a.stability:
            print("\n| plant | " + " | ".join(f"axis error sigma {s * 1000:g} mm" for s in STABILITY_SIGMAS)
                  + " |\n|---|" + "---|" * len(STABILITY_SIGMAS))  # fmt: skip
            for name in [p for p in a.plants if p != "apple_spindle"]:
                st = stability(name)
                stab.append(st)
                print(f"| {name} | " + " | ".join(
                    f"{r['matched']}/{r['true']} = {r['share']:.0%} (off {r['median_offset_mm']} mm)"
                    for r in st["rows"]) + " |", flush=True)  # fmt: skip
            print("\nall vines, and why the true cuts were missed:")
            for i, sigma in enumerate(STABILITY_SIGMAS):
                m = {k: sum(st["rows"][i]["misses"][k] for st in stab) for k in MISS_CLASSES}
                hit = sum(st["rows"][i]["matched"] for st in stab)
                n = sum(st["rows"][i]["true"] for st in stab)
                print(f"- sigma {sigma * 1000:g} mm: {hit}/{n} = {hit / max(n, 1):.1%}; missed: "
                      + (", ".join(f"{k} {v}" for k, v in m.items() if v) or "none"))  # fmt: skip
    finally:
        if not a.keep:
            shutil.rmtree(work, ignore_errors=True)
    if a.json:
        a.json.write_text(json.dumps({"machine": machine(), "rows": rows}
                                     | ({"agreement": agree} if agree and not a.agreement_json else {}),
                                     indent=1))  # fmt: skip
    if a.stability_json:
        a.stability_json.write_text(json.dumps({"machine": machine(), "sigmas_m": STABILITY_SIGMAS,
                                                "stability": stab, "miss_classes": MISS_CLASSES},
                                               indent=1))  # fmt: skip
    if a.agreement_json:
        a.agreement_json.write_text(json.dumps({"machine": machine(), "agreement": agree,
                                                "miss_classes": MISS_CLASSES}, indent=1))  # fmt: skip


if __name__ == "__main__":
    main()
