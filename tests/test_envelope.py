"""The defects of the second reliability round, each reproduced (numbered as in the issue): the
safe envelope of every setting that moves a robot, logs and outputs that never overwrite, a
clean-up that deletes only vinetwin's own files, the lock's mode, Ctrl-C inside a compiled
kernel, the web app's port, and the tracebacks that are now named errors."""

from __future__ import annotations

import errno
import json
import logging
import os
import re
import socket
import time
from pathlib import Path

import numpy as np
import pytest

from vinetwin.cli import main
from vinetwin.errors import InputError, TwinError
from vinetwin.twin import Twin

#: A camera that cannot open: a run refused for its settings says so before reaching it.
NO_CAMERA = ["--camera", "folder:/nowhere", "--robot", "none"]


def said(
    args: list[str], caplog: pytest.LogCaptureFixture, capsys: pytest.CaptureFixture[str]
) -> tuple[int, str]:
    """The exit status of `vinetwin ARGS` and what it said (log and standard error)."""
    caplog.clear()
    capsys.readouterr()
    with caplog.at_level(logging.INFO, logger="vinetwin"):
        rc = main(args)
    out = capsys.readouterr()
    return rc, caplog.text + out.err + out.out


# ----------------------------------------------------------------------------- 1 watchdog
@pytest.mark.parametrize("value", ["1e9", "0.51", "0.0005", "nan", "0"])
def test_a_watchdog_outside_the_envelope_is_refused_before_the_camera_opens(
    twin_dir: Path, value: str, caplog: pytest.LogCaptureFixture, capsys: pytest.CaptureFixture[str]
) -> None:
    from vinetwin.servo.config import ENVELOPE, CommandLimits

    with pytest.raises(InputError, match="watchdog"):
        CommandLimits(watchdog=float(value))
    rc, text = said(
        ["servo", "--twin", str(twin_dir), *NO_CAMERA, "--watchdog", value], caplog, capsys
    )
    assert rc == 2 and "watchdog" in text and "/nowhere" not in text, text
    assert CommandLimits(watchdog=ENVELOPE.max_watchdog).watchdog == 0.5  # the ceiling itself


def test_the_franka_adapter_never_sends_a_command_that_outlives_the_envelope() -> None:
    """Each Franka command expires on the robot after the watchdog: with the envelope's ceiling
    the arm brakes by itself at most 0.5 s after the last command, whatever was asked."""
    from vinetwin.servo.config import ENVELOPE, CommandLimits
    from vinetwin.servo.robot import FrankaRobot, FrankaTransport

    sent: list[float] = []

    class Transport(FrankaTransport):
        def T_base_flange(self) -> np.ndarray:
            return np.eye(4)

        def send_velocity(
            self, linear: np.ndarray, angular: np.ndarray, T: np.ndarray, duration: float
        ) -> None:
            sent.append(duration)

        def stop(self) -> None:
            pass

    for asked in (0.2, 0.5, 1e9):
        try:
            limits = CommandLimits(
                watchdog=asked, max_linear_acceleration=0, max_angular_acceleration=0
            )
        except InputError:
            continue
        robot = FrankaRobot(Transport(), np.eye(4), limits)
        try:
            robot.command(np.array([0.01, 0, 0, 0, 0, 0]))
        finally:
            robot.close()
    assert sent == [0.2, 0.5] and max(sent) <= ENVELOPE.max_watchdog, sent


# ----------------------------------------------------------------------------- 2 the log
def test_the_servo_log_never_overwrites_a_file(
    twin_dir: Path,
    tmp_path: Path,
    caplog: pytest.LogCaptureFixture,
    capsys: pytest.CaptureFixture[str],
) -> None:
    before = (twin_dir / "twin.json").read_bytes()
    args = ["servo", "--twin", str(twin_dir), "--duration", "0.5", "--camera-rate", "10"]
    rc, text = said([*args, "--log", str(twin_dir / "twin.json")], caplog, capsys)
    assert rc == 2 and "exists" in text and "--overwrite" in text, text
    assert (twin_dir / "twin.json").read_bytes() == before
    old_log = tmp_path / "old.jsonl"
    old_log.write_text("a user's notes\n")
    rc, text = said([*args, "--record", str(twin_dir)], caplog, capsys)  # a folder with files
    assert rc == 2 and "not empty" in text, text
    rc, text = said([*args, "--log", str(old_log), "--overwrite"], caplog, capsys)
    assert rc == 0, text
    assert json.loads(old_log.read_text().splitlines()[0])["format"] == "vinetwin-servo-log"


def test_two_default_logs_in_the_same_second_are_both_kept(twin_dir: Path) -> None:
    from vinetwin.servo.runner import default_log_path

    twin = Twin.load(twin_dir)
    first = default_log_path(twin, "p1")
    first.parent.mkdir(parents=True)
    first.write_text("{}\n")
    second = default_log_path(twin, "p1")
    assert second != first and second.parent == first.parent


# ----------------------------------------------------------------------------- 3 gains
@pytest.mark.parametrize(
    ("flag", "value", "needle"),
    [("--gain", "-1", "gain"), ("--gain-far", "-5", "gain_far"), ("--gain", "nan", "gain"),
     ("--gain", "0", "gain"), ("--gain", "1000", "above 5")],
)  # fmt: skip
def test_a_gain_outside_the_envelope_is_refused_by_servo_and_simulation(
    twin_dir: Path,
    flag: str,
    value: str,
    needle: str,
    caplog: pytest.LogCaptureFixture,
    capsys: pytest.CaptureFixture[str],
) -> None:
    from vinetwin.servo.config import ServoConfig
    from vinetwin.sim.config import SimConfig

    for cfg in (ServoConfig, SimConfig):
        with pytest.raises(InputError, match=needle):
            cfg(**{flag[2:].replace("-", "_"): float(value)})
    rc, text = said(["servo", "--twin", str(twin_dir), *NO_CAMERA, flag, value], caplog, capsys)
    assert rc == 2 and needle in text and "/nowhere" not in text, text


# ----------------------------------------------------------------------------- 4 ceilings
@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["--max-linear", "100"], "Panda's own"),
        (["--max-linear", "100", "--override-envelope"], "Panda's own"),
        (["--max-linear", "0.3"], "envelope"),
        (["--max-angular", "1.5"], "envelope"),
        (["--max-linear-acceleration", "1e12"], "Panda's own"),
        (["--max-angular-acceleration", "11"], "envelope"),
        (["--frame-timeout", "5", "--camera-lost", "10"], "frame_timeout"),
    ],
)
def test_limits_above_the_envelope_are_refused_unless_overridden(
    twin_dir: Path,
    args: list[str],
    needle: str,
    caplog: pytest.LogCaptureFixture,
    capsys: pytest.CaptureFixture[str],
) -> None:
    rc, text = said(["servo", "--twin", str(twin_dir), *NO_CAMERA, *args], caplog, capsys)
    assert rc == 2 and needle in text and "/nowhere" not in text, text
    if args[0].startswith("--max-") and "--override-envelope" not in args:
        rc, text = said(["campaign", str(twin_dir), *args], caplog, capsys)
        assert rc == 2 and needle in text, text


def test_the_override_allows_up_to_the_arms_own_limits_and_the_simulation_keeps_them(
    twin_dir: Path,
) -> None:
    """Above the envelope with the override the servo runs (simulation), and no command it
    sends exceeds the limits it was given."""
    from vinetwin.servo.config import ARM_CEILING, Limits
    from vinetwin.servo.loop import read_log

    lim = Limits(max_linear=0.4, max_angular=1.5, override_envelope=True)
    assert lim.max_linear <= ARM_CEILING.max_linear
    log = twin_dir / "fast.jsonl"
    args = ["servo", "--twin", str(twin_dir), "--max-linear", "0.4", "--override-envelope",
            "--gain", "5", "--gain-far", "5", "--duration", "1", "--log", str(log)]  # fmt: skip
    assert main(args) == 0
    _, cycles, _ = read_log(log)
    speeds = [float(np.linalg.norm(c["sent"][:3])) for c in cycles]
    assert cycles and max(speeds) <= 0.4 + 1e-9


# ----------------------------------------------------------------------------- 5 clean-up
def test_the_clean_up_never_deletes_a_users_file_nor_through_a_link(
    twin_dir: Path, tmp_path: Path
) -> None:
    from vinetwin.files import ORPHAN_AGE_S
    from vinetwin.render.export import export_references

    old = time.time() - ORPHAN_AGE_S - 60
    notes = twin_dir / ".notes.tmp"
    notes.write_text("mine")
    outside = tmp_path / "elsewhere"
    outside.mkdir()
    theirs = [outside / ".data.tmp", outside / ".p1.ply.vinetwin-otherhost-1.0123456789.vttmp"]
    for p in theirs:
        p.write_text("x")
    for p in (notes, *theirs):
        os.utime(p, (old, old))
    (twin_dir / "references").symlink_to(outside, target_is_directory=True)
    twin = Twin.load(twin_dir)
    twin.poses[0].name = "renamed"
    twin.save()
    export_references(twin, [twin.poses[0].id], workers=1)
    assert notes.read_text() == "mine"
    assert all(p.exists() for p in theirs)
    assert (outside / f"{twin.poses[0].id}.ply").exists()  # written there, with a warning


def test_export_says_when_its_references_folder_is_a_link(
    twin_dir: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    from vinetwin.render.export import export_references

    (tmp_path / "refs").mkdir()
    (twin_dir / "references").symlink_to(tmp_path / "refs", target_is_directory=True)
    with caplog.at_level(logging.WARNING):
        export_references(Twin.load(twin_dir), ["p1"], workers=1)
    assert "symbolic link" in caplog.text and str(tmp_path / "refs") in caplog.text


# ----------------------------------------------------------------------------- 6 the lock
def test_the_lock_file_follows_the_umask(twin_dir: Path) -> None:
    old = os.umask(0o002)  # a group that shares the twin folder
    try:
        Twin.load(twin_dir).save()
    finally:
        os.umask(old)
    assert (twin_dir / ".twin.lock").stat().st_mode & 0o777 == 0o664


# ----------------------------------------------------------------------------- 7 Ctrl-C
def _kernel_interrupt() -> SystemError:
    """What Ctrl-C inside a numba kernel raises: CPython's SystemError for a call that returned
    a result with an exception set, the KeyboardInterrupt as its cause."""
    try:
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as ki:
            raise SystemError(
                "CPUDispatcher(<function k>) returned a result with an exception set"
            ) from ki
    except SystemError as exc:
        return exc


def test_an_interrupt_inside_a_kernel_stops_a_batch_instead_of_failing_one_job() -> None:
    from vinetwin.executor import ExecutorConfig, run_unordered

    done: list[int] = []

    def job(i: int) -> int:
        if i == 1:
            raise _kernel_interrupt()
        done.append(i)
        return i

    with pytest.raises(KeyboardInterrupt):
        list(run_unordered(job, [0, 1, 2, 3], ExecutorConfig(workers=1)))
    assert done == [0]  # the batch stopped at the interrupt


def test_an_interrupt_inside_a_kernel_stops_the_servo_and_the_command(
    vine_views, monkeypatch: pytest.MonkeyPatch
) -> None:  # type: ignore[no-untyped-def]
    import logging

    import vinetwin.servo.step as step
    from vinetwin.errors import exit_status
    from vinetwin.servo.step import Servo

    sv = Servo(vine_views.reference("p1"), camera=vine_views.twin.camera)

    def interrupted(*args: object, **kwargs: object) -> None:
        raise _kernel_interrupt()

    monkeypatch.setattr(step, "perceive", interrupted)
    with pytest.raises(KeyboardInterrupt):
        sv.step_depth(np.zeros((480, 848), np.float32), stamp=0.0)
    assert exit_status(_kernel_interrupt(), logging.getLogger()) == 130


# ----------------------------------------------------------------------------- 8 the port
def test_the_web_app_refuses_a_port_in_use_or_out_of_range(
    twin_dir: Path, caplog: pytest.LogCaptureFixture, capsys: pytest.CaptureFixture[str]
) -> None:
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        rc, text = said(["web", str(twin_dir), "--port", str(port)], caplog, capsys)
        assert rc == 2 and f"127.0.0.1:{port}" in text and "in use" in text, text
    for bad in ("70000", "0", "-1"):
        rc, text = said(["web", str(twin_dir), "--port", bad], caplog, capsys)
        assert rc == 2 and "1-65535" in text, text


# ----------------------------------------------------------------------------- 9 tracebacks
def _write_twin_json(twin_dir: Path, text: str) -> None:
    (twin_dir / "twin.json").write_text(text)


def test_a_twin_file_with_a_huge_number_or_deep_nesting_is_a_named_error(
    twin_dir: Path, caplog: pytest.LogCaptureFixture, capsys: pytest.CaptureFixture[str]
) -> None:
    good = (twin_dir / "twin.json").read_text()
    for name, text in {
        "5000 digits": good.replace('"format_version": ', '"format_version": ' + "9" * 5000 + ", \"x\": ", 1),
        "deep": good[:-2] + ', "x": ' + "[" * 100_000 + "]" * 100_000 + "}\n",
    }.items():  # fmt: skip
        _write_twin_json(twin_dir, text)
        with pytest.raises(TwinError):
            Twin.load(twin_dir)
        rc, out = said(["info", str(twin_dir)], caplog, capsys)
        assert rc == 2 and "twin.json" in out and "Traceback" not in out, (name, out)


def test_a_reference_sidecar_nested_too_deep_is_rendered_again(twin_dir: Path) -> None:
    from vinetwin.render.export import export_references

    twin = Twin.load(twin_dir)
    export_references(twin, ["p1"], workers=1)
    (twin.references_dir / "p1.json").write_text("[" * 100_000 + "]" * 100_000)
    report = export_references(twin, ["p1", "p2"], workers=1)
    assert [r.status for r in report.results] == ["rendered", "rendered"]


def test_rich_markup_in_a_twin_path_is_printed_as_text(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, capsys: pytest.CaptureFixture[str]
) -> None:
    twin = tmp_path / "vine[" / "oops].twin"  # the path holds "[/oops]", a closing tag
    rc, text = said(
        ["sample", "--out", str(twin), "--edge", "0.006", "--cut-points", "1"], caplog, capsys
    )
    assert rc == 0 and "vine[/oops]" in text, text
    rc, text = said(["info", str(twin)], caplog, capsys)
    assert rc == 0 and "vine[/oops]" in text, text
    assert re.search(r"skeleton skeleton\.json: \d+ branches, [\d.]+ m of wood", text), text


def test_info_names_a_skeleton_it_cannot_read(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, capsys: pytest.CaptureFixture[str]
) -> None:
    """`vinetwin info` validates the twin folder: a torn skeleton.json (which `propose` and the
    web app need) is said after the rest of the summary, and the command fails on it (it
    was not looked at)."""
    twin = tmp_path / "v.twin"
    assert said(["sample", "--out", str(twin), "--edge", "0.006"], caplog, capsys)[0] == 0
    (twin / "skeleton.json").write_text("{torn")
    rc, text = said(["info", str(twin)], caplog, capsys)
    assert rc == 2 and "cannot be read" in text and "cannot read skeleton" in text, text
    assert "pruning poses" in text  # the rest still summarised


def _full_disk(monkeypatch: pytest.MonkeyPatch) -> None:
    """Every file vinetwin writes atomically, and every log line, fails as on a full disk."""
    import vinetwin.files as files

    def full(*args: object, **kwargs: object) -> None:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(files, "_write_renamed", full)


def test_outputs_on_a_full_disk_are_named_errors(
    twin_dir: Path,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    caplog: pytest.LogCaptureFixture,
    capsys: pytest.CaptureFixture[str],
) -> None:
    _full_disk(monkeypatch)
    out = tmp_path / "p1.png"
    rc, text = said(["preview", str(twin_dir), "--pose", "p1", "--out", str(out)], caplog, capsys)
    assert rc == 2 and str(out) in text and "No space left" in text, text
    rc, text = said(["export", str(twin_dir), "--poses", "p1", "--workers", "1"], caplog, capsys)
    assert rc == 2 and "No space left" in text and "Traceback" not in text, text
    rc, text = said(["validate", str(twin_dir), "--poses", "p1", "--variants", "lm", "--starts",
                     "1", "--duration", "0.5", "--workers", "1"], caplog, capsys)  # fmt: skip
    assert rc == 2 and "No space left" in text and "Traceback" not in text, text


def test_a_servo_log_on_a_full_device_stops_the_robot_and_names_the_log(
    twin_dir: Path, caplog: pytest.LogCaptureFixture, capsys: pytest.CaptureFixture[str]
) -> None:
    if not Path("/dev/full").exists():
        pytest.skip("no /dev/full on this system")
    args = ["servo", "--twin", str(twin_dir), "--duration", "0.5", "--log", "/dev/full"]
    rc, text = said(args, caplog, capsys)
    assert rc == 2 and "/dev/full: cannot write the servo log: No space left" in text, text
    assert "Traceback" not in text


@pytest.mark.parametrize(
    "content", ["[]", '"x"', "{}", '{"format": "vinetwin-capture", "frames": 5}']
)
def test_a_capture_json_of_the_wrong_shape_is_a_named_error(
    tmp_path: Path,
    content: str,
    caplog: pytest.LogCaptureFixture,
    capsys: pytest.CaptureFixture[str],
) -> None:
    cap = tmp_path / "cap"
    cap.mkdir()
    (cap / "capture.json").write_text(content)
    rc, text = said(["reconstruct", str(cap), "--twin", str(tmp_path / "r.twin")], caplog, capsys)
    assert rc == 2 and "capture.json" in text and "Traceback" not in text, text
    assert not (tmp_path / "r.twin").exists()


@pytest.mark.parametrize("value", ['"0.5"', "null", "true", "[1]"])
def test_a_profile_value_of_the_wrong_type_is_a_named_error(
    twin_dir: Path,
    tmp_path: Path,
    value: str,
    caplog: pytest.LogCaptureFixture,
    capsys: pytest.CaptureFixture[str],
) -> None:
    profile = tmp_path / "p.json"
    profile.write_text('{"latency": ' + value + "}")
    for cmd in ("campaign", "validate"):
        rc, text = said([cmd, str(twin_dir), "--profile", str(profile)], caplog, capsys)
        assert rc == 2 and "latency" in text and "Traceback" not in text, text


def test_check_reference_refuses_an_out_that_is_a_file_or_holds_a_check(
    twin_dir: Path,
    tmp_path: Path,
    caplog: pytest.LogCaptureFixture,
    capsys: pytest.CaptureFixture[str],
) -> None:
    rc, text = said(
        ["check-reference", str(twin_dir), "--out", str(twin_dir / "twin.json")], caplog, capsys
    )
    assert rc == 2 and "is a file" in text, text
    out = tmp_path / "check"
    out.mkdir()
    (out / "check.json").write_text("an earlier check")
    rc, text = said(["check-reference", str(twin_dir), "--out", str(out)], caplog, capsys)
    assert rc == 2 and "exists" in text and (out / "check.json").read_text() == "an earlier check"


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["servo", "--start-translation", "nan"], "start_translation"),
        (["servo", "--start-rotation", "-1"], "start_rotation"),
        (["servo", "--dynamics-factor", "2"], "dynamics_factor"),
        (["sample", "--seed", "-1"], "seed"),
        (["sample", "--edge", "1e-9"], "edge"),
        (["campaign", "--duration", "1e308"], "duration"),
        (["validate", "--seed", "-3"], "seed"),
    ],
)
def test_options_that_crashed_are_named_errors(
    twin_dir: Path,
    tmp_path: Path,
    args: list[str],
    needle: str,
    caplog: pytest.LogCaptureFixture,
    capsys: pytest.CaptureFixture[str],
) -> None:
    where = {"servo": ["--twin", str(twin_dir)], "sample": ["--out", str(tmp_path / "s.twin")]}
    full = [args[0], *where.get(args[0], [str(twin_dir)]), *args[1:]]
    rc, text = said(full, caplog, capsys)
    assert rc == 2 and needle in text and "Traceback" not in text, text
    assert not (tmp_path / "s.twin").exists()


def test_servo_plot_names_binary_and_malformed_logs(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, capsys: pytest.CaptureFixture[str]
) -> None:
    binary = tmp_path / "bin.jsonl"
    binary.write_bytes(bytes(range(256)) * 10)
    header = '{"format": "vinetwin-servo-log", "format_version": 1}\n'
    logs = {
        "binary": binary,
        "not an object": "[1, 2]\n",
        "not json": "garbage\n",  # was called an empty log
        "bad version": '{"format": "vinetwin-servo-log", "format_version": "x"}\n',
        "bad cycle": header + '{"stamp": 0.0, "true_error": 5, "trusted": true}\n',
        "bad pose": header + '{"stamp": 0.0, "T_ref_cur": [[1]], "trusted": true}\n',
    }
    for name, content in logs.items():
        path = content if isinstance(content, Path) else tmp_path / f"{name}.jsonl"
        if not isinstance(content, Path):
            path.write_text(content)
        rc, text = said(["servo-plot", str(path), "--out", str(tmp_path / "plots")], caplog, capsys)
        assert rc == 2 and str(path) in text and "Traceback" not in text, (name, text)
        assert name != "not json" or "not a vinetwin servo log" in text, text


# ----------------------------------------------------------------------------- 10 small
def test_a_huge_cane_axis_loads_as_its_direction_and_saves(twin_dir: Path) -> None:
    data = json.loads((twin_dir / "twin.json").read_text())
    data["cut_points"][0]["cane_axis"] = [1e308, 1e308, 0]
    (twin_dir / "twin.json").write_text(json.dumps(data))
    twin = Twin.load(twin_dir)
    assert np.allclose(twin.cut_points[0].cane_axis, [2**-0.5, 2**-0.5, 0.0])
    twin.poses[0].name = "saved"
    twin.save()
    assert Twin.load(twin_dir).poses[0].name == "saved"
