"""The wide search: registration from several hypotheses around a prediction, for when tracking
lost the vine (a jerk of the vine, a long occlusion, ICP that slid off along a cane).

Tracking ICP starts from one prediction and has a basin of about a centimetre at its final
levels. The wide search registers the clouds at 8 mm (16 mm then 8 mm voxels, a reach of three
voxels) from the prediction and from 12 hypotheses around it: moved by +-`translation` along
each axis of the reference camera, and turned by +-`rotation` about each axis through the
reference cloud's centre. The coarse answers, best first by the share of the clouds they pair,
are then refined at full resolution (`ICPConfig.coarse_to_fine`'s last levels) until two
distinct ones are known: each refined answer that passes the trust thresholds is a candidate.
When a second candidate, clearly elsewhere, fits nearly as well as the best (a repetitive vine:
the next spur looks like this one), the answer is ambiguous and none is given: the caller keeps
the arm still. Coarse first keeps a search near 10 ms per hypothesis on 2 cores, also on the
many points of a camera far from its goal.

It registers with point-to-plane when the reference has normals (the variant with the widest
basin measured, benchmarks/icp.py), whatever variant tracks: re-acquisition is a separate
stage, and once it has a pose the servo's own variant tracks from there.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from vinetwin.camera import CameraModel
from vinetwin.cloud import Cloud, voxel_downsample
from vinetwin.frames import Array, make_pose, pose_error, so3_exp
from vinetwin.registration.icp import ICP, ICPConfig, ICPResult


@dataclass
class SearchResult:
    """Outcome of `WideSearch.align`."""

    best: ICPResult | None
    """The best candidate (None when none passed the thresholds or the answer is ambiguous)."""
    candidates: int
    """How many hypotheses converged and passed the thresholds."""
    hypotheses: int
    reason: str = ""
    """Why there is no answer (empty with one)."""


#: The voxel (m) of the search's coarse stage.
COARSE_VOXEL = 0.008


class WideSearch:
    """Multi-hypothesis coarse-to-fine registration against one reference cloud."""

    def __init__(
        self,
        reference: Cloud,
        *,
        variant: str = "point_to_plane",
        camera: CameraModel | None = None,
        max_depth: float = math.inf,
    ) -> None:
        """`variant` is the tracking variant; the search uses point-to-plane when the reference
        has normals, else that variant."""
        has_normals = reference.normals is not None and len(reference.normals) == len(
            reference.points
        )
        self.variant = "point_to_plane" if has_normals else variant
        self.coarse_voxel = COARSE_VOXEL
        pts, nrm = voxel_downsample(reference.points, self.coarse_voxel, reference.normals)
        self.coarse = ICP(
            Cloud(pts, nrm),
            ICPConfig(
                variant=self.variant,
                schedule=((2 * self.coarse_voxel, 6 * self.coarse_voxel),),
                max_correspondence_distance=3 * self.coarse_voxel,
                min_points=10,
                min_correspondences=10,
                coarse_tolerance=0.0,  # the search as measured (its re-acquisitions, docs/servo.md)
            ),
            camera=camera,
            max_depth=max_depth,
        )
        fine = ICPConfig.coarse_to_fine(self.variant)
        self.icp = ICP(
            reference,
            ICPConfig(
                variant=self.variant,
                schedule=tuple(lv for lv in fine.levels()[:-1] if lv[0] == 0.0),
                max_correspondence_distance=fine.max_correspondence_distance,
                coarse_tolerance=0.0,
            ),
            camera=camera,
            max_depth=max_depth,
        )
        pts = reference.points
        self.centre = pts.mean(0) if len(pts) else np.zeros(3)

    def hypotheses(self, prediction: Array, translation: float, rotation: float) -> list[Array]:
        """The prediction, then it moved along and turned about each reference axis."""
        out = [np.asarray(prediction, dtype=np.float64)]
        c = self.centre
        for axis in np.eye(3):
            for sign in (1.0, -1.0):
                if translation > 0:
                    out.append(make_pose(t=sign * translation * axis) @ out[0])
                if rotation > 0:
                    R = so3_exp(sign * rotation * axis)
                    turn = make_pose(R, c - R @ c)  # about the cloud's centre
                    out.append(turn @ out[0])
        return out

    def align(
        self,
        current: Cloud,
        prediction: Array,
        *,
        translation: float,
        rotation: float,
        accept: Any,
        distinct_translation: float = 0.01,
        distinct_rotation: float = 0.05,
        ambiguity: float = 0.9,
    ) -> SearchResult:
        """Registers `current` from every hypothesis. `accept(result) -> str` gives the reason a
        converged result is not trusted ("" when it is). A candidate farther than
        `distinct_translation` / `distinct_rotation` from the best whose overlap is at least
        `ambiguity` times the best's makes the answer ambiguous."""
        hyps = self.hypotheses(prediction, translation, rotation)
        pts, nrm = voxel_downsample(current.points, self.coarse_voxel, current.normals)
        small = Cloud(pts, nrm)
        coarse = [r for r in (self.coarse.align(small, h) for h in hyps) if r.converged]
        coarse.sort(key=lambda r: (-r.overlap, r.inlier_rmse))
        ok: list[ICPResult] = []
        last_reason = "no hypothesis converged"
        for c in coarse:  # refine, best first, until two distinct answers are known
            if any(
                _near(c.T_ref_cur, o.T_ref_cur, distinct_translation, distinct_rotation) for o in ok
            ):
                continue
            r = self.icp.align(current, c.T_ref_cur)
            why = f"ICP failed: {r.reason}" if not r.converged else accept(r)
            if why:
                last_reason = why
                continue
            if any(
                _near(r.T_ref_cur, o.T_ref_cur, distinct_translation, distinct_rotation) for o in ok
            ):
                continue
            ok.append(r)
            if len(ok) == 2:
                break
        if not ok:
            return SearchResult(None, 0, len(hyps), f"no hypothesis fits ({last_reason})")
        ok.sort(key=lambda r: (-r.overlap, r.inlier_rmse))
        best = ok[0]
        if len(ok) > 1 and ok[1].overlap >= ambiguity * best.overlap:
            dt, dr = pose_error(ok[1].T_ref_cur, best.T_ref_cur)
            return SearchResult(
                None,
                len(ok),
                len(hyps),
                f"ambiguous: two poses {1000 * dt:.0f} mm / {math.degrees(dr):.1f} deg apart "
                f"fit alike (overlap {best.overlap:.2f} and {ok[1].overlap:.2f})",
            )
        return SearchResult(best, len(ok), len(hyps))


def _near(a: Array, b: Array, translation: float, rotation: float) -> bool:
    dt, dr = pose_error(a, b)
    return dt <= translation and dr <= rotation
