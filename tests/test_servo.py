"""The servo step: every untrusted case gives exactly zero twist and its reason; trusted frames
give the PBVS twist; a kinematic camera closes the loop on rendered D405 frames."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tests.conftest import VineViews
from vinetwin import frames as fr
from vinetwin.cloud import Cloud
from vinetwin.registration.icp import ICPConfig, ICPResult
from vinetwin.servo.pbvs import Limits, kinematic_guess, pbvs_twist
from vinetwin.servo.step import SafetyConfig, Servo

NO_RAMP = {"max_linear_acceleration": 0.0, "max_angular_acceleration": 0.0}
NO_RAMP_LIMITS = Limits(**NO_RAMP)


def seen_from(ref: Cloud, T_ref_cur: np.ndarray) -> Cloud:
    """The reference cloud as the camera at T_ref_cur sees it (a rigid copy)."""
    inv = fr.invert(T_ref_cur)
    assert ref.normals is not None
    return Cloud(fr.transform_points(inv, ref.points), ref.normals @ inv[:3, :3].T)


@pytest.fixture(scope="module")
def ref(vine_views: VineViews) -> Cloud:
    return vine_views.reference("p3")


def servo(ref: Cloud, vine_views: VineViews, **safety: float) -> Servo:
    return Servo(
        ref,
        icp=ICPConfig(variant="point_to_plane"),
        camera=vine_views.twin.camera,
        perception=vine_views.twin.perception,
        safety=SafetyConfig(**safety),  # type: ignore[arg-type]
        limits=NO_RAMP_LIMITS,
    )


def test_trusted_frame_gives_the_pbvs_twist(ref: Cloud, vine_views: VineViews) -> None:
    D = fr.make_pose(fr.so3_exp([0.0, 0.02, 0.01]), [0.004, -0.003, 0.002])
    s = servo(ref, vine_views)
    r = s.step(seen_from(ref, D), stamp=0.0)
    assert r.trusted, r.reason
    assert r.T_ref_cur is not None
    dt, dr = fr.pose_error(r.T_ref_cur, D)
    assert dt < 2e-4 and dr < np.radians(0.02)
    np.testing.assert_allclose(r.twist, pbvs_twist(r.T_ref_cur, 0.8, Limits()), atol=1e-12)
    assert not r.at_goal
    assert s.step(seen_from(ref, np.eye(4)), stamp=0.1).at_goal


@pytest.mark.parametrize(
    ("case", "needle"),
    [
        ("empty", "empty frame"),
        ("nan", "non-finite"),
        ("few points", "fewer than the minimum"),
        ("stale stamp", "stale frame"),
        ("old frame", "stale frame"),
        ("low overlap", "low overlap"),
        ("few pairs", "too few correspondences"),
        ("high rmse", "high RMSE"),
        ("bad base pose", "T_base_camera"),
        ("nothing in reach", "ICP failed: too few correspondences"),
    ],
)
def test_untrusted_frames_give_zero_twist_and_reason(
    ref: Cloud, vine_views: VineViews, case: str, needle: str
) -> None:
    D = fr.make_pose(t=[0.003, 0.0, 0.0])
    good = seen_from(ref, D)
    safety: dict[str, float] = {}
    if case == "low overlap":
        safety["min_overlap"] = 1.01
    if case == "few pairs":
        safety["min_correspondences"] = 10**6
    if case == "high rmse":
        safety["max_rmse"] = 1e-7
    s = servo(ref, vine_views, **safety)
    stamp, now, base = 1.0, None, None
    cloud = good
    if case == "empty":
        cloud = Cloud(np.empty((0, 3)), np.empty((0, 3)))
    elif case == "nan":
        pts = good.points.copy()
        pts[5] = np.nan
        cloud = Cloud(pts, good.normals)
    elif case == "few points":
        cloud = Cloud(good.points[:5], None if good.normals is None else good.normals[:5])
    elif case == "stale stamp":
        assert s.step(good, stamp=2.0).trusted
        stamp = 2.0
    elif case == "old frame":
        now = 1.5
    elif case == "high rmse":  # a rigid copy aligns exactly: add sensor-like noise
        noise = np.random.default_rng(0).normal(0, 3e-4, good.points.shape)
        cloud = Cloud(good.points + noise, good.normals)
    elif case == "bad base pose":
        base = np.full((4, 4), np.nan)
    elif case == "nothing in reach":
        cloud = seen_from(ref, fr.make_pose(t=[0.0, 0.0, 0.2]))
    r = s.step(cloud, stamp=stamp, T_base_camera=base, now=now)
    assert not r.trusted and needle in r.reason, r.reason
    assert np.array_equal(r.twist, np.zeros(6))


def test_pose_jump_is_refused_and_the_restart_is_ramped(ref: Cloud, vine_views: VineViews) -> None:
    s = Servo(ref, camera=vine_views.twin.camera, perception=vine_views.twin.perception)
    base0 = fr.make_pose(t=[0.3, 0.0, 0.5])
    D = fr.make_pose(t=[0.01, 0.0, 0.0])
    assert s.step(seen_from(ref, D), 0.0, T_base_camera=base0).trusted
    # the robot says the camera did not move, the cloud says it moved 2.5 cm: ICP slipped (or
    # the vine was hit); the servo must not follow
    jumped = fr.make_pose(t=[-0.015, 0.0, 0.0])
    r = s.step(seen_from(ref, jumped), 1 / 30, T_base_camera=base0)
    assert not r.trusted and "pose jump" in r.reason, r.reason
    assert np.array_equal(r.twist, np.zeros(6))
    # the same view with the robot's motion that explains it is trusted again, and the twist
    # grows from zero by at most the acceleration limits
    moved = base0 @ fr.invert(D) @ jumped
    r = s.step(seen_from(ref, jumped), 2 / 30, T_base_camera=moved)
    assert r.trusted, r.reason
    dt = 1 / 30
    assert np.linalg.norm(r.twist[:3]) <= s.limits.max_linear_acceleration * dt + 1e-12
    assert np.linalg.norm(r.twist[3:]) <= s.limits.max_angular_acceleration * dt + 1e-12
    assert np.linalg.norm(r.twist) > 0


def test_steady_tracking_runs_the_final_level_alone_and_falls_back_when_it_moved_much(
    ref: Cloud, vine_views: VineViews
) -> None:
    """After a trusted frame, a frame whose kinematic prediction is 0.6 mm / 0.1 deg off is
    aligned by ICP's final level alone (`tracked_frames`), within 0.05 mm / 0.005 deg of what
    the full schedule answers; a frame whose prediction is 4 mm off (a slip of the robot's
    kinematics, within the pose-jump limits) moves it past `track_translation`, so the full
    schedule runs: trusted, not counted as tracked, within 1 mm of the truth."""
    twin = vine_views.twin
    Tg = twin.pose("p3").T_vine_camera
    s = servo(ref, vine_views)
    base = fr.make_pose(t=[0.3, 0.0, 0.5])
    D0 = fr.make_pose(fr.so3_exp([0.0, 0.01, 0.0]), [0.004, -0.002, 0.003])
    r0 = s.step_depth(vine_views.depth(Tg @ D0, 100), 0.0, T_base_camera=base)
    assert r0.trusted and s.tracked_frames == 0, r0.reason  # the first frame: full schedule
    # the camera moved 1 mm; the robot reports it with a 0.6 mm / 0.1 deg error
    D1 = D0 @ fr.make_pose(t=[0.001, 0.0, 0.0])
    slip = fr.make_pose(fr.so3_exp([0.0, 0.0, np.radians(0.1)]), [0.0, 0.0006, 0.0])
    base1 = base @ fr.make_pose(t=[0.001, 0.0, 0.0]) @ slip
    r1 = s.step_depth(vine_views.depth(Tg @ D1, 101), 1 / 30, T_base_camera=base1)
    assert r1.trusted and r1.tracked and s.tracked_frames == 1, r1.reason
    assert r0.T_ref_cur is not None and r1.T_ref_cur is not None and r1.cloud is not None
    guess = kinematic_guess(r0.T_ref_cur, base, base1)
    full = s.icp.align(r1.cloud, guess)
    dt, dr = fr.pose_error(r1.T_ref_cur, full.T_ref_cur)
    assert dt < 5e-5 and dr < np.radians(0.005), (dt, dr)
    assert fr.pose_error(r1.T_ref_cur, D1)[0] < 1e-3
    # the robot reports a 4 mm motion the camera did not make
    base2 = base1 @ fr.make_pose(t=[0.0, 0.004, 0.0])
    r2 = s.step_depth(vine_views.depth(Tg @ D1, 102), 2 / 30, T_base_camera=base2)
    assert r2.trusted and not r2.tracked and s.tracked_frames == 1, r2.reason
    assert r2.T_ref_cur is not None and fr.pose_error(r2.T_ref_cur, D1)[0] < 1e-3


def test_tracking_pass_stops_at_the_safety_tolerance(ref: Cloud, vine_views: VineViews) -> None:
    """The final-level pass from the prediction stops at `SafetyConfig.track_tolerance` when
    that is looser than the ICP's own tolerances (0: the ICP's), and a tolerance that NaN or a
    negative number would switch off is refused by name."""
    from vinetwin.errors import InputError

    own = ICPConfig(variant="point_to_plane")
    loose = servo(ref, vine_views)._tight_icp().config
    assert loose.tolerance_translation == 1e-4
    assert loose.tolerance_rotation == 1e-4
    exact = servo(ref, vine_views, track_tolerance=0.0)._tight_icp().config
    assert exact.tolerance_translation == own.tolerance_translation
    assert exact.tolerance_rotation == own.tolerance_rotation
    for bad in (float("nan"), -1e-4):
        with pytest.raises(InputError, match="track_tolerance"):
            SafetyConfig(track_tolerance=bad)


def test_single_straight_cane_never_moves_the_arm() -> None:
    s, a = np.meshgrid(np.linspace(-0.1, 0.1, 200), np.linspace(0, 2 * np.pi, 24, endpoint=False))
    n = np.column_stack([np.zeros(s.size), np.cos(a.ravel()), np.sin(a.ravel())])
    pts = np.column_stack([s.ravel(), np.zeros(s.size), np.full(s.size, 0.15)]) + 0.004 * n
    cane = Cloud(pts, n)
    for variant in ("point_to_point", "lm", "point_to_plane", "symmetric"):
        sv = Servo(cane, icp=ICPConfig(variant=variant))
        r = sv.step(seen_from(cane, fr.make_pose(t=[0.002, 0.0, 0.0])), 0.0)
        assert not r.trusted and "degenerate" in r.reason, (variant, r.reason)
        assert np.array_equal(r.twist, np.zeros(6))


def test_step_depth_refuses_bad_images(ref: Cloud, vine_views: VineViews) -> None:
    s = servo(ref, vine_views)
    cam = vine_views.twin.camera
    r = s.step_depth(np.full((cam.height, cam.width), np.nan, np.float32), 0.0)
    assert not r.trusted and "empty frame" in r.reason
    r = s.step_depth(np.zeros((10, 10), np.float32), 0.1)
    assert not r.trusted and "bad depth image" in r.reason


@pytest.mark.parametrize("variant", ["point_to_plane", "symmetric"])
def test_kinematic_camera_converges_on_rendered_frames(vine_views: VineViews, variant: str) -> None:
    """Closed loop at 30 Hz: each frame is rendered at the camera's pose with fresh D405 noise,
    perceived, aligned and turned into a twist that moves the camera. From 3 cm / 6 deg the camera
    ends within 2 mm / 0.01 rad of the pruning pose, and the error decays (no growth beyond
    noise between frames)."""
    twin = vine_views.twin
    goal = twin.pose("p3").T_vine_camera
    sv = Servo(
        vine_views.reference("p3"),
        icp=ICPConfig(variant=variant),
        gain=1.5,
        camera=twin.camera,
        perception=twin.perception,
    )
    T = goal @ fr.make_pose(fr.so3_exp(np.radians([3.0, -4.0, 2.0])), [0.02, -0.015, 0.015])
    dt = 1 / 30
    errors = []
    for k in range(90):
        r = sv.step_depth(vine_views.depth(T, 1000 + k), stamp=k * dt)
        assert r.trusted, (k, r.reason)
        T = T @ fr.se3_exp(r.twist * dt)
        errors.append(fr.pose_error(T, goal))
    et, er = errors[-1]
    assert et < 0.002 and er < 0.01, (et, er)
    e = np.array([x[0] for x in errors])
    assert e[30] < 0.5 * e[0] and e[60] < 0.5 * e[30], e[::10]


def test_error_decays_exponentially_with_perfect_alignment(
    ref: Cloud, vine_views: VineViews
) -> None:
    """With rigid copies of the reference (no noise), the error follows exp(-lambda t)."""
    lam, dt = 0.8, 0.01
    s = Servo(
        ref,
        gain=lam,
        limits=Limits(max_linear=0.25, max_angular=1.0, **NO_RAMP),  # never reached here
        camera=vine_views.twin.camera,
    )
    T = fr.make_pose(fr.so3_exp([0.01, -0.02, 0.015]), [0.006, 0.004, -0.005])
    e0 = float(np.linalg.norm(fr.se3_log(T)))
    for k in range(100):
        r = s.step(seen_from(ref, T), stamp=k * dt)
        assert r.trusted, r.reason
        T = T @ fr.se3_exp(r.twist * dt)
    # continuous law: e(t) = e0 exp(-lambda t); the Euler step gives (1 - lambda dt)^k
    expected = e0 * (1 - lam * dt) ** 100
    assert float(np.linalg.norm(fr.se3_log(T))) == pytest.approx(expected, rel=0.05)
    assert math.isclose(expected / e0, math.exp(-lam * 1.0), rel_tol=0.01)


@pytest.mark.parametrize(
    ("jump_t", "jump_r", "by_search"),
    [
        ((0.06, 0.0, 0.0), (0.0, 0.0, 0.2), False),
        ((0.0, -0.06, 0.0), (0.2, 0.1, 0.0), True),
        ((0.05, 0.03, 0.0), (0.0, 0.2, 0.0), None),
    ],
)
def test_a_big_jerk_of_the_vine_is_reacquired(
    ref: Cloud,
    vine_views: VineViews,
    jump_t: tuple[float, ...],
    jump_r: tuple[float, ...],
    by_search: bool | None,
) -> None:
    """The vine jumps about 6 cm / 0.2 rad while the arm is still: tracking refuses the frames
    as a pose jump until the same jump is seen in `reacquire_frames` frames (when tracking ICP
    still finds it), or the wide search finds the new pose and `reacquire_frames` frames agree
    on it (flagged `reacquired`). Either way the pose is within 2 mm / 0.01 rad of the truth,
    well before `lost_after`, and no frame in between moves the arm.

    Which way a jump takes can depend on the reference's noise: tracking's basin is not
    monotonic in the jump's size. Over 17 D405 noise streams (16 and the quantile draws tried in
    e8410dc), the first case was tracked in all 17 and the second searched in all 17; the third
    was searched in 16 (tracked in the quantile stream), as was the second case used before,
    (0, -4, 3) cm and (0.15, 0.1, 0) rad. The pose was within 0.1 mm of the truth in every run."""
    s = servo(ref, vine_views, search_after=0.2)
    base = fr.make_pose(t=[0.3, 0.0, 0.5])
    D = fr.make_pose(t=[0.005, 0.0, 0.0])
    assert s.step(seen_from(ref, D), 0.0, T_base_camera=base).trusted
    jumped = fr.make_pose(fr.so3_exp(np.array(jump_r)), np.array(jump_t)) @ D
    stamps = [k / 30 for k in range(1, 60)]
    results = [s.step(seen_from(ref, jumped), t, T_base_camera=base) for t in stamps]
    trusted = [k for k, r in enumerate(results) if r.trusted]
    assert trusted, [r.reason for r in results[:12]]
    first = trusted[0]
    for r in results[:first]:
        assert np.array_equal(r.twist, np.zeros(6)), r.reason
    got = results[first]
    if by_search is not None:  # None: either way
        assert got.reacquired == by_search and s.reacquisitions == int(by_search)
    assert stamps[first] <= 0.2 + (s.safety.reacquire_frames + 1) / 30 + 1e-9
    assert stamps[first] < s.safety.lost_after
    assert got.T_ref_cur is not None
    et, er = fr.pose_error(got.T_ref_cur, jumped)
    assert et < 0.002 and er < 0.01, (et, er)
    # tracking carries on from there
    assert s.step(seen_from(ref, jumped), stamps[-1] + 1 / 30, T_base_camera=base).trusted


def test_refusals_for_lost_after_seconds_end_in_a_named_stop(
    ref: Cloud, vine_views: VineViews
) -> None:
    """Nothing alignable for `lost_after` s: the servo stops for good with "lost the vine"
    (never silent zeros forever), every twist zero, until it is reset."""
    s = servo(ref, vine_views, lost_after=1.0, search_after=0.3)
    base = fr.make_pose(t=[0.3, 0.0, 0.5])
    assert s.step(seen_from(ref, np.eye(4)), 0.0, T_base_camera=base).trusted
    away = seen_from(ref, fr.make_pose(t=[0.0, 0.0, 0.3]))  # nothing within reach
    out = [s.step(away, k / 30, T_base_camera=base) for k in range(1, 45)]
    lost = [k for k, r in enumerate(out) if r.lost]
    assert lost, out[-1].reason
    k = lost[0]
    assert (k + 1) / 30 - 1 / 30 >= 1.0 - 1e-9  # not before lost_after
    assert (k + 1) / 30 - 1 / 30 <= 1.0 + 1 / 30 + 1e-9  # and at once after it
    assert "lost the vine" in out[k].reason and "no trusted alignment" in out[k].reason
    assert all(np.array_equal(r.twist, np.zeros(6)) and not r.trusted for r in out)
    # a good frame after the stop does not restart the arm...
    again = s.step(seen_from(ref, np.eye(4)), 2.0, T_base_camera=base)
    assert again.lost and not again.trusted and np.array_equal(again.twist, np.zeros(6))
    # ...a reset does
    s.reset()
    assert s.step(seen_from(ref, np.eye(4)), 2.1, T_base_camera=base).trusted


def test_the_first_estimate_must_lie_near_the_believed_pose(
    ref: Cloud, vine_views: VineViews
) -> None:
    s = servo(ref, vine_views, max_guess_translation=0.001, search_after=10.0)
    s.reset(fr.make_pose(t=[0.004, 0.0, 0.0]))  # believed 4 mm off; ICP finds the truth
    r = s.step(seen_from(ref, np.eye(4)), 0.0)
    assert not r.trusted and "implausible first estimate" in r.reason, r.reason
    assert np.array_equal(r.twist, np.zeros(6))


class _SettledICP:
    """An ICP that always ends at `T`, pairing `overlap` of the frame: one settled in a basin
    beside the right pose (as from a 5 cm / 0.15 rad start on a rebuilt twin)."""

    def __init__(self, T: np.ndarray, overlap: float) -> None:
        self.T, self.overlap = T, overlap

    def align(self, cloud: Cloud, guess: np.ndarray) -> ICPResult:
        return ICPResult(self.T.copy(), True, overlap=self.overlap, coverage=self.overlap,
                         inlier_rmse=0.0015, correspondences=500)  # fmt: skip


def test_a_poor_fit_with_a_better_pose_elsewhere_is_refused_then_the_better_one_trusted(
    ref: Cloud, vine_views: VineViews
) -> None:
    """ICP settled 3 cm / 0.05 rad off, pairing half the frame: the wide search around it finds
    the true pose pairing nearly all of it, so the servo stops ("ambiguous alignment", zero
    twist) until `reacquire_frames` frames agree, then trusts the true pose within 1 mm. Without
    the doubt (`doubt_overlap` 0) the wrong pose is trusted and moves the arm."""
    wrong = fr.make_pose(fr.so3_exp([0.0, 0.05, 0.0]), [0.03, 0.0, 0.0])
    frame = seen_from(ref, np.eye(4))
    s = servo(ref, vine_views, search_after=10.0)
    s.icp = _SettledICP(wrong, 0.5)  # type: ignore[assignment]
    s.reset(fr.make_pose(t=[0.01, 0.0, 0.0]))
    need = s.safety.reacquire_frames
    out = [s.step(frame, k / 30) for k in range(need)]
    for r in out[:-1]:
        assert not r.trusted and r.reason.startswith("ambiguous alignment"), r.reason
        assert np.array_equal(r.twist, np.zeros(6))
    last = out[-1]
    assert last.trusted and last.reacquired, last.reason
    assert last.T_ref_cur is not None
    et, er = fr.pose_error(last.T_ref_cur, np.eye(4))
    assert et < 0.001 and er < 0.005, (et, er)

    naive = servo(ref, vine_views, search_after=10.0, doubt_overlap=0.0)
    naive.icp = _SettledICP(wrong, 0.5)  # type: ignore[assignment]
    naive.reset(fr.make_pose(t=[0.01, 0.0, 0.0]))
    r = naive.step(frame, 0.0)
    assert r.trusted and r.T_ref_cur is not None
    assert fr.pose_error(r.T_ref_cur, wrong)[0] < 1e-9


def test_a_poor_fit_with_nothing_better_elsewhere_stays_trusted(
    ref: Cloud, vine_views: VineViews
) -> None:
    """A low overlap alone refuses nothing: the wide search finds the same pose (within the
    pose-jump limits), so the estimate is trusted at once."""
    s = servo(ref, vine_views, search_after=10.0)
    s.icp = _SettledICP(np.eye(4), 0.5)  # type: ignore[assignment]
    r = s.step(seen_from(ref, np.eye(4)), 0.0)
    assert r.trusted and not r.reacquired, r.reason
    assert "doubt" in r.timings


def test_wide_search_finds_a_far_pose_and_names_an_ambiguous_one(ref: Cloud) -> None:
    """The wide search alone: 6 cm / 0.2 rad from its prediction it finds the pose within 1 mm;
    on a repetitive scene (the view and a copy of it 8 cm to the side, the current view seeing
    one copy) two poses fit alike and it gives none, saying why."""
    from vinetwin.registration.search import WideSearch

    T = fr.make_pose(fr.so3_exp(np.array([0.0, 0.0, 0.2])), np.array([0.06, 0.0, 0.0]))
    search = WideSearch(ref)
    res = search.align(seen_from(ref, T), np.eye(4), translation=0.05, rotation=0.15,
                       accept=lambda r: "")  # fmt: skip
    assert res.best is not None, res.reason
    et, er = fr.pose_error(res.best.T_ref_cur, T)
    assert et < 0.001 and er < 0.005, (et, er)
    assert res.hypotheses == 13

    assert ref.normals is not None
    twin_scene = Cloud(
        np.vstack([ref.points, ref.points + [0.08, 0.0, 0.0]]), np.vstack([ref.normals] * 2)
    )
    res = WideSearch(twin_scene).align(
        seen_from(ref, np.eye(4)), fr.make_pose(t=[0.04, 0.0, 0.0]), translation=0.05,
        rotation=0.15, accept=lambda r: "",
    )  # fmt: skip
    assert res.best is None and "ambiguous" in res.reason, res.reason
