"""The servo's commands: campaigns, validation and fidelity in simulation, a servo run (simulated, replayed or on hardware), the live check of a reference, plots of servo logs."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

from vinetwin.cli._common import Nested, Positional, log
from vinetwin.executor import ClusterConfig
from vinetwin.files import refuse_existing_json
from vinetwin.progress import with_progress
from vinetwin.servo.config import ArrivalConfig, CheckConfig, RunnerConfig
from vinetwin.sim.config import CampaignConfig, FidelityConfig, ValidateConfig


@dataclass(frozen=True, kw_only=True)
class Campaign:
    """Servo in simulation from the paper's starts with each ICP variant, plus a disturbance run
    per variant and runs with and without the initial guess, ideal or with the field's errors
    (--profile field, docs/field.md); write a report (Markdown, HTML, PNG plots, JSON)."""

    twin: Annotated[Path, Positional]
    """Twin folder."""
    config: Annotated[CampaignConfig, Nested] = field(default_factory=CampaignConfig)
    out: Path | None = None
    """Report folder (default: TWIN/campaign/PRESET)."""
    json: Path | None = None
    """Also write the figures (campaign.json) here."""
    cluster: Annotated[ClusterConfig, Nested] = field(default_factory=ClusterConfig)
    force: bool = False
    """Run every run again, even those already in OUT/runs with the same inputs."""
    overwrite: bool = False
    """Replace existing files at --json (refused otherwise)."""

    def run(self) -> None:
        from vinetwin.sim.campaign import run_campaign
        from vinetwin.sim.report import print_tables
        from vinetwin.twin.model import Twin

        refuse_existing_json(self.json, self.overwrite)
        out = self.out or (self.twin / "campaign" / self.config.preset)
        data = with_progress("simulating", lambda progress: run_campaign(
            Twin.load(self.twin), self.config, out, progress,
            self.cluster.executor(self.config.workers), self.force, copy_json=self.json))  # fmt: skip
        print_tables(data)
        log.info("report: %s", out / "report.html")


@dataclass(frozen=True, kw_only=True)
class Validate:
    """Closed-loop runs per pruning pose and variant: success rate and basin into TWIN/validation."""

    twin: Annotated[Path, Positional]
    """Twin folder, or a folder of twin folders (a vineyard)."""
    config: Annotated[ValidateConfig, Nested] = field(default_factory=ValidateConfig)
    cluster: Annotated[ClusterConfig, Nested] = field(default_factory=ClusterConfig)
    json: Path | None = None
    """Also write the summary here."""
    overwrite: bool = False
    """Replace existing files at --json (refused otherwise)."""

    def run(self) -> None:
        from vinetwin.sim.validate import validate_folder

        refuse_existing_json(self.json, self.overwrite)
        with_progress("validating", lambda progress: validate_folder(
            self.twin, self.config, progress, self.cluster.executor(self.config.workers),
            json_path=self.json, echo=print))  # fmt: skip


@dataclass(frozen=True, kw_only=True)
class ServoCmd:
    """Servo the camera to one pruning pose: camera frames -> perception -> ICP (kinematic guess)
    -> PBVS -> guarded robot command, every cycle logged. In simulation (--camera sim --robot
    sim|mujoco), replayed without a robot (--camera folder:DIR|bag:FILE --robot none) or on
    hardware (--camera realsense --robot franka:HOST); see docs/hardware.md."""

    twin: Path
    """Twin folder."""
    config: Annotated[RunnerConfig, Nested] = field(default_factory=RunnerConfig)
    log: Path | None = None
    """Cycle log (JSON Lines; default TWIN/servo/POSE-DATE.jsonl)."""
    record: Path | None = None
    """Also write the frames, stamps and robot poses as a capture folder (replayable)."""
    mcap: Path | None = None
    """Also write the run as MCAP for Foxglove or RViz (a ROS 2 bag folder; docs/ros.md)."""
    overwrite: bool = False
    """Replace existing files at --log and --record (refused otherwise)."""
    arrival_settings: ArrivalConfig = field(default_factory=ArrivalConfig)
    """The arrival registration (with --arrival)."""

    def run(self) -> None:
        from vinetwin.servo.runner import RunOutputs, run_pose
        from vinetwin.sim.session import servo_session
        from vinetwin.twin.model import Twin

        outputs = RunOutputs(self.log, self.record, self.mcap, self.overwrite)
        summary, path = run_pose(Twin.load(self.twin), self.config, outputs, servo_session,
                                 self.arrival_settings)  # fmt: skip
        print(f"{summary.describe()}\nlog: {path}")


@dataclass(frozen=True, kw_only=True)
class Fidelity:
    """How good must a twin be? Servo on the true vine with references from twins rebuilt at
    several qualities: final errors against Chamfer and F-score, ablation (docs/field.md)."""

    twin: Annotated[Path, Positional]
    """The true twin (its mesh is the truth)."""
    config: Annotated[FidelityConfig, Nested] = field(default_factory=FidelityConfig)
    out: Path | None = None
    """Report folder (default: TWIN/fidelity)."""

    def run(self) -> None:
        from vinetwin.sim.fidelity import run_fidelity
        from vinetwin.twin.model import Twin

        out = self.out or self.twin / "fidelity"
        with_progress("simulating", lambda progress: run_fidelity(
            Twin.load(self.twin), self.config, out, progress))  # fmt: skip
        log.info("report: %s", out / "fidelity.md")


@dataclass(frozen=True, kw_only=True)
class CheckReference:
    """Live frames at a pruning pose against its reference: twin still valid, vine moved or vine
    changed here (check.json, check.png); exit status 1 unless valid (docs/field.md)."""

    twin: Annotated[Path, Positional]
    """Twin folder."""
    config: Annotated[CheckConfig, Nested] = field(default_factory=CheckConfig)
    out: Path | None = None
    """Folder for check.json and check.png (default TWIN/checks/POSE)."""
    overwrite: bool = False
    """Replace existing files at --out (refused otherwise)."""

    def run(self) -> None:
        from vinetwin.servo.check import run_check

        check = run_check(self.twin, self.config, self.out, self.overwrite)
        print(check.describe())
        raise SystemExit(0 if check.valid else 1)


@dataclass(frozen=True, kw_only=True)
class ServoPlot:
    """Plot servo logs (vinetwin servo --log) as the campaign report draws its runs."""

    logs: Annotated[tuple[Path, ...], Positional]
    """One or more .jsonl logs."""
    out: Path = Path("servo-plots")
    """Folder for errors.png and trajectories.png."""
    overwrite: bool = False
    """Replace existing files at --out (refused otherwise)."""

    def run(self) -> None:
        from vinetwin.sim.report import plot_logs

        paths = plot_logs(list(self.logs), self.out, self.overwrite)
        print("wrote " + " and ".join(str(p) for p in paths))
