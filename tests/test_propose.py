"""Cut proposals: the pruning rules on a vine whose right answer is known by construction, the
pose search's clearance, idempotence, and bad input."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from vinetwin.errors import InputError, TwinError
from vinetwin.plan.config import BodyConfig, ProposeConfig, RuleConfig, SearchConfig
from vinetwin.plan.proposer import is_proposal, propose, review
from vinetwin.plan.rules import BETWEEN_BUDS, propose_cuts
from vinetwin.plan.search import VineObstacles, body_distance, search_pose
from vinetwin.twin.model import Twin, twin_from_skeleton
from vinetwin.twin.poses import Approach, default_approach, pruning_pose
from vinetwin.twin.skeleton import FIRST_NODE, Branch, Skeleton

WIRE = 0.7
CORDON_R = 0.012
INTERNODE = 0.07
NODES = (0.02 + INTERNODE * np.arange(6)).astype(np.float64)  # buds at 2, 9, ..., 37 cm


def _line(a: list[float], b: list[float], n: int = 60) -> np.ndarray:
    return np.linspace(a, b, n)


def known_vine() -> Skeleton:
    """A trunk, a cordon along +X at the wire, three 3 cm spurs at x = 0.1, 0.3, 0.5; spur 1 has
    an upright cane and one leaning 45 deg along -X; spurs 2 and 3 one upright cane each. Every
    cane is straight, 0.42 m long, with a bud every 7 cm from 2 cm."""
    sk = Skeleton()
    sk.branches.append(Branch(_line([0, 0, 0], [0, 0, WIRE]), np.full(60, 0.015), "trunk"))
    sk.branches.append(Branch(_line([0, 0, WIRE], [0.6, 0, WIRE]), np.full(60, CORDON_R),
                              "cordon", parent=0))  # fmt: skip
    top = WIRE + CORDON_R + 0.03
    for x in (0.1, 0.3, 0.5):
        sk.branches.append(Branch(_line([x, 0, WIRE], [x, 0, top], 10), np.full(10, 0.007),
                                  "spur", parent=1, label=f"spur{x}"))  # fmt: skip
        spur = len(sk.branches) - 1
        ends = [[x, 0, top + 0.42]]
        if x == 0.1:
            ends.append([x - 0.42 / math.sqrt(2), 0, top + 0.42 / math.sqrt(2)])
        for k, e in enumerate(ends):
            sk.branches.append(Branch(_line([x, 0, top], e), np.full(60, 0.004), "cane",
                                      parent=spur, label=f"cane{x}-{k}", nodes=NODES))  # fmt: skip
    return sk


def _upright_cut(x: float, buds: int) -> np.ndarray:
    """Where an upright cane of spur x is shortened to `buds` buds (by its nodes)."""
    s = NODES[buds - 1] + BETWEEN_BUDS * INTERNODE
    return np.array([x, 0.0, WIRE + CORDON_R + 0.03 + s])


def test_spur_rule_on_a_known_vine() -> None:
    cuts = propose_cuts(known_vine(), RuleConfig(rule="spur", buds=2))
    shorten = sorted((c for c in cuts if c.action == "shorten"), key=lambda c: c.point[0])
    remove = [c for c in cuts if c.action == "remove"]
    assert len(shorten) == 3 and len(remove) == 1
    for c, x in zip(shorten, (0.1, 0.3, 0.5), strict=True):
        assert np.linalg.norm(c.point - _upright_cut(x, 2)) < 1e-3, c.reason
        assert abs(abs(c.cane_axis[2]) - 1) < 1e-6
    # the leaning cane (the less upright) goes, cut where it parts from the kept one: its axis
    # 2 x 4 mm + 10 mm from the upright's, 18 mm / sin 45 deg along it from the fork
    r = remove[0]
    assert "cane0.1-1" in r.reason and "kept: cane0.1-0" in r.reason
    along = np.linalg.norm(r.point - [0.1, 0, WIRE + CORDON_R + 0.03])
    assert along == pytest.approx(0.018 / math.sin(math.pi / 4), abs=0.003)
    # three buds: the cut moves one internode out
    three = propose_cuts(known_vine(), RuleConfig(rule="spur", buds=3))
    assert min(np.linalg.norm(c.point - _upright_cut(0.3, 3)) for c in three) < 1e-3


def test_a_removed_cane_longer_than_the_kept_one_is_cut_where_they_part() -> None:
    """The leaning cane of spur 1 made the longest: it is still cut where it parts from the
    kept upright cane, not where the spur leaves the cordon (which would take the kept cane with
    it)."""
    sk = known_vine()
    lean = next(b for b in sk.branches if b.label == "cane0.1-1")
    fork = lean.points[0]
    lean.points = fork + np.linspace(0.0, 1.0, 60)[:, None] * 0.5 * np.array(
        [-1, 0, 1]
    ) / math.sqrt(2)
    cuts = propose_cuts(sk, RuleConfig(rule="spur", buds=2))
    r = next(c for c in cuts if c.action == "remove")
    assert "cane0.1-1" in r.reason and "kept: cane0.1-0" in r.reason
    assert np.linalg.norm(r.point - fork) == pytest.approx(0.018 / math.sin(math.pi / 4), abs=0.003)


def test_the_rule_does_not_depend_on_how_finely_the_skeleton_is_sampled() -> None:
    """Canes sampled only at their nodes (7 cm apart, as hydroshoot digitises them), one with a
    1.2 mm lateral starting at its node 7 cm out: the lateral goes with its cane (no cut of
    its own), and every cut is where it is on the same vine sampled every 2 mm. (The rule once
    ramped the lateral's radius from its cane's over its first internode and removed it.)"""
    from vinetwin.twin.skeleton import resample

    sk = known_vine()
    for b in sk.branches:
        if b.kind == "cane":
            b.points, b.radii = b.points[::10], b.radii[::10]  # 7 points, 7 cm apart
    i_cane = next(i for i, b in enumerate(sk.branches) if b.label == "cane0.3-0")
    start = sk.branches[i_cane].points[1]
    way = np.array([0.0, 1.0, 1.0]) / math.sqrt(2)
    sk.branches.append(Branch(start + np.outer(0.07 * np.arange(4), way), np.full(4, 0.0012),
                              "cane", parent=i_cane, label="lateral"))  # fmt: skip
    cfg = RuleConfig(rule="spur", buds=2, internode=INTERNODE)
    sparse = propose_cuts(sk, cfg)
    assert not any("lateral" in c.reason for c in sparse)
    dense = Skeleton([Branch(*resample(b.points, b.radii, 0.002), b.kind, b.parent, b.label, b.nodes)
                      for b in sk.branches])  # fmt: skip
    fine = propose_cuts(dense, cfg)
    assert len(fine) == len(sparse) == 4
    for c in sparse:
        assert min(np.linalg.norm(f.point - c.point) for f in fine) < 1e-3, c.reason


def test_spur_rule_with_a_stated_internode_counts_from_the_cordon() -> None:
    """Without the skeleton's nodes (as on a scan), bud k sits FIRST_NODE + (k-1) internodes
    past the cordon's surface."""
    cuts = propose_cuts(known_vine(), RuleConfig(rule="spur", internode=0.08))
    want = CORDON_R + FIRST_NODE + (1 + BETWEEN_BUDS) * 0.08
    got = sorted(c.point[2] - WIRE for c in cuts if c.action == "shorten")
    assert got == pytest.approx([want] * 3, abs=1e-3)


def test_cane_rule_on_a_known_vine() -> None:
    cuts = propose_cuts(known_vine(), RuleConfig(rule="cane", cane_buds=4, canes=2, buds=2))
    by_x = {round(float(c.point[0]), 1): c for c in cuts if c.action == "shorten"}
    # the two spurs nearest the head (x = 0.1, 0.3) keep a 4-bud cane, x = 0.5 is the renewal
    assert set(by_x) == {0.1, 0.3, 0.5}
    assert np.linalg.norm(by_x[0.1].point - _upright_cut(0.1, 4)) < 1e-3
    assert np.linalg.norm(by_x[0.3].point - _upright_cut(0.3, 4)) < 1e-3
    assert np.linalg.norm(by_x[0.5].point - _upright_cut(0.5, 2)) < 1e-3
    assert "renewal" in by_x[0.5].reason
    assert [c.action for c in cuts].count("remove") == 1
    # one cane kept: the spur at 0.3 becomes the renewal spur, the one at 0.5 goes at the cordon
    one = propose_cuts(known_vine(), RuleConfig(rule="cane", cane_buds=4, canes=1))
    base = [c for c in one if "permanent wood" in c.reason]
    assert len(base) == 1 and abs(base[0].point[0] - 0.5) < 1e-6
    # 1 cm clear of the cordon (the spur's radius 7 mm)
    assert base[0].point[2] - WIRE == pytest.approx(CORDON_R + 0.007 + 0.01, abs=1e-3)


def test_rule_options_out_of_range_are_named() -> None:
    for kw, name in ((dict(buds=0), "buds"), (dict(cane_buds=40), "cane_buds"),
                     (dict(canes=3), "canes"), (dict(internode=0.5), "internode"),
                     (dict(rule="hedge"), "rule")):  # fmt: skip
        with pytest.raises(InputError, match=name):
            RuleConfig(**kw)  # type: ignore[arg-type]
    with pytest.raises(InputError, match="tool_reach"):
        SearchConfig(standoff=0.06)
    with pytest.raises(InputError, match="margin"):
        BodyConfig(margin=-0.01)


def test_cane_rule_refuses_a_tree() -> None:
    sk = Skeleton([Branch(_line([0, 0, 0], [0, 0, 1]), np.full(60, 0.02)),
                   Branch(_line([0, 0, 0.5], [0.4, 0, 0.9]), np.full(60, 0.005), parent=0)])  # fmt: skip
    with pytest.raises(InputError, match="tree"):
        propose_cuts(sk, RuleConfig(rule="cane"))
    assert len(propose_cuts(sk, RuleConfig(rule="spur", internode=0.05))) == 1


@pytest.fixture(scope="module")
def vine_twin(tmp_path_factory: pytest.TempPathFactory) -> Twin:
    return twin_from_skeleton(tmp_path_factory.mktemp("p") / "known.twin", known_vine(),
                              edge=0.003)  # fmt: skip


def _obstacles(twin: Twin) -> VineObstacles:
    m = twin.load_mesh()
    return VineObstacles(np.asarray(m.vertices), np.asarray(m.faces), twin.camera)


def test_the_far_side_search_looks_from_the_far_aisle(vine_twin: Twin) -> None:
    """From the far side (+Y) the grid and the default approach turn half a turn: a cane 7 cm in
    front of the cut on the near side is behind the camera there, and the default is clear."""
    sk = known_vine()
    cut = _upright_cut(0.3, 2)
    sk.branches.append(Branch(_line([0.2, -0.07, cut[2] - 0.1], [0.4, -0.07, cut[2] + 0.1]),
                              np.full(60, 0.004), "cane", parent=-1, label="blocker"))  # fmt: skip
    twin = twin_from_skeleton(vine_twin.root.parent / "blocked_far.twin", sk, edge=0.003)
    obs, cfg, axis = _obstacles(twin), SearchConfig(), np.array([0.0, 0.0, 1.0])
    cane = np.array([cut + [0, 0, dz] for dz in np.linspace(-0.05, 0.05, 11)])
    found = search_pose(obs, cut, axis, cane, 0.004, cfg, far=True)
    assert found.default.clearance >= cfg.body.margin
    assert math.degrees(found.default.approach.azimuth) == pytest.approx(-90.0)
    assert found.best is not None
    T = pruning_pose(cut, axis, found.best.approach)
    assert T[1, 2] < -0.5 and T[1, 3] > cut[1] + 0.1  # on +Y, looking back across the row
    assert all(195 - 1e-6 <= math.degrees(c.approach.azimuth) % 360 <= 345 + 1e-6
               for c in found.ranked)  # fmt: skip


def test_search_refuses_a_pose_inside_a_cane_and_clears_a_blocking_one(vine_twin: Twin) -> None:
    """A cane in front of the cut, on the default approach's line: the default pose's tool runs
    through it (negative clearance); the search turns the approach and keeps every body part
    `margin` clear, checked independently against the mesh with Open3D's distance query."""
    from vinetwin import _lazy

    sk = known_vine()
    cut = _upright_cut(0.3, 2)
    # a blocking cane, 7 cm in front of the cut on the -Y side, across the row
    sk.branches.append(Branch(_line([0.2, -0.07, cut[2] - 0.1], [0.4, -0.07, cut[2] + 0.1]),
                              np.full(60, 0.004), "cane", parent=-1, label="blocker"))  # fmt: skip
    root = vine_twin.root.parent / "blocked.twin"
    twin = twin_from_skeleton(root, sk, edge=0.003)
    obs = _obstacles(twin)
    cfg = SearchConfig()
    axis = np.array([0.0, 0.0, 1.0])
    cane = np.array([cut + [0, 0, dz] for dz in np.linspace(-0.05, 0.05, 11)])
    found = search_pose(obs, cut, axis, cane, 0.004, cfg)
    assert found.default.clearance < 0  # the default approach runs the tool through the blocker
    assert found.best is not None and found.best.clearance >= cfg.body.margin
    assert found.best.cut_seen and found.best.visible >= cfg.min_visible
    # the pose inside the blocking cane: refused by the same measure
    inside = Approach(cfg.standoff, math.pi / 2, 0.0, 0.0)
    T = pruning_pose(cut, axis, inside)
    from vinetwin.plan.search import _clearances

    assert _clearances(obs, cut, axis, [inside], cfg)[0] < 0
    assert abs(T[1, 3] - (cut[1] - cfg.standoff)) < 1e-9
    # independent check of the chosen pose: points on the body's surface, distance to the mesh
    o3d = _lazy.open3d()
    m = twin.load_mesh()
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.asarray(m.vertices, np.float32)),
                        o3d.core.Tensor(np.asarray(m.faces, np.uint32)))  # fmt: skip
    Tb = pruning_pose(cut, axis, found.best.approach)
    body = cfg.body
    zs = np.linspace(0, cfg.standoff, 200)
    ring = np.linspace(0, 2 * math.pi, 16, endpoint=False)
    tool = np.array([[body.tool_radius * math.cos(a), body.tool_radius * math.sin(a), z]
                     for z in zs for a in ring])  # fmt: skip
    far = np.linalg.norm(tool - [0, 0, cfg.standoff], axis=1) > body.jaw_zone + body.tool_radius
    world = tool[far] @ Tb[:3, :3].T + Tb[:3, 3]
    d = scene.compute_distance(o3d.core.Tensor(world.astype(np.float32))).numpy()
    assert d.min() > 0.8 * body.margin
    # and the analytic distance agrees with the sampled body on the vine's points near it
    Q = (obs.points - Tb[:3, 3]) @ Tb[:3, :3]
    dist = body_distance(Q, cfg.standoff, body, np.linalg.norm(obs.points - cut, axis=1) < 0.025)
    assert dist.min() == pytest.approx(found.best.clearance, abs=1e-9)
    assert default_approach(axis).azimuth == pytest.approx(math.pi / 2)


def test_propose_is_idempotent_and_replace_keeps_a_persons_cuts(vine_twin: Twin) -> None:
    twin = Twin.load(vine_twin.root)
    own = twin.add_cut_point([0.3, 0.0, 1.0], [0, 0, 1])
    twin.add_pose(own.id)
    twin.save()
    first = propose(twin, ProposeConfig())
    assert first.counts()["proposed"] == 4 and first.counts()["with_pose"] == 4
    n = len(twin.cut_points)
    again = propose(Twin.load(vine_twin.root), ProposeConfig())
    assert again.counts()["proposed"] == 0 and again.already == 4
    twin = Twin.load(vine_twin.root)
    assert len(twin.cut_points) == n == 5
    # one accepted, then --replace: the three others are proposed again, nothing is doubled
    accepted = next(c.id for c in twin.cut_points if is_proposal(c))
    review(twin, True, [accepted])
    twin.save()
    third = propose(twin, ProposeConfig(replace=True))
    assert third.replaced == 3 and third.already == 1 and third.counts()["proposed"] == 3
    twin = Twin.load(vine_twin.root)
    assert len(twin.cut_points) == 5
    assert twin.cut_point(own.id).source == "manual"
    assert twin.cut_point(accepted).extra["proposal"]["status"] == "accepted"
    # reject all that are still proposed: their poses go with them
    gone = review(twin, False)
    assert len(gone) == 3 and len(twin.cut_points) == 2
    assert {p.cut_point for p in twin.poses} <= {c.id for c in twin.cut_points}
    with pytest.raises(InputError, match="not a proposal"):
        review(twin, False, [own.id])


def test_a_twin_without_a_skeleton_names_the_importers(tmp_path) -> None:
    from vinetwin.twin.skeleton import tube_mesh

    V, F = tube_mesh(known_vine(), edge=0.004)
    twin = Twin.create(tmp_path / "bare.twin", V, F)
    with pytest.raises(TwinError, match="import-scan"):
        propose(twin, ProposeConfig())


def test_spur_rule_shortens_at_the_generators_own_cuts() -> None:
    """On a generated vine the kept canes are cut where the generator put its two-bud
    candidates (from the nodes it grew), and every removal is on a cane of a spur with a kept
    one; the skeleton's nodes survive a save and load."""
    from vinetwin.twin.generator import generate_vine

    sk = generate_vine(3)
    sk = Skeleton.from_json(sk.to_json())
    assert all(len(b.nodes) for b in sk.branches if b.kind == "cane")
    cuts = propose_cuts(sk, RuleConfig(rule="spur"))
    cands = np.array([c.point for c in sk.candidates])
    shortened = [c for c in cuts if c.action == "shorten"]
    assert len(shortened) >= 6
    for c in shortened:  # the generator puts its candidate on a vertex of its 4 mm polyline
        assert np.linalg.norm(cands - c.point, axis=1).min() < 0.0045, c.reason


def test_hydroshoot_shoots_keep_their_nodes() -> None:
    from tests.conftest import ROOT
    from vinetwin.twin.importers import load_skeleton

    path = ROOT.parent / "shared/data/vines/hydroshoot/vsp_ww_grapevine/digit.input"
    if not path.exists():
        pytest.skip("../shared/data is not here")
    sk = load_skeleton(path)
    shoots = [b for b in sk.branches if b.kind == "shoot"]
    assert shoots and all(len(b.nodes) == len(b.points) - 1 for b in shoots if b.parent >= 0)
    cuts = propose_cuts(sk, RuleConfig(rule="spur"))
    assert {c.action for c in cuts} == {"shorten", "remove"}


def test_the_command_names_bad_options_and_a_missing_skeleton(
    vine_twin: Twin,
    tmp_path,
    caplog: pytest.LogCaptureFixture,
    capsys: pytest.CaptureFixture[str],
) -> None:
    from tests.test_envelope import said as said_by
    from vinetwin.twin.skeleton import tube_mesh

    def said(args: list[str]) -> tuple[int, str]:
        return said_by(args, caplog, capsys)

    before = (vine_twin.root / "twin.json").read_text()
    for flag, value in (("--buds", "9"), ("--internode", "0.5"), ("--rule", "hedge"),
                        ("--margin", "-1"), ("--standoff", "nan")):  # fmt: skip
        rc, text = said(["propose", str(vine_twin.root), flag, value])
        assert rc == 2 and flag.strip("-").split("-")[0] in text, (flag, text[-400:])
    assert (vine_twin.root / "twin.json").read_text() == before  # nothing written
    V, F = tube_mesh(known_vine(), edge=0.004)
    Twin.create(tmp_path / "bare.twin", V, F)
    rc, text = said(["propose", str(tmp_path / "bare.twin")])
    assert rc != 0 and "import-scan" in text
    out = tmp_path / "p.json"
    rc, text = said(["propose", str(vine_twin.root), "--replace", "--json", str(out)])
    assert rc == 0 and "cuts proposed by the spur rule" in text
    assert json.loads(out.read_text())["counts"]["proposed"] >= 1
    kept = out.read_text()  # an existing --json is refused (it was overwritten), as elsewhere
    rc, text = said(["propose", str(vine_twin.root), "--replace", "--json", str(out)])
    assert rc == 2 and "--overwrite" in text and out.read_text() == kept
    rc, text = said(["propose", str(vine_twin.root), "--replace", "--json", str(out),
                     "--overwrite"])  # fmt: skip
    assert rc == 0


def test_the_search_keeps_the_arms_wrist_off_the_vine(vine_twin: Twin) -> None:
    """The parts of the arm fixed to the camera (link 7, the tool mount, the housing) are
    checked along the approach as the planner models them (`arm.sphere_model`): a cane where
    link 7 passes on the default approach, clear of the camera and tool, rules that pose out;
    the pose chosen instead keeps every wrist sphere its clearance, checked against the mesh's
    vertices sphere by sphere."""
    from scipy.spatial import cKDTree

    from vinetwin.arm import camera_fixed_spheres
    from vinetwin.plan.job_config import ReachConfig
    from vinetwin.plan.search import Wrist, _clearances

    cfg = SearchConfig()
    T_fc = vine_twin.T_flange_camera
    wrist = Wrist.for_arm(T_fc, cfg)
    travel = cfg.standoff - cfg.body.tool_reach
    cam, radius, part = camera_fixed_spheres(T_fc)
    # for points anywhere around the wrist, the wrist's gap is at most the planner's spheres'
    # (each swept exactly along the approach) plus 0.3 mm: as conservative as the planner
    keep = np.where(np.asarray(part) == "link7", ReachConfig().clearance, cfg.body.margin)
    rng = np.random.default_rng(0)
    Q = rng.uniform([-0.25, -0.2, -0.3], [0.15, 0.2, 0.2], (4000, 3))
    t = np.clip(Q[:, None, 2] - cam[None, :, 2], 0.0, travel)
    seg = np.linalg.norm(Q[:, None] - cam[None] - t[..., None] * [0, 0, 1], axis=2)
    planner = (seg - radius - keep + cfg.body.margin).min(axis=1)
    ours = (np.linalg.norm(Q[:, None] - wrist.points[None], axis=2) - wrist.need).min(axis=1)
    assert (ours <= planner + 3e-4).all()
    assert np.median(planner - ours) < 1e-3  # and not much more

    sk = known_vine()
    cut = _upright_cut(0.3, 2)
    axis = np.array([0.0, 0.0, 1.0])
    T0 = pruning_pose(cut, axis, default_approach(axis, cfg.standoff))
    # a cane along the image's y, 5 cm to the wrist's side of the optical axis, level with the
    # camera's front: 25 mm from the camera's body, through link 7's sweep
    ends = np.array([[-0.05, -0.1, 0.0], [-0.05, 0.1, 0.0]]) @ T0[:3, :3].T + T0[:3, 3]
    sk.branches.append(Branch(_line(list(ends[0]), list(ends[1])), np.full(60, 0.004), "cane",
                              parent=-1, label="blocker"))  # fmt: skip
    twin = twin_from_skeleton(vine_twin.root.parent / "wrist.twin", sk, edge=0.003)
    obs = _obstacles(twin)
    dflt = default_approach(axis, cfg.standoff)
    assert _clearances(obs, cut, axis, [dflt], cfg)[0] > cfg.body.margin  # camera, tool clear
    assert _clearances(obs, cut, axis, [dflt], cfg, wrist)[0] < 0  # link 7 is not
    cane = np.array([cut + [0, 0, dz] for dz in np.linspace(-0.05, 0.05, 11)])
    found = search_pose(obs, cut, axis, cane, 0.004, cfg, wrist)
    assert found.best is not None and found.best.clearance >= cfg.body.margin
    Tb = pruning_pose(cut, axis, found.best.approach)
    tree = cKDTree(np.asarray(twin.load_mesh().vertices))
    for z in np.linspace(0.0, travel, 9):
        world = (cam + [0, 0, z]) @ Tb[:3, :3].T + Tb[:3, 3]
        gap = tree.query(world)[0] - radius - keep
        assert gap.min() > -1.5e-3  # vertices of a 3 mm mesh: the surface within 1.5 mm
