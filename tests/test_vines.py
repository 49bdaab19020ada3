"""Vine skeletons: the procedural generator and the importers of real digitised plants."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from tests.conftest import shared
from vinetwin.errors import ImportFormatError, InputError
from vinetwin.twin.generator import VineParams, generate_vine
from vinetwin.twin.importers import detect_format, load_skeleton, read_cylinders, read_hydroshoot
from vinetwin.twin.skeleton import Branch, Skeleton, tube_mesh

HYDROSHOOT = ["gdc_can1_grapevine", "vsp_ww_grapevine", "virtual_vsp"]
TREES = ["Apple_1_TallSpindle.txt", "Apple_YTrellisL.txt", "Nectarine_30_6_14_1.txt"]


@pytest.mark.parametrize("name", HYDROSHOOT)
def test_hydroshoot_imports_with_matching_extent(name: str) -> None:
    path = shared("vines", "hydroshoot", name, "digit.input")
    assert detect_format(path) == "hydroshoot"
    sk = load_skeleton(path)
    # source extent: every node (cm -> m), grown by its radius (round caps make a swept sphere)
    rows = [ln.split(";") for ln in path.read_text().splitlines()[1:] if ln.strip()]
    xyz = np.array([[float(r[6]), float(r[7]), float(r[8])] for r in rows]) / 100
    centres = np.concatenate([b.points for b in sk.branches])
    # every source node is a skeleton point, to the micrometre
    d = np.linalg.norm(xyz[:, None, :] - centres[None, :, :], axis=2).min(1)
    assert d.max() < 1e-6
    V, _F = tube_mesh(sk, edge=0.004, caps="round")
    src = sk.bounds(inflate_by_radius=True)
    np.testing.assert_allclose(np.stack([V.min(0), V.max(0)]), src, atol=1e-3)
    assert len(sk.candidates) >= 5
    if name == "gdc_can1_grapevine":  # diameters come from the file: trunk about 5 cm
        assert 0.02 < sk.branches[0].radii.mean() < 0.03


@pytest.mark.parametrize("name", TREES)
def test_cylinder_lists_import_with_matching_extent(name: str) -> None:
    path = shared("trees", "tree-models-library", name)
    assert detect_format(path) == "cylinders"
    sk = read_cylinders(path)
    lines = [ln.split() for ln in path.read_text().splitlines()]
    n = int(lines[0][0])  # the branches' block; the fruit's block follows (TreeRead.m)
    rows = np.array(lines[1 : n + 1], float)
    fruit = np.array(lines[n + 2 : n + 2 + int(lines[n + 1][0])], float)
    assert len(fruit) >= 30  # spheres: each radius half its vector's length
    np.testing.assert_allclose(fruit[:, 6], 0.5 * np.linalg.norm(fruit[:, 3:6], axis=1), rtol=0.02)
    assert any(f"a block of {len(fruit)} fruit" in s for s in sk.skipped), sk.skipped
    wood = np.linalg.norm(rows[:, 3:6], axis=1).sum()  # no fruit read as wood
    np.testing.assert_allclose(sum(b.length for b in sk.branches), wood, rtol=1e-3)
    s, a, r = rows[:, :3], rows[:, 3:6], rows[:, 6]
    u = a / np.linalg.norm(a, axis=1, keepdims=True)
    ext = r[:, None] * np.sqrt(np.clip(1 - u**2, 0, 1))  # extent of a disc perpendicular to u
    lo = np.minimum(s - ext, s + a - ext).min(0)
    hi = np.maximum(s + ext, s + a + ext).max(0)
    V, _F = tube_mesh(sk, edge=0.006, caps="flat")
    np.testing.assert_allclose(np.stack([V.min(0), V.max(0)]), np.stack([lo, hi]), atol=1e-3)
    assert [i for i, b in enumerate(sk.branches) if b.parent < 0] == [0]  # one tree, no loop
    assert all(root_of(sk, i) == 0 for i in range(len(sk.branches)))


def root_of(sk: Skeleton, i: int) -> int:
    """The branch that `i`'s chain of parents ends at; -1 when the chain loops."""
    seen: set[int] = set()
    while sk.branches[i].parent >= 0:
        if i in seen:
            return -1
        seen.add(i)
        i = sk.branches[i].parent
    return i


def test_two_laterals_from_one_point_hang_in_the_tree_not_from_each_other(tmp_path: Path) -> None:
    """Two laterals leaving the trunk from one point 1 mm off its axis (as in the Tall Spindle
    apple's file): each one's start lies on the other, and the nearest branch alone made them
    each other's parent, a loop that left both out of the tree."""
    rows = ["0 0 0 0 0 0.6 0.02",  # the trunk
            "0.001 0 0.3 0.1 0 0.05 0.005", "0.001 0 0.3 -0.1 0 0.05 0.005"]  # fmt: skip
    p = tmp_path / "tree.txt"
    p.write_text(f"{len(rows)}\n" + "\n".join(rows) + "\n")
    sk = read_cylinders(p)
    assert [b.parent for b in sk.branches] == [-1, 0, 1]
    assert all(root_of(sk, i) == 0 for i in range(3))


def test_generator_is_deterministic_per_seed() -> None:
    a, b, c = generate_vine(5), generate_vine(5), generate_vine(6)
    assert len(a.branches) == len(b.branches)
    for x, y in zip(a.branches, b.branches, strict=True):
        np.testing.assert_array_equal(x.points, y.points)
        np.testing.assert_array_equal(x.radii, y.radii)
    assert not np.array_equal(a.branches[0].points, c.branches[0].points)


@pytest.mark.parametrize("seed", range(6))
def test_generated_vines_look_like_dormant_vines(seed: int) -> None:
    sk = generate_vine(seed)
    kinds = [b.kind for b in sk.branches]
    trunk = sk.branches[0]
    assert kinds[0] == "trunk" and 1 <= kinds.count("cordon") <= 2
    assert 0.020 <= 2 * np.median(trunk.radii) <= 0.045
    canes = [b for b in sk.branches if b.kind == "cane"]
    assert len(canes) >= 4
    for c in canes:
        assert 0.006 * 0.9 <= 2 * c.radii[0] <= 0.012 * 1.45  # base diameter (+ node swelling)
        assert c.points[-1, 2] > c.points[0, 2]  # canes rise
    assert len(sk.candidates) >= 3
    for cand in sk.candidates:  # candidates lie on their cane's axis
        b = sk.branches[cand.branch]
        assert np.linalg.norm(b.points - cand.point, axis=1).min() < 1e-9
        assert abs(np.linalg.norm(cand.cane_axis) - 1) < 1e-9
    assert VineParams(cordons=1) != VineParams()
    assert sum(b.kind == "cordon" for b in generate_vine(seed, VineParams(cordons=1)).branches) == 1


def test_generated_mesh_is_closed_and_well_shaped() -> None:
    V, F = tube_mesh(generate_vine(3), edge=0.002)
    assert 200_000 < len(F) < 600_000  # real-sized
    mesh = trimesh.Trimesh(V, F, process=False)
    parts = mesh.split(only_watertight=False)
    assert all(p.is_watertight and p.volume > 0 for p in parts)
    tri = V[F]
    edges = np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2)
    aspect = edges.max(1) / edges.min(1)
    assert np.median(aspect) < 1.5  # near equilateral: ray casting stays fast


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        ("Souche;tronc;element\n1;0;1\n", "header"),
        (
            "Plant_Nb;Tronc;Elmnt;Sar;Rameau;Row;X;Y;Z\n8;0;1;0;0;0;a;0;5\n8;0;2;0;0;0;0;0;10\n",
            "bad number",
        ),
        (
            "Plant_Nb;Tronc;Elmnt;Sar;Rameau;Row;X;Y;Z\n8;0;1;0;0;0\n8;0;2;0;0;0;0;0;10\n",
            "expected 9 fields",
        ),
    ],
)
def test_bad_hydroshoot_files(tmp_path: Path, text: str, needle: str) -> None:
    p = tmp_path / "digit.input"
    p.write_text(text)
    with pytest.raises(ImportFormatError, match=needle):
        read_hydroshoot(p)


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        ("3\n", "should follow"),
        ("1\n0 0 0 0 0 1 -0.1\n", "non-positive radius"),
        ("x\n", "cylinder count"),
    ],
)
def test_bad_cylinder_files(tmp_path: Path, text: str, needle: str) -> None:
    p = tmp_path / "tree.txt"
    p.write_text(text)
    with pytest.raises(ImportFormatError, match=needle):
        read_cylinders(p)


def test_unknown_format(tmp_path: Path) -> None:
    p = tmp_path / "x.txt"
    p.write_text("hello world\n")
    with pytest.raises(ImportFormatError, match="unknown skeleton format"):
        load_skeleton(p)


def test_branch_validation_and_skeleton_json_round_trip(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="radii must be positive"):
        Branch(np.zeros((2, 3)), np.array([0.01, 0.0]))
    sk = generate_vine(1)
    sk.save(tmp_path / "s.json")
    back = Skeleton.load(tmp_path / "s.json")
    assert len(back.branches) == len(sk.branches) and len(back.candidates) == len(sk.candidates)
    np.testing.assert_allclose(back.branches[3].points, sk.branches[3].points, atol=1e-6)


def test_degenerate_cylinders_are_skipped_with_their_line_numbers(tmp_path: Path) -> None:
    """Real cylinder lists hold repeated rows, zero-length and zero-radius cylinders, garbage,
    duplicate blocks and disconnected pieces: the usable ones import, each skip is reported
    with its line, and a tube mesh is built."""
    good = [
        "0 0 0 0 0 0.10 0.020",  # trunk
        "0 0 0.10 0 0 0.10 0.018",
        "0 0 0.20 0.08 0 0.02 0.008",  # a lateral from the trunk's top
    ]
    piece_a, piece_b = "1 1 1 0 0 0.05 0.01", "2 2 2 0 0 0.05 0.01"  # disconnected pieces
    text = "\n".join(
        [
            "7",
            *good,
            "0 0 0.20 0.08 0 0.02 0.008",  # line 5: repeats line 4
            "0.5 0.5 0.5 0 0 0 0.01",  # line 6: zero length
            "0.6 0.6 0.6 0 0 0.1 0",  # line 7: zero radius
            "0.7 0.7 0.7 nan 0 0.1 0.01",  # line 8: non-finite
            "2",
            piece_a,
            piece_b,
            "2",  # line 12: repeats the block of line 9
            piece_a,
            piece_b,
            "4",  # line 15: announces 4, holds 1
            "1 1 1.5 0 0 0.05 0.01",
            "x y",  # line 17
        ]
    )
    p = tmp_path / "tree.txt"
    p.write_text(text + "\n")
    sk = read_cylinders(p)
    said = "\n".join(sk.skipped)
    for needle in (
        "line 5: repeats line 4",
        "line 6: zero-length",
        "line 7: non-positive radius",
        "line 8: non-finite",
        "line 12: a block of 2 cylinders repeats an earlier block",
        "line 15: a block announces 4",
        "line 17: expected 7 numbers",
    ):
        assert needle in said, said
    assert len(sk.skipped) == 7
    # trunk (2 cylinders) + lateral + 3 disconnected pieces
    assert sorted(len(b.points) for b in sk.branches) == [2, 2, 2, 2, 3]
    lateral = next(b for b in sk.branches if b.label == "lines 4-4")
    assert lateral.parent == next(i for i, b in enumerate(sk.branches) if b.label == "lines 2-3")
    assert len(sk.candidates) == 1  # the lateral: 8 cm long, grows out of the trunk
    c = sk.candidates[0]
    np.testing.assert_allclose(np.linalg.norm(c.point - [0, 0, 0.20]), 0.03, atol=1e-9)
    V, F = tube_mesh(sk, edge=0.004, caps="flat")
    assert len(F) > 100 and np.all(np.isfinite(V))
    p.write_text("2\n0 0 0 0 0 0 0.1\n0 0 0 0 0 1 -1\n")
    with pytest.raises(ImportFormatError, match=r"zero-length.*non-positive radius"):
        read_cylinders(p)


def test_degenerate_hydroshoot_rows_are_skipped_with_their_line_numbers(tmp_path: Path) -> None:
    src = shared("vines", "hydroshoot", "vsp_ww_grapevine", "digit.input").read_text()
    lines = src.splitlines()
    bad = [
        *lines[:5],
        lines[4],  # line 6: repeats line 5
        "1;1;1;0;0;0;abc;0;0",  # line 7: bad number
        "1;1;1;0",  # line 8: too few fields
        "1;1;1;0;0;0;nan;0;0",  # line 9: non-finite
        *lines[5:],
    ]
    p = tmp_path / "digit.input"
    p.write_text("\n".join(bad) + "\n")
    sk = read_hydroshoot(p)
    said = "\n".join(sk.skipped)
    for needle in (
        "line 6: repeats line 5",
        "line 7: bad number",
        "line 8: expected",
        "line 9: non-finite",
    ):
        assert needle in said, said
    clean = read_hydroshoot(shared("vines", "hydroshoot", "vsp_ww_grapevine", "digit.input"))
    assert len(sk.branches) == len(clean.branches) and len(sk.candidates) == len(clean.candidates)


@pytest.mark.parametrize(
    "path",
    [*(f"vines/hydroshoot/{v}/digit.input" for v in ("gdc_can1_grapevine", "vsp_ww_grapevine", "virtual_vsp")),
     *(f"trees/tree-models-library/{t}" for t in TREES)],
)  # fmt: skip
def test_every_shared_plant_file_imports_as_a_twin(path: str, tmp_path: Path) -> None:
    from vinetwin.twin.importers import import_twin

    twin = import_twin(shared(*path.split("/")), tmp_path / "t.twin", edge=0.01, cut_points=2)
    said = twin.provenance["source"]["skipped"]  # these files are clean: at most fruit left out
    assert all(s.endswith("fruit (spheres: each radius half its length), not wood") for s in said)
    assert len(twin.poses) == 2
    assert len(twin.load_mesh().faces) > 1000


def test_a_dense_vine_has_several_times_the_canes() -> None:
    """`vinetwin sample --dense` (the paper's Table 2 vines): over six seeds, at least 2.5 times
    the canes of the default vine, spurs about twice as close."""
    from vinetwin.twin.generator import DENSE

    def count(kind: str, params: VineParams) -> int:
        return sum(sum(b.kind == kind for b in generate_vine(s, params).branches) for s in range(6))

    plain, dense = VineParams(), VineParams(**DENSE)  # type: ignore[arg-type]
    assert count("cane", dense) >= 2.5 * count("cane", plain)
    assert count("spur", dense) >= 1.6 * count("spur", plain)
