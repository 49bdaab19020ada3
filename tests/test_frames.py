"""SE(3)/SO(3) helpers: property tests with hypothesis, and numbers against scipy."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation, Slerp

from vinetwin import frames as fr
from vinetwin.errors import InputError, PoseError

finite = st.floats(-1.0, 1.0, allow_nan=False)
vec3 = st.tuples(finite, finite, finite).map(np.array)
angles = st.floats(0.0, np.pi - 1e-3)


@st.composite
def rotvecs(draw: st.DrawFn) -> np.ndarray:
    axis = draw(vec3)
    if np.linalg.norm(axis) < 1e-3:
        axis = np.array([0.0, 0.0, 1.0])
    return axis / np.linalg.norm(axis) * draw(angles)


@st.composite
def poses(draw: st.DrawFn) -> np.ndarray:
    return fr.make_pose(fr.so3_exp(draw(rotvecs())), draw(vec3) * 2.0)


@given(rotvecs())
def test_so3_exp_matches_scipy_and_log_inverts(w: np.ndarray) -> None:
    R = fr.so3_exp(w)
    np.testing.assert_allclose(R, Rotation.from_rotvec(w).as_matrix(), atol=1e-12)
    np.testing.assert_allclose(fr.so3_log(R), w, atol=1e-8)


@given(poses())
def test_se3_log_exp_round_trip(T: np.ndarray) -> None:
    np.testing.assert_allclose(fr.se3_exp(fr.se3_log(T)), T, atol=1e-9)


@given(poses(), poses(), poses())
def test_compose_is_associative_and_inverse_cancels(
    A: np.ndarray, B: np.ndarray, C: np.ndarray
) -> None:
    np.testing.assert_allclose(
        fr.compose(fr.compose(A, B), C), fr.compose(A, fr.compose(B, C)), atol=1e-12
    )
    np.testing.assert_allclose(fr.compose(A, fr.invert(A)), np.eye(4), atol=1e-12)
    np.testing.assert_allclose(fr.invert(fr.invert(A)), A, atol=1e-12)


@given(poses(), st.lists(vec3, min_size=1, max_size=5))
def test_transform_points_matches_homogeneous_product(T: np.ndarray, pts: list[np.ndarray]) -> None:
    P = np.array(pts)
    hom = (T @ np.column_stack([P, np.ones(len(P))]).T).T[:, :3]
    np.testing.assert_allclose(fr.transform_points(T, P), hom, atol=1e-12)


def test_so3_log_near_pi_is_stable() -> None:
    rng = np.random.default_rng(0)
    for _ in range(200):
        u = rng.normal(size=3)
        u /= np.linalg.norm(u)
        theta = np.pi - 10 ** rng.uniform(-9, -3)
        w = fr.so3_log(fr.so3_exp(theta * u))
        assert abs(np.linalg.norm(w) - theta) < 1e-6
        np.testing.assert_allclose(fr.so3_exp(w), fr.so3_exp(theta * u), atol=1e-6)


@given(poses(), poses(), st.floats(0.0, 1.0))
@settings(max_examples=50)
def test_interpolate_matches_scipy_slerp_and_lerp(A: np.ndarray, B: np.ndarray, a: float) -> None:
    T = fr.interpolate(A, B, a)
    slerp = Slerp([0, 1], Rotation.from_matrix([A[:3, :3], B[:3, :3]]))
    np.testing.assert_allclose(T[:3, :3], slerp([a]).as_matrix()[0], atol=1e-7)
    np.testing.assert_allclose(T[:3, 3], (1 - a) * A[:3, 3] + a * B[:3, 3], atol=1e-12)


def test_se3_exp_of_pure_translation_and_rotation() -> None:
    np.testing.assert_allclose(fr.se3_exp([1, 2, 3, 0, 0, 0])[:3, 3], [1, 2, 3])
    T = fr.se3_exp([0, 0, 0, 0, 0, np.pi / 2])
    np.testing.assert_allclose(T[:3, :3] @ [1, 0, 0], [0, 1, 0], atol=1e-12)


def test_angle_axis_and_theta_u() -> None:
    R = Rotation.from_rotvec([0, 0.3, 0]).as_matrix()
    theta, u = fr.angle_axis(R)
    assert theta == pytest.approx(0.3)
    np.testing.assert_allclose(u, [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(fr.theta_u(R), [0, 0.3, 0], atol=1e-12)
    assert fr.angle_axis(np.eye(3))[0] == 0.0


def test_look_at_is_opencv() -> None:
    T = fr.look_at([0, -1, 0], [0, 0, 0])
    np.testing.assert_allclose(T[:3, 2], [0, 1, 0], atol=1e-12)  # optical axis at the target
    np.testing.assert_allclose(T[:3, 1], [0, 0, -1], atol=1e-12)  # image down = world down
    np.testing.assert_allclose(T[:3, 0], [1, 0, 0], atol=1e-12)  # image right
    with pytest.raises(InputError):
        fr.look_at([0, 0, 1], [0, 0, 0])


def test_check_pose_names_the_problem() -> None:
    bad = np.eye(4)
    bad[0, 3] = np.nan
    with pytest.raises(PoseError, match="T_x holds a non-finite"):
        fr.check_pose(bad, "T_x")
    with pytest.raises(PoseError, match="4x4"):
        fr.check_pose(np.eye(3), "T_x")
    shear = np.eye(4)
    shear[0, 1] = 0.5
    with pytest.raises(PoseError, match="rotation"):
        fr.check_pose(shear, "T_x")


def test_pose_error_and_random_pose(rng: np.random.Generator) -> None:
    T = fr.random_pose(rng, 0.18, 0.35)
    dt, dr = fr.pose_error(np.eye(4), T)
    assert dt == pytest.approx(0.18) and dr == pytest.approx(0.35)
