"""`vinetwin fidelity TRUE_TWIN`: how good must a twin be for the servo to land within a given
error at the cut? The whole chain against a truth, over a sweep of the twin's quality.

Each sweep point is one twin quality (capture size, capture pose noise, fusion voxel). For it:

1. a synthetic D405 capture of the true vine whose recorded poses carry the capture's error,
   fused into a twin by the TSDF pipeline of `vinetwin reconstruct`, scored against the truth
   (Chamfer distance, F-score at 2 mm) (`sim.field.reconstructed_twin`);
2. the cut points and pruning poses carried across *in the vine frame*: the capture's poses are
   in that frame, so the rebuilt mesh is too, and a pose keeps its meaning (15 cm from the same
   cut point). Re-picking the cut at the nearest point of the rebuilt mesh would hide part of
   the twin's error from the measurement, which is what this command measures;
3. the references rendered from the rebuilt twin, and the servo run on the true vine under the
   chosen error profile (`--profile field`: every other source too) from the preset's starts,
   per ICP variant (a campaign, `sim.campaign`, whose report is kept in `pointK/`);
4. the final error of the camera and of the cut point in the camera (tool) frame, against the
   truth.

`fidelity.md` tabulates each point (twin quality, its Chamfer and F-score, per variant the
median final camera and cut-point errors and the runs converged); `fidelity.png` plots the final
errors against the twin's Chamfer distance and F-score; the middle point's campaign adds the
ablation (each error source alone, per variant) and the ideal grid beside it.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from vinetwin.files import atomic_write_json, atomic_write_text, save_figure
from vinetwin.sim.campaign import run_campaign
from vinetwin.sim.config import CampaignConfig, FidelityConfig, load_profile
from vinetwin.sim.report import COLORS, _plt
from vinetwin.twin.model import Twin


def sweep_points(cfg: FidelityConfig) -> list[tuple[int, float, float]]:
    """(frames, pose noise, voxel) of each point: each axis swept at the others' middle values."""
    mid = (
        cfg.frames[len(cfg.frames) // 2],
        cfg.pose_noise[len(cfg.pose_noise) // 2],
        cfg.voxels[len(cfg.voxels) // 2],
    )
    points = [(f, mid[1], mid[2]) for f in cfg.frames]
    points += [(mid[0], n, mid[2]) for n in cfg.pose_noise]
    points += [(mid[0], mid[1], v) for v in cfg.voxels]
    return list(dict.fromkeys(points))


def _median(values: list[float]) -> float:
    v = [x for x in values if math.isfinite(x)]
    return float(np.median(v)) if v else math.nan


def _variant_stats(data: dict[str, Any], group: str) -> dict[str, dict[str, Any]]:
    out: dict[str, dict[str, Any]] = {}
    for r in data["runs"]:
        if r["group"] != group:
            continue
        s = r["summary"]
        out.setdefault(s["variant"], {"runs": []})["runs"].append(s)
    for stats in out.values():
        runs = stats.pop("runs")
        stats["final_translation_mm"] = 1000 * _median([s["final_translation"] for s in runs])
        stats["final_rotation"] = _median([s["final_rotation"] for s in runs])
        stats["final_cut_mm"] = 1000 * _median([s.get("final_cut_error", math.nan) for s in runs])
        stats["converged"] = f"{sum(s['converged'] for s in runs)}/{len(runs)}"
    return out


def run_fidelity(
    twin: Twin,
    cfg: FidelityConfig,
    out_dir: Path,
    progress: Callable[[dict[str, Any], int, int], None] | None = None,
) -> dict[str, Any]:
    """Runs the sweep into `out_dir` (resumable: each point's campaign keeps its runs)."""
    base = load_profile(cfg.profile)
    sources = tuple(dict.fromkeys(("twin", *base.sources)))
    points = sweep_points(cfg)
    middle = points[len(cfg.frames) // 2]
    rows, ideal = [], {}
    for k, (frames, noise, voxel) in enumerate(points):
        where = out_dir / f"point{k}"
        where.mkdir(parents=True, exist_ok=True)
        prof = replace(
            base, sources=sources, twin_frames=frames, twin_pose_noise_translation=noise,
            twin_pose_noise_rotation=2.0 * noise, twin_voxel=voxel,
            twin_trajectory=cfg.trajectory,
        )  # fmt: skip
        pfile = where / "profile.json"
        atomic_write_text(pfile, json.dumps(prof.to_dict(), indent=1))
        first = (frames, noise, voxel) == middle
        campaign = CampaignConfig(
            preset=cfg.preset, variants=cfg.variants, duration=cfg.duration, profile=str(pfile),
            profile_comparison=first, ablation=cfg.ablation and first, disturbance=False,
            guess_comparison=False, law_comparison=False, seed=cfg.seed, workers=cfg.workers,
        )  # fmt: skip
        data = run_campaign(twin, campaign, where, progress)
        if first:
            ideal = _variant_stats(data, "ideal")
        ev = data.get("field_twin") or {}
        rows.append(
            {
                "point": k, "frames": frames, "pose_noise_mm": 1000 * noise,
                "voxel_mm": 1000 * voxel, "chamfer_mm": ev.get("chamfer_mm", math.nan),
                "fscore_2mm": ev.get("fscore@2mm", math.nan),
                "variants": _variant_stats(data, "grid"), "report": f"point{k}/report.md",
            }
        )  # fmt: skip
    result = {
        "twin": twin.name, "config": cfg.to_dict(), "sources": list(sources), "ideal": ideal,
        "points": rows,
        "ablation_report": f"point{points.index(middle)}/report.md" if cfg.ablation else None,
    }  # fmt: skip
    atomic_write_json(out_dir / "fidelity.json", result)
    write_fidelity_report(result, out_dir)
    return result


def write_fidelity_report(result: dict[str, Any], out_dir: Path) -> None:
    """fidelity.md and fidelity.png."""
    variants = list(result["config"]["variants"])
    head = "| frames | capture noise (mm / mrad) | voxel (mm) | Chamfer (mm) | F-score@2mm | "
    head += " | ".join(f"{v}: camera / cut (mm), converged" for v in variants) + " |"
    lines = [
        f"# Twin fidelity: {result['twin']}\n",
        "The servo on the true vine with references rendered from twins rebuilt from synthetic "
        f"captures of it (error sources: {', '.join(result['sources'])}). Final error: median "
        "over the runs of each run's median true error over its last 0.5 s, of the camera and of "
        "the cut point in the camera (tool) frame. Converged: within the profile's settled band.\n",
        head,
        "|---" * (5 + len(variants)) + "|",
    ]

    def cell(s: dict[str, Any] | None) -> str:
        if not s:
            return "-"
        return (f"{s['final_translation_mm']:.2f} / {s['final_cut_mm']:.2f}, "
                f"{s['converged']}")  # fmt: skip

    if result.get("ideal"):
        lines.append("| the true mesh, ideal profile | - | - | 0 | 1 | "
                     + " | ".join(cell(result["ideal"].get(v)) for v in variants) + " |")  # fmt: skip
    for r in result["points"]:
        noise = r["pose_noise_mm"]
        lines.append(
            f"| {r['frames']} | {noise:.1f} / {2 * noise:.1f} | {r['voxel_mm']:.1f} | "
            f"{r['chamfer_mm']:.2f} | {r['fscore_2mm']:.3f} | "
            + " | ".join(cell(r["variants"].get(v)) for v in variants) + " |"
        )  # fmt: skip
    ablation = result.get("ablation_report")
    lines += [
        "\nEach point's campaign report: `pointK/report.md`; the ablation (each error source "
        "alone, per variant): "
        + (f"[{ablation}]({ablation})" if ablation else "not run for this vine")
        + ".\n",
        "![final error against the twin's quality](fidelity.png)\n",
    ]
    atomic_write_text(out_dir / "fidelity.md", "\n".join(lines))
    plt = _plt()
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    pts = sorted(result["points"], key=lambda r: r["chamfer_mm"])
    for v in variants:
        x = [r["chamfer_mm"] for r in pts]
        f = [r["fscore_2mm"] for r in pts]
        cam = [r["variants"].get(v, {}).get("final_translation_mm", math.nan) for r in pts]
        cut = [r["variants"].get(v, {}).get("final_cut_mm", math.nan) for r in pts]
        axes[0].plot(x, cam, "o", color=COLORS.get(v), label=f"{v}: camera")
        axes[0].plot(x, cut, "s", mfc="none", color=COLORS.get(v), label=f"{v}: cut point")
        order = np.argsort(f)
        axes[1].plot(np.asarray(f)[order], np.asarray(cam)[order], "o", color=COLORS.get(v))
        ideal = result.get("ideal", {}).get(v)
        if ideal:
            axes[0].plot([0.0], [ideal["final_translation_mm"]], "*", ms=11, color=COLORS.get(v))
    axes[0].set_xlabel("twin Chamfer distance to the true vine (mm); star: the true mesh")
    axes[0].set_ylabel("final error (mm)")
    axes[1].set_xlabel("twin F-score at 2 mm")
    axes[1].set_ylabel("final camera error (mm)")
    for ax in axes:
        ax.grid(True, alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.suptitle(f"{result['twin']}: final error against the twin's quality", fontsize=11)
    fig.tight_layout()
    save_figure(fig, out_dir / "fidelity.png", 110)
    plt.close(fig)
