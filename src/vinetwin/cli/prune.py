"""The whole job: `vinetwin prune`, a vine or a row pruned in simulation."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

from vinetwin.cli._common import Nested, Positional, log
from vinetwin.executor import ClusterConfig, ExecutorConfig
from vinetwin.files import atomic_write_json, refuse_existing_json
from vinetwin.progress import with_progress
from vinetwin.sim.prune import PruneConfig


@dataclass(frozen=True, kw_only=True)
class Prune:
    """Prune a vine, or a row (a folder of twins), in simulation: platform stops, reach, cut
    order, collision-free transits (OMPL, timed by ruckig), the ICP servo to each pruning pose,
    the cut and the retreat; a report per vine (docs/prune.md)."""

    twin: Annotated[Path, Positional]
    """Twin folder, or a folder of twin folders (a row)."""
    config: Annotated[PruneConfig, Nested] = field(default_factory=PruneConfig)
    out: Path | None = None
    """Report folder (default: TWIN/prune, or ROW/prune)."""
    json: Path | None = None
    """Also write the row's results (each vine's cuts, collisions, planning_s) here."""
    cluster: Annotated[ClusterConfig, Nested] = field(default_factory=ClusterConfig)
    workers: int = 1
    """Vines run at once on the local pool (0: one per core)."""
    mcap: bool = False
    """Also write each vine run now as OUT/vines/NAME.mcap/ (a ROS 2 bag with MCAP storage:
    the base and camera poses, the joints, the job's events; Foxglove opens it)."""
    force: bool = False
    """Run every vine again, even those already in OUT/vines with the same inputs."""
    overwrite: bool = False
    """Replace an existing file at --json (refused otherwise)."""

    def run(self) -> None:
        from vinetwin.sim.prune_report import write_report
        from vinetwin.sim.prune_row import prune_row

        refuse_existing_json(self.json, self.overwrite)
        out = self.out or (self.twin / "prune")
        executor = self.cluster.executor(self.workers) or ExecutorConfig(workers=self.workers)
        data = with_progress("pruning", lambda progress: prune_row(
            self.twin, self.config, out, executor, self.force, progress, self.mcap))  # fmt: skip
        write_report(data, out)
        s = data["summary"]
        log.info(
            "%d vines: %d of %d reachable cuts done (%d with the blade within %g mm), %d "
            "skipped, %d collisions; median %.1f s per cut; %.1fx real time",
            s["vines"], s["done"], s["reachable"], s["done_right"],
            1000 * self.config.job.cut.max_blade_error, s["skipped"], s["collisions"],
            s["median_time_per_cut_s"], s["realtime_factor"],
        )  # fmt: skip
        if self.json:
            atomic_write_json(self.json, data)
        log.info("report: %s", out / "report.html")
        if data["failed"]:
            from vinetwin.errors import VinetwinError

            raise VinetwinError(
                f"{len(data['failed'])} of {s['vines'] + len(data['failed'])} vines failed (the "
                "report holds the others; run again to retry them): " + "; ".join(
                    f"{name}: {why}" for name, why in list(data["failed"].items())[:5])
            )  # fmt: skip
