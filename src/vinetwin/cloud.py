"""The perception chain shared by reference clouds and live clouds.

Every cloud that reaches ICP, synthetic or live, goes through `perceive` with the twin's
`PerceptionConfig`: a difference between the two chains would be a sim-to-real gap that ICP turns
into a pose error. Steps (the paper's, plus a cheap image-space filter):

1. depth image (metres) -> drop invalid pixels and pixels beyond `max_depth`;
2. flying-pixel filter on the depth image: a pixel whose depth differs from a 4-neighbour by
   more than `edge_threshold` (relative) is dropped (the smeared silhouettes of thin canes);
3. deprojection to camera-frame points;
4. voxel-grid downsampling (`voxel_size`);
5. statistical outlier removal (`sor_neighbors`, `sor_std_ratio`), after the voxel grid (far
   cheaper than before it);
6. normals (for point-to-plane and symmetric ICP), oriented towards the camera.

Open3D is imported only inside the functions that need it.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

#: ICP variants known to vinetwin (the paper's four).
ICP_VARIANTS = ("point_to_point", "lm", "point_to_plane", "symmetric")


@dataclass(frozen=True, kw_only=True)
class PerceptionConfig:
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
    sor_neighbors: int = 16
    """Statistical outlier removal: neighbours considered; 0 disables it."""
    sor_std_ratio: float = 2.0
    """Statistical outlier removal: keep points whose mean neighbour distance is within this many
    standard deviations of the average."""
    normal_radius: float = 0.012
    """Search radius (m) for normals."""
    normal_max_nn: int = 20
    """Most neighbours used for a normal."""

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> PerceptionConfig:
        names = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in data.items() if k in names})
