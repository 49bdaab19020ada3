"""Camera poses from depth odometry: the fallback when there are neither robot poses nor a
structure-from-motion result.

Open3D's dense RGB-D odometry was tried first and failed on vine captures (thin canes against an
empty background: a single pair's error exceeded the motion between the frames; see
docs/reconstruct.md). vinetwin instead chains its own point-to-plane ICP (`registration.icp`, the same
perception chain as the servo) between consecutive frames, each starting from the previous
motion (constant velocity). It needs a video-like capture (frames a few centimetres and degrees
apart). A pair that does not align keeps the previous motion and is reported. Poses come out in
the first frame's camera frame, metric; the drift grows with the path length.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from vinetwin.capture.folder import Capture, CaptureError
from vinetwin.cloud import PerceptionConfig, perceive
from vinetwin.frames import Array
from vinetwin.registration.icp import ICP, ICPConfig


@dataclass
class OdometryResult:
    poses: dict[str, Array]
    """T_first_camera per frame."""
    failed: list[str] = field(default_factory=list)
    """Frames whose alignment to their predecessor failed (pose extrapolated)."""
    seconds: float = 0.0


def odometry_poses(capture: Capture, perception: PerceptionConfig | None = None) -> OdometryResult:
    t0 = time.perf_counter()
    per = perception or PerceptionConfig(max_depth=0.5, voxel_size=0.003)
    cfg = ICPConfig(
        variant="point_to_plane",
        schedule=((0.0, 0.05), (0.0, 0.015)),
        max_correspondence_distance=0.005,
        coarse_tolerance=0.0,  # measured without the early hand-on (docs/reconstruct.md)
    )
    cam = capture.camera
    clouds = [perceive(f.depth(capture.depth_unit), cam, per) for f in capture.frames]
    poses = {capture.frames[0].id: np.eye(4)}
    T = np.eye(4)
    step = np.eye(4)
    failed = []
    for k in range(1, len(clouds)):
        # the previous frame is the reference; the current frame's pose in it is the step
        r = ICP(clouds[k - 1], cfg).align(clouds[k], step)
        if r.converged and r.overlap > 0.3:
            step = r.T_ref_cur
        else:
            failed.append(capture.frames[k].id)
        T = T @ step
        poses[capture.frames[k].id] = T.copy()
    if len(failed) == len(clouds) - 1:
        raise CaptureError(f"{capture.root}: odometry aligned no frame pair")
    return OdometryResult(poses, failed, time.perf_counter() - t0)
