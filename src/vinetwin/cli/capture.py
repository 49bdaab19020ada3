"""The capture's commands: a synthetic capture, a recording imported as a capture folder, TSDF reconstruction."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

from vinetwin.capture.topics import RosTopics
from vinetwin.cli._common import Nested, Positional, log
from vinetwin.files import refuse_existing_json
from vinetwin.progress import with_progress
from vinetwin.reconstruct.config import OdometryConfig, ReconstructConfig, SyntheticCaptureConfig


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
