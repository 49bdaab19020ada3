"""The row's two sides: `vinetwin propose` approaches a far curtain's cuts from the far aisle, and
`vinetwin prune --sides both` (the default) prunes them in a second pass from there (`sim.prune_sides`):
the far twin is the vine turned half a turn, its poses still look at their cuts, and the far
pass's cuts come back in the vine frame."""

from __future__ import annotations

import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from vinetwin.errors import InputError
from vinetwin.plan.config import SearchConfig
from vinetwin.plan.job_config import JobConfig
from vinetwin.twin.model import Twin
from vinetwin.twin.poses import Approach, approach_of, pruning_pose


def _with_a_far_pose(tmp_path: Path, sample_twin_dir: Path) -> tuple[Twin, str]:
    """The sample with its pose p3 and a pose on p1's cut point from the far side (+Y)."""
    dst = tmp_path / "v.twin"
    shutil.copytree(sample_twin_dir, dst,
                    ignore=shutil.ignore_patterns("references", "validation", "prune"))  # fmt: skip
    twin = Twin.load(dst)
    cut = twin.cut_point(twin.pose("p1").cut_point)
    for p in [p.id for p in twin.poses if p.id != "p3"]:
        twin.delete_pose(p)
    back = twin.add_pose(cut.id, Approach(0.15, -math.pi / 2, 0.2, 0.0)).id
    twin.save()
    return Twin.load(dst), back


def test_the_far_twin_is_the_vine_turned_half_a_turn(tmp_path: Path, sample_twin_dir: Path) -> None:
    from vinetwin.plan.sides import far_pose_ids, far_side_twin

    twin, back = _with_a_far_pose(tmp_path, sample_twin_dir)
    assert far_pose_ids(twin) == [back]
    far = far_side_twin(twin, [back])
    assert far.root == twin.root / "far_side.twin"
    assert [p.id for p in Twin.load(far.root).poses] == [back]
    V, W = twin.load_mesh().vertices, far.load_mesh().vertices
    np.testing.assert_allclose(W, V * [-1, -1, 1], atol=1e-6)  # float32 PLY
    p, q = twin.pose(back), far.pose(back)
    c, d = twin.cut_point(p.cut_point), far.cut_point(q.cut_point)
    np.testing.assert_allclose(d.point, c.point * [-1, -1, 1], atol=1e-12)
    T = np.asarray(q.T_vine_camera)
    assert T[1, 2] > 0.5  # it now looks from the robot's side
    # its stored approach still gives its pose
    np.testing.assert_allclose(pruning_pose(d.point, d.cane_axis, q.approach), T, atol=1e-9)
    assert approach_of(T, d.point, d.cane_axis).azimuth == pytest.approx(q.approach.azimuth)
    assert far_pose_ids(far) == []
    sk, sk_far = twin.load_skeleton(), far.load_skeleton()
    assert sk is not None and sk_far is not None
    np.testing.assert_allclose(sk_far.branches[1].points, sk.branches[1].points * [-1, -1, 1])


def test_the_far_aisle_prunes_what_the_near_one_cannot(
    tmp_path: Path, sample_twin_dir: Path
) -> None:
    """With sides both, the pose looking from +Y is done from the far aisle, its blade on the
    true cut; with sides near it is skipped by name. The vine's time is both passes'."""
    pytest.importorskip("ompl")
    from vinetwin.sim.prune import PruneConfig, prune_twin

    twin, back = _with_a_far_pose(tmp_path, sample_twin_dir)
    near = prune_twin(twin.root, PruneConfig(sim="kinematic", job=JobConfig(sides="near")))
    by_pose = {c["pose"]: c for c in near["cuts"]}
    assert by_pose[back]["status"] == "skipped"
    assert "other side" in by_pose[back]["reason"]
    assert by_pose["p3"]["status"] == "done"
    both = prune_twin(twin.root, PruneConfig(sim="kinematic"))
    by_pose = {c["pose"]: c for c in both["cuts"]}
    c = by_pose[back]
    assert c["side"] == "far" and c["status"] == "done", c["reason"]
    assert c["blade_error_m"] < 0.002
    cut = twin.cut_point(twin.pose(back).cut_point).point
    np.testing.assert_allclose(c["point"], cut, atol=1e-9)  # in the vine frame
    assert by_pose["p3"]["side"] == "near" and by_pose["p3"]["status"] == "done"
    assert [c["side"] for c in both["cuts"]] == ["near", "far"]  # the order they were done in
    s = both["summary"]
    assert (s["poses"], s["reachable"], s["done"], s["far_side_poses"]) == (2, 2, 2, 1)
    assert s["simulated_s"] > near["summary"]["simulated_s"] + c["time_s"] - 1e-9
    assert both["plan"]["far_side"]["stops"] and both["collisions"] == 0


def test_a_far_curtain_is_approached_from_the_far_side() -> None:
    cfg = SearchConfig()
    assert cfg.side == "auto"
    assert not cfg.far_for([0.0, 0.2, 1.0]) and cfg.far_for([0.0, 0.45, 1.0])
    assert SearchConfig(side="far").far_for([0.0, -1.0, 1.0])
    assert not SearchConfig(side="near").far_for([0.0, 1.0, 1.0])
    assert cfg.azimuths_for(True) == (195.0, 345.0)
    for bad in ({"side": "back"}, {"far_beyond": 0.0}, {"far_beyond": math.nan}):
        with pytest.raises(InputError):
            SearchConfig(**bad)  # type: ignore[arg-type]
    with pytest.raises(InputError, match="sides must be near or both"):
        JobConfig(sides="far")  # type: ignore[arg-type]


def test_the_field_twin_sweep_covers_the_far_aisle_when_a_pose_looks_from_there(
    tmp_path: Path, sample_twin_dir: Path
) -> None:
    """`vinetwin validate`'s grid capture: with a pose looking from +Y, half its frames come from
    the far aisle, over the same stretch of the row; without one, every frame from -Y."""
    from vinetwin.reconstruct.synthetic import sweep_poses

    twin, back = _with_a_far_pose(tmp_path, sample_twin_dir)
    views = sweep_poses(twin, 21)
    look = np.array([T[:3, 2] for T in views])
    cams = np.array([T[:3, 3] for T in views])
    near = look[:, 1] > 0
    assert (near.sum(), (~near).sum()) == (11, 10)
    assert cams[near, 1].max() < 0 < cams[~near, 1].min()
    for side in (near, ~near):  # both along the sample's whole row (x -0.7 to 0.7 m)
        assert cams[side, 0].min() < -0.3 and cams[side, 0].max() > 0.3
    twin.delete_pose(back)
    assert all(T[1, 2] > 0 for T in sweep_poses(twin, 21))
