"""Importers of real plant skeletons into vinetwin skeletons (then tube meshes, then twins).

Formats:

- **hydroshoot `digit.input`** (openalea/hydroshoot): `;`-separated text with a header; columns
  plant, axis (`tronc`: 0 trunk, 1, 2 cordons or arms; or `BASE`), element (internode along the
  axis; `6.A`, `1.a` name pruning complexes, i.e. spurs), cane (`sarment`), shoot (`rameau`;
  `1.2_1` is a lateral on shoot 1 at its internode 2), rank along the shoot, X Y Z in
  centimetres at the upper end of the internode, and optionally `Diam`, the stem diameter there,
  in centimetres. Each row's parent is the previous node on the same axis; the first node of an
  axis hangs from the node it grows out of (see `_parent_key`).
- **cylinder lists** (e.g. CearLab's Tree-Models-Library): one or more blocks, each a line N
  then N rows `x y z dx dy dz r` in metres: start point, axis vector (its length is the cylinder's length),
  radius. Consecutive cylinders whose start is the previous one's end form one branch. The
  Tree-Models-Library's files hold the branches, then the fruit (spheres: a vector across the
  fruit and a radius half its length), then the trellis (`TreeRead.m`): a later block of
  such spheres (at least 90% of its rows) is fruit, reported in `Skeleton.skipped` and left out.
"""

from __future__ import annotations

import logging
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Literal

import numpy as np

from vinetwin.errors import ImportFormatError
from vinetwin.frames import Array
from vinetwin.twin.skeleton import (
    Branch,
    BranchKind,
    CutCandidate,
    Skeleton,
    ancestors,
    arc_length,
    nearest_on_polyline,
)

if TYPE_CHECKING:
    from vinetwin.twin.model import Twin

log = logging.getLogger(__name__)

SkeletonFormat = Literal["hydroshoot", "cylinders"]

# Diameters (m) used when a hydroshoot file has no Diam column, by kind, base to tip.
_DEFAULT_DIAMETER: dict[str, tuple[float, float]] = {
    "trunk": (0.045, 0.035),
    "cordon": (0.030, 0.020),
    "spur": (0.018, 0.015),
    "cane": (0.014, 0.012),
    "shoot": (0.010, 0.005),
}


def detect_format(path: str | Path) -> SkeletonFormat:
    """Guesses the format of a skeleton file from its first lines."""
    try:
        with open(path, encoding="utf-8", errors="replace") as fh:
            head = [fh.readline() for _ in range(2)]
    except OSError as exc:
        raise ImportFormatError(f"{path}: cannot read: {exc}") from exc
    if ";" in head[0]:
        return "hydroshoot"
    first = head[0].split()
    second = head[1].split() if len(head) > 1 else []
    if len(first) == 1 and first[0].isdigit() and len(second) == 7:
        return "cylinders"
    raise ImportFormatError(
        f"{path}: unknown skeleton format; expected a hydroshoot digit.input (';'-separated with "
        f"a header) or a cylinder list (a count, then rows 'x y z dx dy dz r')"
    )


def load_skeleton(path: str | Path, fmt: SkeletonFormat | None = None) -> Skeleton:
    """Reads a skeleton file in `fmt` (detected when None)."""
    fmt = fmt or detect_format(path)
    if fmt == "hydroshoot":
        return read_hydroshoot(path)
    if fmt == "cylinders":
        return read_cylinders(path)
    raise ImportFormatError(
        f"unknown skeleton format '{fmt}'; choose one of: hydroshoot, cylinders"
    )


# ----------------------------------------------------------------------------- hydroshoot
@dataclass
class _Node:
    row: int
    axis: str
    element: str
    cane: str
    shoot: str
    rank: str
    xyz: Array
    diameter: float | None


def _lead_int(text: str) -> str:
    m = re.match(r"\d+", text)
    return m.group(0) if m else text


def _axis_key(n: _Node) -> tuple[str, ...]:
    """Rows sharing this key form one polyline (an 'axis' of the plant)."""
    if n.shoot != "0":
        return ("shoot", n.axis, n.element, n.cane, n.shoot)
    if n.cane != "0":
        return ("cane", n.axis, n.element, n.cane)
    if not re.fullmatch(r"\d+", n.element) and re.match(r"\d+\D", n.element):
        if re.fullmatch(r"\d+\.[A-Za-z]+", n.element):
            return ("spur", n.axis, n.element)
    return ("main", n.axis)


def _parent_key(n: _Node) -> tuple[str, ...] | None:
    """Node key (see `_node_key`) of the node the first node of n's axis grows from."""
    kind = _axis_key(n)[0]
    if kind == "shoot":
        m = re.fullmatch(r"(\w+)\.(\d+)_\d+", n.shoot)
        if m:  # lateral: grows from node `rank` of shoot `m[1]`
            return (n.axis, n.element, n.cane, m.group(1), m.group(2))
        return (n.axis, n.element, n.cane, "0", "0")
    if kind == "cane":
        return (n.axis, n.element, "0", "0", "0")
    if kind == "spur":
        return (n.axis, _lead_int(n.element), "0", "0", "0")
    return None


def _node_key(n: _Node) -> tuple[str, ...]:
    return (
        n.axis,
        _lead_int(n.element) if _axis_key(n)[0] == "main" else n.element,
        n.cane,
        n.shoot,
        n.rank,
    )


def read_hydroshoot(path: str | Path) -> Skeleton:
    """Reads a hydroshoot `digit.input` file (centimetres) into a skeleton in metres."""
    try:
        lines = Path(path).read_text(encoding="utf-8", errors="replace").splitlines()
    except OSError as exc:
        raise ImportFormatError(f"{path}: cannot read: {exc}") from exc
    lines = [ln.strip() for ln in lines if ln.strip()]
    if len(lines) < 3:
        raise ImportFormatError(f"{path}: a hydroshoot file needs a header and at least 2 rows")
    header = [h.strip().lower() for h in lines[0].split(";")]
    if len(header) < 9 or header[6:9] != ["x", "y", "z"]:
        raise ImportFormatError(
            f"{path}: header must have 9 or 10 ';'-separated columns with X;Y;Z in columns "
            f"7-9, got {lines[0]!r}"
        )
    has_diam = len(header) >= 10
    base: Array | None = None
    nodes: list[_Node] = []
    skipped: list[str] = []
    seen: dict[tuple[str, ...], int] = {}
    for i, ln in enumerate(lines[1:], start=2):
        f = [c.strip() for c in ln.split(";")]
        if len(f) < len(header):
            skipped.append(f"line {i}: expected {len(header)} fields, got {len(f)}")
            continue
        try:
            xyz = np.array([float(f[6]), float(f[7]), float(f[8])]) / 100.0
            diam = float(f[9]) / 100.0 if has_diam and f[9] not in ("", "NA") else None
        except ValueError as exc:
            skipped.append(f"line {i}: bad number: {exc}")
            continue
        if not np.all(np.isfinite(xyz)):
            skipped.append(f"line {i}: non-finite coordinate")
            continue
        if diam is not None and not (math.isfinite(diam) and diam > 0):
            skipped.append(f"line {i}: diameter {diam * 100:g} cm is not positive: default used")
            diam = None
        if f[1].upper() == "BASE":
            base = xyz
            continue
        row = tuple(f)
        if row in seen:
            skipped.append(f"line {i}: repeats line {seen[row]}")
            continue
        seen[row] = i
        nodes.append(_Node(i, f[1], f[2], f[3], f[4], f[5], xyz, diam))
    if len(nodes) < 2:  # one node is no plant
        raise ImportFormatError(
            f"{path}: fewer than 2 usable plant nodes"
            + (": " + "; ".join(skipped[:8]) if skipped else "")
        )

    by_key = {_node_key(n): n for n in nodes}
    axes: dict[tuple[str, ...], list[_Node]] = {}
    for n in nodes:
        axes.setdefault(_axis_key(n), []).append(n)
    main_axes = sorted((k for k in axes if k[0] == "main"), key=lambda k: int(_lead_int(k[1]) or 0))
    trunk_key = main_axes[0] if main_axes else None

    sk = Skeleton(skipped=skipped)
    branch_of: dict[tuple[str, ...], int] = {}
    placed: list[Array] = []

    def nearest_placed(p: Array) -> Array | None:
        if not placed:
            return None
        pts = np.concatenate(placed)
        return pts[np.argmin(np.linalg.norm(pts - p, axis=1))]

    def add_axis(key: tuple[str, ...]) -> None:
        members = axes[key]
        kind = key[0]
        first = members[0]
        start: Array | None
        parent_idx = -1
        if kind == "main":
            if key == trunk_key:
                start = base
            else:  # a cordon or arm grows from the top of the trunk
                start = axes[trunk_key][-1].xyz if trunk_key else None
                parent_idx = branch_of.get(trunk_key, -1) if trunk_key else -1
        else:
            pk = _parent_key(first)
            parent = by_key.get(pk) if pk else None
            start = parent.xyz if parent is not None else nearest_placed(first.xyz)
            if parent is not None:
                parent_idx = branch_of.get(_axis_key(parent), -1)
        pts, diams = [], []
        for m in members:  # a node repeating the previous position adds nothing
            if pts and np.linalg.norm(m.xyz - pts[-1]) <= 1e-9:
                skipped.append(f"line {m.row}: at the same position as the node before: merged")
                continue
            pts.append(m.xyz)
            diams.append(m.diameter)
        first_node = 0  # the axis's own rows are its nodes; a start hung from the parent is not
        if start is not None and np.linalg.norm(start - pts[0]) > 1e-9:
            pts = [start, *pts]
            diams = [diams[0], *diams]
            first_node = 1
        label = "/".join(key[1:]) if len(key) > 1 else kind
        bkind: BranchKind = {"main": "trunk" if key == trunk_key else "cordon"}.get(kind, kind)  # type: ignore[assignment]
        if all(d is not None for d in diams):
            radii = 0.5 * np.asarray(diams, dtype=np.float64)
        else:
            d0, d1 = _DEFAULT_DIAMETER[bkind]
            radii = 0.5 * np.linspace(d0, d1, len(pts))
        if len(pts) < 2:
            # a single node with nothing to hang from: a short stub along +Z
            pts = [pts[0], pts[0] + np.array([0, 0, 2 * radii[0] + 1e-3])]
            radii = np.repeat(radii[:1], 2)
        branch_of[key] = len(sk.branches)
        nodes = arc_length(np.asarray(pts))[first_node:] if bkind in ("shoot", "cane") else []
        sk.branches.append(Branch(np.asarray(pts), np.asarray(radii), kind=bkind,
                                  parent=parent_idx, label=label, nodes=np.asarray(nodes)))  # fmt: skip
        placed.append(np.asarray(pts))

    order = {"main": 0, "spur": 1, "cane": 2, "shoot": 3}
    for key in sorted(axes, key=lambda k: (order[k[0]], min(n.row for n in axes[k]))):
        add_axis(key)

    # Cut-point candidates: on shoots (next year's canes) whose base has at least 3 nodes,
    # 30% of the way from the second node to the third (a two-bud spur).
    for key, idx in branch_of.items():
        if key[0] != "shoot" or "_" in key[-1]:
            continue
        b = sk.branches[idx]
        if len(b.points) < 4:
            continue
        p2, p3 = b.points[2], b.points[3]
        axis = p3 - p2
        norm = np.linalg.norm(axis)
        if norm < 1e-6:
            continue
        sk.candidates.append(
            CutCandidate(
                point=p2 + 0.3 * axis,
                cane_axis=axis / norm,
                branch=idx,
                radius=float(0.5 * (b.radii[2] + b.radii[3])),
                label=b.label,
            )
        )
    return sk


# ----------------------------------------------------------------------------- cylinders
def read_cylinders(path: str | Path) -> Skeleton:
    """Reads a cylinder list (metres) into a skeleton; chains of touching cylinders become
    one branch each.

    Real files have degenerate elements. What cannot be used is skipped and reported in
    `Skeleton.skipped` with its line number: a line that is not a count or 7 numbers, a
    non-finite value, a radius <= 0, a zero-length cylinder, a row repeating an earlier one, a
    block repeating an earlier block, a block with fewer rows than it announces (its rows are
    kept), a later block of fruit (see the module's docstring). Disconnected pieces become
    separate branches. Only a file with nothing usable left
    fails, with the reasons.

    Cut-point candidates (`Skeleton.candidates`), the rule for cylinder trees: every branch
    that grows out of another (its first point within 2 radii of another branch's axis) and is
    at least 4 cm long gets one, `CANDIDATE_OFFSET` (3 cm) from its base along its axis, where a
    pruner heads back a lateral; the tree's root branch gets none."""
    try:
        lines = Path(path).read_text(encoding="utf-8", errors="replace").splitlines()
    except OSError as exc:
        raise ImportFormatError(f"{path}: cannot read: {exc}") from exc
    skipped: list[str] = []
    blocks: list[list[tuple[int, tuple[float, ...]]]] = []
    k = 0
    while k < len(lines):
        toks = lines[k].split()
        k += 1
        if not toks:
            continue
        if len(toks) != 1:
            skipped.append(f"line {k}: expected a cylinder count, got {lines[k - 1].strip()!r:.60}")
            continue
        try:
            n = int(toks[0])
        except ValueError:
            skipped.append(f"line {k}: expected a cylinder count, got {toks[0]!r:.60}")
            continue
        head, block = k, []
        while len(block) < n and k < len(lines):
            row = lines[k].split()
            if len(row) == 1:  # the next block's count: this block is short
                break
            k += 1
            if not row:
                continue
            if len(row) != 7:
                skipped.append(f"line {k}: expected 7 numbers 'x y z dx dy dz r', got {len(row)}")
                continue
            try:
                block.append((k, tuple(float(v) for v in row)))
            except ValueError:
                skipped.append(f"line {k}: not a number in {lines[k - 1].strip()!r:.60}")
        if len(block) < n:
            skipped.append(
                f"line {head}: a block announces {n} cylinders, so {7 * n} numbers should "
                f"follow; got {7 * len(block)} (the rows present are kept)"
            )
        if block and any([r for _, r in block] == [r for _, r in b] for b in blocks):
            skipped.append(f"line {head}: a block of {n} cylinders repeats an earlier block")
            continue
        if blocks and block and np.mean([_is_sphere(r) for _, r in block]) >= 0.9:
            skipped.append(f"line {head}: a block of {len(block)} fruit (spheres: each radius "
                           "half its length), not wood")  # fmt: skip
            continue
        blocks.append(block)
    rows: list[tuple[int, Array]] = []
    seen: dict[tuple[float, ...], int] = {}
    for block in blocks:
        for line, r in block:
            c = np.asarray(r)
            if not np.all(np.isfinite(c)):
                skipped.append(f"line {line}: non-finite value")
            elif c[6] <= 0:
                skipped.append(f"line {line}: non-positive radius {c[6]:g}")
            elif np.linalg.norm(c[3:6]) < 1e-9:
                skipped.append(f"line {line}: zero-length cylinder")
            elif r in seen:
                skipped.append(f"line {line}: repeats line {seen[r]}")
            else:
                seen[r] = line
                rows.append((line, c))
    if not rows:
        raise ImportFormatError(
            f"{path}: no usable cylinders"
            + (": " + "; ".join(skipped[:8]) if skipped else " (empty file)")
        )
    cyl = np.array([c for _, c in rows])
    line_of = [ln for ln, _ in rows]
    starts, axes, radii = cyl[:, :3], cyl[:, 3:6], cyl[:, 6]
    ends = starts + axes
    n = len(cyl)
    sk = Skeleton(skipped=skipped)
    i = 0
    while i < n:
        j = i
        while (
            j + 1 < n
            and np.linalg.norm(starts[j + 1] - ends[j]) < 1e-6
            and abs(radii[j + 1] - radii[j]) <= 0.5 * radii[j]
        ):
            j += 1
        pts = np.concatenate([starts[i : i + 1], ends[i : j + 1]])
        r = np.concatenate([radii[i : i + 1], radii[i : j + 1]])
        sk.branches.append(Branch(pts, r, kind="branch", label=f"lines {line_of[i]}-{line_of[j]}"))
        i = j + 1
    _cylinder_candidates(sk)
    return sk


def _is_sphere(row: tuple[float, ...]) -> bool:
    """A Tree-Models-Library fruit: its file's second block (`TreeRead.m`: branches, then fruit,
    then trellis) holds spheres as a start, a vector across the fruit and a radius half its
    length, rounded in the file to a few per cent (a block of at least 90% such rows is fruit)."""
    length = math.sqrt(row[3] ** 2 + row[4] ** 2 + row[5] ** 2)
    return length > 0 and abs(row[6] - 0.5 * length) <= 0.03 * row[6]


#: Where a cylinder tree's cut-point candidate sits on a lateral: this far from its base (m).
CANDIDATE_OFFSET = 0.03


def _cylinder_candidates(sk: Skeleton) -> None:
    """Parents and the candidates of `read_cylinders`' rule. A branch's parent is the branch
    whose axis passes nearest its first point (within 2 radii), among the branches before it
    in the file when one is that near (cylinder lists, Tree-Models-Library's and TreeQSM's,
    write a parent before its children), else among those that do not make a loop: where two
    laterals leave one point, each one's start lies on the other, and the nearest alone made the
    two each other's parent (41 of the nectarine's 437 branches were in such loops)."""
    for idx, b in enumerate(sk.branches):
        base = b.points[0]
        tol = 2 * max(float(b.radii[0]), 1e-3) + 1e-3
        d = np.array([float(np.linalg.norm(nearest_on_polyline(base, o.points)[2] - base))
                      if k != idx else np.inf for k, o in enumerate(sk.branches)])  # fmt: skip
        best = int(np.argmin(d[:idx])) if idx else -1
        if best < 0 or d[best] > tol:
            best = next((int(k) for k in np.argsort(d) if d[k] <= tol
                         and idx not in ancestors(sk, int(k))), -1)  # fmt: skip
        if best < 0:
            continue
        b.parent = best
        if b.length < 0.04:
            continue
        seg = np.linalg.norm(np.diff(b.points, axis=0), axis=1)
        s = np.concatenate([[0.0], np.cumsum(seg)])
        at = min(CANDIDATE_OFFSET, 0.5 * s[-1])
        m = int(np.searchsorted(s, at, side="right") - 1)
        m = min(max(m, 0), len(seg) - 1)
        while seg[m] < 1e-9 and m + 1 < len(seg):
            m += 1
        axis = (b.points[m + 1] - b.points[m]) / seg[m]
        point = b.points[m] + (at - s[m]) * axis
        sk.candidates.append(
            CutCandidate(point, axis, branch=idx, radius=float(b.radii[m]), label=b.label)
        )


@dataclass(frozen=True, kw_only=True)
class ImportVineConfig:
    """How `vinetwin import-vine` reads and meshes a skeleton file."""

    format: Literal["auto", "hydroshoot", "cylinders"] = "auto"
    """File format; auto detects it from the first lines."""
    edge: float = 0.003
    """Target triangle edge length of the tube mesh, metres."""
    cut_points: int = 0
    """How many cut-point candidates (hydroshoot shoots) become cut points with a pose."""


def import_twin(
    path: str | Path,
    out: str | Path,
    fmt: SkeletonFormat | Literal["auto"] = "auto",
    *,
    edge: float = 0.003,
    cut_points: int = 0,
    overwrite: bool = False,
) -> Twin:
    """`vinetwin import-vine`: a skeleton file (format detected with "auto") meshed and written
    as a twin folder, its first `cut_points` candidates made cut points with pruning poses."""
    from vinetwin.twin.model import twin_from_skeleton

    kind = detect_format(path) if fmt == "auto" else fmt
    sk = load_skeleton(path, kind)
    for what in sk.skipped:
        log.warning("%s: %s", path, what)
    if sk.skipped:
        log.warning("%s: %d elements skipped (listed above)", path, len(sk.skipped))
    source = {"importer": kind, "file": str(path), "skipped": sk.skipped}
    return twin_from_skeleton(
        out, sk, edge=edge, caps="round" if kind == "hydroshoot" else "flat", source=source,
        cut_points=cut_points, overwrite=overwrite,
    )  # fmt: skip
