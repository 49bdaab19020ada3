"""Global registration by features: Open3D's FPFH descriptors matched by RANSAC, with the
settings the servo's arrival and the odometry's joining of runs share. A proposal for a local
registration to refine and check, never an answer on its own: FPFH is weak on thin canes (a
handful of matches survive), and one RANSAC seed can end far off (docs/reconstruct.md)."""

from __future__ import annotations

from typing import Any

import numpy as np

from vinetwin import _lazy
from vinetwin.frames import Array


def fpfh(pcd: Any, radius: float) -> Any:
    """FPFH features of an Open3D point cloud with normals, over `radius` (m), 100 neighbours
    at most."""
    o3d = _lazy.open3d()
    return o3d.pipelines.registration.compute_fpfh_feature(
        pcd, o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=100)
    )


def ransac_proposal(
    src: Any,
    dst: Any,
    src_features: Any,
    dst_features: Any,
    reach: float,
    iterations: int,
    seed: int,
    mutual: bool,
) -> tuple[Array, float]:
    """(T_dst_src, fitness) from RANSAC over feature matches (`mutual`: matches both ways only):
    3 points per hypothesis, kept when the pairs' edge lengths agree within 10% and the pairs lie
    within `reach` (m); `iterations` at most, Open3D's random generator seeded with `seed`."""
    o3d = _lazy.open3d()
    reg = o3d.pipelines.registration
    o3d.utility.random.seed(int(seed))
    res = reg.registration_ransac_based_on_feature_matching(
        src, dst, src_features, dst_features, mutual, reach,
        reg.TransformationEstimationPointToPoint(False), 3,
        [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9),
         reg.CorrespondenceCheckerBasedOnDistance(reach)],
        reg.RANSACConvergenceCriteria(int(iterations), 0.999),
    )  # fmt: skip
    return np.asarray(res.transformation), float(res.fitness)
