"""The D405 sensor model: what a real D405 does to a clean depth image.

Applied in this order, all seeded through one `numpy.random.Generator`:

1. **Silhouettes.** The D405 is a passive stereo camera: its matching window straddles a thin
   cane and the background behind it, so pixels along depth discontinuities are invalid or
   smeared. Pixels within `edge_width` px of a relative depth jump above `edge_jump` become
   invalid with probability `edge_invalid`; of the others, a fraction `edge_smear` take a depth
   between the near and the far side (flying pixels), and background pixels next to a cane take
   the cane's depth with probability `edge_fatten` (foreground fattening).
2. **Scale and axial noise.** Depth scaled by `1 + bias` (0 by default; the field profile's
   scale error), then Gaussian with standard deviation `z^2 * subpixel / (fx * baseline)`
   (Intel's stereo RMS model, used as the standard deviation, not squared).
3. **Dropout.** A fraction `dropout` of valid pixels become invalid, uniformly.
4. **Range.** Depth below the camera's `min_depth` or above `max_depth` is invalid (0).
5. **Quantisation** to the camera's `depth_unit` (0.1 mm), as the 16-bit stream carries it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from vinetwin._config import JsonFields
from vinetwin.camera import CameraModel
from vinetwin.errors import InputError

#: Pixels of the valid pixels' box below which the model runs as one band of rows (a band's
#: hand-off to a thread costs tens of microseconds).
_MIN_BAND_PIXELS = 40_000


@dataclass(frozen=True, kw_only=True)
class SensorConfig(JsonFields):
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
    bias: float = 0.0
    """Depth scale error: every depth is reported (1 + bias) times its true value (the
    field profile's `depth_bias`; 0: none)."""
    quantize: bool = True
    """Round depth to the camera's depth unit."""


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
    from vinetwin import _bands, _cloud_kernels
    from vinetwin.render import _sensor_kernels

    cfg = config or SensorConfig()
    src = camera.check_depth(depth)
    d = np.empty(src.shape, np.float32)
    r0, r1, c0, c1 = _sensor_kernels.clean_depth(src, d)  # 0 where not finite or negative
    if not cfg.enabled:
        return d
    if not (0 <= cfg.edge_invalid <= 1 and 0 <= cfg.edge_smear <= 1 and 0 <= cfg.dropout <= 1):
        raise InputError("sensor probabilities must lie in [0, 1]")
    if r1 < 0:  # nothing valid
        return d
    # work inside the bounding box of the valid pixels (plus a margin): a vine fills little of it
    m = cfg.edge_width + 1
    box = (slice(max(r0 - m, 0), r1 + m + 1), slice(max(c0 - m, 0), c1 + m + 1))
    full = d
    d = np.ascontiguousarray(d[box])  # a copy
    # bands of rows on threads (`vinetwin._bands`) when the box is large enough
    rows = d.shape[0]
    bands = max(1, min(_bands.threads(), d.size // _MIN_BAND_PIXELS, rows // 16))

    # compiled (vinetwin._kernels); the same numbers as the numpy formulation of each step
    # (tests/test_render.py keeps it as the reference)
    if cfg.edge_width > 0 and (cfg.edge_invalid > 0 or cfg.edge_smear > 0 or cfg.edge_fatten > 0):
        # silhouette pixels, then random numbers drawn for them only (a small part of the image)
        w, jump = int(cfg.edge_width), np.float32(cfg.edge_jump)
        if bands == 1:
            ev, eu, nv, fv = _sensor_kernels.d405_edges(d, w, jump)
        else:
            parts = _bands.run(
                _sensor_kernels.d405_edges_rows, (d, w, jump), _bands.even(rows, bands)
            )
            ev, eu, nv, fv = (np.concatenate([p[k] for p in parts]) for k in range(4))
        u1 = rng.random(len(ev), dtype=np.float32)
        u2 = rng.random(len(ev), dtype=np.float32)
        u3 = rng.random(len(ev), dtype=np.float32)
        _sensor_kernels.d405_silhouettes(
            d, ev, eu, nv, fv, u1, u2, u3, np.float32(1 + cfg.edge_jump),
            np.float32(cfg.edge_fatten), np.float32(cfg.edge_invalid),
            np.float32(cfg.edge_invalid + (1 - cfg.edge_invalid) * cfg.edge_smear),
        )  # fmt: skip

    # the rest touches valid pixels only, in row-major order
    before = _cloud_kernels.valid_rows(d, 0.0, np.inf)  # valid pixels before each row
    n = int(before[-1])
    sub = camera.subpixel if cfg.subpixel is None else cfg.subpixel
    normal = (
        _sensor_kernels.standard_normals(rng, n) if cfg.noise else np.zeros(0)
    )  # numpy's stream
    drop = rng.random(n) if cfg.dropout > 0 else np.zeros(0)
    args = (
        d, normal, drop, 1.0 + cfg.bias if cfg.bias else 1.0, float(sub),
        camera.fx * camera.baseline, float(cfg.dropout), camera.min_depth, camera.max_depth,
        camera.depth_unit if cfg.quantize else 0.0, before,
    )  # fmt: skip
    _bands.run(_sensor_kernels.d405_axial, args, _bands.cuts(before, bands))
    full[box] = d
    return full
