"""TSDF fusion of a capture into a vine mesh, clean-up, and evaluation against a ground truth.

Fusion uses Open3D's VoxelBlockGrid (tensor TSDF, CPU) at 1-2 mm voxels with the D405's working range;
the mesh comes out by marching cubes, then loses its small floating components (fusion debris
from flying pixels: few triangles and a few millimetres across; `drop_debris`), is optionally
smoothed (Taubin) and decimated to a target size.

Evaluation samples both meshes and reports the Chamfer distance and the precision, recall and
F-score at given distances (2 mm and 5 mm by default). The ground truth is restricted to the part
the capture measured (`observed`: seen unoccluded and within range by at least 3 frames, at an
incidence of at most 60 degrees), since no capture can rebuild what it never measured; precision
is against the whole ground truth.
"""

from __future__ import annotations

import re
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from vinetwin import _lazy
from vinetwin.capture.folder import Capture, CaptureError
from vinetwin.errors import InputError
from vinetwin.frames import Array, invert, transform_points
from vinetwin.reconstruct.config import FUSED_DEPTH_MAX, TRUNCATION_VOXELS, FusionConfig


@dataclass
class FusionResult:
    vertices: Array
    faces: np.ndarray
    frames_used: list[str] = field(default_factory=list)
    frames_skipped: dict[str, str] = field(default_factory=dict)
    seconds: float = 0.0
    removed_components: int = 0


def drop_debris(mesh: Any, cfg: FusionConfig) -> int:
    """Removes from an Open3D mesh, in place, its connected components with fewer triangles than
    `cfg.min_component` of the largest's that also span less than `cfg.min_component_extent`
    (their bounding box's diagonal); returns how many it removed."""
    if not len(mesh.triangles):
        return 0
    clusters, counts, _ = mesh.cluster_connected_triangles()
    clusters = np.asarray(clusters)
    counts = np.asarray(counts)
    small = counts < cfg.min_component * counts.max()
    if small.any() and cfg.min_component_extent > 0:
        corners = np.asarray(mesh.vertices)[np.asarray(mesh.triangles)]  # (T, 3, 3)
        lo = np.full((len(counts), 3), np.inf)
        hi = np.full((len(counts), 3), -np.inf)
        np.minimum.at(lo, clusters, corners.min(axis=1))
        np.maximum.at(hi, clusters, corners.max(axis=1))
        small &= np.linalg.norm(hi - lo, axis=1) < cfg.min_component_extent
    if small.any():
        mesh.remove_triangles_by_mask(small[clusters])
        mesh.remove_unreferenced_vertices()
    return int(small.sum())


def fuse(
    capture: Capture,
    poses: dict[str, Array],
    config: FusionConfig | None = None,
    progress: Callable[[Any, int, int], None] | None = None,
) -> FusionResult:
    """Fuses the frames that have a pose (`poses`: frame id -> T_world_camera) into a mesh."""
    o3d = _lazy.open3d()
    o3c = o3d.core
    cfg = config or FusionConfig()
    cam = capture.camera
    t0 = time.perf_counter()
    vbg = o3d.t.geometry.VoxelBlockGrid(
        attr_names=("tsdf", "weight", "color"),
        attr_dtypes=(o3c.float32, o3c.float32, o3c.float32),
        attr_channels=((1), (1), (3)),
        voxel_size=cfg.voxel,
        block_resolution=8,
        block_count=cfg.block_count,
        device=o3c.Device("CPU:0"),
    )
    K = o3c.Tensor(cam.K, o3c.float64)
    scale = 1.0 / capture.depth_unit
    trunc_voxels = cfg.truncation / cfg.voxel if cfg.truncation > 0 else float(TRUNCATION_VOXELS)
    depth_min = max(cfg.depth_min, cam.min_depth)  # what the camera calls invalid stays out
    used, skipped = [], {}
    for k, f in enumerate(capture.frames):
        if f.id not in poses:
            skipped[f.id] = "no pose"
            continue
        d16 = f.depth_counts().copy()
        d16[d16 < int(np.ceil(depth_min * scale))] = 0
        d16[d16 > int(cfg.depth_max * scale)] = 0  # Open3D aborts on a frame it cannot use
        n_pixels = int(np.count_nonzero(d16))
        if n_pixels == 0:
            skipped[f.id] = "no depth within range"
            continue
        if n_pixels < cfg.min_pixels:
            skipped[f.id] = (
                f"{n_pixels} depth pixels within range, fewer than the minimum {cfg.min_pixels}"
            )
            continue
        color = (
            f.color()
            if f.color_path is not None
            else np.zeros((cam.height, cam.width, 3), np.uint8)
        )
        depth_img = o3d.t.geometry.Image(o3c.Tensor(d16))
        color_img = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(color)))
        ext = o3c.Tensor(invert(poses[f.id]), o3c.float64)
        try:
            blocks = vbg.compute_unique_block_coordinates(
                depth_img, K, ext, scale, cfg.depth_max, trunc_voxels
            )
            vbg.integrate(
                blocks, depth_img, color_img, K, K, ext, scale, cfg.depth_max, trunc_voxels
            )
        except RuntimeError as exc:  # one frame Open3D refuses does not lose the others
            skipped[f.id] = f"Open3D could not integrate it: {_open3d_message(exc)}"
            continue
        used.append(f.id)
        if progress:
            progress(f.id, k + 1, len(capture.frames))
    if not used:
        raise CaptureError(f"{capture.root}: no frame could be fused ({len(skipped)} skipped)")
    mesh = vbg.extract_triangle_mesh().to_legacy()
    removed = drop_debris(mesh, cfg)
    if cfg.smooth_iterations > 0:
        mesh = mesh.filter_smooth_taubin(cfg.smooth_iterations)
    if cfg.target_triangles > 0 and len(mesh.triangles) > cfg.target_triangles:
        mesh = mesh.simplify_quadric_decimation(cfg.target_triangles)
    V = np.asarray(mesh.vertices, dtype=np.float64)
    F = np.asarray(mesh.triangles, dtype=np.int64)
    if len(F) == 0:
        raise CaptureError(f"{capture.root}: fusion produced an empty mesh")
    return FusionResult(V, F, used, skipped, time.perf_counter() - t0, removed)


def _open3d_message(exc: BaseException) -> str:
    """Open3D's own words from one of its errors, without the C++ signature and colour codes."""
    text = re.sub(r"\x1b\[[0-9;]*m", "", str(exc)).strip()
    return text.split(".cpp:", 1)[-1].split(": ", 1)[-1].strip() or text


def kinematic_poses(capture: Capture) -> dict[str, Array]:
    """Frame poses from the capture's robot kinematics (T_base_camera per frame)."""
    poses = {f.id: f.T_base_camera for f in capture.frames if f.T_base_camera is not None}
    if not poses:
        raise CaptureError(
            f"{capture.root}: no frame has a T_base_camera (robot kinematics); choose another pose source"
        )
    return poses  # type: ignore[return-value]


# ----------------------------------------------------------------------------- evaluation
def _sample(V: Array, F: np.ndarray, n: int, seed: int) -> tuple[Array, Array]:
    """Points spread evenly over a mesh and the normals of their faces."""
    import trimesh

    mesh = trimesh.Trimesh(V, F, process=False)
    pts, face = trimesh.sample.sample_surface_even(mesh, n, seed=seed)
    return np.asarray(pts, dtype=np.float64), np.asarray(mesh.face_normals[face], dtype=np.float64)


def observed(
    points: Array,
    normals: Array,
    capture: Capture,
    poses: dict[str, Array],
    V: Array,
    F: np.ndarray,
    *,
    min_views: int = 3,
    max_incidence_deg: float = 60.0,
    tol: float = 0.003,
) -> np.ndarray:
    """Mask of ground-truth points the capture measured: seen in at least `min_views` frames,
    inside the image, within the range fused (the camera's minimum to `FUSED_DEPTH_MAX`), not behind other ground-truth surface (ray cast of
    the ground truth at that pixel), at an incidence of at most `max_incidence_deg` (beyond it,
    on a cane's silhouette, the stereo depth is dropped or smeared: no capture measures it)."""
    from vinetwin.render.backends import raycaster

    cam = capture.camera
    backend = raycaster(V, F, cam, coarse_step=1)
    views = np.zeros(len(points), int)
    cos_min = float(np.cos(np.radians(max_incidence_deg)))
    for T in poses.values():
        p = transform_points(invert(T), points)
        z = p[:, 2]
        ok = (z >= cam.min_depth) & (z < FUSED_DEPTH_MAX)
        u = np.round(cam.fx * p[:, 0] / np.where(ok, z, 1) + cam.cx).astype(int)
        v = np.round(cam.fy * p[:, 1] / np.where(ok, z, 1) + cam.cy).astype(int)
        ok &= (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
        if not ok.any():
            continue
        idx = np.nonzero(ok)[0]
        d = backend.render(T)
        dz = d[v[idx], u[idx]]
        ray = T[:3, 3] - points[idx]
        ray /= np.linalg.norm(ray, axis=1, keepdims=True)
        facing = np.abs(np.einsum("ij,ij->i", ray, normals[idx])) >= cos_min
        vis = np.isfinite(dz) & (np.abs(dz - z[idx]) < tol) & facing
        views[idx[vis]] += 1
    backend.close()
    return views >= min_views


def evaluate(
    V: Array,
    F: np.ndarray,
    V_gt: Array,
    F_gt: np.ndarray,
    *,
    gt_mask_fn: Callable[[Array, Array], np.ndarray] | None = None,
    thresholds: tuple[float, ...] = (0.002, 0.005),
    samples: int = 200_000,
) -> dict[str, Any]:
    """Chamfer distance and precision/recall/F-score of a mesh against the ground truth."""
    from scipy.spatial import KDTree

    if len(F) == 0 or len(F_gt) == 0:
        raise InputError("evaluation needs two non-empty meshes")
    rec, _ = _sample(V, F, samples, 1)
    gt_all, gt_normals = _sample(V_gt, F_gt, samples, 2)
    gt = gt_all[gt_mask_fn(gt_all, gt_normals)] if gt_mask_fn is not None else gt_all
    if len(gt) == 0:
        raise InputError("no ground-truth surface was observed by the capture")
    # precision: reconstructed points near the (whole) ground truth; recall: observed ground
    # truth near the reconstruction
    d_rec = KDTree(gt_all).query(rec, workers=-1)[0]
    d_gt = KDTree(rec).query(gt, workers=-1)[0]
    out: dict[str, Any] = {
        "chamfer_mm": 1000 * 0.5 * (float(d_rec.mean()) + float(d_gt.mean())),
        "accuracy_mm_median": 1000 * float(np.median(d_rec)),
        "completeness_mm_median": 1000 * float(np.median(d_gt)),
        "observed_gt_samples": len(gt),
    }
    for t in thresholds:
        p = float((d_rec < t).mean())
        r = float((d_gt < t).mean())
        out[f"precision@{1000 * t:g}mm"] = p
        out[f"recall@{1000 * t:g}mm"] = r
        out[f"fscore@{1000 * t:g}mm"] = 2 * p * r / (p + r) if p + r > 0 else 0.0
    return out
