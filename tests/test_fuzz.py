"""Fuzzing the inputs a user hands vinetwin: every numeric option of `servo`, `campaign`,
`validate`, `export` and `sample` with NaN, infinities, zero, negatives and huge values, and
twin.json, profile files, capture.json and export sidecars mutated from valid ones. Each ends in
success or a named error (exit status 2, the field or option named), never a traceback, and a
refusal changes no file.

The commands' work is replaced by a stub at the library call that does it (`STUBS`): what is
fuzzed is everything before it, where every setting is checked; an accepted value reaches the
stub, which checks that no number it was handed is NaN or infinite. Bounded in time: about a
minute in all on a 2-core machine (`docs/testing.md`)."""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
import shutil
import typing
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from vinetwin.cli import COMMANDS, main
from vinetwin.errors import VinetwinError


class Accepted(Exception):
    """Raised by a stub: the command accepted its arguments and reached its work."""


#: Per command: the library function that does its work (replaced by a stub).
STUBS = {
    "servo": ("vinetwin.servo.runner", "run_pose"),
    "campaign": ("vinetwin.sim.campaign", "run_campaign"),
    "validate": ("vinetwin.sim.validate", "validate_folder"),
    "export": ("vinetwin.render.export", "export_references"),
    "sample": ("vinetwin.twin.skeleton", "tube_mesh"),
}
#: Examples per file-mutation test (VINETWIN_FUZZ_EXAMPLES raises it for a longer hunt).
EXAMPLES = int(os.environ.get("VINETWIN_FUZZ_EXAMPLES", "40"))
#: The values every numeric option is tried with.
NASTY = ["nan", "inf", "-inf", "0", "-1", "-0.0", "1e308", "1e-308", "4294967296"]


def _numeric_flags(cls: type) -> Iterator[tuple[str, str]]:
    """(flag, field name) of every int or float option of a command dataclass, nested configs
    included (their prefixes are omitted on the command line)."""
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        t = hints[f.name]
        if typing.get_origin(t) is typing.Annotated:
            t = typing.get_args(t)[0]
        if dataclasses.is_dataclass(t):
            yield from _numeric_flags(t)  # type: ignore[arg-type]
            continue
        args = set(typing.get_args(t)) - {type(None)}
        if t in (int, float) or (args and args <= {int, float}):
            yield "--" + f.name.replace("_", "-"), f.name


def _numbers(x: Any) -> Iterator[float]:
    if isinstance(x, bool):
        return
    if isinstance(x, int | float):
        yield float(x)
    elif dataclasses.is_dataclass(x) and not isinstance(x, type):
        for f in dataclasses.fields(x):
            yield from _numbers(getattr(x, f.name))
    elif isinstance(x, tuple | list):
        for v in x:
            yield from _numbers(v)
    elif isinstance(x, dict):
        for v in x.values():
            yield from _numbers(v)


@pytest.fixture
def stubs(monkeypatch: pytest.MonkeyPatch) -> None:
    import importlib

    def stub(*args: Any, **kwargs: Any) -> None:
        raise Accepted(args, kwargs)

    for module, name in STUBS.values():
        monkeypatch.setattr(importlib.import_module(module), name, stub)


def _run_plain(
    args: list[str], capsys: pytest.CaptureFixture[str], caplog: pytest.LogCaptureFixture
) -> tuple[int, str]:
    """The exit status of `vinetwin ARGS` (0 or 2, no traceback) and what it said."""
    capsys.readouterr()
    caplog.clear()
    with caplog.at_level(logging.ERROR, logger="vinetwin"):
        rc = main(args)
    out = capsys.readouterr()
    text = caplog.text + out.err + out.out
    assert rc in (0, 2) and "Traceback" not in text, (args, rc, text)
    return rc, text


def _run(
    args: list[str], capsys: pytest.CaptureFixture[str], caplog: pytest.LogCaptureFixture
) -> tuple[str, str]:
    """'accepted' (the stub was reached with finite numbers) or 'refused' (exit status 2), and
    what was said; fails on anything else."""
    try:
        rc, text = _run_plain(args, capsys, caplog)
    except Accepted as accepted:
        bad = [v for v in _numbers(accepted.args) if not math.isfinite(v)]
        assert not bad, (args, "accepted a non-finite value", bad)
        return "accepted", ""
    assert rc == 2, (args, rc, text)
    return "refused", text


def _command_args(command: str, twin: Path, tmp: Path) -> list[str]:
    return {
        "servo": ["servo", "--twin", str(twin)],
        "sample": ["sample", "--out", str(tmp / "s.twin")],
    }.get(command, [command, str(twin)])


@pytest.mark.parametrize("command", sorted(STUBS))
def test_every_numeric_option_takes_nasty_values_without_a_traceback(
    command: str,
    twin_dir: Path,
    tmp_path: Path,
    stubs: None,
    capsys: pytest.CaptureFixture[str],
    caplog: pytest.LogCaptureFixture,
) -> None:
    flags = sorted(set(_numeric_flags(COMMANDS[command])))
    assert len(flags) >= 2, flags
    base = _command_args(command, twin_dir, tmp_path)
    before = (twin_dir / "twin.json").read_bytes()
    assert _run(base, capsys, caplog)[0] == "accepted"  # the defaults reach the work
    counts = {"accepted": 0, "refused": 0}
    for flag, name in flags:
        for value in NASTY:
            outcome, text = _run([*base, flag, value], capsys, caplog)
            counts[outcome] += 1
            if outcome == "refused":  # the option is named (tyro names the flag, a check the field)
                assert name in text or flag in text, (flag, value, text)
    assert (twin_dir / "twin.json").read_bytes() == before
    assert not (tmp_path / "s.twin").exists()
    # every option refuses NaN and infinity at least: the counts say the loop ran
    assert counts["refused"] >= 3 * len(flags), counts


@settings(
    max_examples=EXAMPLES * 3 // 2,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)
@given(
    data=st.data(),
    value=st.floats(allow_nan=True, allow_infinity=True) | st.integers(-(2**70), 2**70),
)
def test_servo_options_take_any_number_without_a_traceback(
    data: st.DataObject,
    value: float,
    twin_dir: Path,
    tmp_path: Path,
    stubs: None,
    capsys: pytest.CaptureFixture[str],
    caplog: pytest.LogCaptureFixture,
) -> None:
    command = data.draw(st.sampled_from(sorted(STUBS)))
    flag, _ = data.draw(st.sampled_from(sorted(set(_numeric_flags(COMMANDS[command])))))
    _run([*_command_args(command, twin_dir, tmp_path), flag, repr(value)], capsys, caplog)


# ----------------------------------------------------------------------------- file mutations
#: A JSON value of any shape, and the raw texts that broke readers before (a 5000-digit number,
#: nesting 100 000 deep, rich markup).
JSON_VALUES = st.recursive(
    st.none() | st.booleans() | st.integers(-(2**64), 2**64) | st.floats() | st.text(max_size=8),
    lambda inner: (
        st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=6), inner, max_size=3)
    ),
    max_leaves=6,
)
RAW = [
    "9" * 5000,
    "[" * 100_000 + "]" * 100_000,
    '"[/oops]"',
    '"' + "x" * 10_000 + '"',
    "-0",
    "1e999",
]


def _paths(doc: Any, prefix: tuple[Any, ...] = ()) -> Iterator[tuple[Any, ...]]:
    yield prefix
    if isinstance(doc, dict):
        for k, v in doc.items():
            yield from _paths(v, (*prefix, k))
    elif isinstance(doc, list):
        for i, v in enumerate(doc[:3]):
            yield from _paths(v, (*prefix, i))


def mutate(doc: Any, data: st.DataObject) -> str:
    """`doc` as JSON text with one node replaced, deleted or made a raw nasty text."""
    paths = list(_paths(doc))
    path = data.draw(st.sampled_from(paths[1:] or paths))
    kind = data.draw(st.sampled_from(["value", "delete", "raw"]))
    marker = "__FUZZ_RAW__"
    if not path:
        return json.dumps(data.draw(JSON_VALUES))
    doc = json.loads(json.dumps(doc))
    parent = doc
    for k in path[:-1]:
        parent = parent[k]
    if kind == "delete":
        del parent[path[-1]]
        return json.dumps(doc)
    parent[path[-1]] = marker if kind == "raw" else data.draw(JSON_VALUES)
    text = json.dumps(doc)
    return text.replace(f'"{marker}"', data.draw(st.sampled_from(RAW))) if kind == "raw" else text


FUZZ = settings(
    max_examples=EXAMPLES,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)


@FUZZ
@given(data=st.data())
def test_a_mutated_twin_json_loads_or_is_named_and_changes_nothing(
    data: st.DataObject,
    twin_dir: Path,
    capsys: pytest.CaptureFixture[str],
    caplog: pytest.LogCaptureFixture,
) -> None:
    from vinetwin.twin import Twin

    good = json.loads((twin_dir / "twin.json").read_text())
    text = mutate(good, data)
    (twin_dir / "twin.json").write_text(text)
    try:
        Twin.load(twin_dir)
    except VinetwinError:
        pass
    _run_plain(["info", str(twin_dir), "--no-check-mesh"], capsys, caplog)
    assert (twin_dir / "twin.json").read_text() == text  # reading changes nothing
    (twin_dir / "twin.json").write_text(json.dumps(good))


@FUZZ
@given(data=st.data())
def test_a_mutated_profile_loads_or_is_named(data: st.DataObject, tmp_path: Path) -> None:
    from vinetwin.sim.config import PROFILES, FieldProfile, load_profile

    good = PROFILES["field"].to_dict()
    path = tmp_path / "p.json"
    path.write_text(mutate(good, data))
    try:
        profile = load_profile(str(path))
    except VinetwinError:
        return
    assert isinstance(profile, FieldProfile)
    assert all(math.isfinite(v) for v in _numbers(profile))


@pytest.fixture(scope="module")
def capture_meta(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    from vinetwin.camera import d405
    from vinetwin.capture.folder import CaptureWriter

    root = tmp_path_factory.mktemp("cap")
    writer = CaptureWriter(root, d405("848x480"))
    for k in range(3):
        writer.add(np.full((480, 848), 3000, np.uint16), None, np.eye(4), float(k) / 30)
    writer.close()
    return {"root": str(root), "meta": json.loads((root / "capture.json").read_text())}


def test_a_frame_path_too_long_for_the_file_system_is_named(capture_meta: dict[str, Any]) -> None:
    """Found by the fuzz below: a depth name of 5000 characters made `Path.exists` raise
    OSError (ENAMETOOLONG) instead of naming the frame."""
    from vinetwin.capture.folder import CaptureError, read_capture

    root = Path(capture_meta["root"])
    meta = json.loads(json.dumps(capture_meta["meta"]))
    meta["frames"][0]["depth"] = "x" * 5000
    (root / "capture.json").write_text(json.dumps(meta))
    try:
        with pytest.raises(CaptureError, match=r"frame 000000: depth: .* not a usable path"):
            read_capture(root, check_frames=True)
    finally:
        (root / "capture.json").write_text(json.dumps(capture_meta["meta"]))


@FUZZ
@given(data=st.data())
def test_a_mutated_capture_json_reads_or_is_named(
    data: st.DataObject, capture_meta: dict[str, Any]
) -> None:
    from vinetwin.capture.folder import CaptureError, read_capture

    root = Path(capture_meta["root"])
    (root / "capture.json").write_text(mutate(capture_meta["meta"], data))
    try:
        read_capture(root, check_frames=True)
    except CaptureError:
        pass
    finally:
        (root / "capture.json").write_text(json.dumps(capture_meta["meta"]))


def test_a_capture_format_version_that_is_no_whole_number_is_named(
    capture_meta: dict[str, Any],
) -> None:
    """Found by the fuzz test above: a format_version of 1e999 (infinity once read) crashed
    with OverflowError. Each of these is a CaptureError naming the field; 1.0 still reads."""
    from vinetwin.capture.folder import CaptureError, read_capture

    root = Path(capture_meta["root"])
    good = json.dumps(capture_meta["meta"])
    assert '"format_version": 1' in good
    try:
        for raw in ("1e999", "-1e999", '"x"', "-1", "1.5", "true", "null"):
            (root / "capture.json").write_text(
                good.replace('"format_version": 1', f'"format_version": {raw}', 1)
            )
            with pytest.raises(CaptureError, match="format_version"):
                read_capture(root, check_frames=False)
        (root / "capture.json").write_text(
            good.replace('"format_version": 1', '"format_version": 1.0', 1)
        )
        read_capture(root, check_frames=False)
    finally:
        (root / "capture.json").write_text(good)


@pytest.fixture(scope="module")
def exported(sample_twin_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, str]:
    """A twin with p1 exported, and p1's sidecar as written then."""
    from vinetwin.render.export import export_references
    from vinetwin.twin import Twin

    dst = tmp_path_factory.mktemp("exp") / "t.twin"
    shutil.copytree(sample_twin_dir, dst, ignore=shutil.ignore_patterns("references", "validation"))
    assert export_references(Twin.load(dst), ["p1"], workers=1).ok
    return dst, (dst / "references" / "p1.json").read_text()


@settings(
    max_examples=max(EXAMPLES // 2, 10), deadline=None, suppress_health_check=[HealthCheck.too_slow]
)
@given(data=st.data())
def test_a_mutated_sidecar_is_rendered_again_or_kept_never_a_crash(
    data: st.DataObject, exported: tuple[Path, str]
) -> None:
    """The servo's reader refuses a sidecar that does not vouch for its clouds by name; export
    renders such a reference again (or keeps it when the mutation left it valid)."""
    from vinetwin.render.export import export_references
    from vinetwin.render.reference import reference_for
    from vinetwin.twin import Twin

    twin = Twin.load(exported[0])
    sidecar = twin.references_dir / "p1.json"
    good = json.loads(exported[1])
    sidecar.write_text(mutate(good, data))
    try:
        reference_for(twin, "p1")
    except VinetwinError:
        pass
    report = export_references(twin, ["p1"], workers=1)
    assert [r.status for r in report.results] in (["rendered"], ["skipped"]), report.results
    assert json.loads(sidecar.read_text())["reference_format"] == good["reference_format"]
