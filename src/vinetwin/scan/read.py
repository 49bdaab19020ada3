"""Reading scans: point clouds (PCD, PLY, XYZ/TXT/CSV, LAS/LAZ, E57) and meshes (PLY, OBJ, STL,
GLB/GLTF, OFF), and the units they are in.

Every reader returns a `ScanData` in the file's own units and frame; `detect_units` then says
which unit makes the scan a plant (`config.PLANT_EXTENT`, `config.POINT_SPACING`). Files with
more than `max_points` points are decimated while they are read (every k-th point), so memory
stays bounded; the decimation is named in `ScanData.notes`."""

from __future__ import annotations

import io
import itertools
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from vinetwin.errors import ScanError
from vinetwin.frames import Array
from vinetwin.scan.config import (
    AUTO_UNITS,
    MIN_POINTS,
    PLANT_EXTENT,
    POINT_SPACING,
    ROW_EXTENT,
    UNIT_SCALE,
)

CLOUD_SUFFIXES = (".pcd", ".xyz", ".txt", ".csv", ".pts", ".asc", ".las", ".laz", ".e57")
MESH_SUFFIXES = (".obj", ".stl", ".glb", ".gltf", ".off")
SUFFIXES = (*CLOUD_SUFFIXES, ".ply", *MESH_SUFFIXES)


@dataclass
class ScanData:
    """What a scan file holds, in its own units and frame."""

    points: Array
    """(N, 3) float64 points (for a mesh: points sampled on its surface)."""
    colors: Array | None = None
    """(N, 3) float in [0, 1], when the file has colours."""
    mesh: tuple[Array, np.ndarray] | None = None
    """(vertices, faces) when the file is a mesh."""
    format: str = ""
    notes: list[str] = field(default_factory=list)
    """What the reader did that a user should know (rows skipped, decimation)."""
    read: int = 0
    """Points (or vertices) in the file before NaN rows and decimation."""


def read_scan(path: str | Path, max_points: int) -> ScanData:
    """Reads a scan file by its suffix; raises ScanError naming the file and what is wrong."""
    path = Path(path)
    if not path.is_file():
        raise ScanError(f"{path}: no such file")
    suffix = path.suffix.lower()
    if suffix not in SUFFIXES:
        raise ScanError(
            f"{path}: unknown scan format '{suffix}'; point clouds: .pcd .ply .xyz .txt .csv .pts "
            f".asc .las .laz .e57; meshes: .ply .obj .stl .glb .gltf .off"
        )
    if path.stat().st_size == 0:
        raise ScanError(f"{path}: the file is empty")
    try:
        if suffix == ".pcd":
            data = _read_open3d(path, "pcd")
        elif suffix == ".ply":
            data = _read_ply(path)
        elif suffix in (".las", ".laz"):
            data = _read_las(path, max_points)
        elif suffix == ".e57":
            data = _read_e57(path)
        elif suffix in MESH_SUFFIXES:
            data = _read_mesh(path, suffix[1:])
        else:
            data = _read_text(path, max_points)
    except ScanError:
        raise
    except (OSError, ValueError, RuntimeError, KeyError, IndexError) as exc:
        raise ScanError(f"{path}: cannot read it as {suffix[1:].upper()}: {exc}") from exc
    return _finish(path, data, max_points)


def _finish(path: Path, data: ScanData, max_points: int) -> ScanData:
    pts = np.asarray(data.points, dtype=np.float64).reshape(-1, 3)
    data.read = data.read or len(pts)
    ok = np.asarray(np.isfinite(pts).all(axis=1), dtype=bool)
    if not ok.all():
        data.notes.append(f"{int((~ok).sum())} points with NaN or infinite coordinates dropped")
    pts = pts[ok]
    colors = data.colors[ok] if data.colors is not None and len(data.colors) == len(ok) else None
    if len(pts) > max_points:
        step = math.ceil(len(pts) / max_points)
        data.notes.append(f"decimated: every {step}th of {len(pts)} points kept (max_points)")
        pts = pts[::step]
        colors = colors[::step] if colors is not None else None
    if len(pts) < MIN_POINTS:
        raise ScanError(
            f"{path}: {len(pts)} usable points (of {data.read} read); a plant scan needs at "
            f"least {MIN_POINTS}"
        )
    data.points, data.colors = pts, colors
    return data


# ---------------------------------------------------------------------------- point clouds
def _read_open3d(path: Path, fmt: str) -> ScanData:
    from vinetwin import _lazy

    o3d = _lazy.open3d()

    pc = o3d.io.read_point_cloud(str(path), format=fmt, print_progress=False)
    pts = np.asarray(pc.points)
    if len(pts) == 0:
        raise ScanError(f"{path}: no points could be read (an empty or corrupt {fmt.upper()})")
    colors = np.asarray(pc.colors) if pc.has_colors() else None
    return ScanData(pts, colors, format=fmt)


def _ply_face_count(path: Path) -> int:
    with open(path, "rb") as fh:
        head = fh.read(4096)
    if not head.startswith(b"ply"):
        raise ScanError(f"{path}: not a PLY file (it does not start with 'ply')")
    m = re.search(rb"element\s+face\s+(\d+)", head.split(b"end_header")[0])
    return int(m.group(1)) if m else 0


def _read_ply(path: Path) -> ScanData:
    if _ply_face_count(path) > 0:
        return _read_mesh(path, "ply")
    return _read_open3d(path, "ply")


def _read_mesh(path: Path, fmt: str) -> ScanData:
    import trimesh

    loaded: Any = trimesh.load(str(path), force="mesh", process=False)
    V = np.asarray(getattr(loaded, "vertices", np.zeros((0, 3))), dtype=np.float64)
    F = np.asarray(getattr(loaded, "faces", np.zeros((0, 3))), dtype=np.int64).reshape(-1, 3)
    if len(V) == 0:
        raise ScanError(f"{path}: the mesh has no vertices")
    if len(F) == 0:  # a vertex-only file: a point cloud
        return ScanData(V, format=fmt)
    if not np.isfinite(V).all():
        raise ScanError(f"{path}: the mesh has NaN or infinite vertices")
    return ScanData(V, mesh=(V, F), format=f"{fmt} mesh", read=len(V))


def sample_mesh_surface(V: Array, F: np.ndarray, spacing: float, rng: np.random.Generator) -> Array:
    """Points on a mesh's surface, about `spacing` apart (area-weighted, at most 2 million)."""
    tri = V[F]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    n = int(min(2_000_000, max(MIN_POINTS * 10, area.sum() / spacing**2)))
    pick = rng.choice(len(F), size=n, p=area / area.sum())
    u, v = rng.random((2, n))
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    t = tri[pick]
    return t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + v[:, None] * (t[:, 2] - t[:, 0])


def _read_las(path: Path, max_points: int) -> ScanData:
    try:
        import laspy
    except ImportError as exc:
        raise ScanError(
            f"{path}: reading LAS/LAZ needs laspy (pip install 'vinetwin[scan]')"
        ) from exc
    with laspy.open(str(path)) as fh:
        total = int(fh.header.point_count)
        step = max(1, math.ceil(total / max_points))
        parts, cols = [], []
        for chunk_ in fh.chunk_iterator(1_000_000):
            chunk: Any = chunk_
            xyz = np.column_stack([chunk.x, chunk.y, chunk.z]).astype(np.float64)[::step]
            parts.append(xyz)
            names = set(chunk.point_format.dimension_names)
            if {"red", "green", "blue"} <= names:
                rgb = np.column_stack([chunk.red, chunk.green, chunk.blue]).astype(np.float64)
                cols.append(rgb[::step] / max(1.0, float(rgb.max(initial=1.0))))
    pts = np.concatenate(parts) if parts else np.zeros((0, 3))
    data = ScanData(pts, np.concatenate(cols) if cols else None, format="las", read=total)
    if step > 1:
        data.notes.append(f"decimated: every {step}th of {total} points kept (max_points)")
    return data


def _read_e57(path: Path) -> ScanData:
    try:
        import pye57
    except ImportError as exc:
        raise ScanError(f"{path}: reading E57 needs pye57 (pip install 'vinetwin[scan]')") from exc
    e57 = pye57.E57(str(path))
    try:
        parts = []
        for i in range(e57.scan_count):
            d = e57.read_scan(i, ignore_missing_fields=True, transform=True)
            parts.append(np.column_stack([d["cartesianX"], d["cartesianY"], d["cartesianZ"]]))
    finally:
        e57.close()
    if not parts:
        raise ScanError(f"{path}: the E57 file holds no scan")
    data = ScanData(np.concatenate(parts), format="e57")
    if len(parts) > 1:
        data.notes.append(f"{len(parts)} scan positions merged with their stored poses")
    return data


def _delimiter(line: str) -> str | None:
    for d in (",", ";", "\t"):
        if d in line:
            return d
    return None  # whitespace


def _read_text(path: Path, max_points: int) -> ScanData:
    """Text points: any of , ; tab or spaces between columns; header lines (names or comments)
    skipped; columns x, y, z by name when a header names them, else the first three; extra
    columns (colour, intensity, labels) ignored, colour kept when a header names r g b."""
    with open(path, encoding="utf-8", errors="replace") as fh:
        head = list(itertools.islice(fh, 200))
    header: list[str] | None = None
    first_data = None
    for i, ln in enumerate(head):
        s = ln.strip()
        if not s:
            continue
        toks = re.split(r"[,;\t ]+", s.lstrip("/#").strip())
        if _numeric_row(toks):
            first_data = i
            break
        header = [t.strip().lower() for t in toks]
    if first_data is None:
        raise ScanError(f"{path}: no row of at least 3 numbers in its first {len(head)} lines")
    delim = _delimiter(head[first_data])
    ncols = len(_split(head[first_data], delim))
    cols = [0, 1, 2]
    rgb: list[int] | None = None
    if header and len(header) == ncols and {"x", "y", "z"} <= set(header):
        cols = [header.index(c) for c in ("x", "y", "z")]
        names = [("r", "g", "b"), ("red", "green", "blue")]
        for trio in names:
            if set(trio) <= set(header):
                rgb = [header.index(c) for c in trio]
    use = cols + (rgb or [])
    est_rows = max(1, path.stat().st_size // max(1, len(head[first_data].encode())))
    step = max(1, math.ceil(est_rows / max_points))
    parts, skipped, read = [], 0, 0
    with open(path, encoding="utf-8", errors="replace") as fh:
        for _ in range(first_data):
            next(fh)
        while True:
            block = list(itertools.islice(fh, 1_000_000))
            if not block:
                break
            read += len(block)
            rows = block[::step] if step > 1 else block
            arr, bad = _parse_rows(rows, delim, ncols, use)
            skipped += bad
            parts.append(arr)
    arr = np.concatenate(parts) if parts else np.zeros((0, len(use)))
    data = ScanData(arr[:, :3], format="text", read=read)
    if rgb is not None and len(arr):
        c = arr[:, 3:6]
        data.colors = c / (255.0 if c.max() > 1.0 else 1.0)
    if skipped:
        data.notes.append(f"{skipped} rows that are not {ncols} numbers skipped")
    if step > 1:
        data.notes.append(f"decimated: every {step}th of about {read} rows kept (max_points)")
    return data


def _split(line: str, delim: str | None) -> list[str]:
    return line.strip().split(delim) if delim else line.split()


def _numeric_row(toks: list[str]) -> bool:
    if len(toks) < 3:
        return False
    try:
        [float(t) for t in toks[:3]]
    except ValueError:
        return False
    return True


def _parse_rows(
    rows: list[str], delim: str | None, ncols: int, use: list[int]
) -> tuple[Array, int]:
    """The `use` columns of the rows with `ncols` fields; rows that do not parse are counted."""
    text = "".join(r if r.endswith("\n") else r + "\n" for r in rows)
    try:
        arr = np.loadtxt(io.StringIO(text), delimiter=delim, usecols=use, ndmin=2)
        return arr.reshape(-1, len(use)), 0
    except ValueError:
        good, bad = [], 0
        for r in rows:
            f = _split(r, delim)
            if not f:
                continue
            try:
                if len(f) != ncols:
                    raise ValueError
                good.append([float(f[c]) for c in use])
            except (ValueError, IndexError):
                bad += 1
        return np.asarray(good, dtype=np.float64).reshape(-1, len(use)), bad


# ---------------------------------------------------------------------------- units
def spacing_and_extent(points: Array, rng: np.random.Generator) -> tuple[float, float]:
    """Median nearest-neighbour distance (from up to 20k points) and the largest extent of the
    1st-99th percentile box, both in the points' units."""
    from scipy.spatial import cKDTree

    lo, hi = np.percentile(points, [1, 99], axis=0)
    extent = float((hi - lo).max())
    sample = points if len(points) <= 20_000 else points[rng.choice(len(points), 20_000, False)]
    d, _ = cKDTree(points).query(sample, k=2)
    d = d[:, 1]
    return float(np.median(d[d > 0])) if (d > 0).any() else 0.0, extent


def detect_units(
    points: Array, units: str, plant: str, rng: np.random.Generator
) -> tuple[str, str]:
    """The unit the scan is in (`units`, or the one `auto` finds) and why; raises ScanError when
    no unit (or the one named) makes a plant of this kind, or when `auto` finds several."""
    spacing, extent = spacing_and_extent(points, rng)
    lo_m, hi_m = PLANT_EXTENT[plant]
    if extent <= 0:
        raise ScanError("every point is at the same place: no plant")

    def fits(u: str, hi: float = hi_m) -> bool:
        s = UNIT_SCALE[u]
        return lo_m <= extent * s <= hi and POINT_SPACING[0] <= spacing * s <= POINT_SPACING[1]

    def sizes(u: str) -> str:
        s = UNIT_SCALE[u]
        return f"{extent * s:.3g} m across, points {1000 * spacing * s:.3g} mm apart"

    if units != "auto":  # a row of plants may be longer than one: up to ROW_EXTENT
        if not fits(units, max(hi_m, ROW_EXTENT)):
            raise ScanError(
                f"in {units} the scan would be {sizes(units)}: no {plant} (a {plant} is "
                f"{lo_m:g}-{hi_m:g} m across, a row up to {ROW_EXTENT:g} m, scanned "
                f"{1000 * POINT_SPACING[0]:g}-{1000 * POINT_SPACING[1]:g} mm apart); check --units"
            )
        return units, f"{units} as given ({sizes(units)})"
    ok = [u for u in AUTO_UNITS if fits(u)]
    if len(ok) == 1:
        return ok[0], f"{ok[0]} detected ({sizes(ok[0])})"
    if not ok:
        raise ScanError(
            "no unit makes this scan a plant: "
            + "; ".join(f"in {u}: {sizes(u)}" for u in AUTO_UNITS)
            + f" (a {plant} is {lo_m:g}-{hi_m:g} m across); name --units (a row of plants "
            "longer than one plant: its units are not guessed), or --plant tree"
        )
    raise ScanError(
        "the units are ambiguous: "
        + "; ".join(f"in {u}: {sizes(u)}" for u in ok)
        + "; name one with --units"
    )
