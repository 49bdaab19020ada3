"""Camera poses from the colour frames alone: pycolmap structure-from-motion, made metric with
the depth frames.

SIFT features on the CPU, sequential matching (the frames of a capture come in order; the window
is wide enough to link the rows of a sweep), incremental mapping with the capture's intrinsics
held fixed (PINHOLE). The reconstruction's scale is arbitrary: it is recovered as the median
ratio, over the triangulated points seen in each registered frame, of the depth the D405 measured
at the point's pixel to the point's depth in the reconstruction. Poses come back in the first
registered frame's camera frame (or, when the capture holds robot poses for the registered
frames, aligned to the robot base by a similarity fit of the camera centres, for comparison).
Frames that do not register are reported.
"""

from __future__ import annotations

import shutil
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from vinetwin.capture.folder import Capture, CaptureError
from vinetwin.frames import Array, invert, make_pose, transform_points

#: `align_to`'s lever arm (m): a frame's orientation counts as the displacement of points this far
#: along its axes, about the range at which the D405 sees the vine (0.07-0.5 m; pruning poses at
#: 0.15 m), so that an angle weighs as much as the error it puts on the fused surface.
ALIGN_LEVER = 0.2


@dataclass
class SfmResult:
    poses: dict[str, Array]
    """T_ref_camera per registered frame (ref: the first registered camera, metres)."""
    unregistered: list[str] = field(default_factory=list)
    scale: float = float("nan")
    """Metres per reconstruction unit (from the depth frames)."""
    seconds: float = 0.0
    points: int = 0


def colmap_poses(capture: Capture, overlap: int = 25, max_features: int = 4000) -> SfmResult:
    """Runs structure-from-motion on the capture's colour frames; raises CaptureError when no
    frame registers."""
    import pycolmap

    t0 = time.perf_counter()
    try:  # COLMAP's per-step INFO lines would drown the progress display
        pycolmap.logging.minloglevel = 1
    except AttributeError:
        pass
    cam = capture.camera
    work = Path(tempfile.mkdtemp(prefix="vinetwin-sfm-"))
    try:
        images = work / "images"
        images.mkdir()
        names = {}
        for f in capture.frames:
            if f.color_path is None:
                raise CaptureError(
                    f"frame {f.id}: no colour image; structure-from-motion needs colour"
                )
            name = f"{f.id}.png"
            shutil.copyfile(f.color_path, images / name)
            names[name] = f.id
        db = work / "database.db"
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = "PINHOLE"
        reader.camera_params = f"{cam.fx},{cam.fy},{cam.cx},{cam.cy}"
        extraction = pycolmap.FeatureExtractionOptions()
        extraction.sift.max_num_features = max_features
        extraction.num_threads = -1
        pycolmap.extract_features(
            db, images, camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
            extraction_options=extraction, device=pycolmap.Device.cpu,
        )  # fmt: skip
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = overlap
        pairing.loop_detection = False
        pycolmap.match_sequential(db, pairing_options=pairing, device=pycolmap.Device.cpu)
        opts = pycolmap.IncrementalPipelineOptions()
        opts.ba_refine_focal_length = False
        opts.ba_refine_principal_point = False
        opts.ba_refine_extra_params = False
        out = work / "sparse"
        out.mkdir()
        recs = pycolmap.incremental_mapping(db, images, out, options=opts)
        if not recs:
            raise CaptureError(f"{capture.root}: structure-from-motion registered no frame")
        rec = max(recs.values(), key=lambda r: r.num_reg_images())
        # world-from-camera poses in the reconstruction's frame and units
        T_wc: dict[str, Array] = {}
        for img in rec.images.values():
            if not img.has_pose:
                continue
            M = np.asarray(img.cam_from_world().matrix())  # 3x4
            T_wc[names[img.name]] = invert(np.vstack([M, [0, 0, 0, 1]]))
        if not T_wc:
            raise CaptureError(f"{capture.root}: structure-from-motion registered no frame")
        # metric scale from the depth frames
        ratios = []
        frames = {f.id: f for f in capture.frames}
        for img in rec.images.values():
            if not img.has_pose:
                continue
            fid = names[img.name]
            depth = frames[fid].depth(capture.depth_unit)
            M = np.asarray(img.cam_from_world().matrix())
            for p2d in img.points2D:
                if not p2d.has_point3D():
                    continue
                X = np.asarray(rec.points3D[p2d.point3D_id].xyz)
                z = float(M[2, :3] @ X + M[2, 3])
                u, v = (round(float(c)) for c in p2d.xy)
                if 0 <= v < depth.shape[0] and 0 <= u < depth.shape[1] and z > 0:
                    dm = depth[v, u]
                    if dm > 0:
                        ratios.append(dm / z)
        if len(ratios) < 20:
            raise CaptureError(
                f"{capture.root}: too few depth measurements at triangulated points to recover the scale"
            )
        scale = float(np.median(ratios))
        first = min(T_wc)
        ref = invert(T_wc[first])
        poses = {}
        for fid, T in T_wc.items():
            Tm = ref @ T
            poses[fid] = make_pose(Tm[:3, :3], Tm[:3, 3] * scale)
        unregistered = [f.id for f in capture.frames if f.id not in poses]
        return SfmResult(poses, unregistered, scale, time.perf_counter() - t0, len(rec.points3D))
    finally:
        shutil.rmtree(work, ignore_errors=True)


def align_to(
    poses: dict[str, Array], reference: dict[str, Array], lever: float = ALIGN_LEVER
) -> dict[str, Array]:
    """Poses moved rigidly (no scale) onto `reference` by the frames both hold (Kabsch): e.g.
    SfM or odometry poses expressed in the robot base. Each frame contributes its camera centre
    and the three points `lever` (m) along its axes, so that the frames' orientations count as
    well as their positions: centres alone leave the rotation about their line free when the
    camera moved along a line (one pass of a sweep: 2.1-2.5 deg off, and a fused mesh at
    F-score 0.54 at 5 mm against 0.95 with the true poses). 0: the centres alone (then at
    least 3 frames, not on a line)."""
    common = [k for k in poses if k in reference]
    if len(common) < (3 if lever <= 0 else 1):
        raise CaptureError(
            f"{len(common)} frames in common with the reference poses: cannot align the poses"
        )
    offsets = np.vstack([np.zeros(3), lever * np.eye(3)]) if lever > 0 else np.zeros((1, 3))
    A = np.vstack([transform_points(poses[k], offsets) for k in common])
    B = np.vstack([transform_points(reference[k], offsets) for k in common])
    ca, cb = A.mean(0), B.mean(0)
    U, _, Vt = np.linalg.svd((A - ca).T @ (B - cb))
    D = np.diag([1.0, 1.0, float(np.sign(np.linalg.det(Vt.T @ U.T)))])
    R = Vt.T @ D @ U.T
    G = make_pose(R, cb - R @ ca)
    return {k: G @ T for k, T in poses.items()}
