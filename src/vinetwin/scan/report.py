"""The report of an import (`vinetwin import-scan ... --report DIR`): what was read and removed,
the skeleton over the points (a picture from the front and from the side), each branch's length
and radius, the cut candidates, and with a truth twin the accuracy (`scan.evaluate`).

Files: `report.md` (for people), `report.json` (the same figures), `skeleton.png`, and
`removed.ply` (the removed points coloured by reason: stray red, ground brown, clutter green,
wire blue, post grey, apart orange, other plants of a row purple) to look at in any viewer."""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from vinetwin.files import atomic_write_text, save_figure
from vinetwin.frames import Array
from vinetwin.scan.result import REMOVED
from vinetwin.twin.skeleton import Skeleton

if TYPE_CHECKING:
    from vinetwin.scan.result import ScanImport
    from vinetwin.twin.model import Twin

KIND_COLOURS = {"trunk": "#5b3a1a", "cordon": "#a0522d", "spur": "#d2691e", "cane": "#2e8b57",
                "shoot": "#7cfc00", "branch": "#1f77b4"}  # fmt: skip
REMOVED_COLOURS = {"stray": (1, 0, 0), "ground": (0.55, 0.35, 0.15), "clutter": (0.4, 0.7, 0.2),
                   "wire": (0, 0, 1), "post": (0.5, 0.5, 0.5), "apart": (1, 0.6, 0),
                   "others": (0.6, 0.2, 0.8)}  # fmt: skip


def plot_skeleton(
    path: Path,
    points: Array,
    sk: Skeleton,
    title: str,
    truth: Skeleton | None = None,
    removed: dict[str, Array] | None = None,
) -> None:
    """Front (x-z) and side (y-z) views: the points in grey, removed points in their colours,
    the skeleton by kind, its cut candidates as red crosses, the truth (when given) dashed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D

    rng = np.random.default_rng(0)
    pts = points if len(points) <= 60_000 else points[rng.choice(len(points), 60_000, False)]
    fig, axes = plt.subplots(1, 2, figsize=(16, 8), gridspec_kw={"width_ratios": [2, 1]})
    for ax, (i, j, name) in zip(axes, ((0, 2, "front (x-z)"), (1, 2, "side (y-z)")), strict=True):
        ax.scatter(pts[:, i], pts[:, j], s=0.3, c="#b0b0b0", linewidths=0)
        for why, q in (removed or {}).items():
            if len(q):
                q = q if len(q) <= 20_000 else q[rng.choice(len(q), 20_000, False)]
                ax.scatter(q[:, i], q[:, j], s=0.5, color=REMOVED_COLOURS.get(why, (0, 0, 0)),
                           linewidths=0, label=f"removed: {why}")  # fmt: skip
        if truth is not None:
            for b in truth.branches:
                ax.plot(b.points[:, i], b.points[:, j], "k--", lw=0.7, alpha=0.7)
        for b in sk.branches:
            ax.plot(b.points[:, i], b.points[:, j], color=KIND_COLOURS.get(b.kind, "m"), lw=1.4)
        if sk.candidates:
            c = np.array([c.point for c in sk.candidates])
            ax.plot(c[:, i], c[:, j], "rx", ms=7, mew=2)
        ax.set_aspect("equal")
        ax.set_title(name)
        ax.set_xlabel("xyz"[i] + " (m)")
        ax.set_ylabel("z (m)")
    handles = [Line2D([], [], color=c, lw=2, label=k) for k, c in KIND_COLOURS.items()
               if any(b.kind == k for b in sk.branches)]  # fmt: skip
    handles.append(Line2D([], [], color="r", marker="x", ls="", label="cut candidate"))
    if truth is not None:
        handles.append(Line2D([], [], color="k", ls="--", label="truth"))
    axes[0].legend(handles=handles, loc="upper left", fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
    plt.close(fig)


def write_removed(path: Path, removed: dict[str, Array]) -> None:
    from vinetwin import _lazy

    o3d = _lazy.open3d()

    pts = [q for q in removed.values() if len(q)]
    if not pts:
        return
    cols = [np.tile(REMOVED_COLOURS[k], (len(q), 1)) for k, q in removed.items() if len(q)]
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.concatenate(pts)))
    pc.colors = o3d.utility.Vector3dVector(np.concatenate(cols))
    tmp = path.with_suffix(".tmp.ply")
    o3d.io.write_point_cloud(str(tmp), pc, write_ascii=False)
    tmp.replace(path)


def branch_table(sk: Skeleton) -> list[dict[str, Any]]:
    return [{"branch": i, "kind": b.kind, "parent": b.parent, "length_m": round(b.length, 4),
             "radius_base_mm": round(float(b.radii[0]) * 1000, 2),
             "radius_median_mm": round(float(np.median(b.radii)) * 1000, 2)}
            for i, b in enumerate(sk.branches)]  # fmt: skip


def write_report(folder: Path, scan: ScanImport, twin: Twin, truth: str | Path | None) -> None:
    """Writes the report's files into `folder` (made when missing)."""
    folder.mkdir(parents=True, exist_ok=True)
    summary = scan.summary()
    data: dict[str, Any] = {
        "twin": str(twin.root),
        **summary,
        "branches": branch_table(scan.skeleton),
    }
    truth_sk = None
    if truth is not None:
        from vinetwin.scan.evaluate import mesh_accuracy, skeleton_accuracy
        from vinetwin.twin.model import Twin as _Twin

        t = _Twin.load(truth)
        truth_sk = t.load_skeleton()
        if truth_sk is None:
            from vinetwin.errors import TwinError

            raise TwinError(f"{truth}: the truth twin has no skeleton.json")
        plant = twin.provenance.get("source", {}).get("plant", "vine")
        acc = skeleton_accuracy(scan.skeleton, truth_sk, plant, 0.07, scan_points=scan.points)
        from vinetwin.mesh import load_mesh_arrays

        acc.chamfer_mm, acc.fscore_2mm = mesh_accuracy(*load_mesh_arrays(twin.mesh_path),
                                                       *load_mesh_arrays(t.mesh_path))  # fmt: skip
        data["accuracy"] = acc.to_dict()
        data["accuracy_note"] = ("the truth is taken in the twin's vine frame: a truth in another "
                                 "frame (a scan's) must be imported with the same frame")  # fmt: skip
    plot_skeleton(folder / "skeleton.png", scan.points, scan.skeleton,
                  f"{Path(str(summary.get('file', twin.root))).name}: {len(scan.skeleton.branches)} "
                  f"branches, {len(scan.skeleton.candidates)} cut candidates",
                  truth=truth_sk, removed=scan.removed)  # fmt: skip
    write_removed(folder / "removed.ply", scan.removed)
    atomic_write_text(folder / "report.json", json.dumps(data, indent=1))
    atomic_write_text(folder / "report.md", _markdown(data))


def _markdown(d: dict[str, Any]) -> str:
    c = d["counts"]
    lines = [
        f"# Scan import: {d['twin']}",
        "",
        f"- units: {d['units_note']}",
        f"- up axis from {d['up_from']}; point spacing {d['point_spacing_m'] * 1000:.2f} mm",
        f"- points read {c['read']}, kept {c['kept']}; removed: "
        + ", ".join(f"{k} {c[k]}" for k in REMOVED),
        *[f"- {n}" for n in d.get("notes", [])],
        f"- skeleton: {d['skeleton']['branches']} branches, {d['skeleton']['candidates']} cut "
        f"candidates, {d['skeleton']['bridges']} gaps bridged (voxel "
        f"{d['skeleton']['voxel_m'] * 1000:.2f} mm, slices {d['skeleton']['bin_m'] * 1000:.1f} mm)",
        f"- seconds: {d['seconds']}",
        "",
        "![skeleton](skeleton.png)",
        "",
    ]
    if "accuracy" in d:
        lines += ["## Against the truth", "", "| measure | value |", "|---|---|"]
        lines += [f"| {k} | {v:.3g} |" if isinstance(v, float) else f"| {k} | {v} |"
                  for k, v in d["accuracy"].items()]  # fmt: skip
        lines.append("")
    lines += ["## Branches", "", "| branch | kind | parent | length m | radius at base mm | median radius mm |",
              "|---|---|---|---|---|---|"]  # fmt: skip
    lines += [f"| {b['branch']} | {b['kind']} | {b['parent']} | {b['length_m']} | "
              f"{b['radius_base_mm']} | {b['radius_median_mm']} |" for b in d["branches"]]  # fmt: skip
    return "\n".join(lines) + "\n"
