"""Permanent wood on a scan's skeleton: the cordon rules of `scan.frame.split_cordons` and
`scan.candidates.label_kinds` on the shapes generated dense vines of seeds 6-21 showed (their
cut candidates were 73.7% found before these rules, 90.6% with them and the straightened
cordons: `benchmarks/scan_accuracy.py --set development`)."""

from __future__ import annotations

import numpy as np
import pytest

from vinetwin.scan.candidates import CORDON_RADIUS, SISTER, cut_candidates, label_kinds
from vinetwin.scan.config import FIRST_NODE
from vinetwin.scan.frame import split_cordons
from vinetwin.scan.refine import straighten_bumps
from vinetwin.twin.skeleton import Branch, Skeleton

LINE = np.linspace(0, 1, 60)[:, None]
Z = np.array([0.0, 0.0, 1.0])


def seg(a: list[float], b: list[float], r: float, kind: str = "cane", parent: int = -1) -> Branch:
    A, B = np.asarray(a), np.asarray(b)
    return Branch(A + LINE * (B - A), np.full(60, r), kind, parent)  # type: ignore[arg-type]


def kinds_of(sk: Skeleton) -> list[str]:
    split_cordons(sk, Z)
    label_kinds(sk, Z, "vine")
    return [b.kind for b in sk.branches]


def test_a_bilateral_vines_thinner_cordon_is_a_cordon() -> None:
    """Trunk 18 mm, a 40 cm cordon of 10 mm one way and a 35 cm one of 8.3 mm the other way
    (0.46 of the trunk: under `CORDON_RADIUS`, over `SISTER` of the first; generated vine seed 7):
    both are cordons and a cane on the thinner one is cut counted from its surface. A level
    4 mm cane leaving the head the same way is not one, nor is the thinner branch without a
    thick cordon the other way."""
    trunk = seg([0, 0, 0], [0, 0, 0.7], 0.018, "trunk")
    right = seg([0, 0, 0.7], [0.4, 0, 0.7], 0.010, parent=0)
    left = seg([0, 0, 0.7], [-0.35, 0, 0.7], 0.0083, parent=0)
    cane = seg([-0.2, 0, 0.7], [-0.2, 0, 1.2], 0.004, parent=2)
    thin = seg([0, 0, 0.7], [-0.3, 0.05, 0.71], 0.004, parent=0)
    assert 0.0083 < CORDON_RADIUS * 0.018 and 0.0083 >= SISTER * 0.010
    assert kinds_of(Skeleton([trunk, right, left, cane, thin])) == [
        "trunk", "cordon", "cordon", "cane", "cane"]  # fmt: skip
    sk = Skeleton([trunk, right, left, cane])
    kinds_of(sk)
    cut = next(c for c in cut_candidates(sk, "vine", 0.07) if c.branch == 3)
    assert abs(cut.point[2] - (0.7 + 0.0083 + FIRST_NODE + 1.3 * 0.07)) < 2e-3, cut.point
    lone = Skeleton([trunk, seg([0, 0, 0.7], [-0.35, 0, 0.7], 0.0083, parent=0),
                     seg([-0.2, 0, 0.7], [-0.2, 0, 1.2], 0.004, parent=1)])  # fmt: skip
    assert kinds_of(lone) == ["trunk", "cane", "cane"]


@pytest.mark.parametrize("turn", ["up", "down"])
def test_a_cordons_end_on_the_chain_of_its_last_cane_is_split_where_it_turns(turn: str) -> None:
    """A 35 cm cordon (10 mm; trunk 15 mm) whose last 12 cm (8 mm) and the cane of its last spur
    make one chain of the skeleton, the cane turning up (or a shoot hanging down) there
    (generated vines of seeds 9, 12, 13): the chain is split where it turns, its level start
    carries the cordon on and the cane hangs from it, cut counted from the cordon's end."""
    trunk = seg([0, 0, 0], [0, 0, 0.7], 0.015, "trunk")
    cordon = seg([0, 0, 0.7], [0.35, 0, 0.7], 0.010, parent=0)
    end = [0.47, 0.0, 0.7]
    far = [0.52, 0.0, 1.15] if turn == "up" else [0.52, 0.0, 0.25]
    tail, rising = seg([0.35, 0, 0.7], end, 0.008), seg(end, far, 0.004)
    chain = Branch(np.vstack([tail.points, rising.points[1:]]),
                   np.r_[tail.radii, rising.radii[1:]], "cane", 1)  # fmt: skip
    sk = Skeleton([trunk, cordon, chain])
    assert kinds_of(sk) == ["trunk", "cordon", "cordon", "cane"]
    assert np.linalg.norm(sk.branches[2].points[-1] - end) < 0.01, sk.branches[2].points[-1]
    assert sk.branches[3].parent == 2
    (cut,) = cut_candidates(sk, "vine", 0.07)
    d = np.linalg.norm(sk.branches[3].points - np.asarray(end), axis=1)
    want = 0.008 + FIRST_NODE + 1.3 * 0.07  # off the carried-on cordon's surface
    k = int(np.argmin(np.abs(d - want)))
    assert np.linalg.norm(cut.point - sk.branches[3].points[k]) < 3e-3, (cut.point, want)


def test_a_cane_lying_along_a_cordons_end_is_split_where_it_rises_past_its_junction() -> None:
    """A cane lying 20 cm along a cordon's end (10 mm; the cane 8 mm) and then rising 60
    degrees, one chain of the skeleton that starts on the cordon's axis and steps 1 cm down to
    its own within its first centimetre (generated vine seed 21): that step is its junction,
    not its turn, so the chain is split where it rises and the rising part is a cane, not
    cordon wood 1 cm off the true cordon for every cane cut measured from it. A cane rising
    from the cordon's end through a curved base stays a cane."""
    trunk = seg([0, 0, 0], [0, 0, 0.7], 0.015, "trunk")
    cordon = seg([0, 0, 0.7], [0.35, 0, 0.7], 0.010, parent=0)
    step = np.array([[0.35, 0, 0.7], [0.352, 0, 0.696], [0.354, 0, 0.692], [0.356, 0, 0.69]])
    level = seg([0.356, 0, 0.69], [0.55, 0, 0.69], 0.008).points[1:]
    rise = seg([0.55, 0, 0.69], [0.61, 0, 0.794], 0.006).points[1:]
    P = np.vstack([step, level, rise])
    R = np.r_[np.full(len(step) + len(level), 0.008), np.full(len(rise), 0.006)]
    sk = Skeleton([trunk, cordon, Branch(P, R, "cane", 1)])
    assert kinds_of(sk) == ["trunk", "cordon", "cordon", "cane"]
    end = sk.branches[2].points[-1]
    assert end[2] < 0.7 and 0.53 < end[0] < 0.56, end
    assert sk.branches[3].parent == 2 and sk.branches[3].points[-1][2] > 0.79
    # a cane rising from the cordon's end through a curved base (a 2.5 cm step up, 5 cm flat,
    # then steep; seed 21) rises from its start: no piece of it is taken for cordon
    step = np.array([[0.35, 0, 0.7], [0.355, 0, 0.712], [0.36, 0, 0.725]])
    flat = seg([0.36, 0, 0.725], [0.41, 0, 0.727], 0.008).points[1:]
    up = seg([0.41, 0, 0.727], [0.45, 0, 1.2], 0.006).points[1:]
    P = np.vstack([step, flat, up])
    R = np.r_[np.full(len(step) + len(flat), 0.008), np.full(len(up), 0.006)]
    sk = Skeleton([trunk, cordon, Branch(P, R, "cane", 1)])
    assert kinds_of(sk) == ["trunk", "cordon", "cane"]


@pytest.mark.parametrize(("heading", "kind"), [((1.0, 0.0), "cordon"), ((0.0, 1.0), "cane")])
def test_a_cordons_last_centimetres_past_its_last_spur_carry_it_on(
    heading: tuple[float, float], kind: str
) -> None:
    """An 8 cm level piece (8 mm) leaving a 40 cm cordon's end (10 mm): carrying it on in its
    own direction it is a cordon (generated vines of seeds 12, 13: the cordon's last
    centimetres past its last spur); heading 90 degrees off it is a cane."""
    trunk = seg([0, 0, 0], [0, 0, 0.7], 0.015, "trunk")
    cordon = seg([0, 0, 0.7], [0.4, 0, 0.7], 0.010, parent=0)
    piece = seg([0.4, 0, 0.7], [0.4 + 0.08 * heading[0], 0.08 * heading[1], 0.7], 0.008, parent=1)
    spur_cane = seg([0.3, 0, 0.7], [0.3, 0, 1.2], 0.004, parent=1)
    assert kinds_of(Skeleton([trunk, cordon, piece, spur_cane])) == [
        "trunk", "cordon", kind, "cane"]  # fmt: skip


def test_a_cordon_split_near_the_head_is_still_carried_on() -> None:
    """The trunk's chain runs 13 cm along a cordon (10 mm) and turns up a cane; the cordon goes
    on for 25 cm more in a chain of its own (9 mm) that turns up another cane (generated vine
    seed 16): the first piece is too short for a cordon's 15 cm yet is one (an arm's shape at
    the head), so the second is carried on from it, and both canes hang from cordon wood."""
    trunk = seg([0, 0, 0], [0, 0, 0.7], 0.015, "trunk")
    first = np.vstack([seg([0, 0, 0.7], [-0.13, 0, 0.7], 0.010).points,
                       seg([-0.13, 0, 0.7], [-0.15, 0, 1.1], 0.0045).points[1:]])  # fmt: skip
    r1 = np.r_[np.full(60, 0.010), np.full(59, 0.0045)]
    on = np.vstack([seg([-0.12, 0, 0.7], [-0.37, 0, 0.7], 0.009).points,
                    seg([-0.37, 0, 0.7], [-0.4, 0, 1.2], 0.004).points[1:]])  # fmt: skip
    r2 = np.r_[np.full(60, 0.009), np.full(59, 0.004)]
    sk = Skeleton([trunk, Branch(first, r1, "cane", 0), Branch(on, r2, "cane", 1)])
    kinds = kinds_of(sk)
    cordons = [b for b in sk.branches if b.kind == "cordon"]
    assert len(cordons) == 2 and kinds.count("cane") == 2, kinds
    assert min(float(b.points[:, 0].min()) for b in cordons) < -0.35
    for b in sk.branches:
        if b.kind == "cane":
            assert sk.branches[b.parent].kind == "cordon"


def test_a_cane_leaving_the_head_beside_a_short_arm_is_not_carried_on_from_it() -> None:
    """A head-trained vine (trunk 19.9 mm): a 6 cm arm (12.5 mm) carrying a cane, and beside it
    a cane leaving the trunk's head whose first 19 cm rise gently and read 9.3 mm thick (a D405
    rig's smear), then turn up: the cane stays a cane (it leaves the trunk, not the arm's end)."""
    trunk = seg([0, 0, 0], [0, 0, 0.5], 0.0199, "trunk")
    arm = seg([0, 0, 0.5], [-0.06, 0, 0.5], 0.0125, parent=0)
    on_arm = seg([-0.06, 0, 0.5], [-0.1, 0, 1.0], 0.005, parent=1)
    start, bend = (
        seg([0, 0, 0.5], [0.17, 0.05, 0.58], 0.0093),
        seg([0.17, 0.05, 0.58], [0.25, 0.04, 0.95], 0.006),
    )
    cane = Branch(np.vstack([start.points, bend.points[1:]]), np.r_[start.radii, bend.radii[1:]],
                  "cane", 0)  # fmt: skip
    kinds = kinds_of(Skeleton([trunk, arm, on_arm, cane]))
    assert kinds[:3] == ["trunk", "cordon", "cane"] and kinds.count("cordon") == 1, kinds


def test_a_cordons_tail_hanging_from_a_cane_listed_before_it_is_carried_on() -> None:
    """A trunk (18 mm) whose chain runs level 28 cm at 10 mm, 30 cm more at 8 mm (under the
    trunk's rule: split off), then turns up a cane; the cordon's last 8.5 cm (7 mm) hang from
    that cane and come before the cordon's pieces in the branch list (generated vine seed 8):
    they carry the cordon on all the same, and parents still come first."""
    trunk = seg([0, 0, 0], [0, 0, 0.7], 0.018, "trunk")
    parts = [seg([0, 0, 0.7], [0.28, 0, 0.7], 0.010), seg([0.28, 0, 0.7], [0.58, 0, 0.7], 0.008),
             seg([0.58, 0, 0.7], [0.6, 0, 1.2], 0.004)]  # fmt: skip
    chain = Branch(np.vstack([parts[0].points] + [p.points[1:] for p in parts[1:]]),
                   np.r_[parts[0].radii, parts[1].radii[1:], parts[2].radii[1:]], "cane", 0)  # fmt: skip
    tail = seg([0.585, 0, 0.712], [0.67, 0, 0.7], 0.007, parent=1)
    sk = Skeleton([trunk, chain, tail])
    kinds_of(sk)
    (t,) = [b for b in sk.branches if np.linalg.norm(b.points[-1] - [0.67, 0, 0.7]) < 1e-6]
    assert t.kind == "cordon", [(b.kind, b.parent) for b in sk.branches]
    assert sk.branches[t.parent].kind == "cordon"
    assert sum(b.kind == "cordon" for b in sk.branches) == 3
    assert all(b.parent < i for i, b in enumerate(sk.branches)), [b.parent for b in sk.branches]


@pytest.mark.parametrize("height", [0.018, 0.007])
def test_a_cordons_axis_pulled_up_into_a_spur_is_straightened(height: float) -> None:
    """A level 50 cm cordon (9 mm) whose skeleton rises 18 mm (or 6 mm: two thirds of its
    radius on the nodes, generated vines of seeds 7, 12 and 21) into a spur over 4 cm, its radius there 14 mm,
    with a cane going up from there (generated vine seed 9): `straighten_bumps` puts that
    stretch back on the cordon's line with the cordon's radius, the cane starts there, and its
    cut stands the rule's offset off the cordon's true surface (it came 1.5-2 cm high). A
    cordon bending with a 25 cm radius is left as it is, and so is an arm turning 60 degrees
    at a corner (the VSP vine's, 15 mm off the chord across it: a corner, not a detour)."""
    x = np.linspace(0, 0.5, 51)
    bump = np.clip(1 - np.abs(x - 0.255) / 0.02, 0, 1)
    z = 0.7 + height * bump
    r = np.where(bump > 0.5, 0.014, 0.009)
    cordon = Branch(np.c_[x, np.zeros_like(x), z], r, "cordon", 0)
    trunk = seg([0, 0, 0], [0, 0, 0.7], 0.018, "trunk")
    cane = seg([0.255, 0, 0.7 + height], [0.26, 0, 1.3], 0.004, parent=1)
    sk = Skeleton([trunk, cordon, cane])
    assert straighten_bumps(sk) > 0
    assert np.abs(sk.branches[1].points[:, 2] - 0.7).max() < 2e-3
    assert np.abs(sk.branches[1].radii - 0.009).max() < 1e-3
    assert abs(sk.branches[2].points[0, 2] - 0.7) < 2e-3
    (cut,) = cut_candidates(sk, "vine", 0.07)
    assert abs(cut.point[2] - (0.7 + 0.009 + FIRST_NODE + 1.3 * 0.07)) < 3e-3, cut.point
    a = np.linspace(0, 2.0, 60)  # 50 cm of a 25 cm-radius bend, level
    bend = np.c_[0.25 * np.sin(a), 0.25 * (1 - np.cos(a)), np.full(60, 0.7)]
    curved = Skeleton([trunk, Branch(bend, np.full(60, 0.009), "cordon", 0)])
    before = curved.branches[1].points.copy()
    assert straighten_bumps(curved) == 0
    assert np.array_equal(curved.branches[1].points, before)
    d = np.array([np.cos(np.radians(60)), np.sin(np.radians(60)), 0.0])
    arm = np.vstack([np.c_[np.linspace(0, 0.12, 25), np.zeros((25, 1)), np.full((25, 1), 0.7)],
                     [0.12, 0, 0.7] + np.linspace(0, 0.1, 21)[1:, None] * d])  # fmt: skip
    corner = Skeleton([trunk, Branch(arm, np.full(len(arm), 0.012), "cordon", 0)])
    assert straighten_bumps(corner) == 0


def test_a_detour_at_the_joint_of_two_cordon_pieces_is_straightened() -> None:
    """A level cordon (9 mm) that the skeleton split in two where canes leave it, the joint
    lifted 8 mm into their bases (generated vines of seeds 7, 12 and 17): straightened along
    the chain of pieces as along one branch, and the cane there starts on the cordon's line."""
    x = np.linspace(0, 0.5, 51)
    z = 0.7 + 0.008 * np.clip(1 - np.abs(x - 0.3) / 0.02, 0, 1)
    P = np.c_[x, np.zeros_like(x), z]
    trunk = seg([0, 0, 0], [0, 0, 0.7], 0.018, "trunk")
    first = Branch(P[:31], np.full(31, 0.009), "cordon", 0)
    second = Branch(P[30:], np.full(21, 0.009), "cordon", 1)
    cane = seg([0.3, 0, 0.708], [0.3, 0, 1.2], 0.004, parent=1)
    sk = Skeleton([trunk, first, second, cane])
    assert straighten_bumps(sk) > 0
    for b in sk.branches[1:3]:
        assert np.abs(b.points[:, 2] - 0.7).max() < 1e-3, b.points[:, 2]
    assert abs(sk.branches[3].points[0, 2] - 0.7) < 1e-3
