"""A row of vines pruned in simulation (`vinetwin prune TWIN|VINEYARD`): each vine's job
(`sim.prune.prune_twin`) on the executor (this process, the local pool or Ray: the same results
either way, since a job's simulated times and plans do not depend on the machine's load or on
which worker ran it), each vine's result kept on disk as it finishes (`OUT/vines/NAME.json`,
with a digest of its inputs) so a killed run resumes where it stopped, then the row's summary
and report (`sim.prune_report`)."""

from __future__ import annotations

import hashlib
import json
import logging
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from vinetwin.errors import InputError, VinetwinError
from vinetwin.executor import ExecutorConfig, run_unordered
from vinetwin.files import atomic_write_json, file_sha256, read_json
from vinetwin.sim.prune import PruneConfig, prune_twin
from vinetwin.twin.model import Twin, find_twins, load_twins

log = logging.getLogger(__name__)


def _digest(twin: Twin, cfg: PruneConfig) -> str:
    h = hashlib.sha256()
    h.update(json.dumps(twin.to_json(), sort_keys=True, default=str).encode())
    h.update(file_sha256(twin.mesh_path).encode())
    h.update(json.dumps(cfg.to_dict(), sort_keys=True).encode())
    return h.hexdigest()


def _job(job: tuple[str, dict[str, Any], str]) -> dict[str, Any]:
    """One vine (a worker's job: plain data in, plain data out; the MCAP, if asked, written by
    the worker, a fresh one over any earlier run's)."""
    import shutil

    path, cfg, mcap = job
    if mcap:
        shutil.rmtree(mcap, ignore_errors=True)
    return prune_twin(path, PruneConfig.from_dict(cfg), Path(mcap) if mcap else None)


def vine_name(twin_dir: Path, base: Path) -> str:
    """A vine's name in the row: its folder relative to the row's, '/' as '__'."""
    return "__".join(twin_dir.relative_to(base).parts)


def prune_row(
    path: str | Path,
    cfg: PruneConfig,
    out: Path,
    executor: ExecutorConfig | None = None,
    force: bool = False,
    progress: Callable[[dict[str, Any], int, int], None] | None = None,
    mcap: bool = False,
) -> dict[str, Any]:
    """Prunes every twin at `path` (one twin, or a folder of them); returns the row's data
    (`vines`: each vine's result, `summary`), also written to OUT/prune.json. `mcap`: each vine
    run now also as OUT/vines/NAME.mcap/ (a ROS 2 bag for Foxglove)."""
    from vinetwin.sim.config import load_profile

    root = Path(path)
    twins = find_twins(root)
    load_profile(cfg.profile)  # a profile that cannot be read is named before any vine runs
    base = root.parent if (root / "twin.json").exists() else root
    vines_dir = out / "vines"
    vines_dir.mkdir(parents=True, exist_ok=True)
    results: dict[str, dict[str, Any]] = {}
    jobs: list[tuple[str, dict[str, Any], str]] = []
    names: dict[str, str] = {}
    digests: dict[str, str] = {}
    failed: dict[str, str] = {}
    loaded, unread = load_twins(twins)
    for r, why in unread:  # a twin that does not load fails by name
        names[str(r)] = failed_name = vine_name(r, base)
        failed[failed_name] = why
        log.error("%s: %s", failed_name, why)
    for twin in loaded:
        t = twin.root
        name = vine_name(t, base)
        names[str(t)] = name
        digest = _digest(twin, cfg)
        digests[str(t)] = digest
        kept = vines_dir / f"{name}.json"
        if kept.exists() and not force:
            try:
                old = read_json(kept, InputError)
            except InputError:
                old = None
            if isinstance(old, dict) and old.get("digest") == digest:
                results[name] = old["result"]
                log.info("%s: done before (same inputs), kept", name)
                continue
        jobs.append((str(t), cfg.to_dict(), str(vines_dir / f"{name}.mcap") if mcap else ""))
    done = 0
    for outcome in run_unordered(_job, jobs, executor):
        t = jobs[outcome.index][0]
        name = names[t]
        done += 1
        if outcome.ok:
            results[name] = outcome.value
            atomic_write_json(vines_dir / f"{name}.json",
                              {"digest": digests[t], "result": outcome.value})  # fmt: skip
            if progress:
                progress(outcome.value["summary"], done, len(jobs))
        else:
            failed[name] = str(outcome.error)
            log.error("%s: %s", name, outcome.error)
    ordered = {names[str(t)]: results[names[str(t)]] for t in twins if names[str(t)] in results}
    if failed and not ordered:  # nothing to report: an earlier report is left as it was
        raise VinetwinError(f"every vine failed; nothing written to {out}: " + "; ".join(
            f"{name}: {why}" for name, why in list(failed.items())[:5]))  # fmt: skip
    data = {"config": cfg.to_dict(), "vines": ordered, "failed": failed,
            "summary": row_summary(ordered)}  # fmt: skip
    atomic_write_json(out / "prune.json", data)
    return data


def row_summary(vines: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """The row's figures over its vines: cuts done and done right, skipped, collisions, the
    median time per cut, planning per vine, simulated and wall time."""
    cuts = [c for v in vines.values() for c in v["cuts"]]
    done = [c for c in cuts if c["status"] == "done"]
    reachable = sum(v["summary"]["reachable"] for v in vines.values())
    tol = max((v["config"]["job"]["cut"]["max_blade_error"] for v in vines.values()),
              default=0.005)  # fmt: skip
    right = [c for c in done if c["blade_error_m"] <= tol]
    errs = [1000 * c["blade_error_m"] for c in done]
    sim = sum(v["summary"]["simulated_s"] for v in vines.values())
    wall = sum(v["summary"]["wall_s"] for v in vines.values())
    return {
        "vines": len(vines),
        "poses": sum(v["summary"]["poses"] for v in vines.values()),
        "reachable": reachable,
        "done": len(done),
        "done_right": len(right),
        "done_right_share_of_reachable": len(right) / reachable if reachable else math.nan,
        "skipped": len(cuts) - len(done),
        "collisions": sum(v["collisions"] for v in vines.values()),
        "median_blade_error_mm": float(np.median(errs)) if errs else math.nan,
        "p95_blade_error_mm": float(np.percentile(errs, 95)) if errs else math.nan,
        "median_time_per_cut_s": (
            float(np.median([c["time_s"] for c in done])) if done else math.nan
        ),
        "time_per_vine_s": [v["summary"]["simulated_s"] for v in vines.values()],
        "max_planning_per_vine_s": max((v["planning_s"] for v in vines.values()), default=0.0),
        "simulated_s": sim,
        "wall_s": wall,
        "realtime_factor": sim / wall if wall > 0 else math.nan,
    }


def _rounded(x: Any) -> Any:
    if isinstance(x, float):
        return round(x, 9)
    if isinstance(x, dict):
        return {k: _rounded(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_rounded(v) for v in x]
    return x


def comparable(result: dict[str, Any]) -> dict[str, Any]:
    """What of a vine's result must be identical whichever executor ran it (its plan, cuts,
    times, blade errors, contacts): everything but compute and wall time, numbers to 1e-9 (a
    worker's thread count changes the order of floating-point sums in the last digits: 1e-15
    m between the in-process run and the pool, measured)."""
    cuts = [{k: v for k, v in c.items() if k != "phases"} | {
        "phases": {k: v for k, v in c.get("phases", {}).items() if k != "planning"}}
        for c in result["cuts"]]  # fmt: skip
    plan = {k: v for k, v in result["plan"].items() if k != "planning_s"}
    return _rounded({"plan": plan, "cuts": cuts, "collisions": result["collisions"],
                     "contacts": result["contacts"]})  # fmt: skip
