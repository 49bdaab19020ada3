"""Pinhole depth-camera model with Intel RealSense D405 presets.

The D405 is a passive stereo camera (no projector), baseline 18 mm, field of view about
87 x 58 degrees, ideal range 7-50 cm, depth unit 0.1 mm. Its minimum depth depends on the
resolution. Axial depth noise follows Intel's stereo model: RMS = z^2 * subpixel / (f_px * B),
with subpixel about 0.08 px; vinetwin uses that RMS as the standard deviation.

Presets derive intrinsics from the field of view with square pixels and the principal point at
the image centre: for 16:9 modes the horizontal 87 degrees sets f (the vertical field then is
about 56 degrees); for 4:3 the vertical 58 degrees does. Real units differ (one measured D405
gave about 382 px at 640x480): give measured intrinsics with `CameraModel.from_realsense` or
`d405(..., fx=..., fy=...)` when you have them.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from vinetwin._config import JsonFields
from vinetwin.errors import CameraError, InputError
from vinetwin.frames import Array, as_points

#: The D405's depth modes (width, height) and their minimum depth (m), from Intel's datasheet:
#: the one list of modes (the presets, the live source and fusion's depth range read it). The
#: datasheet gives no minimum for the 424x240 mode, so it is not offered.
D405_MIN_DEPTH: dict[tuple[int, int], float] = {
    (1280, 720): 0.100,
    (848, 480): 0.070,
    (640, 480): 0.055,
    (640, 360): 0.055,
    (480, 270): 0.045,
}
#: An unlisted mode is given the largest minimum depth of the listed ones: nearer depth is called
#: invalid, never trusted.
D405_MIN_DEPTH_UNLISTED = max(D405_MIN_DEPTH.values())
D405_HFOV_DEG = 87.0
D405_VFOV_DEG = 58.0
D405_BASELINE_M = 0.018
D405_SUBPIXEL_PX = 0.08
D405_DEPTH_UNIT_M = 1e-4
D405_MAX_DEPTH_M = 1.0


@dataclass(frozen=True, kw_only=True)
class CameraModel(JsonFields):
    """A pinhole depth camera in the OpenCV convention (+X right, +Y down, +Z forward)."""

    width: int
    """Image width in pixels."""
    height: int
    """Image height in pixels."""
    fx: float
    """Focal length along x, pixels."""
    fy: float
    """Focal length along y, pixels."""
    cx: float
    """Principal point x, pixels (pixel centres at integer coordinates)."""
    cy: float
    """Principal point y, pixels."""
    min_depth: float = D405_MIN_DEPTH[(848, 480)]
    """Smallest depth the sensor reports, metres (closer surfaces read as invalid)."""
    max_depth: float = D405_MAX_DEPTH_M
    """Largest depth the sensor reports, metres."""
    depth_unit: float = D405_DEPTH_UNIT_M
    """Size of one step of the raw 16-bit depth value, metres (D405 default 0.1 mm)."""
    baseline: float = D405_BASELINE_M
    """Stereo baseline, metres (noise model)."""
    subpixel: float = D405_SUBPIXEL_PX
    """Stereo matching subpixel RMS, pixels (noise model)."""
    name: str = "custom"
    """Preset name or a free label."""

    def __post_init__(self) -> None:
        vals = [self.fx, self.fy, self.cx, self.cy, self.min_depth, self.max_depth]
        if not all(math.isfinite(float(v)) for v in vals):
            raise CameraError(f"camera '{self.name}': intrinsics and depth range must be finite")
        if self.width <= 0 or self.height <= 0:
            raise CameraError(f"camera size must be positive, got {self.width}x{self.height}")
        if self.fx <= 0 or self.fy <= 0:
            raise CameraError(f"focal lengths must be positive, got fx={self.fx}, fy={self.fy}")
        if not 0 <= self.min_depth < self.max_depth:
            raise CameraError(
                f"depth range must satisfy 0 <= min_depth < max_depth, got "
                f"{self.min_depth}..{self.max_depth}"
            )
        if self.depth_unit <= 0 or self.baseline <= 0 or self.subpixel < 0:
            raise CameraError("depth_unit and baseline must be positive, subpixel non-negative")

    # ------------------------------------------------------------------ derived
    @property
    def K(self) -> Array:
        """3x3 intrinsic matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def fov_deg(self) -> tuple[float, float]:
        """(horizontal, vertical) field of view in degrees."""
        h = 2 * math.degrees(math.atan(self.width / (2 * self.fx)))
        v = 2 * math.degrees(math.atan(self.height / (2 * self.fy)))
        return h, v

    def depth_noise_rms(self, z: npt.ArrayLike) -> npt.NDArray[np.float64]:
        """Axial depth noise RMS (m) at depth z (m): z^2 * subpixel / (fx * baseline)."""
        z = np.asarray(z, dtype=np.float64)
        return z * z * self.subpixel / (self.fx * self.baseline)

    # ------------------------------------------------------------------ geometry
    def project(self, points_camera: Any) -> tuple[Array, Array]:
        """Projects (N, 3) camera-frame points; returns pixel coordinates (N, 2) and depth (N,).

        Points at or behind the camera get NaN pixel coordinates.
        """
        p = as_points(points_camera, "points_camera")
        z = p[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = self.fx * p[:, 0] / z + self.cx
            v = self.fy * p[:, 1] / z + self.cy
        uv = np.column_stack([u, v])
        uv[z <= 0] = np.nan
        return uv, z.copy()

    def deproject_pixels(self, uv: Any, depth: Any) -> Array:
        """Camera-frame points (N, 3) of pixels uv (N, 2) at z-depth (N,) metres."""
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        z = np.asarray(depth, dtype=np.float64).reshape(-1)
        if z.shape[0] != uv.shape[0]:
            raise InputError(f"uv has {uv.shape[0]} rows but depth has {z.shape[0]}")
        x = (uv[:, 0] - self.cx) / self.fx * z
        y = (uv[:, 1] - self.cy) / self.fy * z
        return np.column_stack([x, y, z])

    def deproject(self, depth: Any) -> tuple[Array, npt.NDArray[np.bool_]]:
        """Points (N, 3) of the valid pixels of a z-depth image (H, W) in metres, and the mask.

        A pixel is valid when its depth is finite and > 0. The mask (H, W) says which pixels the
        returned rows come from, in row-major order.
        """
        d = self.check_depth(depth)
        valid = np.isfinite(d) & (d > 0)
        vs, us = np.nonzero(valid)
        z = d[vs, us].astype(np.float64)
        x = (us - self.cx) / self.fx * z
        y = (vs - self.cy) / self.fy * z
        return np.column_stack([x, y, z]), valid

    def check_depth(self, depth: Any) -> npt.NDArray[np.floating[Any]]:
        """Checks that a depth image has this camera's size; returns it as an array."""
        d = np.asarray(depth)
        if d.shape != (self.height, self.width):
            raise InputError(
                f"depth image has shape {d.shape}, camera '{self.name}' expects "
                f"({self.height}, {self.width})"
            )
        if not np.issubdtype(d.dtype, np.floating):
            raise InputError(
                f"depth image must be float metres, got {d.dtype}; convert raw 16-bit depth with "
                f"depth_raw * camera.depth_unit"
            )
        return d

    def ray_directions(self) -> Array:
        """Unit-z ray directions (H, W, 3) through each pixel centre (z component 1)."""
        us, vs = np.meshgrid(np.arange(self.width), np.arange(self.height))
        x = (us - self.cx) / self.fx
        y = (vs - self.cy) / self.fy
        return np.stack([x, y, np.ones(us.shape)], axis=-1).astype(np.float64)

    # ------------------------------------------------------------------ conversions
    def scaled(self, width: int, height: int) -> CameraModel:
        """The same optics at another resolution (intrinsics scaled by the size ratio)."""
        sx, sy = width / self.width, height / self.height
        return dataclasses.replace(
            self,
            width=width,
            height=height,
            fx=self.fx * sx,
            fy=self.fy * sy,
            cx=(self.cx + 0.5) * sx - 0.5,
            cy=(self.cy + 0.5) * sy - 0.5,
        )

    def decimated(self, n: int) -> CameraModel:
        """The camera of `depth[::n, ::n]`: pixel (u, v) of it is pixel (n u, n v) of this one,
        so each deprojects to the same ray (not `scaled`, which resamples the whole image)."""
        return dataclasses.replace(
            self,
            width=(self.width + n - 1) // n,
            height=(self.height + n - 1) // n,
            fx=self.fx / n,
            fy=self.fy / n,
            cx=self.cx / n,
            cy=self.cy / n,
        )

    @classmethod
    def from_realsense(
        cls, intrinsics: Any, depth_scale: float = D405_DEPTH_UNIT_M, name: str = "realsense"
    ) -> CameraModel:
        """Builds a model from a `pyrealsense2.intrinsics` (or any object or dict with
        width, height, fx, fy, ppx, ppy) and the device's depth scale (m per unit).

        Distortion is not modelled: the D405's depth stream is rectified (model "none" or
        Brown-Conrady with zero coefficients).
        """

        def get(key: str) -> Any:
            if isinstance(intrinsics, dict):
                return intrinsics[key]
            return getattr(intrinsics, key)

        w, h = int(get("width")), int(get("height"))
        return cls(
            width=w,
            height=h,
            fx=float(get("fx")),
            fy=float(get("fy")),
            cx=float(get("ppx")),
            cy=float(get("ppy")),
            min_depth=D405_MIN_DEPTH.get((w, h), D405_MIN_DEPTH_UNLISTED),
            depth_unit=float(depth_scale),
            name=name,
        )


D405_RESOLUTIONS = tuple(f"{w}x{h}" for w, h in D405_MIN_DEPTH)


def d405(resolution: str = "848x480", **overrides: Any) -> CameraModel:
    """The D405 preset at `resolution` (one of D405_RESOLUTIONS); keyword overrides replace
    fields, e.g. measured `fx`, `fy`, `cx`, `cy`."""
    if resolution not in D405_RESOLUTIONS:
        raise CameraError(
            f"unknown D405 resolution '{resolution}'; choose one of: {', '.join(D405_RESOLUTIONS)}"
        )
    w, h = (int(s) for s in resolution.split("x"))
    if w * 9 == h * 16:
        f = (w / 2) / math.tan(math.radians(D405_HFOV_DEG / 2))
    else:
        f = (h / 2) / math.tan(math.radians(D405_VFOV_DEG / 2))
    params: dict[str, Any] = dict(
        width=w,
        height=h,
        fx=f,
        fy=f,
        cx=(w - 1) / 2,
        cy=(h - 1) / 2,
        min_depth=D405_MIN_DEPTH[(w, h)],
        name=f"d405_{resolution}",
    )
    params.update(overrides)
    return CameraModel(**params)
