"""A pose's reference cloud, owned here: render depth at a pruning pose, apply the D405 model,
run the shared perception chain (`render_reference`), read an exported one with its hash check
(`check_reference_files`, `read_reference_cloud`), and write one (PLY, PCD for PCL users, JSON
sidecar). `reference_for` is the one entry for "the reference of this pose of this twin": the
servo, the simulator, the web app, `preview` and `check-reference` all call it."""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from vinetwin.camera import CameraModel
from vinetwin.cloud import DENSE_FACTOR, Cloud, PerceptionConfig, perceive
from vinetwin.errors import InputError, VinetwinError
from vinetwin.files import file_sha256
from vinetwin.frames import invert, transform_points
from vinetwin.jobstore import JobStore
from vinetwin.render.backends import DepthBackend
from vinetwin.render.sensor import SensorConfig, apply_d405_model

if TYPE_CHECKING:
    from vinetwin.twin.model import Twin

log = logging.getLogger(__name__)

#: Bump when the rendering or perception algorithm changes what a reference holds: every
#: exported reference is then re-rendered on the next export.
REFERENCE_FORMAT = 1


def pose_seed(base_seed: int, pose_id: str) -> int:
    """A stable per-pose noise seed derived from the export seed and the pose id."""
    h = hashlib.sha256(f"{base_seed}:{pose_id}".encode()).digest()
    return int.from_bytes(h[:4], "little")


@dataclass(frozen=True)
class Reference:
    """A pose's reference: the cloud (reference camera frame), the depth it came from (None when
    read from exported files), its noise seed, and what the servo may also want: the dense cloud
    (`dense_cloud`) and the cut point in the reference camera frame (the view-keeping law's
    target)."""

    cloud: Cloud
    depth: npt.NDArray[np.float32] | None
    seed: int
    dense: Cloud | None = None
    cut: npt.NDArray[np.float64] | None = None
    exported: bool = False
    """Read from the twin's exported files (`vinetwin export`), not rendered now."""


def render_reference(
    backend: DepthBackend,
    T_vine_camera: Any,
    perception: PerceptionConfig,
    sensor: SensorConfig,
    seed: int,
    dense: bool = False,
) -> Reference:
    """Depth at the pose -> D405 model -> perception chain; with `dense`, the same depth also
    through the chain at a finer voxel (`dense_cloud`): one render either way. An empty view
    gives an empty cloud; the caller reports it (export in its report and log, preview in its
    log, the servo refuses it)."""
    depth = render_depth(backend, T_vine_camera, sensor, seed)
    cloud = perceive(depth, backend.camera, perception, normals=True)
    fine = dense_cloud(depth, backend.camera, perception, DENSE_FACTOR) if dense else None
    return Reference(cloud, depth, seed, dense=fine)


def render_depth(
    backend: DepthBackend, T_vine_camera: Any, sensor: SensorConfig, seed: int
) -> npt.NDArray[np.float32]:
    """The D405's depth image at the pose: the render through the sensor model, its noise
    drawn from `seed`."""
    clean = backend.render(T_vine_camera)
    return apply_d405_model(clean, backend.camera, np.random.default_rng(seed), sensor)


def dense_cloud(
    depth: npt.NDArray[np.float32], camera: Any, perception: PerceptionConfig, factor: int
) -> Cloud:
    """The same depth image through the perception chain at `1/factor` of its voxel: the dense
    reference point-to-point and LM pair their final ICP level against (`ServoConfig.
    dense_reference`), so their answer is not tied to the lattice of the voxel grid."""
    fine = replace(perception, voxel_size=perception.voxel_size / max(factor, 1))
    return perceive(depth, camera, fine, normals=True)


def reference_for(
    twin: Twin,
    pose_id: str,
    *,
    dense: bool = False,
    use_exported: bool = True,
    renderer: DepthBackend | None = None,
    seed: int = 0,
) -> Reference:
    """The reference of one pose of a twin, with its cut point in the reference camera frame.

    `use_exported`: the twin's exported `references/POSE.ply` when there is one (refused, naming
    why, when its files do not match the hashes its sidecar recorded, or when it was exported
    for another pose or other settings than the twin's now: `stale_reference`); else the pose
    rendered
    now with the twin's settings and the export's noise seed (`pose_seed(seed, pose_id)`), as
    `vinetwin export` would. `dense`: also the dense cloud, from the same render (for an exported
    reference, from one render of its depth: the sensor model and seed its sidecar names). `renderer`: render with it (kept open; for example a
    reconstructed twin's mesh, or a session's own renderer); default: the export's backend for
    one view, opened and closed here."""
    pose = twin.pose(pose_id)
    T = np.asarray(pose.T_vine_camera, float)
    cut = transform_points(invert(T), twin.cut_point(pose.cut_point).point[None])[0]
    path = twin.references_dir / f"{pose.id}.ply"
    if use_exported and path.exists():
        problem = check_reference_files(twin.references_dir, pose.id) or stale_reference(twin, pose)
        if problem:
            raise InputError(f"refusing reference {path}: {problem}; run `vinetwin export` again")
        # current (`stale_reference`): its sidecar names the sensor model and the seed it used
        sidecar = references_store(twin.references_dir).read(pose.id) or {}
        exported = Reference(
            read_reference_cloud(path), None, int(sidecar["noise_seed"]), cut=cut, exported=True
        )
        if not dense:
            return exported
        # the dense cloud from the depth the export rendered: its sensor model and seed
        sensor = SensorConfig.from_dict(sidecar["sensor"])
        with _renderer_for(twin, renderer) as r:
            depth = render_depth(r, T, sensor, exported.seed)
        return replace(
            exported, dense=dense_cloud(depth, twin.camera, twin.perception, DENSE_FACTOR)
        )
    if use_exported:
        log.warning("%s: not exported; rendering the reference with the twin's settings", path)
    with _renderer_for(twin, renderer) as r:
        rendered = render_reference(
            r, T, twin.perception, SensorConfig(), pose_seed(seed, pose.id), dense
        )
    return replace(rendered, cut=cut)


@contextlib.contextmanager
def _renderer_for(twin: Twin, renderer: DepthBackend | None) -> Iterator[DepthBackend]:
    """`renderer` (kept open), or the export's backend for one view of the twin's mesh, opened
    here and closed after."""
    if renderer is not None:
        yield renderer
        return
    from vinetwin.render.backends import get_backend, resolve_backend

    mesh = twin.load_mesh()
    own = get_backend(resolve_backend(None), mesh.vertices, mesh.faces, twin.camera)
    try:
        yield own
    finally:
        own.close()


# ----------------------------------------------------------------------------- files
def references_store(folder: Path) -> JobStore:
    """The references folder: a sidecar `POSE.json` per reference, carrying the digest of its
    inputs (`inputs_sha256`); its clouds `POSE.ply` and `.pcd` are its companions.

    Its files are written without an fsync each (three per reference were a fifth of a
    reference's time): the sidecar records the clouds' hashes, which are checked before a
    reference is reused or servoed to (`check_reference_files`), so a file a power loss left
    empty or old is rendered again, never used; the export flushes them all at its end."""
    return JobStore(
        folder,
        REFERENCE_FORMAT,
        format_key="reference_format",
        digest_key="inputs_sha256",
        sync=False,
    )


def check_reference_files(folder: Path, pose_id: str) -> str:
    """Why the reference's cloud files are not the ones its sidecar recorded ("" when they
    are): missing, truncated or changed since export."""
    sidecar = references_store(folder).read(pose_id)
    if sidecar is None:
        return f"{folder / pose_id}.json: no readable sidecar"
    want = sidecar.get("files_sha256")
    if not isinstance(want, dict):
        return f"{folder / pose_id}.json records no file hashes (exported by an older vinetwin)"
    for ext in ("ply", "pcd"):
        path = folder / f"{pose_id}.{ext}"
        if not path.exists():
            return f"{path} is missing"
        if file_sha256(path) != want.get(ext):
            return f"{path} does not match the hash its sidecar recorded (truncated or changed)"
    return ""


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


def stale_reference(twin: Twin, pose: Any) -> str:
    """Why the pose's exported reference is not the one an export would make now ("" when it
    is): the pose moved, or the mesh, camera or perception settings changed since the export
    (its sidecar's inputs digest, made with the sidecar's own sensor model, backend and seed).
    A servo to a stale reference would move the robot to where the pose was."""
    sidecar = references_store(twin.references_dir).read(pose.id) or {}
    try:
        sensor = SensorConfig.from_dict(sidecar["sensor"])
        common = digest_inputs(
            file_sha256(twin.mesh_path), twin.camera, twin.perception, sensor, sidecar["backend"]
        )
        current = pose_digest(common, pose.T_vine_camera, int(sidecar["noise_seed"]))
    except (KeyError, TypeError, ValueError) as exc:
        return f"its sidecar does not say what it was exported from ({exc})"
    if current == sidecar.get("inputs_sha256"):
        return ""
    then = np.asarray(sidecar.get("T_vine_camera", np.zeros((4, 4))), float)
    if then.shape != (4, 4) or not np.allclose(then, pose.T_vine_camera, atol=1e-9):
        return f"pose {pose.id} moved since its reference was exported"
    if sidecar.get("mesh_sha256") != common["mesh"]:
        return "the twin's mesh changed since the reference was exported"
    if (
        sidecar.get("camera") != common["camera"]
        or sidecar.get("perception") != common["perception"]
    ):
        return "the twin's camera or perception settings changed since the reference was exported"
    return "its inputs changed since it was exported"


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
