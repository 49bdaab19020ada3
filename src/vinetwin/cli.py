"""The `vinetwin` command: argument definitions and calls. Each subcommand is a dataclass parsed by
tyro that nests the library's config dataclasses: every setting has one declaration and one
default, in the library. `run()` imports lazily: `--help` stays fast. The jobs are library calls."""

from __future__ import annotations

import logging
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Literal

import tyro

from vinetwin.capture.topics import RosTopics
from vinetwin.errors import exit_status
from vinetwin.executor import ClusterConfig
from vinetwin.files import refuse_existing_json
from vinetwin.progress import with_progress
from vinetwin.reconstruct.config import OdometryConfig, ReconstructConfig, SyntheticCaptureConfig
from vinetwin.render.backends import BackendName
from vinetwin.scan.config import ScanImportConfig
from vinetwin.servo.config import ArrivalConfig, CheckConfig, RunnerConfig
from vinetwin.sim.config import CampaignConfig, FidelityConfig, ValidateConfig
from vinetwin.twin.generator import SampleConfig
from vinetwin.web.config import WebConfig

log = logging.getLogger("vinetwin")

Positional, Nested = tyro.conf.Positional, tyro.conf.OmitArgPrefixes
#: "auto" or a render backend (`render.backends.BACKENDS`, where the names are declared).
BackendChoice = Literal["auto"] | BackendName


@dataclass(frozen=True, kw_only=True)
class Sample:
    """Grow a procedural dormant grapevine and write it as a twin folder."""

    out: Path
    """Twin folder to create (e.g. vine7.twin)."""
    config: Annotated[SampleConfig, Nested] = field(default_factory=SampleConfig)
    overwrite: bool = False
    """Replace a twin already in OUT."""

    def run(self) -> None:
        from vinetwin.twin.generator import sample_twin
        from vinetwin.twin.summary import print_summary

        c = self.config
        print_summary(sample_twin(self.out, c.seed, cordons=c.cordons, edge=c.edge,
                                  cut_points=c.cut_points, overwrite=self.overwrite,
                                  dense=c.dense))  # fmt: skip


@dataclass(frozen=True, kw_only=True)
class ImportVine:
    """Import a digitised plant skeleton (hydroshoot digit.input or a cylinder list) as a twin."""

    file: Annotated[Path, Positional]
    """Skeleton file to import."""
    out: Path
    """Twin folder to create."""
    format: Literal["auto", "hydroshoot", "cylinders"] = "auto"
    """File format; auto detects it from the first lines."""
    edge: float = 0.003
    """Target triangle edge length of the tube mesh, metres."""
    cut_points: int = 0
    """How many cut-point candidates (hydroshoot shoots) become cut points with a pose."""
    overwrite: bool = False
    """Replace a twin already in OUT."""

    def run(self) -> None:
        from vinetwin.twin.importers import import_twin
        from vinetwin.twin.summary import print_summary

        print_summary(import_twin(self.file, self.out, self.format, edge=self.edge,
                                  cut_points=self.cut_points, overwrite=self.overwrite))  # fmt: skip


@dataclass(frozen=True, kw_only=True)
class ImportScan:
    """Make a twin from a scan of a plant (point cloud: PCD PLY XYZ TXT CSV LAS LAZ E57; mesh: PLY
    OBJ STL GLB): units, the vine frame, cleaning, a skeleton, cut candidates (docs/scans.md)."""

    file: Annotated[Path, Positional]
    """Scan file."""
    out: Path
    """Twin folder to create."""
    config: Annotated[ScanImportConfig, Nested] = field(default_factory=ScanImportConfig)
    report: Path | None = None
    """Also write a report here: counts, removed points, the skeleton over the points."""
    truth: Path | None = None
    """A twin of the same plant in the same frame: its accuracy goes into the report."""
    overwrite: bool = False
    """Replace a twin already in OUT."""

    def run(self) -> None:
        from vinetwin.scan.importer import import_scan
        from vinetwin.twin.summary import print_summary

        print_summary(import_scan(self.file, self.out, self.config, report=self.report,
                                  truth=self.truth, overwrite=self.overwrite,
                                  progress=lambda step: log.info("import-scan: %s", step))[0])  # fmt: skip


@dataclass(frozen=True, kw_only=True)
class Info:
    """Validate a twin folder and print what it holds."""

    twin: Annotated[Path, Positional]
    """Twin folder."""
    check_mesh: bool = True
    """Also read and check the mesh."""

    def run(self) -> None:
        from vinetwin.twin.model import Twin
        from vinetwin.twin.summary import print_summary

        print_summary(Twin.load(self.twin), mesh=self.check_mesh)


@dataclass(frozen=True, kw_only=True)
class Export:
    """Render each pruning pose's reference cloud into TWIN/references (PLY, PCD, JSON), for one
    twin or every twin of a vineyard folder; resumable."""

    twin: Annotated[Path, Positional]
    """Twin folder, or a folder of twin folders (a vineyard)."""
    poses: tuple[str, ...] = ()
    """Pose ids to export (default: all; one twin only)."""
    backend: BackendChoice = "auto"
    """Depth renderer; auto: raster (vinetwin's compiled rasteriser, no OpenGL needed), else open3d
    saying why (docs/render.md)."""
    workers: int = 0
    """Processes; 0 chooses (1 for open3d, else one per core; Ray: its CPUs)."""
    cluster: Annotated[ClusterConfig, Nested] = field(default_factory=ClusterConfig)
    seed: int = 0
    """Base seed of the D405 noise; each pose derives its own."""
    force: bool = False
    """Re-render references whose inputs did not change."""
    clean: bool = False
    """Render without the D405 sensor model (exact depth)."""

    def run(self) -> None:
        from vinetwin.render.export import check_export_ok, export_twins, print_report

        report, where = with_progress("exporting references", lambda progress: export_twins(
            self.twin, self.poses, backend=self.backend, workers=self.workers, seed=self.seed,
            clean=self.clean, force=self.force, executor=self.cluster.executor(self.workers),
            progress=progress))  # fmt: skip
        print_report(report, where)
        check_export_ok(report)


@dataclass(frozen=True, kw_only=True)
class Preview:
    """Render one pose's D405 depth image and reference cloud into a PNG to look at."""

    twin: Annotated[Path, Positional]
    """Twin folder."""
    pose: str
    """Pose id."""
    out: Path = Path("preview.png")
    """PNG to write."""
    backend: BackendChoice = "auto"
    """Depth renderer, as for export."""
    seed: int = 0
    """Base seed of the D405 noise."""
    overwrite: bool = False
    """Replace existing files at --out (refused otherwise)."""

    def run(self) -> None:
        from vinetwin.render.preview import preview_pose
        from vinetwin.twin.model import Twin

        preview_pose(Twin.load(self.twin), self.pose, self.out, self.backend, self.seed,
                     self.overwrite)  # fmt: skip


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


@dataclass(frozen=True, kw_only=True)
class CaptureSynthetic:
    """Render a synthetic RGB-D capture of a twin (D405 depth, textured colour, true poses)."""

    twin: Annotated[Path, Positional]
    """Twin folder whose mesh is captured."""
    out: Path
    """Capture folder to write."""
    config: Annotated[SyntheticCaptureConfig, Nested] = field(default_factory=SyntheticCaptureConfig)  # fmt: skip

    def run(self) -> None:
        from vinetwin.reconstruct.synthetic import synthetic_capture
        from vinetwin.twin.model import Twin

        c = self.config
        path = with_progress("rendering frames", lambda progress: synthetic_capture(
            Twin.load(self.twin), self.out, c.frames, c.distance, c.seed, c.pose_noise, progress,
            c.trajectory))  # fmt: skip
        log.info("capture: %s (%d frames)", path, c.frames)


@dataclass(frozen=True, kw_only=True)
class ImportRecording:
    """A ROS 1/2 bag (poses from /tf; docs/ros.md) or librealsense recording as a capture folder."""

    recording: Annotated[Path, Positional]
    """Recording: a file, or a ROS 2 bag folder."""
    out: Path
    """Capture folder to write."""
    topics: Annotated[RosTopics, Nested] = field(default_factory=RosTopics)
    max_frames: int = 0
    """Stop after this many frames (0: all)."""

    def run(self) -> None:
        from vinetwin.capture.rosbag import import_recording

        out = import_recording(self.recording, self.out, self.topics, self.max_frames)
        log.info("capture: %s", out)


@dataclass(frozen=True, kw_only=True)
class Reconstruct:
    """Fuse a capture folder into a vine mesh (TSDF) in a twin; optionally score it (Chamfer, F)."""

    capture: Annotated[Path, Positional]
    """Capture folder (capture.json, color/, depth/)."""
    twin: Path
    """Twin folder to create (or update with --overwrite)."""
    config: Annotated[ReconstructConfig, Nested] = field(default_factory=ReconstructConfig)
    odometry: OdometryConfig = field(default_factory=OdometryConfig)
    """With --poses odometry: the frames' clouds and the ICP schedule."""
    overwrite: bool = False
    """Replace an existing twin's mesh (cut points and poses kept) and an existing --json."""
    ground_truth: Path | None = None
    """A twin folder or mesh file to evaluate against."""
    json: Path | None = None
    """Write the fusion report and the evaluation here."""

    def run(self) -> None:
        from vinetwin.reconstruct.pipeline import reconstruct

        refuse_existing_json(self.json, self.overwrite)
        with_progress("fusing frames", lambda progress: reconstruct(
            self.capture, self.twin, self.config, self.odometry, overwrite=self.overwrite,
            ground_truth=self.ground_truth, progress=progress, json_path=self.json))  # fmt: skip


@dataclass(frozen=True, kw_only=True)
class Web:
    """Serve the authoring app: click canes, adjust pruning poses, preview, save, export."""

    twin: Annotated[Path | None, Positional] = None
    """Twin folder (default: a copy of the bundled sample in out/web)."""
    host: str = "127.0.0.1"
    """Address to listen on."""
    port: int = 8080
    """Port to listen on."""
    config: Annotated[WebConfig, Nested] = field(default_factory=WebConfig)

    def run(self) -> None:
        from vinetwin.web.server import serve_folder

        serve_folder(self.twin, self.host, self.port, forever=True, config=self.config)


@dataclass(frozen=True, kw_only=True)
class Demo:
    """The main job, headless: the bundled sample copied to OUT, its references and a preview."""

    out: Path = Path("out/demo")
    """Folder for the demo's outputs (the bundled sample itself is never modified)."""

    def run(self) -> None:
        from vinetwin.render.export import run_demo

        run_demo(self.out)


COMMANDS: dict[str, type] = {
    "sample": Sample, "import-vine": ImportVine, "import-scan": ImportScan, "info": Info,
    "export": Export, "preview": Preview, "demo": Demo, "campaign": Campaign, "validate": Validate,
    "web": Web, "capture-synthetic": CaptureSynthetic, "import-recording": ImportRecording,
    "servo": ServoCmd, "servo-plot": ServoPlot, "check-reference": CheckReference,
    "fidelity": Fidelity, "reconstruct": Reconstruct,
}  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    """Entry point of the `vinetwin` command; returns the exit status."""
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    try:  # a config dataclass refuses a bad value while the arguments are parsed
        cmd = tyro.extras.subcommand_cli_from_dict(
            COMMANDS,
            args=sys.argv[1:] if argv is None else argv,
            description="vinetwin: reference clouds and digital twins for robotic vine pruning.",
        )
        cmd.run()
    except BaseException as exc:
        return exit_status(exc, log)
    return 0


if __name__ == "__main__":
    sys.exit(main())
