"""The servo's check of proposed poses (`propose --check-profile`): which direction is kept, that
the twin holds the pose it was checked at, and the check's settings named when out of range."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tests.test_propose import known_vine
from vinetwin.errors import InputError
from vinetwin.plan.config import ProposeConfig, ServoCheckConfig
from vinetwin.plan.proposer import propose as plain_propose
from vinetwin.sim import servo_check as sc
from vinetwin.twin.model import Twin, twin_from_skeleton
from vinetwin.twin.poses import pruning_pose


def propose(twin: Twin, cfg: ProposeConfig):  # the check is the simulation's: handed in
    return sc.propose_checked(twin, cfg)


@pytest.fixture
def twin(tmp_path) -> Twin:
    return twin_from_skeleton(tmp_path / "known.twin", known_vine(), edge=0.003)


def _fake_rates(script: dict[str, list[float]], calls: list[tuple[str, float]]):
    """A stand-in for the closed-loop runs: each pose's success rates in the order asked (1.0
    for a pose the script does not name); records (pose, azimuth) per call."""
    seen: dict[str, int] = {}

    def rates(twin: Twin, cfg: ServoCheckConfig, pids: list[str]) -> dict[str, tuple[float, str]]:
        out = {}
        for pid in pids:
            k = seen.get(pid, 0)
            seen[pid] = k + 1
            calls.append((pid, twin.pose(pid).approach.azimuth))
            seq = script.get(pid, [1.0])
            out[pid] = (seq[min(k, len(seq) - 1)], "")
        return out

    return rates


def _approach_matches(twin: Twin, pid: str, summary: dict) -> bool:
    ap = twin.pose(pid).approach
    return (math.isclose(math.degrees(ap.azimuth), summary["azimuth_deg"], abs_tol=0.06)
            and math.isclose(math.degrees(ap.elevation), summary["elevation_deg"], abs_tol=0.06))  # fmt: skip


def test_the_direction_converging_from_most_starts_is_kept_and_validated_again(
    twin: Twin, monkeypatch: pytest.MonkeyPatch
) -> None:
    calls: list[tuple[str, float]] = []
    # p1: its best-scored direction converges from 2 of 4 starts, the next from 3, the third
    # from 1: the second is kept, and validated again once it is back in the twin
    monkeypatch.setattr(sc, "_rates", _fake_rates({"p1": [0.5, 0.75, 0.25, 0.75]}, calls))
    check = ServoCheckConfig(check_profile="ideal", check_alternatives=2)
    result = propose(twin, ProposeConfig(servo=check))
    rows = {r["pose_id"]: r for r in result.rows if "pose_id" in r}
    assert len(rows) == 4
    c = rows["p1"]["servo_check"]
    assert c == {"profile": "ideal", "tried": 3, "success_rates": [0.5, 0.75, 0.25], "kept": 1,
                 "success_rate": 0.75}  # fmt: skip
    for pid in ("p2", "p3", "p4"):
        assert rows[pid]["servo_check"]["tried"] == 1  # converged at once: nothing else tried
    # p1 asked five times: the three directions, the kept one again, and once more for the
    # map of every pose (stored runs: nothing runs again); all four poses at first in one round
    p1 = [az for pid, az in calls if pid == "p1"]
    assert len(p1) == 5 and p1[3] == p1[4] == p1[1] and len({p1[0], p1[1], p1[2]}) == 3
    assert [pid for pid, _ in calls[:4]] == ["p1", "p2", "p3", "p4"]
    assert [pid for pid, _ in calls[-4:]] == ["p1", "p2", "p3", "p4"]
    saved = Twin.load(twin.root)
    pose = saved.pose("p1")
    assert pose.extra["servo_check"]["kept"] == 1
    # the twin holds the kept direction, and its search scores and the proposal's agree
    rec = saved.cut_point(pose.cut_point).extra["proposal"]
    assert rec["search"] == pose.extra["search"] == rows["p1"]["search"]
    assert rec["servo_check"] == c
    assert _approach_matches(saved, "p1", rec["search"])
    cut = saved.cut_point(pose.cut_point)
    T = pruning_pose(cut.point, cut.cane_axis, pose.approach)
    assert np.allclose(T, pose.T_vine_camera, atol=1e-9)
    assert "servo check (ideal): converged from 75% of the starts, direction 2 of 3" in (
        __import__("vinetwin.plan.proposer", fromlist=["describe_cut"]).describe_cut(saved, cut.id)
    )
    assert "servo check" in result.markdown() and "75% (3)" in result.markdown()


def test_a_tie_keeps_the_better_scored_direction(twin: Twin, monkeypatch) -> None:
    calls: list[tuple[str, float]] = []
    monkeypatch.setattr(sc, "_rates", _fake_rates({"p2": [0.5, 0.5]}, calls))
    cfg = ProposeConfig(servo=ServoCheckConfig(check_profile="ideal", check_alternatives=1))
    result = propose(twin, cfg)
    row = next(r for r in result.rows if r.get("pose_id") == "p2")
    assert row["servo_check"]["kept"] == 0 and row["servo_check"]["tried"] == 2
    p2 = [az for pid, az in calls if pid == "p2"]
    assert len(p2) == 4 and p2[2] == p2[3] == p2[0] != p2[1]  # back to the first, again
    assert _approach_matches(Twin.load(twin.root), "p2", row["search"])


def test_the_check_runs_the_closed_loop_and_writes_its_validation(twin: Twin) -> None:
    """The real runs (ideal profile, one start per pose): every pose of the known vine
    converges, and its validation is in the twin as `vinetwin validate` writes it."""
    check = ServoCheckConfig(check_profile="ideal", check_starts=1, check_workers=1)
    cfg = ProposeConfig(servo=check)
    result = propose(twin, cfg)
    saved = Twin.load(twin.root)
    assert len(saved.poses) == 4
    converged = 0
    for r in result.rows:
        c = r["servo_check"]
        v = saved.pose(r["pose_id"]).extra["validation"]["variants"]["point_to_plane"]
        assert v["starts"] == 1 and v["success_rate"] == c["success_rate"], (r, v)
        # a pose that converged was not searched further; one that did not, to the end
        assert c["tried"] == (1 if c["success_rate"] == 1.0 else 4), c
        converged += c["success_rate"] == 1.0
    assert converged >= 3
    # the servo-ability map covers every checked pose, not only the last round's
    summary = (saved.validation_dir / "summary.md").read_text()
    assert all(f"| {p.id} |" in summary for p in saved.poses)


@pytest.mark.parametrize(
    ("kw", "name"),
    [({"check_starts": 0}, "check_starts"), ({"check_alternatives": 11}, "check_alternatives"),
     ({"check_workers": -1}, "check_workers"),
     ({"check_translation": 0.5}, "check_translation"), ({"check_rotation": float("nan")},
     "check_rotation")],
)  # fmt: skip
def test_check_settings_out_of_range_are_named(kw: dict, name: str) -> None:
    with pytest.raises(InputError, match=name):
        ServoCheckConfig(**kw)


def test_an_unknown_profile_or_no_check_is_named_before_anything_is_written(twin: Twin) -> None:
    before = (twin.root / "twin.json").read_text()
    with pytest.raises(InputError, match="no-such-profile"):
        propose(twin, ProposeConfig(servo=ServoCheckConfig(check_profile="no-such-profile")))
    # the planner alone cannot run the check (it does not import the simulation): it says so
    with pytest.raises(InputError, match="propose_checked"):
        plain_propose(twin, ProposeConfig(servo=ServoCheckConfig(check_profile="ideal")))
    assert (twin.root / "twin.json").read_text() == before


def test_the_command_names_a_bad_check_and_writes_nothing(
    twin: Twin, caplog: pytest.LogCaptureFixture, capsys: pytest.CaptureFixture[str]
) -> None:
    from tests.test_envelope import said

    before = (twin.root / "twin.json").read_text()
    for flag, value in (("--check-profile", "no-such-profile"), ("--check-starts", "0"),
                        ("--check-alternatives", "99")):  # fmt: skip
        rc, text = said(["propose", str(twin.root), flag, value], caplog, capsys)
        assert rc == 2 and (value in text or flag.strip("-").replace("-", "_") in text), text
    assert (twin.root / "twin.json").read_text() == before
