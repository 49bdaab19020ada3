"""Arrival registration: the first live view against the whole twin, from a belief off by the
platform's error; a wrong or doubtful answer is a named refusal with no pose."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from vinetwin.frames import make_pose, pose_error, so3_exp
from vinetwin.render.backends import get_backend
from vinetwin.render.sensor import apply_d405_model
from vinetwin.servo.arrival import ArrivalConfig, ArrivalRegistration
from vinetwin.twin import Twin


@pytest.fixture(scope="module")
def rig(sample_twin_dir: Path):  # type: ignore[no-untyped-def]
    twin = Twin.load(sample_twin_dir)
    mesh = twin.load_mesh()
    live = get_backend("open3d", mesh.vertices, mesh.faces, twin.camera)
    arrival = ArrivalRegistration(mesh.vertices, mesh.faces, twin.camera, twin.perception)
    yield twin, live, arrival
    arrival.close()
    live.close()


def _off(T: np.ndarray, t: np.ndarray, r: np.ndarray) -> np.ndarray:
    return make_pose(so3_exp(r) @ T[:3, :3], T[:3, 3] + t)


def test_arrival_corrects_a_belief_centimetres_off(rig) -> None:  # type: ignore[no-untyped-def]
    twin, live, arrival = rig
    rng = np.random.default_rng(4)
    for k, pose in enumerate(twin.poses[:3]):
        T = np.asarray(pose.T_vine_camera)
        depth = apply_d405_model(live.render(T), twin.camera, rng)
        t = rng.normal(size=3)
        r = rng.normal(size=3)
        belief = _off(T, 0.04 * t / np.linalg.norm(t), np.radians(4) * r / np.linalg.norm(r))
        assert pose_error(belief, T)[0] > 0.035
        result = arrival.register(depth, belief)
        assert result.ok, result.reason
        assert result.T_vine_camera is not None
        et, er = pose_error(result.T_vine_camera, T)
        assert et < 0.005 and er < 0.03, (k, et, er)
        assert result.score > 0.5 and result.runner_up < result.score


def test_arrival_failures_are_named_and_carry_no_pose(rig) -> None:  # type: ignore[no-untyped-def]
    twin, live, arrival = rig
    T = np.asarray(twin.poses[0].T_vine_camera)
    cam = twin.camera
    empty = np.zeros((cam.height, cam.width), np.float32)
    r = arrival.register(empty, T)
    assert not r.ok and r.T_vine_camera is None and "too few live points" in r.reason
    wall = np.full((cam.height, cam.width), 0.2, np.float32)  # not the vine: a flat wall
    r = arrival.register(wall, T)
    assert not r.ok and r.T_vine_camera is None and r.reason
    # a belief half a metre off: nothing of the twin where the view is believed to be
    depth = apply_d405_model(live.render(T), cam, np.random.default_rng(0))
    r = arrival.register(depth, _off(T, np.array([0.5, 0.0, 0.0]), np.zeros(3)))
    assert not r.ok and r.T_vine_camera is None
    assert "no surface near" in r.reason or "agreement" in r.reason or "correction" in r.reason
    with pytest.raises(Exception, match="min_score"):
        ArrivalConfig(min_score=0)


def test_the_simulated_servo_starts_from_the_arrival_answer(
    sample_twin_dir: Path, tmp_path: Path
) -> None:
    """`vinetwin servo --camera sim --arrival`: a platform belief 6 cm / 6 degrees off becomes a
    first guess within millimetres of the truth, before the first command."""
    import json

    from vinetwin.frames import invert
    from vinetwin.servo.config import RunnerConfig
    from vinetwin.sim.session import servo_session

    twin = Twin.load(sample_twin_dir)
    profile = tmp_path / "platform.json"
    profile.write_text(
        json.dumps(
            {"sources": ["registration"], "registration_translation": 0.06,
             "registration_rotation": 0.105}
        )
    )  # fmt: skip
    pose = twin.poses[1]
    goal = np.asarray(pose.T_vine_camera)
    for arrival in (False, True):
        cfg = RunnerConfig(pose=pose.id, profile=str(profile), arrival=arrival, seed=3)
        session = servo_session(twin, pose, cfg)
        try:
            truth = invert(goal) @ session.robot.true_camera()  # type: ignore[union-attr]
            et, er = pose_error(session.servo.initial_guess, truth)
        finally:
            session.close()
        if arrival:
            assert et < 0.005 and er < 0.03, (et, er)
        else:
            assert et > 0.03  # the platform's error, as configured
