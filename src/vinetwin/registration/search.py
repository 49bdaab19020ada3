"""The wide search: registration from several hypotheses around a prediction, for when tracking
lost the vine (a jerk of the vine, a long occlusion, ICP that slid off along a cane).

Tracking ICP starts from one prediction and has a basin of about a centimetre at its final
levels. The wide search runs a coarse-to-fine ICP (`ICPConfig.coarse_to_fine`: 16 mm and 8 mm
voxels first) from the prediction and from 12 hypotheses around it: moved by +-`translation`
along each axis of the reference camera, and turned by +-`rotation` about each axis through the
reference cloud's centre. Each converged answer that passes the trust thresholds is a candidate;
the best is the one pairing the largest share of the clouds (`ICPResult.overlap`), then the
lowest RMSE. When another candidate, clearly elsewhere, fits nearly as well (a repetitive vine:
the next spur looks like this one), the answer is ambiguous and none is given: the caller keeps
the arm still.

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
from vinetwin.cloud import Cloud
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
        self.icp = ICP(
            reference, ICPConfig.coarse_to_fine(self.variant), camera=camera, max_depth=max_depth
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
        ok: list[ICPResult] = []
        last_reason = "no hypothesis converged"
        for h in hyps:
            r = self.icp.align(current, h)
            why = f"ICP failed: {r.reason}" if not r.converged else accept(r)
            if why:
                last_reason = why
                continue
            ok.append(r)
        if not ok:
            return SearchResult(None, 0, len(hyps), f"no hypothesis fits ({last_reason})")
        ok.sort(key=lambda r: (-r.overlap, r.inlier_rmse))
        best = ok[0]
        for other in ok[1:]:
            dt, dr = pose_error(other.T_ref_cur, best.T_ref_cur)
            if (dt > distinct_translation or dr > distinct_rotation) and (
                other.overlap >= ambiguity * best.overlap
            ):
                return SearchResult(
                    None,
                    len(ok),
                    len(hyps),
                    f"ambiguous: two poses {1000 * dt:.0f} mm / {math.degrees(dr):.1f} deg apart "
                    f"fit alike (overlap {best.overlap:.2f} and {other.overlap:.2f})",
                )
        return SearchResult(best, len(ok), len(hyps))
