"""The defects of the reliability issue, each reproduced: lost concurrent edits, orphan workers,
files written outside the twin, unsafe ids and options, tracebacks instead of named errors, file
modes, an unauthenticated editor on every interface, corrupted references taken as done."""

from __future__ import annotations

import json
import logging
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import ROOT
from vinetwin.cli import main
from vinetwin.errors import InputError, MeshError, TwinConflictError, TwinError, TwinFieldError
from vinetwin.twin import Twin


# ----------------------------------------------------------------------------- 1 lost updates
def test_two_stale_copies_keep_each_others_edits(twin_dir: Path) -> None:
    a, b = Twin.load(twin_dir), Twin.load(twin_dir)
    cut = a.add_cut_point([0.1, 0.0, 0.7], [0.0, 0.0, 1.0])
    new = a.add_pose(cut.id)
    a.save()
    b.poses[0].name = "renamed in b"
    b.delete_pose(b.poses[1].id)
    gone = Twin.load(twin_dir).poses[1].id
    b.save()
    t = Twin.load(twin_dir)
    assert new.id in [p.id for p in t.poses] and cut.id in [c.id for c in t.cut_points]
    assert t.pose(t.poses[0].id).name == "renamed in b"
    assert gone not in [p.id for p in t.poses]
    assert t.revision == 2
    # the stale copy now holds the merged twin, and saves again without conflict
    assert new.id in [p.id for p in b.poses]
    b.save()
    assert Twin.load(twin_dir).revision == 3


def test_the_same_field_changed_twice_is_a_named_conflict(twin_dir: Path) -> None:
    a, b = Twin.load(twin_dir), Twin.load(twin_dir)
    a.poses[0].name = "from a"
    a.save()
    before = (twin_dir / "twin.json").read_text()
    b.poses[0].name = "from b"
    with pytest.raises(TwinConflictError, match=rf"pruning_poses '{a.poses[0].id}' field 'name'"):
        b.save()
    assert (twin_dir / "twin.json").read_text() == before  # nothing written


def test_validate_keeps_a_cut_point_saved_while_it_ran(twin_dir: Path) -> None:
    """Validate loads the twin, runs, then writes its results: an edit saved meanwhile stays."""
    from vinetwin.executor import ExecutorConfig
    from vinetwin.sim.config import ValidateConfig
    from vinetwin.sim.validate import validate

    stale = Twin.load(twin_dir)
    outside = Twin.load(twin_dir)
    cut = outside.add_cut_point([0.1, 0.0, 0.7], [0.0, 0.0, 1.0])
    pose = outside.add_pose(cut.id)
    outside.save()
    cfg = ValidateConfig(variants=("lm",), poses=("p1",), starts=1, duration=1.0)
    validate(stale, cfg, executor=ExecutorConfig(workers=1))
    t = Twin.load(twin_dir)
    assert pose.id in [p.id for p in t.poses] and cut.id in [c.id for c in t.cut_points]
    assert "validation" in t.pose("p1").extra


def test_the_web_session_keeps_an_outside_pose(twin_dir: Path) -> None:
    from vinetwin.web.session import AuthoringSession

    sess = AuthoringSession(twin_dir)
    outside = Twin.load(twin_dir)
    cut = outside.add_cut_point([0.1, 0.0, 0.7], [0.0, 0.0, 1.0])
    pose = outside.add_pose(cut.id)
    outside.save()
    sess.rename("p1", "renamed in the app")
    assert sess.problem == ""
    t = Twin.load(twin_dir)
    assert pose.id in [p.id for p in t.poses]
    assert t.pose("p1").name == "renamed in the app"
    assert sess.undo() and Twin.load(twin_dir).pose("p1").name != "renamed in the app"


# ----------------------------------------------------------------------------- 2 orphan workers
_ORPHAN_SCRIPT = """
import os, sys, time
from pathlib import Path
from vinetwin.executor import ExecutorConfig, run_unordered

OUT = Path(sys.argv[1])

def job(k):
    (OUT / f"pid{k}").write_text(str(os.getpid()))
    time.sleep(6)
    (OUT / f"done{k}").write_text("finished")
    return k

if __name__ == "__main__":
    for _ in run_unordered(job, [0, 1], ExecutorConfig(workers=2)):
        pass
"""


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    stat = Path(f"/proc/{pid}/stat")
    return not (stat.exists() and stat.read_text().split(") ", 1)[1].startswith("Z"))


def test_pool_workers_die_with_a_killed_parent(tmp_path: Path) -> None:
    script = tmp_path / "orphans.py"
    script.write_text(_ORPHAN_SCRIPT)
    proc = subprocess.Popen([sys.executable, str(script), str(tmp_path)], cwd=tmp_path)
    deadline = time.monotonic() + 60
    while len(list(tmp_path.glob("pid*"))) < 2 and time.monotonic() < deadline:
        time.sleep(0.1)
    pids = [int(p.read_text()) for p in tmp_path.glob("pid*")]
    assert len(pids) == 2, "the workers did not start"
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    deadline = time.monotonic() + 5
    while any(_alive(p) for p in pids) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not any(_alive(p) for p in pids), "pool workers outlived their killed parent"
    time.sleep(6.5)  # when the jobs would have finished
    assert not list(tmp_path.glob("done*"))


# ----------------------------------------------------------------------------- 3, 4 ids
def test_an_id_that_is_a_path_is_refused_by_save_and_export(twin_dir: Path) -> None:
    from vinetwin.render.export import export_references

    t = Twin.load(twin_dir)
    t.poses[0].id = "../../escape"
    with pytest.raises(TwinFieldError, match=r"pruning_poses\[0\]\.id"):
        t.save()
    with pytest.raises(InputError, match="pose id"):
        export_references(t, ["../../escape"], workers=1)
    assert not list(twin_dir.parent.parent.glob("escape*"))


def test_an_id_with_a_trailing_newline_is_refused(twin_dir: Path) -> None:
    data = json.loads((twin_dir / "twin.json").read_text())
    data["pruning_poses"][0]["id"] = "p1\n"
    (twin_dir / "twin.json").write_text(json.dumps(data))
    with pytest.raises(TwinFieldError, match=r"pruning_poses\[0\]\.id"):
        Twin.load(twin_dir)
    assert main(["info", str(twin_dir)]) == 2


# ----------------------------------------------------------------------------- 5 max-cycle
@pytest.mark.parametrize("value", ["0", "-1", "nan"])
def test_the_overrun_stop_cannot_be_turned_off(twin_dir: Path, value: str) -> None:
    from vinetwin.servo.config import LoopConfig

    with pytest.raises(InputError, match="max_cycle"):
        LoopConfig(max_cycle=float(value))
    args = ["servo", "--twin", str(twin_dir), "--camera", "folder:/nowhere", "--robot", "none"]
    assert main([*args, "--max-cycle", value]) == 2


# ----------------------------------------------------------------------------- 6 named errors
def test_bad_arguments_are_named_errors_not_tracebacks(
    twin_dir: Path,
    tmp_path: Path,
    caplog: pytest.LogCaptureFixture,
    capsys: pytest.CaptureFixture[str],
) -> None:
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    cases = {
        "preview .txt": (["preview", str(twin_dir), "--pose", "p1", "--out", "x.txt"], ".png"),
        "validate nan": (["validate", str(twin_dir), "--radius-translation", "nan"], "radius"),
        "validate inf": (["validate", str(twin_dir), "--radius-rotation", "inf"], "radius"),
        "sample edge 0": (["sample", "--out", str(tmp_path / "s0"), "--edge", "0"], "edge"),
        "sample edge -1": (["sample", "--out", str(tmp_path / "s1"), "--edge", "-1"], "edge"),
        "sample onto a file": (["sample", "--out", str(a_file)], "is a file"),
        "servo log unwritable": (
            ["servo", "--twin", str(twin_dir), "--log", str(a_file / "x.jsonl")], "--log"
        ),
        "servo record onto a file": (
            ["servo", "--twin", str(twin_dir), "--record", str(a_file)], "--record"
        ),
        "campaign camera rate nan": (["campaign", str(twin_dir), "--camera-rate", "nan"], "camera_rate"),
    }  # fmt: skip
    for name, (args, needle) in cases.items():
        caplog.clear()
        capsys.readouterr()
        with caplog.at_level(logging.ERROR, logger="vinetwin"):
            assert main(args) == 2, name
        said = caplog.text + capsys.readouterr().err
        assert needle in said and "Traceback" not in said, (name, said)
    assert not (tmp_path / "s0").exists() and not (tmp_path / "s1").exists()


def test_preview_into_a_missing_folder_makes_it(twin_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "new" / "folder" / "p1.png"
    assert main(["preview", str(twin_dir), "--pose", "p1", "--out", str(out)]) == 0
    assert out.stat().st_size > 1000


# ----------------------------------------------------------------------------- 7 file modes
def test_atomic_writes_honour_the_umask_and_keep_a_files_mode(twin_dir: Path) -> None:
    from vinetwin.files import atomic_write_text

    old = os.umask(0o022)
    try:
        t = Twin.load(twin_dir)
        (twin_dir / "twin.json").chmod(0o644)
        t.save()
        assert (twin_dir / "twin.json").stat().st_mode & 0o777 == 0o644
        new = twin_dir / "new.txt"
        atomic_write_text(new, "x")
        assert new.stat().st_mode & 0o777 == 0o644
        new.chmod(0o640)
        atomic_write_text(new, "y")
        assert new.stat().st_mode & 0o777 == 0o640
    finally:
        os.umask(old)


# ----------------------------------------------------------------------------- 8 web host
def test_the_web_app_warns_when_it_listens_beyond_loopback(
    twin_dir: Path, caplog: pytest.LogCaptureFixture
) -> None:
    from vinetwin.web.server import serve

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with caplog.at_level(logging.WARNING):
        app = serve(twin_dir, "0.0.0.0", port)
    try:
        assert "no authentication" in caplog.text
    finally:
        app.close()


# ----------------------------------------------------------------------------- 9 references
def test_a_corrupted_reference_is_rendered_again_and_refused_by_the_servo(twin_dir: Path) -> None:
    from vinetwin.render.export import export_references
    from vinetwin.render.reference import reference_for

    t = Twin.load(twin_dir)
    assert export_references(t, ["p1", "p2"], workers=1).count("rendered") == 2
    sidecar = json.loads((t.references_dir / "p1.json").read_text())
    assert set(sidecar["files_sha256"]) == {"ply", "pcd"}
    ply = t.references_dir / "p1.ply"
    good = ply.read_bytes()
    ply.write_bytes(good[: len(good) // 2])  # truncated
    with pytest.raises(InputError, match="does not match the hash"):
        reference_for(t, "p1")
    again = export_references(t, ["p1", "p2"], workers=1)
    assert [r.status for r in again.results] == ["rendered", "skipped"]
    assert ply.read_bytes() == good  # the same seed renders the same cloud
    assert len(reference_for(t, "p1").cloud.points) > 100


def test_export_flushes_once_and_renders_again_what_a_power_loss_left_empty(
    twin_dir: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """References are written without an fsync each and flushed together at the end; a cloud
    or sidecar a power loss left empty (what an unsynced file can become) is rendered again."""
    import os

    import vinetwin.render.export as export_mod
    from vinetwin.render.export import export_references

    calls = {"fsync": 0, "sync": 0}
    real_fsync = os.fsync
    monkeypatch.setattr(os, "fsync", lambda fd: calls.__setitem__("fsync", calls["fsync"] + 1))
    monkeypatch.setattr(
        export_mod, "sync_to_disk", lambda: calls.__setitem__("sync", calls["sync"] + 1)
    )
    t = Twin.load(twin_dir)
    assert export_references(t, ["p1", "p2"], workers=1).count("rendered") == 2
    assert calls == {"fsync": 0, "sync": 1}
    monkeypatch.setattr(os, "fsync", real_fsync)
    good = (t.references_dir / "p2.pcd").read_bytes()
    (t.references_dir / "p2.pcd").write_bytes(b"")
    (t.references_dir / "p1.json").write_bytes(b"")
    again = export_references(t, ["p1", "p2"], workers=1)
    assert [r.status for r in again.results] == ["rendered", "rendered"]
    assert (t.references_dir / "p2.pcd").read_bytes() == good


# ----------------------------------------------------------------------------- 10 minor
def test_minor_messages_name_the_right_thing(twin_dir: Path, tmp_path: Path) -> None:
    from vinetwin.mesh import check_mesh_arrays

    with pytest.raises(MeshError, match="no triangle faces"):
        check_mesh_arrays(np.zeros((0, 3)), np.zeros((0, 3), int), "m.ply")
    with pytest.raises(TwinError, match="--overwrite"):
        Twin.create(twin_dir, *_triangle())
    data = json.loads((twin_dir / "twin.json").read_text())
    for bad in ("/etc/passwd", "../vine.twin/skeleton.json"):
        data["skeleton"] = bad
        (twin_dir / "twin.json").write_text(json.dumps(data))
        with pytest.raises(TwinFieldError, match="skeleton"):
            Twin.load(twin_dir)


def _triangle() -> tuple[np.ndarray, np.ndarray]:
    return np.eye(3), np.array([[0, 1, 2]])


def test_the_architecture_issue_left_no_second_speed_default() -> None:
    """The safety limits have one default, the one docs/hardware.md states."""
    from vinetwin.servo.config import CommandLimits, Limits
    from vinetwin.sim.config import CampaignConfig, SimConfig, ValidateConfig

    doc = (ROOT / "docs" / "hardware.md").read_text()
    assert "5 cm/s and 0.25 rad/s" in doc and "0.5 m/s² and 2.5 rad/s²" in doc
    assert (Limits().max_linear, Limits().max_angular) == (0.05, 0.25)
    assert (Limits().max_linear_acceleration, Limits().max_angular_acceleration) == (0.5, 2.5)
    for cfg in (
        CommandLimits(),
        SimConfig().limits,
        CampaignConfig().limits,
        ValidateConfig().limits,
    ):
        assert (cfg.max_linear, cfg.max_angular) == (0.05, 0.25)


# ----------------------------------------------------------------------------- fault injection
#: the refusal each frame fault must cause
EXPECTED_REFUSAL = {
    "stall": "stale frame",
    "zero": "empty frame",
    "nan": "empty frame",
    "half_nan": "corrupt depth image",
    "stale": "stale frame",
    "duplicate": "stale frame",
    "jerk": "pose jump",
}


@pytest.mark.parametrize(
    "cls",
    ["drop", "stall", "zero", "nan", "half_nan", "stale", "duplicate", "jerk", "leaf",
     "lost_command"],
)  # fmt: skip
def test_injected_faults_never_move_the_arm_on_an_untrusted_frame(vine_views, cls: str) -> None:  # type: ignore[no-untyped-def]
    from vinetwin.render.reference import pose_seed
    from vinetwin.sim.config import FaultConfig, SimConfig
    from vinetwin.sim.session import SimSpec, SimWorld, start_pose
    from vinetwin.sim.simulate import simulate

    twin = vine_views.twin
    pose = twin.poses[0]
    cut = twin.cut_point(pose.cut_point).point
    start = start_pose(
        pose.T_vine_camera, cut, (0.02, 0.05), np.random.default_rng(0), twin.camera, 0.4
    )
    faults = FaultConfig(classes=(cls,), rate=0.25 if cls != "jerk" else 0.4, seed=3)
    cfg = SimConfig(duration=3.0, settle=0.0, fixed_period=1 / 30, faults=faults)
    run = simulate(
        SimSpec(pose.T_vine_camera, start, cfg, reference_seed=pose_seed(0, pose.id)),
        SimWorld(vine_views.backend, twin.perception),
    )
    f = run.summary()["faults"]
    assert f["commands_over_limit"] == 0 and f["motion_on_untrusted"] == 0, f
    events = f["classes"][cls]["events"]
    assert events >= 2, f
    assert f["classes"][cls]["never_recovered"] == 0, f
    if cls in EXPECTED_REFUSAL:
        assert EXPECTED_REFUSAL[cls] in run.reasons, run.reasons
    if cls == "drop":
        assert len(run.t) < 0.8 * 3.0 * 30  # frames went missing
