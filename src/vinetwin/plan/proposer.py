"""Proposals written into a twin, and their review.

`propose` applies a rule (`rules`) to the twin's skeleton, searches a pose for each cut
(`search`) and adds each cut as a cut point with `source="proposal"`, its record under the cut
point's `proposal` field (rule, action, reason, status "proposed", the pose's scores or why it
has none, and the default approach's scores), and its pose when one was found. A person accepts
a proposal (status "accepted": from then on it is theirs, and `--replace` keeps it) or rejects
it (the cut point and its pose are deleted). Re-running never duplicates a cut: a proposal
within `SAME_CUT` of a cut point already there is not added; `replace` first removes the
proposals still "proposed", never a person's own cuts or accepted ones.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from vinetwin.errors import InputError, TwinError
from vinetwin.files import atomic_write_text
from vinetwin.plan.config import ProposeConfig
from vinetwin.plan.rules import propose_cuts
from vinetwin.plan.search import VineObstacles, Wrist, search_pose
from vinetwin.twin.model import CutPoint, Twin

#: A proposal this close (m) to a cut point already in the twin is that cut.
SAME_CUT = 0.01


def is_proposal(cut: CutPoint, status: str | None = None) -> bool:
    """Whether a cut point came from `propose` (and, when given, has that status)."""
    rec = cut.extra.get("proposal")
    return isinstance(rec, dict) and (status is None or rec.get("status") == status)


@dataclass
class ProposeResult:
    """What one `propose` did."""

    rule: str
    rows: list[dict[str, Any]] = field(default_factory=list)
    """One per proposed cut: id, action, reason, pose (found or why not), scores."""
    already: int = 0
    """Proposals not added: a cut point was already there."""
    replaced: int = 0
    """Earlier proposals removed (`replace`)."""
    seconds: float = 0.0

    def counts(self) -> dict[str, int]:
        posed = sum(r["pose"] == "found" for r in self.rows)
        return {"proposed": len(self.rows), "with_pose": posed, "without_pose": len(self.rows) - posed,
                "already_there": self.already, "replaced": self.replaced}  # fmt: skip

    def to_json(self) -> dict[str, Any]:
        return {"rule": self.rule, "counts": self.counts(), "seconds": round(self.seconds, 2),
                "cuts": self.rows}  # fmt: skip

    def markdown(self) -> str:
        c = self.counts()
        lines = [
            f"{c['proposed']} cuts proposed by the {self.rule} rule, {c['with_pose']} with a "
            f"pose ({self.seconds:.1f} s); {c['already_there']} already there, "
            f"{c['replaced']} earlier proposals replaced.",
            "",
            "| cut | action | reason | pose | clearance mm | cane seen | points | default clearance mm |",
            "|---|---|---|---|---|---|---|---|",
        ]
        checked = any("servo_check" in r for r in self.rows)
        if checked:
            lines[2] += " servo check: converged (directions tried) |"
            lines[3] += "---|"
        for r in self.rows:
            s, d = r.get("search") or {}, r["default"]
            line = (
                f"| {r['id']} | {r['action']} | {r['reason']} | {r['pose']} | "
                f"{s.get('clearance_m', float('nan')) * 1000:.1f} | {s.get('visible', 0):.0%} | "
                f"{s.get('points', 0)} | {d['clearance_m'] * 1000:.1f} |"
            )
            if checked:
                c = r.get("servo_check")
                line += f" {c['success_rate']:.0%} ({c['tried']}) |" if c else " |"
            lines.append(line)
        return "\n".join(lines)


def _require_skeleton(twin: Twin) -> Any:
    sk = twin.load_skeleton()
    if sk is None or not sk.branches:
        raise TwinError(
            f"twin '{twin.name}' has no skeleton, which the pruning rules need: make the twin "
            "with `vinetwin import-scan` (a scan), `vinetwin import-vine` (a digitised plant) "
            "or `vinetwin sample`"
        )
    return sk


def propose(
    twin: Twin,
    cfg: ProposeConfig | None = None,
    *,
    obstacles: VineObstacles | None = None,
    progress: Callable[[int, int], None] | None = None,
    save: bool = True,
    check: Callable[[Twin, dict[str, list[Any]], Any], dict[str, Any]] | None = None,
) -> ProposeResult:
    """Proposes cuts on the twin by `cfg.rule`, each with a searched pose, and saves the twin
    (unless `save` is False: the web app's session saves itself). With `cfg.servo.check_profile`,
    `check` is the servo's check (`sim.servo_check.servo_check`; `sim.servo_check.propose_checked`
    passes it): it runs the simulation, which this package does not import."""
    cfg = cfg or ProposeConfig()
    if cfg.servo.check_profile and check is None:
        raise InputError(
            "the servo's check (check_profile) runs the simulation: call "
            "vinetwin.sim.servo_check.propose_checked, or `vinetwin propose --check-profile`"
        )
    t0 = time.perf_counter()
    sk = _require_skeleton(twin)
    proposals = propose_cuts(sk, cfg.rule)
    result = ProposeResult(cfg.rule.rule)
    earlier = {
        c.extra["proposal"].get("rule") for c in twin.cut_points if is_proposal(c, "proposed")
    }
    if not cfg.replace and earlier - {cfg.rule.rule}:
        raise InputError(
            f"twin '{twin.name}' holds proposals of the {', '.join(sorted(map(str, earlier)))} "
            f"rule not yet reviewed; pass --replace to replace them with the {cfg.rule.rule} "
            "rule's (a person's own cuts and accepted proposals stay)"
        )
    if cfg.replace:
        for cut in [c for c in twin.cut_points if is_proposal(c, "proposed")]:
            twin.delete_cut_point(cut.id)
            result.replaced += 1
    if obstacles is None:
        mesh = twin.load_mesh()
        obstacles = VineObstacles(np.asarray(mesh.vertices), np.asarray(mesh.faces), twin.camera)
    wrist = Wrist.for_arm(twin.T_flange_camera, cfg.search)
    settings = cfg.to_dict()
    ranked: dict[str, list[Any]] = {}
    for k, p in enumerate(proposals):
        if progress:
            progress(k, len(proposals))
        if any(np.linalg.norm(c.point - p.point) < SAME_CUT for c in twin.cut_points):
            result.already += 1
            continue
        far = cfg.search.far_for(p.point)
        found = search_pose(obstacles, p.point, p.cane_axis, p.cane, p.radius, cfg.search, wrist,
                            far)  # fmt: skip
        cut = twin.add_cut_point(p.point, p.cane_axis, name=f"{p.label} {p.action}",
                                 source="proposal")  # fmt: skip
        rec: dict[str, Any] = {
            "status": "proposed", "rule": cfg.rule.rule, **p.to_json(),
            "side": "far" if far else "near",
            "pose": "found" if found.best else found.reason,
            "default": found.default.summary(), "tried": found.tried,
        }  # fmt: skip
        row = {"id": cut.id, **rec}
        if found.best is not None:
            pose = twin.add_pose(cut.id, found.best.approach, name=f"{cut.id} {p.label}")
            pose.extra["search"] = found.best.summary()
            rec["search"] = row["search"] = found.best.summary()
            row["pose_id"] = pose.id
            ranked[pose.id] = found.ranked
        cut.extra["proposal"] = rec
        result.rows.append(row)
    twin.extra["proposal_settings"] = settings
    if check is not None and cfg.servo.check_profile and ranked:
        checks = check(twin, ranked, cfg.servo)
        for row in result.rows:
            c = checks.get(row.get("pose_id", ""))
            if c is None:
                continue
            rec = twin.cut_point(row["id"]).extra["proposal"]
            rec["search"] = row["search"] = c.ranked[c.kept].summary()
            rec["servo_check"] = row["servo_check"] = c.to_json(cfg.servo.check_profile)
        save = True  # the check's validations are in the twin already
    if save:
        twin.save()
    result.seconds = time.perf_counter() - t0
    return result


def review(twin: Twin, accept: bool, cut_ids: list[str] | None = None) -> list[str]:
    """Accepts (status "accepted") or rejects (deletes, with their poses) the given proposals,
    or every one still "proposed" when `cut_ids` is None; returns the ids changed. Does not save."""
    todo = (
        [c for c in twin.cut_points if is_proposal(c, "proposed")]
        if cut_ids is None
        else [twin.cut_point(i) for i in cut_ids]
    )
    for c in todo:
        if not is_proposal(c):
            raise InputError(f"cut point {c.id} is not a proposal (a person's own cut)")
    for c in todo:
        if accept:
            c.extra["proposal"] = {**c.extra["proposal"], "status": "accepted"}
        else:
            twin.delete_cut_point(c.id)
    return [c.id for c in todo]


def propose_folder(
    path: str | Path,
    cfg: ProposeConfig,
    *,
    json_path: Path | None = None,
    echo: Callable[[str], None] | None = None,
    propose_fn: Callable[..., ProposeResult] | None = None,
) -> ProposeResult:
    """`vinetwin propose`: proposes on the twin at `path` (with `propose_fn`, default
    `propose`), prints the table, writes the JSON."""
    twin = Twin.load(path)
    result = (propose_fn or propose)(twin, cfg)
    if echo is not None:
        echo(result.markdown())
    if json_path is not None:
        json_path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(json_path, json.dumps(result.to_json(), indent=1))
    return result


def describe_cut(twin: Twin, cut_id: str) -> str:
    """A cut's review status in words (Markdown): whose it is, the rule's reason, its pose's
    search scores or why it has none, and its servo validations."""
    cut = twin.cut_point(cut_id)
    poses = [p for p in twin.poses if p.cut_point == cut_id]
    if not is_proposal(cut):
        head = f"**{cut.name or cut.id}**: a person's cut ({cut.source})"
    else:
        rec = cut.extra["proposal"]
        head = f"**{cut.id}**: {rec.get('status', '?')} by the {rec.get('rule', '?')} rule: {rec.get('reason', '')}"
        if rec.get("pose") != "found" and not poses:
            return f"{head}. **No pose**: {rec.get('pose')}."
    lines = [head + "."]
    for p in poses:
        s = p.extra.get("search")
        if s:
            lines.append(f"pose {p.id}: clearance {s['clearance_m'] * 1000:.1f} mm, cane seen "
                         f"{s['visible']:.0%}, {s['points']} points")  # fmt: skip
        chk = p.extra.get("servo_check")
        if isinstance(chk, dict) and "success_rate" in chk:
            lines.append(f"servo check ({chk.get('profile')}): converged from "
                         f"{chk['success_rate']:.0%} of the starts, direction "
                         f"{chk.get('kept', 0) + 1} of {chk.get('tried', 1)} tried")  # fmt: skip
        for key, val in sorted(p.extra.items()):
            if key.startswith("validation") and isinstance(val, dict):
                rates = [
                    f"{v}: {c['success_rate']:.0%}" for v, c in val.get("variants", {}).items()
                ]
                profile = key.removeprefix("validation").lstrip("_") or "ideal"
                lines.append(f"servo-able ({profile}): " + ", ".join(rates))
        if not any(k.startswith("validation") for k in p.extra):
            lines.append(f"pose {p.id}: not validated yet (Validate, or `vinetwin validate`)")
    return "; ".join(lines)
