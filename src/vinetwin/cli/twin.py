"""The twin's commands: make a twin (sample, import-vine, import-scan), propose cuts, inspect it, export its references, preview a pose, serve the web app, the demo."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

from vinetwin.cli._common import BackendChoice, Nested, Positional, _summary, log
from vinetwin.executor import ClusterConfig
from vinetwin.plan.config import ProposeConfig
from vinetwin.progress import with_progress
from vinetwin.scan.config import ScanImportConfig
from vinetwin.twin.generator import SampleConfig
from vinetwin.twin.importers import ImportVineConfig
from vinetwin.web.config import WebConfig


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

        c = self.config
        _summary(sample_twin(self.out, c.seed, cordons=c.cordons, edge=c.edge,
                             cut_points=c.cut_points, overwrite=self.overwrite, dense=c.dense))  # fmt: skip


@dataclass(frozen=True, kw_only=True)
class ImportVine:
    """Import a digitised plant skeleton (hydroshoot digit.input or a cylinder list) as a twin."""

    file: Annotated[Path, Positional]
    """Skeleton file to import."""
    out: Path
    """Twin folder to create."""
    config: Annotated[ImportVineConfig, Nested] = field(default_factory=ImportVineConfig)
    overwrite: bool = False
    """Replace a twin already in OUT."""

    def run(self) -> None:
        from vinetwin.twin.importers import import_twin

        c = self.config
        _summary(import_twin(self.file, self.out, c.format, edge=c.edge, cut_points=c.cut_points,
                             overwrite=self.overwrite))  # fmt: skip


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

        _summary(import_scan(self.file, self.out, self.config, report=self.report,
                             truth=self.truth, overwrite=self.overwrite,
                             progress=lambda step: log.info("import-scan: %s", step))[0])  # fmt: skip


@dataclass(frozen=True, kw_only=True)
class Propose:
    """Propose cuts by a pruning rule on a twin's skeleton, each with a searched collision-free
    pruning pose (docs/proposals.md); review them in `vinetwin web`."""

    twin: Annotated[Path, Positional]
    """Twin folder (with a skeleton)."""
    config: Annotated[ProposeConfig, Nested] = field(default_factory=ProposeConfig)
    json: Path | None = None
    """Also write the proposals and their scores here."""
    overwrite: bool = False
    """Replace an existing file at --json (refused otherwise, before any cut is proposed)."""

    def run(self) -> None:
        from vinetwin.files import refuse_existing_json
        from vinetwin.plan.proposer import propose_folder

        refuse_existing_json(self.json, self.overwrite)
        fn = None
        if self.config.servo.check_profile:  # the servo's check runs the simulation
            from vinetwin.sim.servo_check import propose_checked as fn
        propose_folder(self.twin, self.config, json_path=self.json, echo=print, propose_fn=fn)


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
