"""The pruning job's report: per vine a table of its cuts (done or skipped with the reason, blade
error, time and its phases), a timeline figure and a picture of the vine seen from the robot's
side with each cut coloured by its outcome; the row's summary; as Markdown, HTML and JSON."""

from __future__ import annotations

import html
import math
from pathlib import Path
from typing import Any

import numpy as np

from vinetwin.files import atomic_write_text, save_figure
from vinetwin.sim.report import _html_table, _markdown_table, _plt

PHASES = ("platform", "transit", "servo", "cut", "close", "retreat")
PHASE_COLOURS = {"platform": "tab:gray", "transit": "tab:blue", "servo": "tab:orange",
                 "cut": "tab:red", "close": "black", "retreat": "tab:purple"}  # fmt: skip


def _f(x: Any, scale: float = 1.0, digits: int = 1) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "-"
    return f"{scale * float(x):.{digits}f}"


def cut_rows(vine: dict[str, Any], tol: float) -> list[dict[str, str]]:
    rows = []
    for c in vine["cuts"]:
        err = c.get("blade_error_m")
        outcome = c["status"]
        if outcome == "done":
            outcome = "done" if err <= tol else f"done, blade {1000 * err:.1f} mm off"
        rows.append({
            "cut": c["cut"] or "-", "pose": c["pose"] or "-", "side": c.get("side", "near"),
            "stop (m)": _f(c.get("stop"), 1, 2), "outcome": outcome,
            "blade error (mm)": _f(err, 1000, 2), "time (s)": _f(c["time_s"]),
            **{f"{p} (s)": _f(c.get("phases", {}).get(p)) for p in PHASES},
            "reason": c["reason"] or "",
        })  # fmt: skip
    return rows


def summary_rows(data: dict[str, Any]) -> list[dict[str, str]]:
    rows = []
    for name, v in data["vines"].items():
        s = v["summary"]
        rows.append({
            "vine": name, "poses": str(s["poses"]), "reachable": str(s["reachable"]),
            "done": str(s["done"]), "done right": str(s["done_right"]),
            "skipped": str(s["skipped"]), "collisions": str(v["collisions"]),
            "median blade error (mm)": _f(s["median_blade_error_mm"], 1, 2),
            "median time per cut (s)": _f(s["median_time_per_cut_s"]),
            "time per vine (s)": _f(s["simulated_s"]),
            "planning (s)": _f(v["planning_s"], 1, 2),
            "x real time": _f(s["realtime_factor"]),
        })  # fmt: skip
    return rows


def plot_timeline(vine: dict[str, Any], path: Path) -> None:
    """Each cut's phases as consecutive bars along the vine's simulated time."""
    plt = _plt()
    cuts = [c for c in vine["cuts"] if c.get("phases")]
    fig, ax = plt.subplots(figsize=(10, 0.5 + 0.35 * max(1, len(cuts))))
    t = 0.0
    for i, c in enumerate(cuts):
        for p in PHASES:
            d = c["phases"].get(p, 0.0)
            if d > 0:
                ax.barh(i, d, left=t, color=PHASE_COLOURS[p], edgecolor="white", linewidth=0.3)
            t += d
    ax.set_yticks(range(len(cuts)), [f"{c['pose']} ({c['status']})" for c in cuts])
    ax.invert_yaxis()
    ax.set_xlabel("simulated time (s)")
    ax.legend(handles=[plt.Rectangle((0, 0), 1, 1, color=PHASE_COLOURS[p]) for p in PHASES],
              labels=list(PHASES), ncol=6, loc="lower center", bbox_to_anchor=(0.5, 1.0),
              fontsize=8, frameon=False)  # fmt: skip
    fig.tight_layout()
    save_figure(fig, path)
    plt.close(fig)


def plot_vine(vine: dict[str, Any], path: Path, tol: float) -> None:
    """The vine's mesh seen from the robot's side (X along the row, Z up), its cuts coloured:
    green done right, orange done with the blade off, red skipped; the platform stops below."""
    from vinetwin.twin.model import Twin

    plt = _plt()
    twin = Twin.load(vine["twin"])
    V = np.asarray(twin.load_mesh().vertices)
    if len(V) > 60000:
        V = V[np.random.default_rng(0).choice(len(V), 60000, replace=False)]
    fig, ax = plt.subplots(figsize=(9, 6))
    ax.scatter(V[:, 0], V[:, 2], s=0.2, c="0.6", linewidths=0)
    for c in vine["cuts"]:
        if not c.get("point"):
            continue
        x, _, z = c["point"]
        if c["status"] == "done":
            colour = "tab:green" if c["blade_error_m"] <= tol else "tab:orange"
        else:
            colour = "tab:red"
        ax.plot(x, z, "o", ms=7, mfc="none", mec=colour, mew=2)
        ax.annotate(c["pose"], (x, z), xytext=(4, 4), textcoords="offset points", fontsize=7)
    for s in vine["plan"]["stops"]:
        ax.axvline(s, color="tab:blue", lw=0.8, ls="--")
    for s in vine["plan"].get("far_side", {}).get("stops", []):
        ax.axvline(s, color="tab:purple", lw=0.8, ls=":")
    ax.set_aspect("equal")
    ax.set_xlabel("x along the row (m); platform stops: dashed near aisle, dotted far aisle")
    ax.set_ylabel("z (m)")
    ax.set_title("cuts: green done right, orange blade off, red skipped")
    fig.tight_layout()
    save_figure(fig, path)
    plt.close(fig)


def write_report(data: dict[str, Any], out: Path) -> None:
    """OUT/report.md and report.html, with a timeline and a vine picture per vine."""
    tol = data["config"]["job"]["cut"]["max_blade_error"]
    s = data["summary"]
    head = (
        f"{s['vines']} vines, {s['poses']} poses, {s['reachable']} reachable: {s['done']} done, "
        f"{s['done_right']} with the blade within {1000 * tol:g} mm of the true cut point, "
        f"{s['skipped']} skipped; {s['collisions']} collisions; median time per cut "
        f"{_f(s['median_time_per_cut_s'])} s; simulation {_f(s['realtime_factor'])}x real time "
        f"(sim {data['config']['sim']}, profile {data['config']['profile']})."
    )
    md = ["# Pruning job", "", head, "", _markdown_table(summary_rows(data))]
    page = [f"<h1>Pruning job</h1><p>{html.escape(head)}</p>", _html_table(summary_rows(data))]
    for name, v in data["vines"].items():
        tl, pic = f"{name}_timeline.png", f"{name}_vine.png"
        plot_timeline(v, out / tl)
        plot_vine(v, out / pic, tol)
        rows = cut_rows(v, tol)
        md += [f"## {name}", "", _markdown_table(rows), f"![timeline]({tl})", "",
               f"![vine]({pic})", ""]  # fmt: skip
        if v["contacts"]:
            md += ["Collisions:", ""] + [f"- {e}" for e in v["contacts"]] + [""]
        page += [f"<h2>{html.escape(name)}</h2>", _html_table(rows),
                 f'<img src="{tl}"><br><img src="{pic}">']  # fmt: skip
    for name, err in data.get("failed", {}).items():
        md += [f"## {name}: failed", "", err, ""]
        page += [f"<h2>{html.escape(name)}: failed</h2><p>{html.escape(err)}</p>"]
    atomic_write_text(out / "report.md", "\n".join(md) + "\n")
    style = (
        "<style>table{border-collapse:collapse}td,th{border:1px solid #ccc;padding:2px 6px}</style>"
    )
    atomic_write_text(out / "report.html",
                      f"<!doctype html><meta charset=utf-8><title>Pruning job</title>{style}"
                      + "".join(page))  # fmt: skip
