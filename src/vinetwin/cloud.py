"""The perception chain shared by reference clouds and live clouds.

Every cloud that reaches ICP, synthetic or live, goes through `perceive` with the twin's
`PerceptionConfig`: a difference between the two chains would be a sim-to-real gap that ICP turns
into a pose error. Steps (the paper's, plus a cheap image-space filter):

1. depth image (metres) -> drop invalid pixels and pixels beyond `max_depth`;
2. flying-pixel filter on the depth image: a pixel whose depth differs from a 4-neighbour by
   more than `edge_threshold` (relative) is dropped (the smeared silhouettes of thin canes);
3. deprojection to camera-frame points;
4. voxel-grid downsampling (`voxel_size`);
5. outlier removal after the voxel grid (far cheaper than before it), by `outlier_rule`: the
   radius rule (default: at least `radius_neighbors` others within `outlier_radius`), the
   paper's statistical rule (`sor_neighbors`, `sor_std_ratio`) or none;
6. normals (for point-to-plane and symmetric ICP), oriented towards the camera. They come from
   the organised depth image (central differences of neighbouring pixels) averaged per voxel,
   which is far cheaper than a neighbour search on the points and averages the noise of ~100
   pixels per voxel. A voxel made only of pixels whose normal is undefined (a 1-2 px sliver at
   a silhouette) is dropped when normals are asked for.

The per-pixel and per-point loops are compiled (`vinetwin._cloud_kernels` and `_outlier_kernels`, numba): steps 1-4 and the
per-pixel normals run as one pass over the image (no per-pixel arrays), in bands of rows on
numba's thread count of Python threads (the kernels release the GIL) when the image has enough
in-range pixels, and step 5 finds each point's neighbours by a search of grid cells instead of
a k-d tree. The radius rule counts the points of the 27 cells around a point's cell; the statistical
rule gathers them once for all the points of a cell and selects each point's k nearest among
them (exact: the same answer as the tree, `tests/test_cloud.py`; a point whose k-th neighbour
may lie farther is searched alone in growing rings). The steps match Open3D's
`voxel_down_sample`, `remove_radius_outlier` and `remove_statistical_outlier`
(tests/test_cloud.py compares them).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from vinetwin._config import JsonFields
from vinetwin.camera import CameraModel
from vinetwin.errors import InputError

#: ICP variants known to vinetwin (the paper's four).
ICP_VARIANTS = ("point_to_point", "lm", "point_to_plane", "symmetric")
#: How much finer than the perception voxel the dense reference is (the voxel divided by this;
#: `render.reference.dense_cloud`, `ServoConfig.dense_reference`).
DENSE_FACTOR = 4
#: The largest `PerceptionConfig.decimation` (every 8th pixel of a 848x480 image: 106x60).
MAX_DECIMATION = 8
#: Outlier rules of the perception chain (`PerceptionConfig.outlier_rule`).
OUTLIER_RULES = ("radius", "statistical", "none")


@dataclass(frozen=True, kw_only=True)
class PerceptionConfig(JsonFields):
    """Settings of the perception chain (stored in twin.json under `perception`)."""

    max_depth: float = 0.40
    """Points farther than this (m, along the optical axis) are dropped."""
    min_depth: float = 0.0
    """Points nearer than this (m) are dropped (the sensor's own minimum applies anyway)."""
    edge_threshold: float = 0.03
    """Flying-pixel filter: relative depth jump to a 4-neighbour above which a pixel is dropped;
    0 disables it."""
    voxel_size: float = 0.004
    """Voxel-grid size (m); 0 disables downsampling."""
    decimation: int = 1
    """Use every n-th pixel of every n-th row (RealSense's decimation filter, without its
    median): n^2 times fewer pixels deprojected into the voxel grid. Normals keep the same
    2-pixel baseline in the full image; the flying-pixel filter compares a pixel with its
    decimated neighbours, n pixels away. 1 (default) uses every pixel."""
    outlier_rule: str = "radius"
    """How points are judged outliers after the voxel grid (`OUTLIER_RULES`): "radius" keeps a
    point with at least `radius_neighbors` others within `outlier_radius` (PCL's and Open3D's
    radius outlier removal), "statistical" applies Open3D's statistical rule (`sor_neighbors`,
    `sor_std_ratio`), "none" keeps every point. The radius rule is the default: on the views
    of four vines it gives the statistical rule's ICP accuracy, the rule itself in a tenth of
    the statistical rule's time (`benchmarks/perception.py`, `docs/render.md`)."""
    outlier_radius: float = 0.006
    """Radius outlier removal: the radius (m)."""
    radius_neighbors: int = 2
    """Radius outlier removal: other points needed within `outlier_radius`; 0 disables it."""
    sor_neighbors: int = 16
    """Statistical outlier removal: neighbours considered; 0 disables it."""
    sor_std_ratio: float = 2.0
    """Statistical outlier removal: keep points whose mean neighbour distance is within this many
    standard deviations of the average."""
    normal_radius: float = 0.012
    """Search radius (m) for normals."""
    normal_max_nn: int = 20
    """Most neighbours used for a normal."""

    def __post_init__(self) -> None:
        if self.outlier_rule not in OUTLIER_RULES:
            raise InputError(
                f"unknown outlier rule '{self.outlier_rule}'; choose one of: "
                f"{', '.join(OUTLIER_RULES)}"
            )
        d = self.decimation
        if isinstance(d, bool) or not isinstance(d, int) or not 1 <= d <= MAX_DECIMATION:
            raise InputError(f"decimation must be an integer from 1 to {MAX_DECIMATION}, not {d!r}")
        if self.outlier_rule == "radius" and self.radius_neighbors > 0 and self.outlier_radius <= 0:
            raise InputError("outlier_radius must be positive for the radius outlier rule")


# ----------------------------------------------------------------------------- the chain
@dataclass
class Cloud:
    """A point cloud in one camera frame: points (N, 3) metres, optional unit normals (N, 3)
    oriented towards the camera."""

    points: npt.NDArray[np.float64]
    normals: npt.NDArray[np.float64] | None = None

    def __len__(self) -> int:
        return int(self.points.shape[0])

    @property
    def empty(self) -> bool:
        return len(self) == 0


#: In-range pixels below which an image is one band (a band's hand-off to a thread costs tens
#: of microseconds; half of 20k pixels takes about 0.4 ms).
_MIN_BAND_PIXELS = 20_000


def _depth_voxels(
    d: npt.NDArray[np.float32],
    camera: CameraModel,
    cfg: PerceptionConfig,
    step: int,
    o: Any,
    threads: int | None = None,
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """Steps 1-4 and the per-pixel normals (`_cloud_kernels.depth_voxel_band`), the image cut into
    `threads` (default `_bands.threads()`, numba's thread count) bands of rows with equal numbers of in-range pixels
    (`vinetwin._bands`), the bands merged in row order (`_cloud_kernels.merge_voxel_bands`): voxel
    centroids and normal sums. The same voxels in the same order as one band, their sums equal
    to rounding."""
    from vinetwin import _bands, _cloud_kernels

    dmin = max(cfg.min_depth, 1e-6)
    args = (
        d, camera.fx, camera.fy, camera.cx, camera.cy, dmin, cfg.max_depth, cfg.edge_threshold,
        step, float(cfg.voxel_size), float(o[0]), float(o[1]), float(o[2]),
    )  # fmt: skip
    threads = _bands.threads() if threads is None else threads
    H = d.shape[0]
    rows = [0, H]
    if threads > 1 and H >= 32:
        work = _cloud_kernels.valid_rows(d, dmin, cfg.max_depth)  # in-range pixels before each row
        bands = max(1, min(threads, int(work[-1]) // _MIN_BAND_PIXELS))
        rows = _bands.cuts(work, bands)
    parts = _bands.run(_cloud_kernels.depth_voxel_band, args, rows)
    found = np.array([len(p[3]) for p in parts], np.int64)
    joined = (
        parts[0] if len(parts) == 1 else [np.concatenate([p[k] for p in parts]) for k in range(4)]
    )
    return _cloud_kernels.merge_voxel_bands(joined[0], joined[1], joined[2], joined[3], found)


def voxel_downsample(
    points: npt.NDArray[np.float64],
    voxel: float,
    normals: npt.NDArray[np.float64] | None = None,
    origin: npt.ArrayLike | None = None,
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64] | None]:
    """Centroid of the points in each occupied voxel; normals, when given, are averaged per voxel
    and returned as unit vectors (zero where the voxel's normals cancel or are undefined).

    The grid is anchored at `origin` (default: the frame's origin, so the grid is the same for
    every cloud in that frame). Open3D's `voxel_down_sample` anchors it at the cloud's minimum
    corner less half a voxel; pass that as `origin` to reproduce it exactly.
    """
    if voxel <= 0 or len(points) == 0:
        return points, normals
    from vinetwin import _cloud_kernels

    o = np.zeros(3) if origin is None else np.asarray(origin, dtype=np.float64).reshape(3)
    pts = np.ascontiguousarray(points, dtype=np.float64)
    nrm = (
        np.ascontiguousarray(normals, dtype=np.float64) if normals is not None else np.zeros((0, 3))
    )
    out, nout = _cloud_kernels.voxel_grid(
        pts, nrm, float(voxel), o[0], o[1], o[2], normals is not None
    )
    if normals is None:
        return out, None
    length = np.linalg.norm(nout, axis=1, keepdims=True)
    return out, np.divide(nout, length, out=np.zeros_like(nout), where=length > 1e-12)


def statistical_outliers(
    points: npt.NDArray[np.float64],
    neighbors: int,
    std_ratio: float,
    spacing: float | None = None,
) -> npt.NDArray[np.bool_]:
    """Mask of points to keep: mean distance to the `neighbors` nearest others within
    mean + std_ratio * std over the cloud (Open3D's remove_statistical_outlier rule).

    `spacing`: the cloud's typical point spacing (its voxel size); with it the neighbours are
    found by a compiled search of grid cells (exact, 4-10x faster than a k-d tree on a
    voxel-grid cloud); without it, or for points the cells leave unresolved, by scipy's tree."""
    n = len(points)
    if neighbors <= 1 or n <= neighbors:
        return np.ones(n, dtype=bool)
    from scipy.spatial import KDTree

    pts = np.ascontiguousarray(points, dtype=np.float64)
    if spacing is not None and spacing > 0:
        from vinetwin import _bands, _outlier_kernels

        cell = spacing * max(1.0, 0.75 * math.sqrt(neighbors))
        mean_d = _outlier_kernels.knn_mean_distance(pts, int(neighbors), cell, 3, _bands.threads())
        todo = np.flatnonzero(np.isnan(mean_d))
        if 0 < len(todo) <= 32:  # a few isolated points: against every point (no tree to build)
            for i in todo:
                d = np.sqrt(((pts - pts[i]) ** 2).sum(axis=1))
                mean_d[i] = np.partition(d, neighbors - 1)[:neighbors].mean()
        elif len(todo):
            dist, _ = KDTree(pts).query(pts[todo], k=neighbors)
            mean_d[todo] = dist.mean(axis=1)
    else:
        # like Open3D, the k neighbours include the point itself (at distance 0)
        dist, _ = KDTree(pts).query(pts, k=neighbors)
        mean_d = dist.mean(axis=1)
    mu = mean_d.mean()
    sd = mean_d.std(ddof=1)
    return mean_d <= mu + std_ratio * sd


def radius_outliers(
    points: npt.NDArray[np.float64], neighbors: int, radius: float
) -> npt.NDArray[np.bool_]:
    """Mask of points to keep: those with at least `neighbors` other points within `radius`
    (Open3D's `remove_radius_outlier(neighbors, radius)`, by a compiled search of grid cells)."""
    n = len(points)
    if neighbors <= 0 or n == 0:
        return np.ones(n, dtype=bool)
    from vinetwin import _outlier_kernels

    pts = np.ascontiguousarray(points, dtype=np.float64)
    return _outlier_kernels.radius_counts(pts, float(radius), int(neighbors)) >= neighbors


def outlier_mask(
    points: npt.NDArray[np.float64], config: PerceptionConfig
) -> npt.NDArray[np.bool_] | None:
    """The points the chain's outlier rule keeps (None: all of them)."""
    if config.outlier_rule == "radius" and config.radius_neighbors > 0:
        return radius_outliers(points, config.radius_neighbors, config.outlier_radius)
    if config.outlier_rule == "statistical" and config.sor_neighbors > 1:
        return statistical_outliers(
            points, int(config.sor_neighbors), config.sor_std_ratio, config.voxel_size or None
        )
    return None


def perceive(
    depth: Any,
    camera: CameraModel,
    config: PerceptionConfig | None = None,
    *,
    normals: bool = True,
    grid_origin: npt.ArrayLike | None = None,
) -> Cloud:
    """The perception chain: a z-depth image (H, W) in metres to a filtered cloud in the camera
    frame. Reference clouds and live clouds both come from here.

    An empty or all-invalid image (NaN, zeros) gives an empty cloud, never an exception.
    `grid_origin` anchors the voxel grid (default: the camera's origin; see `voxel_downsample`).

    The points do not depend on `normals`: a voxel none of whose pixels has a normal (the rim of
    a cane, two pixels from where its depth ends) is dropped either way, so a live cloud taken
    without normals and a reference taken with them sample the vine alike (without this rule the
    live cloud kept the canes' rims and the reference did not: a 0.3-0.4 mm bias of
    point-to-point at the goal, measured on the sample).
    """
    from vinetwin import _cloud_kernels

    cfg = config or PerceptionConfig()
    d = np.ascontiguousarray(camera.check_depth(depth), dtype=np.float32)
    step = 2  # pixels between the neighbours a normal is taken from
    if cfg.decimation > 1:
        n = cfg.decimation
        d = np.ascontiguousarray(d[::n, ::n])
        camera = camera.decimated(n)
        step = max(1, round(2 / n))
    if cfg.voxel_size > 0:
        o = np.zeros(3) if grid_origin is None else np.asarray(grid_origin, np.float64).reshape(3)
        # deprojection, flying-pixel filter, normals and the voxel grid in one compiled pass
        pts, nrm = _depth_voxels(d, camera, cfg, step, o)
    else:
        pts, nrm = _cloud_kernels.organised_points(
            d, camera.fx, camera.fy, camera.cx, camera.cy, max(cfg.min_depth, 1e-6),
            cfg.max_depth, cfg.edge_threshold, step, True,
        )  # fmt: skip
    if len(pts) == 0:
        return Cloud(np.empty((0, 3)), np.empty((0, 3)) if normals else None)
    keep = outlier_mask(pts, cfg)
    if keep is None:
        keep = np.ones(len(pts), dtype=bool)
    # the kept points with a normal, their normals made unit and turned to face the camera (at
    # the origin); one compiled loop: with numpy these five steps took 1.5 ms for 12k points
    pts, nrm = _cloud_kernels.unit_normals(pts, nrm, keep)
    if not normals:
        return Cloud(pts, None)
    return Cloud(pts, nrm)
