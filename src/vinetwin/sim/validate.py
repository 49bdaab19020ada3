"""Per-pose validation: can the servo reach each pruning pose, with which ICP variant, from how far?

For each pruning pose and variant, `starts` closed-loop runs (kinematic simulation) begin at
stratified distances: start k (1..N) is k/N of `radius_translation` and `radius_rotation` away from
the pose, in a random direction that still sees the cut. Per pose and variant this gives:

- the success rate (runs that converged: final static error within 2 mm / 0.01 rad);
- the convergence basin: the largest fraction k/N such that every start at or below it converged,
  as a distance and an angle (0 when even the nearest start failed).

Written to `TWIN/validation/POSE.VARIANT.json` as each pose and variant completes (resumable: a
file whose inputs digest matches is not run again unless forced), summarised in `twin.json` under
each pruning pose's `validation` field, and drawn as a servo-ability map
(`validation/summary.md`, `validation/summary.png`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from vinetwin._faults import fault_point
from vinetwin.executor import ExecutorConfig
from vinetwin.files import (
    atomic_write_json,
    atomic_write_text,
    file_sha256,
    json_sha256,
    save_figure,
)
from vinetwin.jobstore import JobStore
from vinetwin.render.reference import pose_seed
from vinetwin.sim.config import FaultConfig, SimConfig, ValidateConfig, servo_settings
from vinetwin.sim.session import SimSpec, start_pose
from vinetwin.sim.simulate import simulate
from vinetwin.sim.workers import run_jobs, twin_context, worker_world
from vinetwin.twin.model import Twin, check_id

VALIDATION_FORMAT = 2


@dataclass
class _Group:
    pose_id: str
    variant: str
    goal: list[list[float]]
    starts: list[list[list[float]]]
    fractions: list[float]
    reference_seed: int
    sim: dict[str, Any]
    digest: str
    out: str
    context: dict[str, Any]
    """The twin, for the worker (`workers.twin_context`)."""
    reference: dict[str, Any]
    """Under a field profile's twin source: the reconstructed twin's mesh (see campaign)."""
    cut: list[float]
    """The pose's cut point (vine frame): the view-keeping law's target."""


class _Refused(str):
    """Why a pose was not run (its field twin does not show it): a failure with its remedy."""


def _digest(twin: Twin, mesh_sha: str, pose_id: str, variant: str, cfg: ValidateConfig) -> str:
    pose = twin.pose(pose_id)
    return json_sha256(
        {
            "format": VALIDATION_FORMAT,
            "mesh": mesh_sha,
            "T": np.round(np.asarray(pose.T_vine_camera), 12).tolist(),
            "cut": np.round(twin.cut_point(pose.cut_point).point, 12).tolist(),
            "camera": twin.camera.to_dict(),
            "perception": twin.perception.to_dict(),
            "variant": variant,
            "starts": cfg.starts,
            "radius": [cfg.radius_translation, cfg.radius_rotation],
            "duration": cfg.duration,
            "limits": cfg.limits.to_dict(),
            "faults": [list(cfg.faults), cfg.fault_rate],
            "seed": cfg.seed,
            "servo": servo_settings(variant),
            **({"profile": cfg.field_profile().to_dict()} if cfg.profile_dir() else {}),
        }
    )


def _run_group(group: _Group) -> dict[str, Any]:
    goal = np.asarray(group.goal)
    runs = []
    for k, start in enumerate(group.starts):
        sim = SimConfig.from_dict({**group.sim, "seed": group.sim["seed"] + k})
        spec = SimSpec(goal, np.asarray(start), sim, group.pose_id, np.asarray(group.cut),
                       reference_seed=group.reference_seed)  # fmt: skip
        run = simulate(spec, worker_world(group.context, group.reference, spec))
        runs.append({"fraction": group.fractions[k], **run.summary()})
        fault_point(f"{group.pose_id}.{group.variant}", f"run{k}")
    basin = 0.0
    for r in sorted(runs, key=lambda r: r["fraction"]):
        if not r["converged"]:
            break
        basin = r["fraction"]
    data = {
        "pose": group.pose_id,
        "variant": group.variant,
        "success_rate": sum(r["converged"] for r in runs) / len(runs),
        "basin_fraction": basin,
        "lost": sum(bool(r.get("lost")) for r in runs),
        "runs": runs,
    }
    # written whole and atomically, last: a group is done only once its file exists
    out = Path(group.out)
    return JobStore(out.parent, VALIDATION_FORMAT).put(out.stem, group.digest, data)


def validate(
    twin: Twin,
    cfg: ValidateConfig,
    progress: Callable[[dict[str, Any], int, int], None] | None = None,
    executor: ExecutorConfig | None = None,
) -> dict[str, Any]:
    """Validates the twin's pruning poses; returns the summary (also written to the twin)."""
    return validate_many([twin], cfg, progress, executor)[0]


def validate_folder(
    path: str | Path,
    cfg: ValidateConfig,
    progress: Callable[[dict[str, Any], int, int], None] | None = None,
    executor: ExecutorConfig | None = None,
    *,
    json_path: Path | None = None,
    echo: Callable[[str], None] | None = None,
) -> list[dict[str, Any]]:
    """`vinetwin validate`: the twin folder at `path`, or every twin of a vineyard folder.
    `echo` receives each twin's servo-ability map (Markdown); `json_path` receives the summary
    (a list for a vineyard). Raises VinetwinError naming the pose/variant validations that
    failed (a rerun completes only them)."""
    from vinetwin.errors import VinetwinError
    from vinetwin.twin.model import find_twins, load_twins

    loaded, unread = load_twins(find_twins(path))  # one that does not load fails by name
    twins, broken = loaded, [f"{r}: {why}" for r, why in unread]
    if not twins:
        raise VinetwinError("; ".join(broken))
    summaries = validate_many(twins, cfg, progress, executor)
    if echo is not None:
        for twin in twins:
            echo((_store(twin, cfg).folder / "summary.md").read_text())
    if json_path is not None:
        json_path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_json(json_path, summaries[0] if len(summaries) == 1 else summaries)
    failed = [f for s in summaries for f in s.get("failed", [])]
    if failed:
        raise VinetwinError(
            f"{len(failed)} pose/variant validations failed (run again to complete them; "
            "one its field twin does not show, with the remedy): "
            + "; ".join(f"{f['pose']}.{f['variant']}: {f['error']}" for f in failed[:5])
            + "".join(f"; twin {b}" for b in broken)
        )
    if broken:
        raise VinetwinError(f"{len(broken)} twins could not be read (the others were "
                            "validated): " + "; ".join(broken))  # fmt: skip
    return summaries


def validate_many(
    twins: list[Twin],
    cfg: ValidateConfig,
    progress: Callable[[dict[str, Any], int, int], None] | None = None,
    executor: ExecutorConfig | None = None,
) -> list[dict[str, Any]]:
    """Validates the pruning poses of several twins (a vineyard) in one pool of workers;
    returns each twin's summary. A pose and variant whose runs failed (an error, a worker that
    died) is reported under `failed` in its twin's summary and left unwritten, so a rerun runs
    only it."""
    if cfg.world and len(twins) > 1:
        from vinetwin.errors import InputError

        raise InputError(f"world names one vine; validate one twin with it, not {len(twins)}")
    plans = [_plan(twin, cfg) for twin in twins]
    groups = [g for _, gs, _ in plans for g in gs]
    where = {id(g): k for k, (_, gs, _) in enumerate(plans) for g in gs}
    results: list[dict[tuple[str, str], Any]] = [dict(done) for _, _, done in plans]
    # a pose the field profile's rebuilt twin does not show is refused by name, not run
    failed: list[dict[tuple[str, str], str]] = [
        {key: why for key, why in list(done.items()) if isinstance(why, _Refused)}
        for _, _, done in plans
    ]
    for k, r in enumerate(results):
        for key in failed[k]:
            del r[key]
    done, errors, _ = run_jobs(
        groups, executor or ExecutorConfig(workers=cfg.workers), _run_group, progress
    )
    for g, d in done:
        results[where[id(g)]][(g.pose_id, g.variant)] = d
    for g, err in errors:
        failed[where[id(g)]][(g.pose_id, g.variant)] = err
    for twin in twins:  # a broken pool terminates writers mid-file
        _store(twin, cfg).clean()
    summaries = []
    for k, (twin, _, _) in enumerate(plans):
        summary = _summarise(twin, cfg, _pose_ids(twin, cfg), results[k], failed[k])
        _write_map(summary, _store(twin, cfg).folder)
        summaries.append(summary)
    return summaries


def _store(twin: Twin, cfg: ValidateConfig) -> JobStore:
    """validation/ for the ideal profile; validation/PROFILE/ for another."""
    sub = cfg.profile_dir()
    return JobStore(twin.validation_dir / sub if sub else twin.validation_dir, VALIDATION_FORMAT)


def _pose_ids(twin: Twin, cfg: ValidateConfig) -> list[str]:
    return list(cfg.poses) or [p.id for p in twin.poses]


def _plan(twin: Twin, cfg: ValidateConfig) -> tuple[Twin, list[_Group], dict[tuple[str, str], Any]]:
    """The groups to run and the results already current on disk."""
    pose_ids = _pose_ids(twin, cfg)
    for pid in pose_ids:
        check_id(twin.pose(pid).id, "pose id")  # unknown or unsafe ids fail before any work
    store = _store(twin, cfg).open()  # removes what writers killed in an earlier run left
    mesh_sha = file_sha256(twin.mesh_path)
    ctx = twin_context(twin)
    profile = cfg.field_profile()
    rebuilt: dict[str, Any] = {}
    true_mesh = rebuilt_mesh = None
    world = cfg.world_mesh()
    if world is not None:  # the camera sees the true vine; the twin is the reconstruction
        from vinetwin.mesh import load_mesh

        ctx = {**ctx, "mesh_path": str(world), "mesh_sha256": file_sha256(world)}
        rebuilt = {"mesh_path": str(twin.mesh_path), "mesh_sha256": mesh_sha}
        true_mesh, rebuilt_mesh = load_mesh(world), twin.load_mesh()
        mesh_sha = json_sha256([mesh_sha, ctx["mesh_sha256"]])
    elif profile.on("twin"):
        from vinetwin.mesh import load_mesh
        from vinetwin.sim.field import reconstructed_twin

        mesh, _ = reconstructed_twin(twin, profile, cfg.seed, store.folder / "field_twins")
        rebuilt = {"mesh_path": str(mesh), "mesh_sha256": file_sha256(mesh)}
        true_mesh, rebuilt_mesh = twin.load_mesh(), load_mesh(mesh)
    fractions = [(k + 1) / cfg.starts for k in range(cfg.starts)]
    groups, results = [], {}
    for pid in pose_ids:
        pose = twin.pose(pid)
        cut = twin.cut_point(pose.cut_point).point
        goal = np.asarray(pose.T_vine_camera)
        if rebuilt_mesh is not None:
            from vinetwin.errors import VinetwinError
            from vinetwin.sim.field import check_field_twin_view

            try:
                if world is None:
                    check_field_twin_view(true_mesh, rebuilt_mesh, twin.camera, profile, pid,
                                          goal, twin.perception.max_depth)  # fmt: skip
                else:
                    _check_world_view(true_mesh, rebuilt_mesh, twin, pid, goal, world)
            except VinetwinError as exc:
                results.update({(pid, v): _Refused(str(exc)) for v in cfg.variants})
                continue
        for v in cfg.variants:
            digest = _digest(twin, mesh_sha, pid, v, cfg)
            out = store.path(f"{pid}.{v}")
            old = None if cfg.force else store.current(f"{pid}.{v}", digest)
            if old is not None:
                results[(pid, v)] = old
                continue
            rng = np.random.default_rng([cfg.seed, int(pose_seed(cfg.seed, pid))])
            starts = [
                start_pose(goal, cut, (f * cfg.radius_translation, f * cfg.radius_rotation), rng,
                           twin.camera, twin.perception.max_depth).tolist()
                for f in fractions
            ]  # fmt: skip
            faults = FaultConfig(classes=cfg.faults, rate=cfg.fault_rate, seed=cfg.seed)
            sim = SimConfig(
                variant=v, duration=cfg.duration, limits=cfg.limits, faults=faults, seed=cfg.seed,
                profile=profile,
            )  # fmt: skip
            groups.append(
                _Group(
                    pid,
                    v,
                    goal.tolist(),
                    starts,
                    fractions,
                    pose_seed(cfg.seed, pid),
                    sim.to_dict(),
                    digest,
                    str(out),
                    ctx,
                    rebuilt,
                    np.asarray(cut, float).tolist(),
                )
            )
    return twin, groups, results


def _check_world_view(world_mesh: Any, twin_mesh: Any, twin: Twin, pid: str, goal: Any,
                      world: Path) -> None:  # fmt: skip
    """Refuses a pose where the twin and the world do not show each other: either shows under
    `MIN_VIEW_COVERAGE` of what the other shows (an empty reference or an empty view; a world
    not in the twin's vine frame, most likely)."""
    from vinetwin.errors import VinetwinError
    from vinetwin.sim.field import MIN_VIEW_COVERAGE, view_coverage

    far = twin.perception.max_depth
    twin_share = view_coverage(world_mesh, twin_mesh, twin.camera, goal, far)
    world_share = view_coverage(twin_mesh, world_mesh, twin.camera, goal, far)
    if min(twin_share, world_share) < MIN_VIEW_COVERAGE:
        w, t = (
            float(np.ptp(np.asarray(m.vertices), axis=0).max()) for m in (world_mesh, twin_mesh)
        )
        units = (f" The world is {w:.3g} across, the twin {t:.3g} m: is the world in another "
                 "unit (it must be in metres)?" if t > 0 and not 0.1 <= w / t <= 10 else "")  # fmt: skip
        raise VinetwinError(
            f"the twin shows {100 * twin_share:.0f}% of what the world {world} shows at pose "
            f"{pid!r}, the world {100 * world_share:.0f}% of what the twin shows (less than "
            f"{100 * MIN_VIEW_COVERAGE:.0f}%): the reference or the view would be empty; is the "
            "world in the twin's vine frame?" + units
        )


def _final_errors(runs: list[dict[str, Any]]) -> dict[str, float | None]:
    """Medians over the runs of the final pose error (m, rad) and of the cut point's error in
    the camera (m): against the world's vine when `ValidateConfig.world` is given (None where
    no run has one)."""
    keys = ("final_translation", "final_rotation", "final_cut_error")
    out: dict[str, float | None] = {}
    for k in keys:
        v = np.asarray([r.get(k, np.nan) for r in runs], float)
        v = v[np.isfinite(v)]
        out["median_" + k] = float(np.median(v)) if v.size else None
    return out


def _summarise(
    twin: Twin,
    cfg: ValidateConfig,
    pose_ids: list[str],
    results: dict[tuple[str, str], Any],
    failed: dict[tuple[str, str], str] | None = None,
) -> dict[str, Any]:
    failed = failed or {}
    rows = []
    for pid in pose_ids:
        per_variant: dict[str, Any] = {}
        for v in cfg.variants:
            if (pid, v) in failed:
                per_variant[v] = {"failed": failed[(pid, v)]}
                continue
            r = results[(pid, v)]
            per_variant[v] = {
                "success_rate": r["success_rate"],
                "basin_translation": r["basin_fraction"] * cfg.radius_translation,
                "basin_rotation": r["basin_fraction"] * cfg.radius_rotation,
                "starts": len(r["runs"]),
                "lost": r.get("lost", 0),
                **_final_errors(r["runs"]),
            }
        twin.pose(pid).extra["validation" + (f"_{sub}" if (sub := cfg.profile_dir()) else "")] = {
            "radius_translation": cfg.radius_translation,
            "radius_rotation": cfg.radius_rotation,
            "variants": {v: c for v, c in per_variant.items() if "failed" not in c},
        }
        rows.append({"pose": pid, "variants": per_variant})
    twin.save()
    out = {"twin": twin.name, "config": cfg.to_dict(), "poses": rows}
    if failed:
        out["failed"] = [{"pose": p, "variant": v, "error": e} for (p, v), e in failed.items()]
    return out


def _profile_line(cfg: dict[str, Any]) -> list[str]:
    """The error profile the runs had, and how they were judged (nothing for ideal runs)."""
    c = ValidateConfig.from_dict(cfg)
    p = c.field_profile()
    if not p.sources:
        return []
    t, r = SimConfig(profile=p).tolerances()
    return [
        f"Error profile: {c.profile} (sources: {', '.join(p.sources)}); a run converged when its "
        f"final error is within {1000 * t:.0f} mm / {r:.2f} rad.\n"
    ]


def _world_line(cfg: dict[str, Any]) -> list[str]:
    w = cfg.get("world")
    if not w:
        return []
    return [
        f"World: {w}. The camera saw that vine and the reference was rendered from this twin, "
        "so every error is against the world's vine, the twin's own error included.\n"
    ]


def _write_map(summary: dict[str, Any], out_dir: Path) -> None:
    cfg = summary["config"]
    variants = list(cfg["variants"])
    lines = [
        f"# Servo-ability of {summary['twin']}\n",
        f"{cfg['starts']} starts per pose and variant, up to {1000 * cfg['radius_translation']:.0f} mm "
        f"and {cfg['radius_rotation']:.2f} rad away. Each cell: success rate; convergence basin "
        "(every start this close converged); the median final error at the cut (the cut point's "
        "offset in the camera from where the pose puts it); runs that ended with a named stop "
        '("lost the vine", "the arm does not follow"), if any.\n',
        *_world_line(cfg),
        *_profile_line(cfg),
        "| pose | " + " | ".join(variants) + " |",
        "|---|" + "---|" * len(variants),
    ]
    for row in summary["poses"]:
        cells = []
        for v in variants:
            c = row["variants"][v]
            if "failed" in c:
                shown = "the field twin rebuilt" in c["failed"]  # `_Refused`: not run
                unseen = c["failed"].startswith("the twin shows")
                cells.append("not in the field twin's view" if shown
                             else "not in the twin's view" if unseen else "failed (run again)")  # fmt: skip
                continue
            lost = f"; {c['lost']} stopped" if c.get("lost") else ""
            cut = c.get("median_final_cut_error")
            at_cut = f"; cut {1000 * cut:.1f} mm" if cut is not None else ""
            cells.append(
                f"{100 * c['success_rate']:.0f}%; {1000 * c['basin_translation']:.0f} mm / "
                f"{c['basin_rotation']:.2f} rad{at_cut}{lost}"
            )
        lines.append(f"| {row['pose']} | " + " | ".join(cells) + " |")
    lines.append("\n![servo-ability map](summary.png)\n")
    atomic_write_text(out_dir / "summary.md", "\n".join(lines))
    atomic_write_json(out_dir / "summary.json", summary)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    poses = [r["pose"] for r in summary["poses"]]
    rate = np.array(
        [[r["variants"][v].get("success_rate", np.nan) for v in variants] for r in summary["poses"]]
    )
    basin = np.array(
        [
            [r["variants"][v].get("basin_translation", np.nan) for v in variants]
            for r in summary["poses"]
        ]
    )
    fig, ax = plt.subplots(figsize=(max(1.9 * len(variants) + 2, 7.0), 0.5 * len(poses) + 1.8))
    im = ax.imshow(rate, vmin=0, vmax=1, cmap="RdYlGn", aspect="auto")
    for i in range(len(poses)):
        for j in range(len(variants)):
            ax.text(
                j,
                i,
                f"{100 * rate[i, j]:.0f}%\n{1000 * basin[i, j]:.0f} mm"
                if np.isfinite(rate[i, j])
                else "failed",
                ha="center",
                va="center",
                fontsize=8,
            )
    ax.set_xticks(range(len(variants)), variants)
    ax.set_yticks(range(len(poses)), poses)
    ax.set_title("servo-ability: success rate, basin (mm)")
    fig.colorbar(im, ax=ax, label="success rate")
    fig.tight_layout()
    save_figure(fig, out_dir / "summary.png", 110)
    plt.close(fig)
