"""The reconstruction's settings, declared once: the TSDF fusion's (`FusionConfig`, its voxel,
truncation rule and depth range), depth odometry's (`OdometryConfig`) and what `vinetwin
reconstruct` runs (`ReconstructConfig`). Light to import: the command line reads it."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

from vinetwin._config import JsonFields, check_counts, check_finite
from vinetwin.cloud import PerceptionConfig
from vinetwin.errors import InputError

if TYPE_CHECKING:
    from vinetwin.registration.icp import ICPConfig

#: The TSDF voxel (m): a 5 mm cane is 3 voxels across.
TSDF_VOXEL = 0.0015
#: The SDF truncation distance, in voxels (Open3D's examples use 4-8; 4 keeps thin canes apart).
TRUNCATION_VOXELS = 4
#: The farthest depth fused (m): beyond it the D405's noise blurs canes.
FUSED_DEPTH_MAX = 0.5
#: The TSDF voxel's range (m): under 0.5 mm is finer than the D405 resolves depth at its nearest
#: (the grid only grows); over 1 cm a 5 mm cane is lost within one voxel.
VOXEL_RANGE = (0.0005, 0.01)


def _check_fusion(cfg: FusionConfig) -> None:
    """Refuses, by name, fusion settings that make no mesh or an absurd one (Open3D stopped on a
    voxel of 0 with its own exception)."""
    from vinetwin.camera import D405_MAX_DEPTH_M

    check_finite(cfg, ("voxel", "truncation", "depth_min", "depth_max", "min_component",
                       "min_component_extent"))  # fmt: skip
    lo, hi = VOXEL_RANGE
    if not lo <= cfg.voxel <= hi:
        raise InputError(f"voxel must lie in [{lo:g}, {hi:g}] m, got {cfg.voxel}")
    if not 0.0 < cfg.depth_max <= D405_MAX_DEPTH_M or cfg.depth_min >= cfg.depth_max:
        raise InputError(f"depth_max must lie in (0, {D405_MAX_DEPTH_M:g}] m and above "
                         f"depth_min, got {cfg.depth_max}")  # fmt: skip
    if cfg.min_component > 1.0:
        raise InputError(f"min_component is a share of the largest component's triangles, in "
                         f"[0, 1], got {cfg.min_component}")  # fmt: skip
    for n in ("target_triangles", "smooth_iterations", "block_count", "min_pixels"):
        v, least = getattr(cfg, n), int(n == "block_count")
        if isinstance(v, bool) or not isinstance(v, int) or v < least:
            raise InputError(f"{n} must be an integer >= {least}, got {v!r}")


@dataclass(frozen=True, kw_only=True)
class FusionConfig:
    voxel: float = TSDF_VOXEL
    """TSDF voxel size (m)."""
    truncation: float = 0.0
    """SDF truncation distance (m); 0: `TRUNCATION_VOXELS` voxels."""
    depth_min: float = 0.0
    """Nearest depth used (m); never nearer than the capture camera's own minimum
    (`CameraModel.min_depth`: 0.045-0.100 m by D405 resolution), which is used by default."""
    depth_max: float = FUSED_DEPTH_MAX
    """Farthest depth used (m)."""
    min_component: float = 0.02
    """Drop connected components with fewer triangles than this fraction of the largest, unless
    they span `min_component_extent`."""
    min_component_extent: float = 0.02
    """Keep a connected component whose bounding box spans at least this (m), however few its
    triangles: a cane seen apart from the rest of the vine (a capture around far-apart pruning
    poses rebuilds each as its own piece; a sweep past a large vine, its loose cane ends) is vine,
    not debris. On synthetic captures of the sample, dense, GDC and VSP vines every component this
    long lay on the true surface (median distance under 1.3 mm), while flying-pixel debris spans
    millimetres."""
    smooth_iterations: int = 0
    """Taubin smoothing iterations (0: none)."""
    target_triangles: int = 0
    """Decimate to at most this many triangles (0: keep)."""
    block_count: int = 200_000
    """Capacity of the voxel-block hash map (blocks of 8^3 voxels)."""
    min_pixels: int = 100
    """A frame with fewer depth pixels than this within [depth_min, depth_max] is skipped and
    named: it adds nothing a mesh could keep, and Open3D aborts the whole integration on some
    (four scattered pixels, in a sweep past a large vine: "No block is touched")."""

    def __post_init__(self) -> None:
        _check_fusion(self)


@dataclass(frozen=True, kw_only=True)
class OdometryConfig(JsonFields):
    """Depth odometry's perception and ICP schedule (`odometry_poses`): frame-to-frame
    point-to-plane ICP on clouds coarser than the servo's, over the sweep's range."""

    max_depth: float = FUSED_DEPTH_MAX
    """Farthest depth used (m): the fusion's."""
    voxel: float = 0.003
    """Voxel of the frames' clouds (m)."""
    coarse_radius: float = 0.05
    """Pairing distance of the coarse ICP level (m): a step between frames up to about this."""
    fine_radius: float = 0.015
    """Pairing distance of the fine ICP level (m)."""
    max_correspondence: float = 0.005
    """Pairs further apart than this after alignment count as outliers (m)."""

    def __post_init__(self) -> None:
        check_finite(self, ("max_depth", "voxel", "coarse_radius", "fine_radius",
                            "max_correspondence"), positive=True)  # fmt: skip
        if self.fine_radius > self.coarse_radius:
            raise InputError(
                f"fine_radius ({self.fine_radius}) must not exceed coarse_radius "
                f"({self.coarse_radius})"
            )

    def perception(self) -> PerceptionConfig:
        return PerceptionConfig(max_depth=self.max_depth, voxel_size=self.voxel)

    def icp(self) -> ICPConfig:
        from vinetwin.registration.icp import ICPConfig

        return ICPConfig(
            variant="point_to_plane",
            schedule=((0.0, self.coarse_radius), (0.0, self.fine_radius)),
            max_correspondence_distance=self.max_correspondence,
            coarse_tolerance=0.0,  # measured without the early hand-on (docs/reconstruct.md)
        )


@dataclass(frozen=True, kw_only=True)
class ReconstructConfig:
    """How frames become a mesh."""

    poses: Literal["kinematics", "colmap", "odometry"] = "kinematics"
    """Pose source: the capture's robot kinematics, pycolmap structure-from-motion on the colour
    frames (metric scale from the depth), or depth odometry (frame-to-frame ICP; needs a
    video-like capture)."""
    voxel: float = TSDF_VOXEL
    """TSDF voxel size (m); the truncation is `fusion.TRUNCATION_VOXELS` of them."""
    depth_max: float = FUSED_DEPTH_MAX
    """Farthest depth fused (m); the nearest is the camera's own minimum."""
    target_triangles: int = 0
    """Decimate the mesh to at most this many triangles (0: keep)."""

    def __post_init__(self) -> None:
        self.fusion()  # its settings checked where the fusion's are

    def fusion(self) -> FusionConfig:
        """The fusion's settings these make."""
        return FusionConfig(voxel=self.voxel, depth_max=self.depth_max,
                            target_triangles=self.target_triangles)  # fmt: skip


@dataclass(frozen=True, kw_only=True)
class SyntheticCaptureConfig:
    """A synthetic capture of a twin (`vinetwin capture-synthetic`)."""

    frames: int = 120
    """Number of frames."""
    distance: float = 0.3
    """Camera distance to the vine (m)."""
    pose_noise: tuple[float, float] = (0.0, 0.0)
    """Standard deviation of the error added to the recorded poses (m, rad)."""
    trajectory: Literal["grid", "path", "poses"] = "grid"
    """grid: viewpoints over the vine; path: a video-like sweep; poses: around the pruning poses."""
    seed: int = 0

    def __post_init__(self) -> None:
        from vinetwin.camera import D405_MAX_DEPTH_M, D405_MIN_DEPTH

        check_counts(self, ("seed",))
        f = self.frames
        if isinstance(f, bool) or not isinstance(f, int) or not 1 <= f <= 100_000:
            raise InputError(f"frames must be an integer in [1, 100000], got {f!r}")
        check_finite(self, ("distance",))
        # the nearest any D405 mode sees (nearer than its own mode's minimum, a frame is empty)
        near = min(D405_MIN_DEPTH.values())
        if not near <= self.distance <= D405_MAX_DEPTH_M:
            raise InputError(
                f"distance must lie within the D405's depth range, {near:g}-"
                f"{D405_MAX_DEPTH_M:g} m, got {self.distance}"
            )
        noise = tuple(float(v) for v in self.pose_noise)
        if len(noise) != 2 or not all(0.0 <= v <= 1.0 for v in noise):  # NaN fails too
            raise InputError(
                f"pose_noise must be 2 values in [0, 1] (m, rad), got {self.pose_noise}"
            )
        if self.trajectory not in ("grid", "path", "poses"):
            raise InputError(f"unknown trajectory {self.trajectory!r}; choose grid, path or poses")
