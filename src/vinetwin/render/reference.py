"""One reference cloud: render depth at a pruning pose, apply the D405 model, run the shared
perception chain, and read/write the result (PLY, PCD for PCL users, JSON sidecar)."""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from vinetwin.camera import CameraModel
from vinetwin.cloud import Cloud, PerceptionConfig, perceive
from vinetwin.errors import VinetwinError
from vinetwin.render.backends import DepthBackend
from vinetwin.render.sensor import SensorConfig, apply_d405_model

#: Bump when the rendering or perception algorithm changes what a reference holds: every
#: exported reference is then re-rendered on the next export.
REFERENCE_FORMAT = 1


def pose_seed(base_seed: int, pose_id: str) -> int:
    """A stable per-pose noise seed derived from the export seed and the pose id."""
    h = hashlib.sha256(f"{base_seed}:{pose_id}".encode()).digest()
    return int.from_bytes(h[:4], "little")


@dataclass
class Reference:
    """A rendered reference: the cloud (reference camera frame) and the depth it came from."""

    cloud: Cloud
    depth: npt.NDArray[np.float32]
    seed: int


def render_reference(
    backend: DepthBackend,
    T_vine_camera: Any,
    perception: PerceptionConfig,
    sensor: SensorConfig,
    seed: int,
) -> Reference:
    """Depth at the pose -> D405 model -> perception chain. An empty view gives an empty cloud;
    the caller reports it (export in its report and log, preview in its log)."""
    clean = backend.render(T_vine_camera)
    depth = apply_d405_model(clean, backend.camera, np.random.default_rng(seed), sensor)
    cloud = perceive(depth, backend.camera, perception, normals=True)
    return Reference(cloud, depth, seed)


def dense_cloud(
    depth: npt.NDArray[np.float32], camera: Any, perception: PerceptionConfig, factor: int
) -> Cloud:
    """The same depth image through the perception chain at `1/factor` of its voxel: the dense
    reference point-to-point and LM pair their final ICP level against (`ServoConfig.
    dense_reference`), so their answer is not tied to the lattice of the voxel grid."""
    from dataclasses import replace

    dense = replace(perception, voxel_size=perception.voxel_size / max(factor, 1))
    return perceive(depth, camera, dense, normals=True)


# ----------------------------------------------------------------------------- files
def reference_files(cloud: Cloud) -> dict[str, bytes]:
    """A reference cloud's files, by extension: `ply`, binary little-endian PLY with float32
    x y z (and nx ny nz when the cloud has normals); `pcd`, PCL's PCD v0.7, binary, fields x y z
    (normal_x normal_y normal_z), viewpoint at the origin. Both carry the same float32 body."""
    normals = cloud.normals
    data = cloud.points if normals is None else np.hstack([cloud.points, normals])
    body = np.ascontiguousarray(data, dtype="<f4").tobytes()
    names = ["x", "y", "z"] + ([] if normals is None else ["nx", "ny", "nz"])
    ply = (
        "ply\nformat binary_little_endian 1.0\ncomment vinetwin reference cloud, metres, camera frame (OpenCV)\n"
        f"element vertex {len(cloud)}\n"
        + "".join(f"property float {n}\n" for n in names)
        + "end_header\n"
    )
    fields = ["x", "y", "z"] + ([] if normals is None else ["normal_x", "normal_y", "normal_z"])
    k = len(fields)
    pcd = (
        "# .PCD v0.7 - Point Cloud Data file format\n"
        "VERSION 0.7\n"
        f"FIELDS {' '.join(fields)}\n"
        f"SIZE {' '.join(['4'] * k)}\n"
        f"TYPE {' '.join(['F'] * k)}\n"
        f"COUNT {' '.join(['1'] * k)}\n"
        f"WIDTH {len(cloud)}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {len(cloud)}\nDATA binary\n"
    )
    return {"ply": ply.encode("ascii") + body, "pcd": pcd.encode("ascii") + body}


def read_reference_cloud(path: Path) -> Cloud:
    """Reads a reference PLY written by `reference_files` (or any PLY Open3D can read)."""
    from vinetwin import _lazy

    o3d = _lazy.open3d()
    if not Path(path).exists():
        raise VinetwinError(f"{path}: reference cloud does not exist; run `vinetwin export`")
    pc = o3d.io.read_point_cloud(str(path))
    pts = np.asarray(pc.points, dtype=np.float64)
    if len(pts) == 0 or not np.all(np.isfinite(pts)):
        raise VinetwinError(f"{path}: no points, or non-finite ones: not a usable reference cloud")
    nrm = np.asarray(pc.normals, dtype=np.float64) if pc.has_normals() else None
    return Cloud(pts, nrm)


def digest_inputs(
    mesh_sha256: str,
    camera: CameraModel,
    perception: PerceptionConfig,
    sensor: SensorConfig,
    backend: str,
) -> dict[str, Any]:
    """The inputs every reference of one export shares, for `pose_digest` (made once per
    export, not once per pose)."""
    return {
        "format": REFERENCE_FORMAT,
        "mesh": mesh_sha256,
        "camera": camera.to_dict(),
        "perception": perception.to_dict(),
        "sensor": sensor.to_dict(),
        "backend": backend,
    }


def pose_digest(common: dict[str, Any], T_vine_camera: Any, seed: int) -> str:
    """Digest of everything a reference depends on (`digest_inputs`' shared part, the pose, its
    noise seed): an unchanged digest means the reference can be skipped."""
    T = np.round(np.asarray(T_vine_camera, dtype=np.float64), 12).tolist()
    blob = json.dumps({**common, "T": T, "seed": seed}, sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()
