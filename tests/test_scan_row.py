"""A scan of a row of plants (`scan.row`): its trunks are found, a row is refused unless one plant
is named, and the plant named is imported alone."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from tests.test_scan import _ply_cloud, _tube_points
from vinetwin.errors import ScanError
from vinetwin.scan.config import ScanImportConfig
from vinetwin.scan.evaluate import skeleton_accuracy
from vinetwin.scan.importer import analyse_scan, import_scan
from vinetwin.scan.read import detect_units
from vinetwin.scan.row import find_feet, split_plants
from vinetwin.scan.synthetic import QUALITY_LADDER, simulate_scan
from vinetwin.twin.generator import generate_vine
from vinetwin.twin.skeleton import transform_skeleton, tube_mesh

UP = np.array([0.0, 0.0, 1.0])
SPACING = 1.4


def _row_of_cylinders(
    rng: np.random.Generator, post: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """Three cordon vines `SPACING` apart along x (a trunk 0.6 m tall, a cordon 1.4 m long whose
    ends touch the neighbours', canes up from it); the first has a double trunk (two stems 8 cm
    apart); optionally a post 1.8 m tall touching the last cordon's end. Returns the points and
    each point's vine (-1: the post)."""
    P, lab = [], []

    def add(a: list[float], b: list[float], r: float, k: int) -> None:
        q = _tube_points(np.array(a), np.array(b), r, 0.005, rng)
        P.append(q)
        lab.append(np.full(len(q), k))

    for k in range(3):
        x = k * SPACING
        add([x, 0, 0], [x, 0, 0.6], 0.02, k)
        if k == 0:
            add([x + 0.08, 0, 0], [x + 0.02, 0, 0.55], 0.015, k)
        add([x - 0.69, 0, 0.6], [x + 0.69, 0, 0.6], 0.015, k)
        for c in (-0.45, -0.15, 0.2, 0.5):
            add([x + c, 0, 0.62], [x + c + 0.05, 0.02, 1.1], 0.005, k)
    if post:
        add([2 * SPACING + 0.74, 0, 0], [2 * SPACING + 0.74, 0, 1.8], 0.04, -1)
    return np.vstack(P), np.concatenate(lab)


def test_feet_are_found_one_per_plant_and_each_point_goes_to_its_plant() -> None:
    P, lab = _row_of_cylinders(np.random.default_rng(0))
    feet = find_feet(P, UP)
    assert len(feet) == 3  # the double trunk is one plant
    order = np.argsort(feet[:, 0])
    assert np.allclose(feet[order, 0], [0.0, SPACING, 2 * SPACING], atol=0.1)
    got = split_plants(P, feet, 0.005)
    # each point to its own vine, but where two cordons' ends touch (within 3 cm of the middle)
    mid = np.abs(((P[:, 0] + SPACING / 2) % SPACING) - SPACING / 2) > SPACING / 2 - 0.03
    share = float(np.mean(order[got[~mid]] == lab[~mid]))
    assert share > 0.99, share


def test_a_row_is_refused_naming_its_trunks_and_one_plant_is_imported_on_its_own(
    tmp_path: Path,
) -> None:
    truth = generate_vine(0)
    V, F = tube_mesh(truth, edge=0.003)
    gap = 1.45  # the bundled sample is 1.42 m across: its canes touch its neighbour's
    V2, F2 = np.vstack([V, V + [gap, 0, 0]]), np.vstack([F, F + len(V)])
    q = dataclasses.replace(QUALITY_LADDER["realistic"], trellis=True)
    P, _ = simulate_scan(V2, F2, q, seed=1, wire_height=float(truth.branches[0].points[-1][2]))
    f = _ply_cloud(tmp_path / "row.ply", P)
    with pytest.raises(ScanError, match=r"holds 2 plants \(a row\).*--plant-number"):
        import_scan(f, tmp_path / "refused.twin")
    assert not (tmp_path / "refused.twin").exists()  # nothing written
    with pytest.raises(ScanError, match="--plant-number 3: the scan holds 2 plants"):
        analyse_scan(f, ScanImportConfig(plant_number=3))
    for k in (1, 2):
        scan = analyse_scan(f, ScanImportConfig(plant_number=k))
        assert [b.kind for b in scan.skeleton.branches].count("trunk") == 1
        c = scan.counts()  # the other vine's points, and the posts touching the canes
        assert c["others"] > 0.5 * c["kept"] and c["post"] > 1000
        assert f"plant {k} of the 2" in " ".join(scan.notes)
        mine = transform_skeleton(generate_vine(0), scan.T_vine_scan)
        for b in mine.branches:  # the k-th copy, in the twin's frame
            b.points = b.points + (k - 1) * gap * scan.T_vine_scan[:3, 0]
        acc = skeleton_accuracy(scan.skeleton, mine, "vine", 0.07)
        assert acc.completeness > 0.95 and acc.precision > 0.95, (k, acc)
        assert acc.candidates_found >= 0.9 * acc.candidates_true, (k, acc)


def test_a_post_touching_the_canes_is_no_plant_and_one_plant_needs_no_number(
    tmp_path: Path,
) -> None:
    P, lab = _row_of_cylinders(np.random.default_rng(1), post=True)
    f = _ply_cloud(tmp_path / "row.ply", P)
    with pytest.raises(ScanError, match=r"holds 3 plants"):  # the post is not a fourth
        analyse_scan(f, ScanImportConfig(up="z"))
    scan = analyse_scan(f, ScanImportConfig(up="z", plant_number=3))
    assert scan.counts()["post"] > 0.8 * int((lab == -1).sum())
    one = _ply_cloud(tmp_path / "one.ply", P[lab == 1])
    assert analyse_scan(one, ScanImportConfig(up="z")).counts()["others"] == 0
    with pytest.raises(ScanError, match="--plant-number 2: the scan holds one plant"):
        analyse_scan(one, ScanImportConfig(up="z", plant_number=2))


def test_a_row_longer_than_a_plant_needs_its_units_named() -> None:
    P, _ = _row_of_cylinders(np.random.default_rng(2))
    row = np.vstack([P + [k * 3 * SPACING, 0, 0] for k in range(2)]) * 1000  # 8.4 m, in mm
    rng = np.random.default_rng(0)
    with pytest.raises(ScanError, match="a row of plants"):
        detect_units(row, "auto", "vine", rng)
    assert detect_units(row, "mm", "vine", rng)[0] == "mm"
    with pytest.raises(ScanError, match="a row up to 100 m"):
        detect_units(row * 1000, "mm", "vine", rng)  # 8.4 km


def test_a_plant_too_large_for_the_units_named_is_refused(tmp_path: Path) -> None:
    P, lab = _row_of_cylinders(np.random.default_rng(3))
    one = _ply_cloud(tmp_path / "one.ply", P[lab == 1] * 1000)  # 1.4 m, in millimetres
    with pytest.raises(ScanError, match=r"in cm the vine would be 1\d.\d m across"):
        analyse_scan(one, ScanImportConfig(up="z", units="cm"))  # a row's units let it in
