"""The D405 sensor model: what a real D405 does to a clean depth image.

Applied in this order, all seeded through one `numpy.random.Generator`:

1. **Silhouettes.** The D405 is a passive stereo camera: its matching window straddles a thin
   cane and the background behind it, so pixels along depth discontinuities are invalid or
   smeared. Pixels within `edge_width` px of a relative depth jump above `edge_jump` become
   invalid with probability `edge_invalid`; of the others, a fraction `edge_smear` take a depth
   between the near and the far side (flying pixels), and background pixels next to a cane take
   the cane's depth with probability `edge_fatten` (foreground fattening).
2. **Axial noise.** Gaussian with standard deviation `z^2 * subpixel / (fx * baseline)`
   (Intel's stereo RMS model, used as the standard deviation, not squared).
3. **Dropout.** A fraction `dropout` of valid pixels become invalid, uniformly.
4. **Range.** Depth below the camera's `min_depth` or above `max_depth` is invalid (0).
5. **Quantisation** to the camera's `depth_unit` (0.1 mm), as the 16-bit stream carries it.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from vinetwin.camera import CameraModel
from vinetwin.errors import InputError


@dataclass(frozen=True, kw_only=True)
class SensorConfig:
    """Settings of the D405 sensor model; `SensorConfig(enabled=False)` gives clean depth."""

    enabled: bool = True
    """Apply the model at all."""
    noise: bool = True
    """Axial Gaussian noise from the stereo RMS model."""
    subpixel: float | None = None
    """Override of the camera's subpixel RMS (px); None uses the camera's."""
    edge_jump: float = 0.05
    """Relative depth jump between neighbours that marks a silhouette."""
    edge_width: int = 1
    """Pixels on each side of a silhouette that it affects."""
    edge_invalid: float = 0.5
    """Probability that a silhouette pixel is invalid."""
    edge_smear: float = 0.2
    """Probability that a remaining silhouette pixel takes a depth between near and far sides."""
    edge_fatten: float = 0.3
    """Probability that a background pixel next to a near surface takes the near depth."""
    dropout: float = 0.0
    """Fraction of valid pixels dropped uniformly at random."""
    quantize: bool = True
    """Round depth to the camera's depth unit."""

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> SensorConfig:
        names = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in data.items() if k in names})


def _neighbour_extremes(d: npt.NDArray[np.float32], width: int) -> tuple[np.ndarray, np.ndarray]:
    """Nearest (smallest valid) and farthest depth within `width` px (square window)."""
    from scipy import ndimage

    size = 2 * width + 1
    far = ndimage.maximum_filter(d, size=size, mode="nearest")
    near = ndimage.minimum_filter(np.where(d > 0, d, np.inf), size=size, mode="nearest")
    return near, far


def apply_d405_model(
    depth: Any,
    camera: CameraModel,
    rng: np.random.Generator,
    config: SensorConfig | None = None,
) -> npt.NDArray[np.float32]:
    """Returns what a D405 would report for a clean z-depth image (metres, 0 = nothing).

    Args:
        depth: (H, W) clean z-depth, metres, 0 or NaN where nothing was hit.
        camera: the camera model (size, focal length, baseline, range, depth unit).
        rng: the random generator (seed it for reproducible references).
        config: the sensor settings; default SensorConfig().
    """
    cfg = config or SensorConfig()
    d = np.array(camera.check_depth(depth), dtype=np.float32, copy=True)
    d[~np.isfinite(d) | (d < 0)] = 0.0
    if not cfg.enabled:
        return d
    if not (0 <= cfg.edge_invalid <= 1 and 0 <= cfg.edge_smear <= 1 and 0 <= cfg.dropout <= 1):
        raise InputError("sensor probabilities must lie in [0, 1]")
    valid = d > 0

    if cfg.edge_width > 0 and (cfg.edge_invalid > 0 or cfg.edge_smear > 0 or cfg.edge_fatten > 0):
        from scipy import ndimage

        near, far = _neighbour_extremes(d, cfg.edge_width)
        near_ok = np.isfinite(near)  # some surface within the window
        holes = ndimage.minimum_filter(valid, size=2 * cfg.edge_width + 1, mode="nearest") == 0
        big_jump = (far - near) > cfg.edge_jump * np.where(near_ok, near, 1.0)
        edge = near_ok & (big_jump | holes)
        u = rng.random(d.shape, dtype=np.float32)
        # foreground fattening: background (or empty) pixels beside a near surface take its depth
        behind = edge & ((~valid) | (d > near * (1 + cfg.edge_jump)))
        fatten = behind & (u < cfg.edge_fatten)
        out = d.copy()
        out[fatten] = near[fatten]
        rest = edge & ~fatten
        u2 = rng.random(d.shape, dtype=np.float32)
        invalid = rest & (u2 < cfg.edge_invalid)
        smear = (
            rest
            & ~invalid
            & valid
            & (u2 < cfg.edge_invalid + (1 - cfg.edge_invalid) * cfg.edge_smear)
        )
        if smear.any():
            lo = near[smear]
            hi = np.where(far[smear] > 0, far[smear], lo)
            out[smear] = lo + rng.random(int(smear.sum()), dtype=np.float32) * (hi - lo)
        out[invalid] = 0.0
        d = out
        valid = d > 0

    if cfg.noise:
        sub = camera.subpixel if cfg.subpixel is None else cfg.subpixel
        sigma = d[valid].astype(np.float64) ** 2 * sub / (camera.fx * camera.baseline)
        d[valid] = (d[valid] + rng.standard_normal(int(valid.sum())) * sigma).astype(np.float32)

    if cfg.dropout > 0:
        d[valid & (rng.random(d.shape, dtype=np.float32) < cfg.dropout)] = 0.0

    d[(d < camera.min_depth) | (d > camera.max_depth)] = 0.0
    if cfg.quantize:
        d = (np.round(d / camera.depth_unit) * camera.depth_unit).astype(np.float32)
    return d
