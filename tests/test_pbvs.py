"""PBVS (paper eqs. 6-8, 11): interaction matrix against finite differences, exponential decay of
the error for a kinematic camera, gains, saturation and the kinematic initial guess."""

from __future__ import annotations

import numpy as np
import pytest

from vinetwin import frames as fr
from vinetwin.servo.pbvs import (
    Gain,
    Limits,
    interaction_matrix,
    kinematic_guess,
    pbvs_error,
    pbvs_twist,
    saturate,
    target_twist,
)


@pytest.mark.parametrize("seed", range(8))
def test_interaction_matrix_matches_finite_differences(seed: int) -> None:
    rng = np.random.default_rng(seed)
    T = fr.random_pose(rng, rng.uniform(0.01, 0.3), rng.uniform(0.05, 2.5))
    L = interaction_matrix(T)
    h = 1e-6
    J = np.zeros((6, 6))
    for i in range(6):
        xi = np.zeros(6)
        xi[i] = h
        # the camera moves with twist xi expressed in its own (current) frame
        J[:, i] = (pbvs_error(T @ fr.se3_exp(xi)) - pbvs_error(T @ fr.se3_exp(-xi))) / (2 * h)
    np.testing.assert_allclose(L, J, atol=1e-6)


def test_interaction_matrix_at_identity_is_identity() -> None:
    np.testing.assert_allclose(interaction_matrix(np.eye(4)), np.eye(6))


@pytest.mark.parametrize(
    ("t0", "r0"), [(0.184749, 0.351915), (0.034708, 0.550662), (0.316327, 0.12695)]
)
def test_control_law_decays_exponentially(t0: float, r0: float) -> None:
    rng = np.random.default_rng(3)
    T = fr.random_pose(rng, t0, r0)
    lam, dt = 0.8, 0.002
    e0 = pbvs_error(T)
    for _ in range(int(2.0 / dt)):  # two seconds of a purely kinematic camera
        T = T @ fr.se3_exp(pbvs_twist(T, lam) * dt)
    # de/dt = L v = -lambda e: every component decays as exp(-lambda t)
    # (explicit Euler at 2 ms adds about lambda * dt / 2 relative error per step: < 0.5% here)
    np.testing.assert_allclose(pbvs_error(T), e0 * np.exp(-lam * 2.0), rtol=5e-3, atol=1e-7)


def test_the_law_and_L_give_minus_lambda_e() -> None:
    rng = np.random.default_rng(1)
    T = fr.random_pose(rng, 0.2, 1.0)
    np.testing.assert_allclose(
        interaction_matrix(T) @ pbvs_twist(T, 0.5), -0.5 * pbvs_error(T), atol=1e-12
    )


def test_adaptive_gain() -> None:
    g = Gain(l0=2.0, l_inf=0.5, l0_slope=10.0, adaptive=True)
    assert g(0.0) == pytest.approx(2.0)
    assert g(10.0) == pytest.approx(0.5, abs=1e-6)
    h = 1e-7
    assert (g(h) - g(0.0)) / h == pytest.approx(-10.0, rel=1e-4)
    assert Gain(l0=0.7)(5.0) == 0.7


def test_saturation_keeps_direction() -> None:
    twist = np.array([0.3, 0.0, 0.4, 0.0, 2.0, 0.0])
    out = saturate(twist, Limits(max_linear=0.1, max_angular=0.5))
    assert np.linalg.norm(out[:3]) <= 0.1 + 1e-12 and np.linalg.norm(out[3:]) <= 0.5 + 1e-12
    np.testing.assert_allclose(out / np.linalg.norm(out), twist / np.linalg.norm(twist))
    small = np.full(6, 1e-3)
    np.testing.assert_array_equal(saturate(small, Limits()), small)


def test_kinematic_guess_equation_11() -> None:
    rng = np.random.default_rng(5)
    T_base_ref = fr.random_pose(rng, 0.5, 1.0)
    T_base_prev = T_base_ref @ fr.random_pose(rng, 0.1, 0.3)
    T_base_now = T_base_prev @ fr.random_pose(rng, 0.01, 0.02)  # the robot moved a little
    T_ref_prev = fr.invert(T_base_ref) @ T_base_prev  # what ICP found at the previous frame
    guess = kinematic_guess(T_ref_prev, T_base_prev, T_base_now)
    np.testing.assert_allclose(guess, fr.invert(T_base_ref) @ T_base_now, atol=1e-12)


@pytest.mark.parametrize(
    ("t0", "r0"), [(0.184749, 0.351915), (0.166275, 0.567889), (0.034708, 0.550662)]
)
def test_target_law_moves_the_cut_on_a_straight_line_and_reaches_the_goal(
    t0: float, r0: float
) -> None:
    """The view-keeping law (PBVS on c_t_o and theta*u): the target's coordinates in the camera
    frame decay exponentially towards their goal value along a straight line, its image pixel
    moves on a straight line, and the camera ends at the reference pose."""
    rng = np.random.default_rng(5)
    T = fr.random_pose(rng, t0, r0)
    o = np.array([0.004, -0.003, 0.15])  # the cut, 15 cm in front of the reference camera
    lam, dt = 0.8, 0.001

    def p_of(T: np.ndarray) -> np.ndarray:
        return fr.transform_points(fr.invert(T), o[None])[0]

    p0 = p_of(T)
    path = [p0]
    for _ in range(int(3.0 / dt)):
        T = T @ fr.se3_exp(target_twist(T, o, lam) * dt)
        path.append(p_of(T))
    path_a = np.array(path)
    # p(t) - o = (p0 - o) exp(-lambda t): straight line, exponential decay (Euler: < 0.2%)
    expected = o + (p0 - o) * np.exp(-lam * 3.0)
    np.testing.assert_allclose(path_a[-1], expected, atol=2e-3 * np.linalg.norm(p0 - o))
    d = (p0 - o) / np.linalg.norm(p0 - o)
    off_line = np.linalg.norm(np.cross(path_a - o, d), axis=1)
    assert off_line.max() < 1e-3 * np.linalg.norm(p0 - o)
    # the pixel path is straight too (a straight 3D line projects to a straight image line)
    uv = path_a[:, :2] / path_a[:, 2:]
    chord = uv[-1] - uv[0]
    normal = np.array([-chord[1], chord[0]]) / np.linalg.norm(chord)
    assert np.abs((uv - uv[0]) @ normal).max() < 1e-3 * np.linalg.norm(chord)
    # and the rotation decays as with eq. 8
    np.testing.assert_allclose(
        pbvs_error(T)[3:], fr.so3_log(fr.random_pose(np.random.default_rng(5), t0, r0)[:3, :3])
        * np.exp(-lam * 3.0), atol=1e-3 * r0,
    )  # fmt: skip
    for _ in range(int(12.0 / dt)):  # long enough: the camera reaches the reference pose
        T = T @ fr.se3_exp(target_twist(T, o, lam) * dt)
    et, er = fr.pose_error(T, np.eye(4))
    assert et < 1e-5 and er < 1e-5


def test_target_law_is_zero_at_the_goal_and_saturates() -> None:
    o = np.array([0.0, 0.0, 0.15])
    np.testing.assert_allclose(target_twist(np.eye(4), o, 0.8), np.zeros(6), atol=1e-15)
    T = fr.random_pose(np.random.default_rng(2), 0.3, 1.0)
    lim = Limits(max_linear=0.05, max_angular=0.25)
    tw = target_twist(T, o, 0.8, lim)
    assert np.linalg.norm(tw[:3]) <= 0.05 + 1e-12 and np.linalg.norm(tw[3:]) <= 0.25 + 1e-12
