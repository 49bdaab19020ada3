"""`vinetwin import-scan`: a scan of a plant becomes a twin with a skeleton and cut candidates.

read (`read`) -> units -> strays, ground (`clean`) -> the up axis (given, the ground's normal, or
the trunk's direction from a first skeleton) -> wires and posts -> one plant of a row (`row`)
-> the skeleton (`skeletonize`)
-> the vine frame (`frame`) -> kinds and cut candidates (`candidates`) -> the mesh (tubes around
the skeleton, or the scan's mesh) -> the twin. Nothing is written when any step refuses."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from vinetwin.errors import ScanError, SeveralPlants, TwinError
from vinetwin.frames import Array
from vinetwin.scan.candidates import cut_candidates, label_kinds
from vinetwin.scan.clean import (
    find_clutter,
    find_ground,
    find_posts,
    find_wires,
    statistical_strays,
)
from vinetwin.scan.config import (
    PLANT_EXTENT,
    UNIT_SCALE,
    VINE_MAX_SPACING,
    VINE_MAX_THICKNESS,
    ScanImportConfig,
)
from vinetwin.scan.frame import (
    axis_vector,
    guess_up,
    row_axis,
    split_cordons,
    split_trunk,
    vine_from_scan,
)
from vinetwin.scan.read import (
    ScanData,
    detect_units,
    read_scan,
    sample_mesh_surface,
    spacing_and_extent,
)
from vinetwin.scan.refine import straighten_bumps
from vinetwin.scan.result import ScanImport
from vinetwin.scan.row import find_feet, plants_of_row, split_plants
from vinetwin.scan.skeletonize import skeletonize
from vinetwin.twin.skeleton import Skeleton, transform_skeleton

if TYPE_CHECKING:
    from vinetwin.twin.model import Twin

log = logging.getLogger(__name__)


def analyse_scan(
    path: str | Path,
    config: ScanImportConfig,
    progress: Callable[[str], None] | None = None,
) -> ScanImport:
    """Every step of the import but writing: reads, cleans, finds the frame and the skeleton."""
    t0 = time.perf_counter()
    secs: dict[str, float] = {}

    def step(name: str) -> None:
        nonlocal t0
        t = time.perf_counter()
        secs[name] = t - t0
        t0 = t
        if progress:
            progress(name)

    rng = np.random.default_rng(0)
    data: ScanData = read_scan(path, config.max_points)
    notes = list(data.notes)
    probe = data.points
    if data.mesh is not None:  # vertices may repeat (STL) or be far apart: use the surface
        V, F = data.mesh
        probe = sample_mesh_surface(V, F, float(np.ptp(V, axis=0).max()) / 400, rng)
    units, unit_note = detect_units(probe, config.units, config.plant, rng)
    scale = UNIT_SCALE[units]
    pts = data.points * scale
    mesh = None
    if data.mesh is not None:
        V, F = data.mesh
        mesh = (V * scale, F)
        pts = sample_mesh_surface(mesh[0], F, 0.003, rng)
        notes.append(f"{len(pts)} points sampled on the mesh's surface, about 3 mm apart")
    elif config.mesh == "scan":
        raise ScanError(f"{path}: --mesh scan needs a mesh file; this is a point cloud")
    step("read")
    removed_scan: dict[str, Array] = {}
    cl = config.clean
    if cl.strays:
        m = statistical_strays(pts, cl.outlier_neighbours, cl.outlier_std)
        removed_scan["stray"], pts = pts[m], pts[~m]
    spacing, _ = spacing_and_extent(pts, rng)
    if config.plant == "vine" and spacing > VINE_MAX_SPACING:
        raise ScanError(
            f"{path}: its points lie {1000 * spacing:.0f} mm apart (median): too sparse for a "
            f"vine's canes, 5-15 mm thick (a vine's scan wants 3-5 mm; past "
            f"{1000 * VINE_MAX_SPACING:g} mm nothing holds); --plant tree for a tree's limbs"
        )
    ground = find_ground(pts, spacing, rng) if cl.ground else None
    up: Array | None = None
    up_from = ""
    if config.up != "auto":
        up, up_from = axis_vector(config.up), f"given ({config.up})"
    elif ground is not None:
        up, up_from = ground.normal, "the ground plane's normal"
    if ground is not None:
        removed_scan["ground"], pts = pts[ground.mask], pts[~ground.mask]
        if cl.clutter:
            m = find_clutter(pts, ground.normal, ground.offset, spacing)
            removed_scan["clutter"], pts = pts[m], pts[~m]
    step("clean")
    if up is None:
        found = skeletonize(pts, config.skeleton, spacing, None, config.plant)
        assert found.up is not None
        up, up_from = guess_up(found.up, found.up_from)
        if not found.up_trusted:
            notes.append(f"the up axis is uncertain (from {found.up_from}): look at the "
                         "report's picture, or name --up (or scan the ground)")  # fmt: skip
    if cl.wires:
        m = find_wires(pts, up, spacing, rng)
        removed_scan["wire"], pts = pts[m], pts[~m]
    if cl.posts:
        m = find_posts(pts, up, max(spacing, 0.01))
        removed_scan["post"], pts = pts[m], pts[~m]
    if len(pts) < 100:
        raise ScanError(f"{path}: nothing of a plant is left after cleaning ({len(pts)} points)")
    level = ground.offset if ground is not None and float(ground.normal @ up) > 0.95 else None
    pts = _one_plant(pts, up, level, spacing, scale, config.plant_number, cl.posts, path,
                     removed_scan, notes)  # fmt: skip
    extent = float(np.ptp(pts, axis=0).max())
    if extent > PLANT_EXTENT[config.plant][1]:  # named units let a row through, not a plant
        raise ScanError(f"{path}: in {units} the {config.plant} would be {extent:.3g} m across "
                        f"(at most {PLANT_EXTENT[config.plant][1]:g} m): check --units")  # fmt: skip
    step("wires and posts")
    res = skeletonize(pts, config.skeleton, spacing, up, config.plant)
    removed_scan["apart"] = pts[res.stray_mask]
    pts = pts[~res.stray_mask]
    step("skeleton")
    _check_plant(res.skeleton, pts, path, config.plant)
    sk = res.skeleton
    foot = sk.branches[0].points[0].copy()
    if ground is not None:  # the trunk's foot on the ground
        foot = foot - (foot @ ground.normal - ground.offset) * ground.normal
    x = row_axis(sk, up)
    T = vine_from_scan(up, x, foot)
    transform_skeleton(sk, T)
    z = np.array([0.0, 0.0, 1.0])
    if config.plant == "vine":
        split_trunk(sk, z)
        split_cordons(sk, z)
    label_kinds(sk, z, config.plant)
    if config.plant == "vine":
        straighten_bumps(sk)  # a spur's base pulls the cordon's axis (`scan.refine`)
    cands = cut_candidates(sk, config.plant, config.internode)
    sk.candidates = [c for c in cands if sk.branches[c.branch].kind not in ("trunk", "cordon")]
    step("frame and candidates")

    def to_vine(p: Array) -> Array:
        return p @ T[:3, :3].T + T[:3, 3]

    mesh_v = (to_vine(mesh[0]), mesh[1]) if mesh is not None else None
    return ScanImport(
        skeleton=sk, T_vine_scan=T, units=units, unit_note=unit_note,
        up_from=up_from, points=to_vine(pts),
        removed={k: to_vine(v) for k, v in removed_scan.items()}, read=data.read,
        spacing=spacing, result=res, notes=notes, mesh=mesh_v, seconds=secs,
    )  # fmt: skip


def _one_plant(pts: Array, up: Array, ground_offset: float | None, spacing: float, scale: float,
               number: int, posts: bool, path: str | Path, removed: dict[str, Array],
               notes: list[str]) -> Array:  # fmt: skip
    """The points of the one plant imported: all of them when the scan holds one; the
    `number`-th along the row when it holds several (`scan.row`; the others' points removed as
    "others"); a row without `number` is refused, naming where its trunks stand."""
    feet = find_feet(pts, up, ground_offset)
    lab: np.ndarray | None = None  # each point's plant, while it holds for these points and feet
    if len(feet) > 1:  # a post touching the canes stands on the ground like a trunk
        found = len(feet)
        feet, post, lab = plants_of_row(pts, feet, up, spacing)
        dropped = post.any() and posts  # else the column's points go with the plants
        if dropped:
            removed["post"] = np.concatenate([removed.get("post", np.zeros((0, 3))), pts[post]])
            pts = pts[~post]
        if dropped or len(feet) < found:
            lab = None
    where = "; ".join(f"{k + 1}: ({', '.join(f'{v / scale:.4g}' for v in f)})"
                      for k, f in enumerate(feet))  # fmt: skip
    if len(feet) == 1:
        if number > 1:
            raise ScanError(f"{path}: --plant-number {number}: the scan holds one plant")
        return pts
    if number == 0:
        raise SeveralPlants(
            f"{path}: the scan holds {len(feet)} plants (a row); their trunks' feet, along the "
            f"row, in the file's coordinates: {where}. Import one with --plant-number K "
            "(docs/scans.md, rows)",
            len(feet),
        )
    if number > len(feet):
        raise ScanError(f"{path}: --plant-number {number}: the scan holds {len(feet)} plants "
                        f"({where})")  # fmt: skip
    if lab is None:  # posts or weeds left out: split again among the plants
        lab = split_plants(pts, feet, spacing)
    removed["others"] = pts[lab != number - 1]
    notes.append(f"plant {number} of the {len(feet)} in the scan (trunks' feet along the row, "
                 f"in the file's coordinates: {where}); the others' points removed")  # fmt: skip
    return pts[lab == number - 1]


#: A plant is tubes: the skeleton's median radius (length-weighted) is under this share of the
#: plant's extent (a vine's canes 0.3-0.5%, a tree's branches under 2%; a plane's or a ball's
#: level sets are arcs as wide as the thing itself, 10-50%).
MAX_RADIUS_SHARE = 0.05


def _check_plant(sk: Skeleton, points: Array, path: str | Path, plant: str = "vine") -> None:
    """Refuses what is no plant: a skeleton with almost no length, or whose branches are as
    wide as the scan (a plane, a ball); for a vine, branches thicker than a vine's wood is
    (`VINE_MAX_THICKNESS`: a volume of scattered points)."""
    total = sum(b.length for b in sk.branches)
    extent = float(np.ptp(points, axis=0).max())
    r = np.concatenate([0.5 * (b.radii[1:] + b.radii[:-1]) for b in sk.branches])
    w = np.concatenate([np.linalg.norm(np.diff(b.points, axis=0), axis=1) for b in sk.branches])
    order = np.argsort(r)
    med = float(r[order][np.searchsorted(np.cumsum(w[order]), 0.5 * w.sum())]) if w.sum() > 0 else 0
    if total < 0.1 or med > MAX_RADIUS_SHARE * extent:
        raise ScanError(
            f"{path}: no plant found: the skeleton is {total:.2f} m long with branches "
            f"{2 * med * 100:.1f} cm thick in a scan {extent:.2f} m across (a plane, a ball or a "
            f"block, not branches)"
        )
    if plant == "vine" and 2 * med > VINE_MAX_THICKNESS:
        raise ScanError(
            f"{path}: no vine found: its skeleton's branches are {2 * med * 100:.1f} cm thick "
            f"(the median over their length; a vine's canes and cordons are 0.5-4 cm); "
            "--plant tree for a tree"
        )


def import_scan(
    path: str | Path,
    out: str | Path,
    config: ScanImportConfig | None = None,
    *,
    report: str | Path | None = None,
    truth: str | Path | None = None,
    overwrite: bool = False,
    progress: Callable[[str], None] | None = None,
) -> tuple[Twin, ScanImport]:
    """`vinetwin import-scan`: analyses the scan, then writes the twin (and the report when
    `report` is a folder; with `truth`, a twin of the same plant, its accuracy too)."""
    from vinetwin.twin.model import TWIN_FILE, twin_from_skeleton

    config = config or ScanImportConfig()
    out = Path(out)
    if (out / TWIN_FILE).exists() and not overwrite:  # before minutes of work
        raise TwinError(f"{out}: already holds a twin; pass --overwrite to replace it")
    scan = analyse_scan(path, config, progress)
    source = {"importer": "scan", "file": str(path), "format": Path(path).suffix.lower()[1:],
              "plant": config.plant, "scan": scan.summary()}  # fmt: skip
    if config.mesh == "scan":
        twin = _twin_from_scan_mesh(out, scan, source, config, overwrite)
    else:
        twin = twin_from_skeleton(out, scan.skeleton, edge=config.edge, caps="round",
                                  source=source, cut_points=config.cut_points,
                                  overwrite=overwrite, progress=progress)  # fmt: skip
    if report is not None:
        from vinetwin.scan.report import write_report

        write_report(Path(report), scan, twin, truth)
    return twin, scan


def _twin_from_scan_mesh(
    out: Path, scan: ScanImport, source: dict[str, Any], config: ScanImportConfig, overwrite: bool
) -> Twin:
    from vinetwin.twin.model import Twin

    assert scan.mesh is not None
    V, F = scan.mesh
    twin = Twin.create(out, V, F, skeleton=scan.skeleton, source=source, overwrite=overwrite)
    cands = scan.skeleton.candidates
    if config.cut_points and cands:
        picks = np.unique(
            np.linspace(0, len(cands) - 1, min(config.cut_points, len(cands))).round().astype(int)
        )
        for i in picks:
            c = cands[i]
            cut = twin.add_cut_point(c.point, c.cane_axis, name=c.label, source="candidate")
            twin.add_pose(cut.id)
        twin.save()
    return twin


def scan_frame_pose(twin: Twin, T_vine_x: Array) -> Array:
    """A pose in the twin's vine frame given back in the scanner's frame (metres):
    T_scan_x = inv(T_vine_scan) @ T_vine_x; raises TwinError for a twin not made from a scan."""
    src = twin.provenance.get("source", {})
    try:
        T = np.asarray(src["scan"]["T_vine_scan"], dtype=np.float64).reshape(4, 4)
    except (KeyError, TypeError, ValueError) as exc:
        raise TwinError(f"{twin.root}: not imported from a scan (no T_vine_scan)") from exc
    return np.linalg.inv(T) @ T_vine_x
