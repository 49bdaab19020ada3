"""The servo's check of proposed poses (`vinetwin propose --check-profile PROFILE`).

It lives in `sim` (it runs the closed loop) and is handed to `plan.proposer.propose` as its
`check` (`propose_checked` does both): `plan` does not import the simulation.

The search (`search`) ranks the clear directions of each cut by what it can see from the mesh:
clearance, the cane's visible share, the points in view. Whether the ICP servo converges to the
pose from where the arm will start it is another matter, which only the closed loop tells (on
the dense generated vine, 1 of 15 cane-rule poses settles 12 mm off under the field profile
while every pose around it converges). So each proposed pose is run through `vinetwin
validate` (the same runs, written into the twin as `validate` writes them); a pose that does not
converge from every start is replaced by the search's next direction, best score first, up to
`check_alternatives`, and of those tried the one converging from the most starts is kept (a
tie: the better score). The poses of one round are validated together, so the workers share
them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from vinetwin.plan.config import ProposeConfig, ServoCheckConfig
from vinetwin.plan.search import Candidate
from vinetwin.sim.config import ValidateConfig, load_profile
from vinetwin.twin.model import Twin
from vinetwin.twin.poses import pruning_pose


@dataclass
class Checked:
    """One pose's check: the directions tried (index into the search's ranking), the share of
    starts each converged from, and the one kept."""

    ranked: list[Candidate]
    rates: list[float] = field(default_factory=list)
    errors: list[str] = field(default_factory=list)
    """Why a direction's runs failed (a field twin that does not show the pose), or ""."""
    kept: int = 0

    def best(self) -> int:
        """The direction converging from the most starts (the first of equals: the better
        score)."""
        return self.rates.index(max(self.rates))

    def to_json(self, profile: str) -> dict[str, Any]:
        k = self.kept
        return {"profile": profile, "tried": len(self.rates),
                "success_rates": [round(r, 3) for r in self.rates], "kept": k,
                "success_rate": round(self.rates[k], 3),
                **({"error": self.errors[k]} if self.errors[k] else {})}  # fmt: skip


def _set(twin: Twin, pid: str, c: Candidate) -> None:
    cut = twin.cut_point(twin.pose(pid).cut_point)
    twin.set_pose(pid, pruning_pose(cut.point, cut.cane_axis, c.approach))
    twin.pose(pid).extra["search"] = c.summary()


def validate_config(cfg: ServoCheckConfig, poses: tuple[str, ...]) -> ValidateConfig:
    """The `ValidateConfig` of the check, for these poses."""
    return ValidateConfig(variants=("point_to_plane",), poses=poses, starts=cfg.check_starts,
                          radius_translation=cfg.check_translation,
                          radius_rotation=cfg.check_rotation, seed=cfg.check_seed,
                          workers=cfg.check_workers, profile=cfg.check_profile)  # fmt: skip


def _rates(twin: Twin, cfg: ServoCheckConfig, pids: list[str]) -> dict[str, tuple[float, str]]:
    from vinetwin.sim.validate import validate

    summary = validate(twin, validate_config(cfg, tuple(pids)))
    out: dict[str, tuple[float, str]] = {}
    for row in summary["poses"]:
        cell = row["variants"]["point_to_plane"]
        out[row["pose"]] = (
            (0.0, str(cell["failed"])) if "failed" in cell else (cell["success_rate"], "")
        )
    return out


def servo_check(
    twin: Twin,
    ranked: dict[str, list[Candidate]],
    cfg: ServoCheckConfig,
) -> dict[str, Checked]:
    """Checks the poses `ranked` names (pose id: the search's passing directions, best first;
    the pose set to the first) and replaces those that do not converge from every start, in
    place; saves the twin. Returns each pose's check."""
    checks = {pid: Checked(cands) for pid, cands in ranked.items() if cands}
    if not checks:
        return checks
    twin.save()
    todo = list(checks)
    for k in range(cfg.check_alternatives + 1):
        if k > 0:
            for pid in todo:
                _set(twin, pid, checks[pid].ranked[k])
            twin.save()
        for pid, (rate, err) in _rates(twin, cfg, todo).items():
            checks[pid].rates.append(rate)
            checks[pid].errors.append(err)
        todo = [pid for pid in todo
                if max(checks[pid].rates) < 1.0 and len(checks[pid].ranked) > k + 1]  # fmt: skip
        if not todo:
            break
    # where an earlier direction did better than the last tried: back to it, validated again so
    # that the twin's stored validation is of the pose it holds
    for c in checks.values():
        c.kept = c.best()
    back = [pid for pid, c in checks.items() if c.kept != len(c.rates) - 1]
    for pid in back:
        _set(twin, pid, checks[pid].ranked[checks[pid].kept])
    if back:
        twin.save()
        for pid, (rate, err) in _rates(twin, cfg, back).items():  # the same seed and starts
            c = checks[pid]
            c.rates[c.kept], c.errors[c.kept] = rate, err
    for pid, c in checks.items():
        twin.pose(pid).extra["servo_check"] = c.to_json(cfg.check_profile)
    twin.save()
    # the servo-ability map of every checked pose (their runs are stored: nothing runs again)
    _rates(twin, cfg, list(checks))
    return checks


def propose_checked(twin: Twin, cfg: ProposeConfig, **kw: Any) -> Any:
    """`plan.proposer.propose` with the servo's check (when `cfg.servo.check_profile` names a
    profile; an unknown one is named before the search, and nothing is written)."""
    from vinetwin.plan.proposer import propose

    if cfg.servo.check_profile:
        load_profile(cfg.servo.check_profile)
    return propose(twin, cfg, check=servo_check, **kw)
