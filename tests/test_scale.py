"""Vineyard-size batches: export and validation over a folder of twins through the local process
pool and through Ray (a local Ray with 2 CPUs), with identical outputs, per-job failure
isolation, and workers killed in the middle of a job (fault injection: the worker kills its own
process with SIGKILL at a named point) losing and corrupting nothing."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import signal
import time
from dataclasses import replace
from pathlib import Path

import pytest

from tests.conftest import SAMPLES
from vinetwin._faults import FAULT_VAR
from vinetwin.cli import main
from vinetwin.executor import ExecutorConfig, Outcome, run_unordered
from vinetwin.render.export import export_many
from vinetwin.sim.config import ValidateConfig
from vinetwin.sim.validate import validate_many
from vinetwin.twin.model import Twin, find_twins


def _vineyard(tmp_path: Path, name: str = "vineyard") -> Path:
    """Two bundled sample twins (9 pruning poses between them) in rows of a vineyard folder."""
    root = tmp_path / name
    for row, sample in (("row1", "vine_bilateral"), ("row2", "vine_unilateral")):
        shutil.copytree(
            SAMPLES / f"{sample}.twin", root / row / f"{sample}.twin",
            ignore=shutil.ignore_patterns("references", "validation", "campaign", "servo"),
        )  # fmt: skip
    return root


def _files(root: Path) -> dict[str, object]:
    """Every file under a vineyard's references: the SHA-256 of each cloud's bytes (a short diff
    when they differ), and sidecars less their timestamp."""
    out: dict[str, object] = {}
    for p in sorted(root.rglob("references/*")):
        key = str(p.relative_to(root))
        if p.suffix == ".json":
            meta = json.loads(p.read_text())
            meta.pop("created")
            out[key] = meta
        else:
            out[key] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def _twins(root: Path) -> list[Twin]:
    return [Twin.load(p) for p in find_twins(root)]


def _square(x: int) -> int:
    if x == 3:
        raise ValueError("three is refused")
    return x * x


def _die_on_two(x: int) -> int:
    if x == 2:
        os.kill(os.getpid(), signal.SIGKILL)
    time.sleep(0.05 * (x % 3))
    return x + 100


@pytest.mark.parametrize("kind", ["local", "ray"])
def test_executor_isolates_a_dying_worker(kind: str) -> None:
    """Only the job whose worker died fails, however the deaths and completions interleave."""
    if kind == "ray":
        pytest.importorskip("ray")
    for _ in range(2 if kind == "local" else 1):
        outs = list(
            run_unordered(
                _die_on_two, list(range(8)), ExecutorConfig(kind=kind, workers=2, retries=0)
            )
        )
        by = {o.index: o for o in outs}
        assert sorted(by) == list(range(8)) and len(outs) == 8
        assert by[2].worker_died and "worker died" in by[2].error
        assert all(by[i].value == i + 100 for i in range(8) if i != 2)


def _worker_thread_env(_: int) -> dict[str, str | None]:
    return {k: os.environ.get(k) for k in ("LP_NUM_THREADS", "OMP_NUM_THREADS")}


def test_pool_workers_get_their_share_of_the_cores(monkeypatch: pytest.MonkeyPatch) -> None:
    """Each of n local workers gets cores // n threads, Mesa's llvmpipe included (0: it
    rasterises in the rendering thread, no threads of its own); the caller's environment is
    restored afterwards."""
    monkeypatch.setattr(os, "cpu_count", lambda: 4)
    monkeypatch.setenv("LP_NUM_THREADS", "7")
    for workers, omp, lp in ((2, "2", "2"), (4, "1", "0")):
        outs = list(
            run_unordered(_worker_thread_env, list(range(workers)), ExecutorConfig(workers=workers))
        )
        assert all(o.value == {"LP_NUM_THREADS": lp, "OMP_NUM_THREADS": omp} for o in outs)
    assert os.environ["LP_NUM_THREADS"] == "7"


def _log_at_exit(folder: str) -> int:
    """Registers an exit handler and logs to a buffered file handler, neither flushed yet."""
    import atexit
    import logging

    pid = os.getpid()
    handler = logging.StreamHandler(open(Path(folder) / f"{pid}.log", "w"))
    logging.getLogger("tests.worker_exit").addHandler(handler)
    logging.getLogger("tests.worker_exit").warning("worker %d logged", pid)
    atexit.register(lambda: (Path(folder) / f"{pid}.atexit").write_text("ran"))
    return pid


def test_pool_workers_leave_after_their_exit_handlers(tmp_path: Path) -> None:
    """A worker skips the interpreter's teardown when the pool shuts down
    (`executor._QuickExitProcess`), but its exit handlers still run and its log is flushed
    and closed (logging's own exit handler)."""
    outs = list(run_unordered(_log_at_exit, [str(tmp_path)] * 4, ExecutorConfig(workers=2)))
    pids = {o.value for o in outs}
    assert all(o.ok for o in outs) and 1 <= len(pids) <= 2
    for pid in pids:
        assert (tmp_path / f"{pid}.atexit").read_text() == "ran"
        assert f"worker {pid} logged" in (tmp_path / f"{pid}.log").read_text()


@pytest.mark.parametrize("kind", ["local", "ray"])
def test_executor_isolates_a_failing_job(kind: str) -> None:
    if kind == "ray":
        pytest.importorskip("ray")
    outs = list(run_unordered(_square, list(range(6)), ExecutorConfig(kind=kind, workers=2)))
    by = {o.index: o for o in outs}
    assert sorted(by) == list(range(6))
    assert by[3].error == "ValueError: three is refused" and not by[3].worker_died
    assert all(by[i].value == i * i for i in range(6) if i != 3)
    assert isinstance(outs[0], Outcome)


@pytest.mark.numpy_noise
def test_vineyard_export_is_identical_through_every_executor(tmp_path: Path) -> None:
    pytest.importorskip("ray")
    roots = {k: _vineyard(tmp_path, k) for k in ("inprocess", "pool", "ray")}
    assert len(find_twins(roots["pool"])) == 2
    reports = {
        "inprocess": export_many(_twins(roots["inprocess"]), executor=ExecutorConfig(workers=1)),
        "pool": export_many(_twins(roots["pool"]), executor=ExecutorConfig(workers=2)),
        "ray": export_many(_twins(roots["ray"]), executor=ExecutorConfig(kind="ray", workers=2)),
    }
    for name, r in reports.items():
        assert r.ok and r.count("rendered") == 9, (name, r.results)
    assert reports["pool"].workers == 2 and reports["ray"].executor == "ray"
    files = {k: _files(v) for k, v in roots.items()}
    assert len(files["pool"]) == 9 * 3  # PLY, PCD, JSON per pose
    assert files["pool"] == files["inprocess"]
    assert files["ray"] == files["inprocess"]


@pytest.mark.numpy_noise
@pytest.mark.parametrize("kind", ["local", "ray"])
def test_a_worker_killed_mid_export_loses_nothing(
    kind: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The worker rendering one pose dies between writing its PLY and its sidecar: that pose is
    reported failed, every other pose completes, and a rerun renders only the killed one, to
    the same files an uninterrupted export writes."""
    if kind == "ray":
        pytest.importorskip("ray")
    clean = _vineyard(tmp_path, "clean")
    export_many(_twins(clean), executor=ExecutorConfig(workers=1))
    root = _vineyard(tmp_path, "killed")
    victim = find_twins(root)[0]
    monkeypatch.setenv(FAULT_VAR, f"kill:{victim}/p2@ply")
    executor = ExecutorConfig(kind=kind, workers=2, retries=0)
    report = export_many(_twins(root), executor=executor)
    failed = [r for r in report.results if r.status == "failed"]
    assert [(Path(r.twin), r.pose_id) for r in failed] == [(victim, "p2")]
    assert "worker died" in failed[0].error
    assert report.count("rendered") == 8
    assert (victim / "references" / "p2.ply").exists()  # written before the kill ...
    assert not (victim / "references" / "p2.json").exists()  # ... but never made current
    assert not list(root.rglob("references/.*"))  # no temporary file left behind

    monkeypatch.delenv(FAULT_VAR)
    again = export_many(_twins(root), executor=executor)
    assert again.ok and again.count("rendered") == 1 and again.count("skipped") == 8
    assert [r.pose_id for r in again.results if r.status == "rendered"] == ["p2"]
    assert _files(root) == _files(clean)


@pytest.mark.numpy_noise
@pytest.mark.parametrize("kind", ["local", "ray"])
def test_a_writer_killed_before_its_rename_leaves_no_litter(
    kind: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A worker dies with a reference's temporary file written but not yet renamed (as when
    a broken pool terminates the other workers mid-file): the export removes the orphan when
    it ends, and the folder then holds exactly what an uninterrupted export writes."""
    if kind == "ray":
        pytest.importorskip("ray")
    clean = _vineyard(tmp_path, "clean")
    export_many(_twins(clean), executor=ExecutorConfig(workers=1))
    root = _vineyard(tmp_path, "killed")
    victim = find_twins(root)[1] / "references" / "p1.pcd"
    monkeypatch.setenv(FAULT_VAR, f"kill:{victim}@write")
    executor = ExecutorConfig(kind=kind, workers=2, retries=0)
    report = export_many(_twins(root), executor=executor)
    assert [r.pose_id for r in report.results if r.status == "failed"] == ["p1"]
    assert not list(root.rglob("references/.*"))  # the killed writer's temporary file is gone
    monkeypatch.delenv(FAULT_VAR)
    again = export_many(_twins(root), executor=executor)
    assert again.ok and again.count("rendered") == 1
    assert _files(root) == _files(clean)


def test_a_killed_worker_is_replaced_and_its_job_retried(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    root = _vineyard(tmp_path)
    victim = find_twins(root)[1]
    monkeypatch.setenv(FAULT_VAR, f"kill:{victim}/p1@render")
    monkeypatch.setenv(FAULT_VAR + "_ONCE", str(tmp_path / "killed-once"))
    report = export_many(_twins(root), executor=ExecutorConfig(workers=2, retries=1))
    assert report.ok and report.count("rendered") == 9
    assert (tmp_path / "killed-once").exists()  # the first attempt was killed


def test_vineyard_validation_on_ray_resumes_after_a_kill(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    pytest.importorskip("ray")
    root = _vineyard(tmp_path)
    twins = _twins(root)
    cfg = ValidateConfig(
        variants=("point_to_plane",), poses=("p1",), starts=2, duration=3.0,
        radius_translation=0.02, radius_rotation=0.05,
    )  # fmt: skip
    monkeypatch.setenv(FAULT_VAR, "kill:p1.point_to_plane@run0")
    ray = ExecutorConfig(kind="ray", workers=2, retries=0)
    summaries = validate_many(twins, cfg, executor=ray)
    # both twins' p1 groups were killed after their first run: nothing written, both reported
    assert all(len(s["failed"]) == 1 for s in summaries)
    assert not list(root.rglob("validation/p1.point_to_plane.json"))
    assert "failed" in (twins[0].root / "validation" / "summary.md").read_text()

    monkeypatch.delenv(FAULT_VAR)
    summaries = validate_many(_twins(root), cfg, executor=ray)
    assert all("failed" not in s for s in summaries)
    files = sorted(root.rglob("validation/p1.point_to_plane.json"))
    assert len(files) == 2
    for s in summaries:
        cell = s["poses"][0]["variants"]["point_to_plane"]
        assert cell["starts"] == 2 and 0.0 <= cell["success_rate"] <= 1.0
    stamps = [f.stat().st_mtime_ns for f in files]
    validate_many(_twins(root), cfg, executor=ExecutorConfig(workers=1))  # all current: no runs
    assert [f.stat().st_mtime_ns for f in files] == stamps
    assert "validation" in json.loads((twins[1].root / "twin.json").read_text())["pruning_poses"][0]


def test_a_broken_twin_in_a_vineyard_fails_by_name_and_the_others_export(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], caplog: pytest.LogCaptureFixture
) -> None:
    """One twin's mesh corrupt and another's twin.json: the export names both (exit status 2)
    and writes every other twin's references (the first broken twin stopped the whole export,
    before anything was rendered)."""
    root = _vineyard(tmp_path)
    good, bad = find_twins(root)
    shutil.copytree(bad, root / "row3" / "torn.twin")
    (Twin.load(bad).mesh_path).write_bytes(b"not a mesh")
    (root / "row3" / "torn.twin" / "twin.json").write_text("{torn")
    assert main(["export", str(root), "--workers", "1"]) == 2
    said = caplog.text
    assert "2 of " in said and "not a mesh" not in said  # the mesh's file named, not its bytes
    assert f"{bad.name} (all): " in said and "torn.twin (all): " in said, said
    n = len(Twin.load(good).poses)
    assert len(list((good / "references").glob("*.ply"))) == n
    assert f"{n} rendered" in capsys.readouterr().out
    # validate: the torn twin named, the others validated (it stopped the whole vineyard)
    from vinetwin.errors import VinetwinError
    from vinetwin.sim.validate import validate_folder

    shutil.rmtree(bad)
    cfg = ValidateConfig(variants=("point_to_plane",), starts=1, duration=2.0, workers=1)
    with pytest.raises(VinetwinError, match=r"1 twins could not be read .*torn\.twin"):
        validate_folder(root, cfg)
    assert (good / "validation" / "summary.json").exists()


def test_cli_exports_a_vineyard_with_ray(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    pytest.importorskip("ray")
    root = _vineyard(tmp_path)
    assert main(["export", str(root), "--ray", "--workers", "2"]) == 0
    out = capsys.readouterr().out
    assert "9 rendered" in out and "ray" in out
    assert main(["export", str(root)]) == 0
    assert "0 rendered, 9 unchanged" in capsys.readouterr().out


def test_a_campaign_keeps_its_finished_runs_when_a_worker_dies(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A worker dies at the end of one campaign run: the campaign fails naming that run, the
    other runs are on disk, and running it again runs only the killed one, then writes the
    report; with `force` everything runs again."""
    from vinetwin.errors import VinetwinError
    from vinetwin.sim.campaign import run_campaign
    from vinetwin.sim.config import CampaignConfig

    twin = Twin.load(SAMPLES / "vine_bilateral.twin")
    cfg = CampaignConfig(
        preset="quick",
        variants=("point_to_plane", "symmetric"),
        duration=3.0,
        disturbance=False,
        guess_comparison=False,
        law_comparison=False,
    )
    out = tmp_path / "campaign"
    executor = ExecutorConfig(workers=2, retries=0)
    monkeypatch.setenv(FAULT_VAR, "kill:grid/0/symmetric@run")
    with pytest.raises(VinetwinError, match=r"1 of 2 runs failed: grid/0/symmetric: .*worker died"):
        run_campaign(twin, cfg, out, executor=executor)
    kept = out / "runs" / "grid.0.point_to_plane.json"
    assert sorted(p.name for p in (out / "runs").iterdir()) == [kept.name]
    assert not (out / "campaign.json").exists()
    stamp = kept.stat().st_mtime_ns

    monkeypatch.delenv(FAULT_VAR)
    seen: list[str] = []
    data = run_campaign(twin, cfg, out, lambda r, n, total: seen.append(r["key"]), executor)
    assert seen == ["grid/0/symmetric"] and data["resumed"] == 1
    assert [r["key"] for r in data["runs"]] == ["grid/0/point_to_plane", "grid/0/symmetric"]
    assert kept.stat().st_mtime_ns == stamp
    assert json.loads((out / "campaign.json").read_text())["runs"] == data["runs"]
    assert "1 of the runs come from an earlier campaign" in (out / "report.md").read_text()

    # other inputs (a longer run) are not taken for done; force runs everything again
    seen.clear()
    longer = run_campaign(twin, replace(cfg, duration=3.5), out,
                          lambda r, n, total: seen.append(r["key"]), executor)  # fmt: skip
    assert sorted(seen) == ["grid/0/point_to_plane", "grid/0/symmetric"]
    assert longer["resumed"] == 0
    seen.clear()
    run_campaign(twin, cfg, out, lambda r, n, total: seen.append(r["key"]), executor, force=True)
    assert len(seen) == 2
