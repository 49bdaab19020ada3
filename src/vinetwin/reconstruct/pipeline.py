"""The reconstruction pipeline behind `vinetwin reconstruct`, reusable from Python: a capture
folder -> camera poses (the robot's kinematics, pycolmap structure-from-motion, or depth
odometry) -> TSDF fusion -> a vine mesh written into a twin, optionally scored against a
ground-truth mesh.

    report = reconstruct("capture/", "vine.twin", ReconstructConfig(poses="colmap"))
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

from vinetwin.errors import TwinError
from vinetwin.files import atomic_write_json
from vinetwin.reconstruct.config import OdometryConfig, ReconstructConfig

log = logging.getLogger(__name__)


def reconstruct(
    capture: str | Path,
    twin: str | Path,
    config: ReconstructConfig | None = None,
    odometry: OdometryConfig | None = None,
    *,
    overwrite: bool = False,
    ground_truth: str | Path | None = None,
    progress: Callable[[object, int, int], None] | None = None,
    json_path: str | Path | None = None,
) -> dict[str, Any]:
    """Fuses the capture folder into a mesh in the twin folder `twin` (created; or, with
    `overwrite`, an existing twin's mesh replaced, its cut points and poses kept). With
    `ground_truth` (a twin folder or a mesh file) the mesh is scored: Chamfer distance and
    F-scores under `report["evaluation"]`. `odometry`: depth odometry's settings (with
    `config.poses` odometry). Returns the report, also written to `json_path`."""
    import numpy as np

    from vinetwin.capture.folder import CaptureError, read_capture
    from vinetwin.mesh import load_mesh
    from vinetwin.reconstruct.fusion import evaluate, fuse, kinematic_poses, observed
    from vinetwin.twin.model import TWIN_FILE, Twin

    cfg = config or ReconstructConfig()
    capture, twin_dir = Path(capture), Path(twin)
    if (twin_dir / TWIN_FILE).exists() and not overwrite:
        raise TwinError(
            f"{twin_dir}: already holds a twin; pass --overwrite (overwrite=True) to replace its "
            "mesh (its cut points and poses are kept)"
        )
    cap = read_capture(capture)
    pose_report: dict[str, object] = {}
    not_fused: dict[str, str] = {}
    if cfg.poses == "odometry":
        from vinetwin.reconstruct.odometry import MIN_RUN_FRAMES, odometry_poses
        from vinetwin.reconstruct.sfm import align_to

        odo = odometry_poses(cap, odometry)
        run = odo.longest_run
        if len(run) < MIN_RUN_FRAMES:
            raise CaptureError(
                f"{capture}: odometry linked at most {len(run)} consecutive frames of "
                f"{len(cap.frames)} ({len(odo.failed)} pairs did not align): the capture is not "
                "video-like (frames a few centimetres and degrees apart, most of the view within "
                "0.5 m); choose --poses kinematics or colmap"
            )
        # only the linked frames (the longest run and the runs joined to it): a frame after a
        # failed pair is placed by a guess, and so is every frame chained to it, until joined
        linked = odo.linked
        poses = {k: odo.poses[k] for k in linked}
        if cap.has_poses:
            poses = align_to(poses, kinematic_poses(cap))
        pose_report = {
            "failed_pairs": odo.failed, "searched_pairs": odo.searched, "seconds": odo.seconds,
            "runs": [[r[0], r[-1], len(r)] for r in odo.runs],
            "joined_runs": odo.joined, "runs_not_joined": odo.not_joined,
        }  # fmt: skip
        log.info(
            "odometry over %d frames in %.1f s%s%s", len(cap.frames), odo.seconds,
            f"; pairs aligned by the wide search: {', '.join(odo.searched)}" if odo.searched else "",
            f"; pairs that did not align: {', '.join(odo.failed)}" if odo.failed else "",
        )  # fmt: skip
        if len(odo.runs) > 1:
            for first, fitness in odo.joined.items():
                log.info(
                    "odometry: the run from %s joined to the longest by global registration "
                    "(fitness %.2f)", first, fitness,
                )  # fmt: skip
            for first, why in odo.not_joined.items():
                log.warning("odometry: the run from %s was not joined: %s", first, why)
            if len(linked) < len(cap.frames):
                log.warning(
                    "odometry linked %d runs of frames; fusing %d of %d frames (the longest run, "
                    "%s to %s, and %d joined to it): the others' poses relative to it are unknown",
                    len(odo.runs), len(linked), len(cap.frames), run[0], run[-1], len(odo.joined),
                )  # fmt: skip
            skip = f"odometry: not linked to the run fused ({run[0]} to {run[-1]})"
            not_fused = {f.id: skip for f in cap.frames if f.id not in poses}
    elif cfg.poses == "colmap":
        from vinetwin.reconstruct.sfm import align_to, colmap_poses

        sfm = colmap_poses(cap)
        poses = sfm.poses
        not_fused = dict.fromkeys(sfm.unregistered, "structure-from-motion did not register it")
        if cap.has_poses:  # express the mesh in the robot base, as kinematics would
            poses = align_to(poses, kinematic_poses(cap))
        pose_report = {
            "registered": len(sfm.poses),
            "unregistered": sfm.unregistered,
            "scale_m_per_unit": sfm.scale,
            "seconds": sfm.seconds,
            "points": sfm.points,
        }
        log.info(
            "structure-from-motion registered %d of %d frames in %.1f s%s",
            len(sfm.poses), len(cap.frames), sfm.seconds,
            f"; not registered: {', '.join(sfm.unregistered)}" if sfm.unregistered else "",
        )  # fmt: skip
    else:
        poses = kinematic_poses(cap)
    res = fuse(cap, poses, cfg.fusion(), progress)
    res.frames_skipped.update(not_fused)  # why they had no pose
    source = {"reconstructed_from": str(capture), "poses": cfg.poses, "voxel": cfg.voxel}
    if (twin_dir / TWIN_FILE).exists():
        existing = Twin.load(twin_dir)
        existing.write_mesh(res.vertices, res.faces)
        existing.extra["provenance_reconstruction"] = source
        existing.save()
    else:
        Twin.create(twin_dir, res.vertices, res.faces, camera=cap.camera, source=source)
    report: dict[str, Any] = {
        "frames_fused": len(res.frames_used),
        "frames_skipped": res.frames_skipped,
        "seconds": res.seconds,
        "triangles": len(res.faces),
        "removed_components": res.removed_components,
        "poses": cfg.poses,
        **({f"{cfg.poses}_report": pose_report} if pose_report else {}),
    }
    log.info(
        "fused %d frames in %.1f s: %d triangles -> %s",
        len(res.frames_used), res.seconds, len(res.faces), twin_dir,
    )  # fmt: skip
    if res.frames_skipped:
        reasons: dict[str, list[str]] = {}
        for fid, why in res.frames_skipped.items():
            reasons.setdefault(why, []).append(fid)
        for why, fids in reasons.items():
            log.warning("%d frames not fused (%s): %s", len(fids), why, ", ".join(fids))
    if ground_truth is not None:
        gt_path = Path(ground_truth)
        gt = (
            Twin.load(gt_path).load_mesh() if (gt_path / TWIN_FILE).exists() else load_mesh(gt_path)
        )
        Vg, Fg = np.asarray(gt.vertices), np.asarray(gt.faces)
        gt_poses = kinematic_poses(cap) if cap.has_poses else poses
        ev = report["evaluation"] = evaluate(
            res.vertices, res.faces, Vg, Fg,
            gt_mask_fn=lambda p, n: observed(p, n, cap, gt_poses, Vg, Fg),
        )  # fmt: skip
        log.info(
            "against %s: Chamfer %.2f mm, F-score@2mm %.3f, F-score@5mm %.3f", gt_path,
            ev["chamfer_mm"], ev["fscore@2mm"], ev["fscore@5mm"],
        )  # fmt: skip
    if json_path is not None:
        Path(json_path).parent.mkdir(parents=True, exist_ok=True)
        atomic_write_json(Path(json_path), report)
    return report
