"""What the servo's check while proposing (`vinetwin propose --check-profile`) buys.

Each plant and rule of `benchmarks/propose.py` is proposed twice: as `vinetwin propose` does
by default, and with the servo's check under the field profile at seed 0 (each pose run
through `vinetwin validate`, a pose that does not converge from every start replaced by the
search's next direction). Both twins are then validated under the field profile at ANOTHER
seed (1: other starts, other noise, another rebuilt field twin): a check that only fits its own
draw shows no gain there. The GDC and the apple use a field profile capturing their twin
around the poses (`"twin_trajectory": "poses"`), as the table of `docs/proposals.md` does.

    .venv/bin/python benchmarks/propose_check.py [--plants sample dense ...] [--rules spur cane]
        [--json benchmarks/results/propose_check.json [--update]]

Prints, per plant and rule, the poses and how many converge from all 4 starts (and from at
least 3): the check's own runs at seed 0, then both twins at seed 1.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
from dataclasses import replace
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
from propose import PLANTS, make_twin
from results_file import machine

from vinetwin.plan.config import ProposeConfig, RuleConfig, ServoCheckConfig
from vinetwin.plan.proposer import propose
from vinetwin.sim.config import load_profile
from vinetwin.sim.servo_check import _rates, propose_checked
from vinetwin.twin.model import Twin

AROUND_POSES = ("gdc_can1", "apple_spindle")
"""The plants too large for the field profile's grid sweep at 0.3 m."""
CHECK_SEED, MEASURE_SEED = 0, 1


def profile_for(name: str, work: Path) -> str:
    if name not in AROUND_POSES:
        return "field"
    path = work / "field_around_poses.json"
    if not path.exists():
        prof = replace(load_profile("field"), twin_trajectory="poses")
        path.write_text(json.dumps(prof.to_dict(), indent=1))
    return str(path)


def rates(twin: Twin, cfg: ServoCheckConfig, seed: int) -> dict[str, Any]:
    """Each pose's share of starts converged under `cfg`'s profile at `seed` (or why it did not
    run: a field twin that does not show the pose): the check's own validation, another seed."""
    pids = [p.id for p in twin.poses]
    got = _rates(twin, replace(cfg, check_seed=seed), pids) if pids else {}
    return {pid: {"error": why[:160]} if why else rate for pid, (rate, why) in got.items()}


def counts(r: dict[str, Any]) -> tuple[int, int]:
    vals = [v if isinstance(v, float | int) else 0.0 for v in r.values()]
    return sum(v >= 1.0 for v in vals), sum(v >= 0.75 for v in vals)


def run(name: str, rule: str, work: Path) -> dict[str, Any]:
    check = ServoCheckConfig(check_profile=profile_for(name, work), check_seed=CHECK_SEED)
    rule_cfg = RuleConfig(rule=rule)  # type: ignore[arg-type]
    plain = make_twin(name, work / f"{name}_{rule}_plain.twin")
    propose(plain, ProposeConfig(rule=rule_cfg))
    checked = make_twin(name, work / f"{name}_{rule}_checked.twin")
    result = propose_checked(checked, ProposeConfig(rule=rule_cfg, servo=check))
    own = {r["pose_id"]: r["servo_check"] for r in result.rows if "servo_check" in r}
    plain, checked = Twin.load(plain.root), Twin.load(checked.root)
    return {
        "twin": f"{name}_{rule}", "profile": Path(check.check_profile).stem,
        "check_seed0": own,
        "validate_seed1_without_check": rates(plain, check, MEASURE_SEED),
        "validate_seed1_with_check": rates(checked, check, MEASURE_SEED),
    }  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--plants", nargs="*", default=list(PLANTS))
    ap.add_argument("--rules", nargs="*", default=["spur", "cane"])
    ap.add_argument("--keep", type=Path, help="leave the twins in this folder")
    ap.add_argument("--json", type=Path)
    ap.add_argument("--update", action="store_true",
                    help="replace in --json only the rows of the plants and rules run now; the "
                         "others keep theirs (each row names the commit it was measured at)")  # fmt: skip
    a = ap.parse_args()
    work = Path(a.keep) if a.keep else Path(tempfile.mkdtemp(prefix="propose-check-"))
    work.mkdir(parents=True, exist_ok=True)
    rows: list[dict[str, Any]] = []
    print("| plant | rule | poses | with the check, its own runs (seed 0): all 4 (>= 3) "
          "| seed 1, without the check | seed 1, with the check | directions tried again |")  # fmt: skip
    print("|---|---|---|---|---|---|---|")
    try:
        for name in a.plants:
            for rule in a.rules:
                if name == "apple_spindle" and rule == "cane":
                    continue  # the cane rule is for vines: `propose` refuses a tree's
                r = run(name, rule, work)
                rows.append(r)
                own = {k: v["success_rate"] for k, v in r["check_seed0"].items()}
                retried = [k for k, v in r["check_seed0"].items() if v["tried"] > 1]
                c0, w, c = (counts(own), counts(r["validate_seed1_without_check"]),
                            counts(r["validate_seed1_with_check"]))  # fmt: skip
                print(f"| {name} | {rule} | {len(own)} | {c0[0]} ({c0[1]}) | {w[0]} ({w[1]}) "
                      f"| {c[0]} ({c[1]}) | {', '.join(retried) or '-'} |", flush=True)  # fmt: skip
    finally:
        if not a.keep:
            shutil.rmtree(work, ignore_errors=True)
    tot = [sum(x) for x in zip(*(
        counts({k: v["success_rate"] for k, v in r["check_seed0"].items()})
        + counts(r["validate_seed1_without_check"]) + counts(r["validate_seed1_with_check"])
        for r in rows), strict=True)]  # fmt: skip
    n = sum(len(r["check_seed0"]) for r in rows)
    if tot:
        print(
            f"| all | | {n} | {tot[0]} ({tot[1]}) | {tot[2]} ({tot[3]}) | {tot[4]} ({tot[5]}) | |"
        )
    if a.json:
        here = machine()
        for r in rows:
            r["commit"] = here["commit"]
        if a.update and a.json.exists():
            old = json.loads(a.json.read_text())
            for r in old["rows"]:
                r.setdefault("commit", old["machine"]["commit"])
            new = {r["twin"]: r for r in rows}
            rows = [new.pop(r["twin"], r) for r in old["rows"]] + list(new.values())
        a.json.write_text(json.dumps({
            "machine": here,
            "settings": {"profile": "field (gdc_can1, apple_spindle: field with twin_trajectory "
                                    "poses)", "variant": "point_to_plane", "starts": 4,
                         "radius_translation": 0.05, "radius_rotation": 0.15,
                         "check_seed": CHECK_SEED, "measure_seed": MEASURE_SEED},
            "rows": rows}, indent=1))  # fmt: skip


if __name__ == "__main__":
    main()
