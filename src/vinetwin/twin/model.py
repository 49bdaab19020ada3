"""The twin folder: a vine mesh, its camera, cut points and pruning poses, on disk.

```
NAME.twin/
  twin.json        format version, units, mesh file, T_world_vine, camera, T_flange_camera,
                   T_flange_tool (optional),
                   cut points, pruning poses, perception settings, provenance
  vine.ply         the mesh, metres, vine frame
  skeleton.json    optional: branches and cut-point candidates (generator, importers)
  references/      <pose_id>.ply, .pcd, .json (written by `vinetwin export`)
  validation/      simulated servo results per pose
```

Rules: twin.json is validated on load and every error names the field and the bad value; a file
written by a newer format version is refused; unknown fields survive a load/save round trip;
every write goes to a temporary file in the same folder, is flushed, then renamed over the old one,
so a crash during a save leaves the previous file intact.
"""

from __future__ import annotations

import datetime as _dt
import json
import logging
import math
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

import vinetwin
from vinetwin.camera import CameraModel, d405
from vinetwin.cloud import ICP_VARIANTS, MAX_DECIMATION, OUTLIER_RULES, PerceptionConfig
from vinetwin.errors import CameraError, InputError, TwinError, TwinVersionError
from vinetwin.files import (
    atomic_write_bytes,
    atomic_write_text,
)
from vinetwin.frames import Array, check_pose, make_pose, unit_vector
from vinetwin.mesh import check_mesh_arrays, load_mesh, mesh_ply_bytes
from vinetwin.twin.poses import (
    DEFAULT_STANDOFF,
    Approach,
    approach_of,
    default_approach,
    pruning_pose,
)
from vinetwin.twin.skeleton import Skeleton
from vinetwin.twin.store import (
    ID_RE,
    TWIN_FILE,
    FieldReader,
    read_saved,
    read_twin_file,
    write_twin_json,
)

if TYPE_CHECKING:
    import trimesh

log = logging.getLogger(__name__)

FORMAT_NAME = "vinetwin-twin"
FORMAT_VERSION = 1


def check_id(value: Any, what: str = "id") -> str:
    """`value` if it is a valid cut point or pose id: 1-64 letters, digits, `_` or `-`, nothing
    else (ids name files: `references/ID.ply`, `validation/ID.VARIANT.json`); else InputError."""
    if not isinstance(value, str) or not ID_RE.fullmatch(value):
        raise InputError(f"{what} must match [A-Za-z0-9_-]{{1,64}}, got {value!r}")
    return value


#: Default hand-eye transform: a D405 on the Panda hand, 5 cm off the flange axis and 4 cm along
#: it, looking along the flange's +Z. Replace it with your calibration.
DEFAULT_T_FLANGE_CAMERA: Array = make_pose(np.eye(3), [0.05, 0.0, 0.04])
#: From the camera to the pruning tool's blade (m), along the optical axis: the D405's minimum
#: depth (7 cm), so the cut stays in view until the blade is on it.
TOOL_REACH = 0.07
#: Default tool frame on the flange: its origin is the blade point, TOOL_REACH ahead of the camera
#: on its optical axis, its +Z the direction the blade moves in. Replace it with your tool's.
DEFAULT_T_FLANGE_TOOL: Array = DEFAULT_T_FLANGE_CAMERA @ make_pose(
    np.eye(3), [0.0, 0.0, TOOL_REACH]
)


# ----------------------------------------------------------------------------- entities
@dataclass
class CutPoint:
    """A place on a cane where the pruner cuts, in the vine frame."""

    id: str
    point: Array
    cane_axis: Array
    name: str = ""
    source: str = "manual"
    """Where it came from: manual (a person), candidate (generator/importer), click (web)."""
    extra: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return {
            **self.extra,
            "id": self.id,
            "name": self.name,
            "point": [float(v) for v in self.point],
            "cane_axis": [float(v) for v in self.cane_axis],
            "source": self.source,
        }

    @classmethod
    def from_json(cls, data: Any, f: FieldReader, where: str) -> CutPoint:
        """One entry of twin.json's `cut_points` (`where`: its field path, e.g. "cut_points[2]");
        unknown keys are kept in `extra`."""
        w = f"{where}."
        c = f.obj(data, where)
        known = {"id", "name", "point", "cane_axis", "source"}
        return cls(
            id=f.ident(c, w),
            point=f.vec3(c, "point", w),
            cane_axis=f.vec3(c, "cane_axis", w, unit=True),
            name=f.string(c, "name", w, default=""),
            source=f.string(c, "source", w, default="manual"),
            extra={k: v for k, v in c.items() if k not in known},
        )


@dataclass
class PruningPose:
    """Where the camera must be for one cut: T_vine_camera with its approach description."""

    id: str
    cut_point: str
    T_vine_camera: Array
    standoff: float
    icp_variant: str = "point_to_plane"
    name: str = ""
    approach: Approach = field(default_factory=Approach)
    extra: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return {
            **self.extra,
            "id": self.id,
            "name": self.name,
            "cut_point": self.cut_point,
            "T_vine_camera": np.asarray(self.T_vine_camera).tolist(),
            "standoff": float(self.standoff),
            "icp_variant": self.icp_variant,
            "approach": {
                "azimuth": self.approach.azimuth,
                "elevation": self.approach.elevation,
                "roll": self.approach.roll,
            },
        }

    @classmethod
    def from_json(cls, data: Any, f: FieldReader, where: str) -> PruningPose:
        """One entry of twin.json's `pruning_poses` (its cut point is checked by the twin)."""
        w = f"{where}."
        p = f.obj(data, where)
        variant = f.string(p, "icp_variant", w, default="point_to_plane")
        if variant not in ICP_VARIANTS:
            raise f.fail(
                f"{w}icp_variant",
                f"unknown ICP variant {variant!r}; choose one of: {', '.join(ICP_VARIANTS)}",
            )
        standoff = f.number(p, "standoff", w)
        if standoff <= 0:
            raise f.fail(f"{w}standoff", f"must be > 0 m, got {standoff}")
        ap = f.obj(p.get("approach", {}), f"{w}approach")
        a = f"{w}approach."
        known = {"id", "name", "cut_point", "T_vine_camera", "standoff", "icp_variant", "approach"}
        return cls(
            id=f.ident(p, w),
            cut_point=f.string(p, "cut_point", w),
            T_vine_camera=f.pose(p, "T_vine_camera", w),
            standoff=standoff,
            icp_variant=variant,
            name=f.string(p, "name", w, default=""),
            approach=Approach(
                standoff=standoff,
                azimuth=f.number(ap, "azimuth", a, default=math.pi / 2),
                elevation=f.number(ap, "elevation", a, default=0.0),
                roll=f.number(ap, "roll", a, default=0.0),
            ),
            extra={k: v for k, v in p.items() if k not in known},
        )


_TOP_KEYS = {
    "format",
    "format_version",
    "units",
    "name",
    "mesh",
    "skeleton",
    "T_world_vine",
    "camera",
    "T_flange_camera",
    "T_flange_tool",
    "cut_points",
    "pruning_poses",
    "perception",
    "provenance",
    "revision",
}


# ----------------------------------------------------------------------------- the twin
@dataclass
class Twin:
    """A twin folder loaded in memory. Mutate through the methods, then `save()`."""

    root: Path
    name: str
    mesh_file: str = "vine.ply"
    skeleton_file: str | None = None
    T_world_vine: Array = field(default_factory=lambda: np.eye(4))
    camera: CameraModel = field(default_factory=d405)
    T_flange_camera: Array = field(default_factory=lambda: DEFAULT_T_FLANGE_CAMERA.copy())
    T_flange_tool: Array = field(default_factory=lambda: DEFAULT_T_FLANGE_TOOL.copy())
    """The pruning tool on the flange: its origin is the blade point (`prune` closes it there)."""
    cut_points: list[CutPoint] = field(default_factory=list)
    poses: list[PruningPose] = field(default_factory=list)
    perception: PerceptionConfig = field(default_factory=PerceptionConfig)
    provenance: dict[str, Any] = field(default_factory=dict)
    extra: dict[str, Any] = field(default_factory=dict)
    revision: int = 0
    """How many times twin.json was saved; checked by `save` (a stale copy merges)."""
    _base: dict[str, Any] | None = field(default=None, repr=False, compare=False)
    """twin.json as this copy last read or wrote it (normalised), the base of a merge."""

    # ------------------------------------------------------------------ paths
    @property
    def json_path(self) -> Path:
        return self.root / TWIN_FILE

    @property
    def mesh_path(self) -> Path:
        return self.root / self.mesh_file

    @property
    def references_dir(self) -> Path:
        return self.root / "references"

    @property
    def validation_dir(self) -> Path:
        return self.root / "validation"

    # ------------------------------------------------------------------ creation
    @classmethod
    def create(
        cls,
        root: str | Path,
        vertices: Any,
        faces: Any,
        *,
        name: str | None = None,
        camera: CameraModel | None = None,
        skeleton: Skeleton | None = None,
        source: dict[str, Any] | None = None,
        overwrite: bool = False,
    ) -> Twin:
        """Creates a twin folder holding a mesh (vertices (V, 3) metres, faces (F, 3)).

        Refuses to write into a folder that already holds a twin.json unless `overwrite`.
        """
        root = Path(root)
        if root.exists() and not root.is_dir():
            raise TwinError(f"{root}: is a file, not a folder; choose another --out")
        if (root / TWIN_FILE).exists() and not overwrite:
            raise TwinError(
                f"{root}: already holds a twin; pass --overwrite (overwrite=True) to replace it"
            )
        V = np.asarray(vertices, dtype=np.float64)
        F = np.asarray(faces)
        check_mesh_arrays(V, F, str(root))
        root.mkdir(parents=True, exist_ok=True)
        twin = cls(root=root, name=name or root.name.removesuffix(".twin"), camera=camera or d405())
        twin.write_mesh(V, F)
        if skeleton is not None:
            twin.skeleton_file = "skeleton.json"
            atomic_write_text(root / "skeleton.json", json.dumps(skeleton.to_json()))
        old = read_saved(root, twin._loader()) if overwrite else None
        twin.revision = int(old["revision"]) if old else 0  # replaced, not merged
        twin.provenance = {
            "created_by": f"vinetwin {vinetwin.__version__}",
            "created": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
            "source": source or {},
        }
        twin.save()
        return twin

    def write_mesh(self, vertices: Array, faces: np.ndarray) -> None:
        """Writes the mesh as binary PLY (float32 vertices, metres), atomically."""
        atomic_write_bytes(self.mesh_path, mesh_ply_bytes(vertices, faces, str(self.mesh_path)))

    # ------------------------------------------------------------------ load / save
    @classmethod
    def load(cls, root: str | Path) -> Twin:
        """Loads and validates a twin folder (the mesh is checked to exist, not read)."""
        return cls.from_json(*read_twin_file(root))

    @classmethod
    def from_json(cls, root: Path, data: Any, path: Path | None = None) -> Twin:
        """The twin that twin.json's content `data` describes, validated (`TwinFieldError`
        naming the field and its bad value; `TwinVersionError` for a newer format)."""
        f = FieldReader(path or root / TWIN_FILE)
        data = f.obj(data, "(top level)")
        fmt = f.string(data, "format", "")
        if fmt != FORMAT_NAME:
            raise f.fail("format", f"must be '{FORMAT_NAME}', got {fmt!r}")
        version = data.get("format_version")
        if isinstance(version, bool) or not isinstance(version, int):
            raise f.fail("format_version", f"must be an integer, got {version!r}")
        if version > FORMAT_VERSION:
            raise TwinVersionError(
                f"{f.path}: written by format version {version}, but this vinetwin "
                f"({vinetwin.__version__}) reads versions up to {FORMAT_VERSION}; upgrade vinetwin"
            )
        if version < 1:
            raise f.fail("format_version", f"must be >= 1, got {version}")
        units = f.string(data, "units", "", default="m")
        if units != "m":
            raise f.fail("units", f"must be 'm' (metres), got {units!r}")
        mesh_file = f.string(data, "mesh", "")
        if Path(mesh_file).is_absolute() or ".." in Path(mesh_file).parts:
            raise f.fail("mesh", f"must be a file name inside the twin folder, got {mesh_file!r}")
        if not (root / mesh_file).exists():
            raise f.fail("mesh", f"file '{mesh_file}' does not exist in {root}")
        skel = data.get("skeleton")
        if skel is not None and (
            not isinstance(skel, str)
            or Path(skel).is_absolute()
            or ".." in Path(skel).parts
            or not (root / skel).exists()
        ):
            raise f.fail("skeleton", f"must name a file in the twin folder, got {skel!r}")
        revision = data.get("revision", 0)
        if isinstance(revision, bool) or not isinstance(revision, int) or revision < 0:
            raise f.fail("revision", f"must be an integer >= 0, got {revision!r}")

        cam_data = f.obj(f.req(data, "camera", ""), "camera")
        for key in ("width", "height"):
            v = f.req(cam_data, key, "camera.")
            if isinstance(v, bool) or not isinstance(v, int) or v <= 0:
                raise f.fail(f"camera.{key}", f"must be a positive integer, got {v!r}")
        for key in ("fx", "fy", "cx", "cy"):
            f.number(cam_data, key, "camera.")
        for key in ("min_depth", "max_depth", "depth_unit", "baseline", "subpixel"):
            if key in cam_data:
                f.number(cam_data, key, "camera.")
        try:
            camera = CameraModel.from_dict(cam_data)
        except (CameraError, TypeError) as exc:
            raise f.fail("camera", str(exc)) from exc

        perc_data = f.obj(data.get("perception", {}), "perception")
        for key, val in perc_data.items():
            if key == "outlier_rule":
                if val not in OUTLIER_RULES:
                    raise f.fail(
                        "perception.outlier_rule",
                        f"must be one of {', '.join(OUTLIER_RULES)}, got {val!r}",
                    )
            elif key == "decimation":
                if (
                    isinstance(val, bool)
                    or not isinstance(val, int)
                    or not 1 <= val <= MAX_DECIMATION
                ):
                    raise f.fail(
                        "perception.decimation",
                        f"must be an integer 1-{MAX_DECIMATION}, got {val!r}",
                    )
            elif key in {fl for fl in PerceptionConfig.__dataclass_fields__}:
                f.number(perc_data, key, "perception.")
                if val < 0:
                    raise f.fail(f"perception.{key}", f"must be >= 0, got {val}")

        cut_points = [
            CutPoint.from_json(c, f, f"cut_points[{i}]")
            for i, c in enumerate(f.seq(data, "cut_points"))
        ]
        poses = [
            PruningPose.from_json(p, f, f"pruning_poses[{i}]")
            for i, p in enumerate(f.seq(data, "pruning_poses"))
        ]
        f.unique([c.id for c in cut_points], "cut_points")
        f.unique([p.id for p in poses], "pruning_poses")
        cut_ids = {c.id for c in cut_points}
        for i, p in enumerate(poses):
            if p.cut_point not in cut_ids:
                raise f.fail(
                    f"pruning_poses[{i}].cut_point", f"names no cut point: {p.cut_point!r}"
                )
        prov = data.get("provenance", {})
        if not isinstance(prov, dict):
            raise f.fail("provenance", "must be an object")
        twin = cls(
            root=root,
            revision=revision,
            name=f.string(data, "name", "", default=root.name),
            mesh_file=mesh_file,
            skeleton_file=skel,
            T_world_vine=f.pose(data, "T_world_vine", ""),
            camera=camera,
            T_flange_camera=f.pose(data, "T_flange_camera", ""),
            T_flange_tool=(
                f.pose(data, "T_flange_tool", "")
                if "T_flange_tool" in data
                else DEFAULT_T_FLANGE_TOOL.copy()
            ),
            cut_points=cut_points,
            poses=poses,
            perception=PerceptionConfig.from_dict(perc_data),
            provenance=prov,
            extra={k: v for k, v in data.items() if k not in _TOP_KEYS},
        )
        twin._base = twin.to_json()
        return twin

    def to_json(self) -> dict[str, Any]:
        return {
            **self.extra,
            "format": FORMAT_NAME,
            "format_version": FORMAT_VERSION,
            "revision": self.revision,
            "units": "m",
            "name": self.name,
            "mesh": self.mesh_file,
            "skeleton": self.skeleton_file,
            "T_world_vine": np.asarray(self.T_world_vine).tolist(),
            "camera": self.camera.to_dict(),
            "T_flange_camera": np.asarray(self.T_flange_camera).tolist(),
            "T_flange_tool": np.asarray(self.T_flange_tool).tolist(),
            "cut_points": [c.to_json() for c in self.cut_points],
            "pruning_poses": [p.to_json() for p in self.poses],
            "perception": self.perception.to_dict(),
            "provenance": self.provenance,
        }

    def save(self) -> None:
        """Writes twin.json atomically (temporary file, fsync, rename), one revision up.

        Nothing another writer saved is lost: when twin.json was saved by someone else since
        this copy read it (its revision moved on), the two are merged against what this copy
        read, entity by entity and field by field (cut points and poses by id). Changes that do
        not touch the same field are both kept, and this copy is updated to the merged twin;
        two different changes of one field raise `TwinConflictError` naming it, and nothing is
        written. The content is validated first (ids, references between entities): a twin
        that would not load again is not saved."""
        if not self.root.is_dir():
            raise TwinError(f"{self.root}: twin folder does not exist")
        ours = self.to_json()
        path = self.json_path
        type(self).from_json(self.root, ours, path)  # refuse what would not load
        merged, fresh = write_twin_json(
            path,
            ours,
            self._base,
            self.revision,
            lambda d: type(self).from_json(self.root, d, path),
        )
        if fresh is not None:
            self.__dict__.update(fresh.__dict__)
        else:
            self.revision = merged["revision"]
        self._base = self.to_json()

    def _loader(self) -> Callable[[Any], Twin]:
        """twin.json's content to a twin of this folder (what the store merges with)."""
        root, path, cls = self.root, self.json_path, type(self)
        return lambda data: cls.from_json(root, data, path)

    def restored(self, data: dict[str, Any]) -> Twin:
        """A copy holding `data` (an earlier `to_json` of this twin: an undo) as an edit of
        this copy, so that saving it replaces what this copy last saved (merged with what
        others saved since, like any edit)."""
        twin = Twin.from_json(self.root, data, self.json_path)
        twin.revision, twin._base = self.revision, self._base
        return twin

    # ------------------------------------------------------------------ content
    def load_mesh(self) -> trimesh.Trimesh:
        """Reads and checks the mesh; raises MeshError when it is unreadable, empty or NaN."""
        return load_mesh(self.mesh_path)

    def load_skeleton(self) -> Skeleton | None:
        if not self.skeleton_file:
            return None
        try:
            return Skeleton.load(self.root / self.skeleton_file)
        except (OSError, ValueError, KeyError) as exc:
            raise TwinError(
                f"{self.root / self.skeleton_file}: cannot read skeleton: {exc}"
            ) from exc

    def cut_point(self, cut_id: str) -> CutPoint:
        for c in self.cut_points:
            if c.id == cut_id:
                return c
        raise TwinError(f"no cut point '{cut_id}' in twin '{self.name}'")

    def pose(self, pose_id: str) -> PruningPose:
        for p in self.poses:
            if p.id == pose_id:
                return p
        known = ", ".join(p.id for p in self.poses) or "none"
        raise TwinError(f"no pruning pose '{pose_id}' in twin '{self.name}'; poses: {known}")

    def _next_id(self, prefix: str, existing: list[str]) -> str:
        n = 1 + max(
            (int(m.group(1)) for e in existing if (m := re.fullmatch(rf"{prefix}(\d+)", e))),
            default=0,
        )
        return f"{prefix}{n}"

    def add_cut_point(
        self, point: Any, cane_axis: Any, *, name: str = "", source: str = "manual"
    ) -> CutPoint:
        p = np.asarray(point, dtype=np.float64).reshape(3)
        if not np.all(np.isfinite(p)):
            raise InputError("a cut point needs a finite point and a finite non-zero cane axis")
        a = unit_vector(cane_axis, "cane axis")
        cid = self._next_id("c", [c.id for c in self.cut_points])
        cut = CutPoint(cid, p, a, name=name or cid, source=source)
        self.cut_points.append(cut)
        return cut

    def move_cut_point(self, cut_id: str, point: Any, cane_axis: Any | None = None) -> CutPoint:
        """Moves a cut point; its poses follow (same approach angles and standoff)."""
        cut = self.cut_point(cut_id)
        p = np.asarray(point, dtype=np.float64).reshape(3)
        if not np.all(np.isfinite(p)):
            raise InputError("cut point must be finite")
        cut.point = p
        if cane_axis is not None:
            cut.cane_axis = unit_vector(cane_axis, "cane axis")
        for pose in self.poses:
            if pose.cut_point == cut_id:
                pose.T_vine_camera = pruning_pose(cut.point, cut.cane_axis, pose.approach)
        return cut

    def delete_cut_point(self, cut_id: str) -> list[PruningPose]:
        """Deletes a cut point and returns its poses, which are deleted with it."""
        cut = self.cut_point(cut_id)
        self.cut_points.remove(cut)
        gone = [p for p in self.poses if p.cut_point == cut_id]
        self.poses = [p for p in self.poses if p.cut_point != cut_id]
        return gone

    def add_pose(
        self,
        cut_id: str,
        approach: Approach | None = None,
        *,
        standoff: float = DEFAULT_STANDOFF,
        icp_variant: str = "point_to_plane",
        name: str = "",
    ) -> PruningPose:
        """Derives and adds the pruning pose of a cut point (default approach unless given)."""
        if icp_variant not in ICP_VARIANTS:
            raise InputError(
                f"unknown ICP variant '{icp_variant}'; choose one of: {', '.join(ICP_VARIANTS)}"
            )
        cut = self.cut_point(cut_id)
        ap = approach or default_approach(cut.cane_axis, standoff)
        T = pruning_pose(cut.point, cut.cane_axis, ap)
        pid = self._next_id("p", [p.id for p in self.poses])
        pose = PruningPose(pid, cut_id, T, ap.standoff, icp_variant, name or pid, ap)
        self.poses.append(pose)
        return pose

    def set_pose(self, pose_id: str, T_vine_camera: Any) -> PruningPose:
        """Replaces a pose's T_vine_camera (e.g. from a gizmo) and updates its description."""
        pose = self.pose(pose_id)
        T = check_pose(T_vine_camera, "T_vine_camera")
        cut = self.cut_point(pose.cut_point)
        pose.T_vine_camera = T
        pose.approach = approach_of(T, cut.point, cut.cane_axis)
        pose.standoff = pose.approach.standoff
        return pose

    def delete_pose(self, pose_id: str) -> PruningPose:
        pose = self.pose(pose_id)
        self.poses.remove(pose)
        return pose


# ----------------------------------------------------------------------------- meshes
def find_twins(path: str | Path) -> list[Path]:
    """The twin folders at `path`: itself when it holds a twin.json, else every folder below it
    that does (a vineyard: a folder of twin folders, at any depth), in sorted order."""
    root = Path(path)
    if (root / "twin.json").exists():
        return [root]
    if not root.is_dir():
        raise TwinError(f"{root}: no such folder")
    found = sorted({p.parent for p in root.rglob("twin.json")})
    # a twin inside another (its field profile's rebuilt twin, say) is that twin's, not the row's
    found = [t for t in found if not any(o != t and o in t.parents for o in found)]
    if not found:
        raise TwinError(
            f"{root}: neither a twin folder nor a folder of twin folders (no twin.json)"
        )
    return found


def load_twins(paths: list[Path]) -> tuple[list[Twin], list[tuple[Path, str]]]:
    """The twins at `paths` that load, and (folder, why) for each that does not: a vineyard's
    batch runs the others and names these."""
    from vinetwin.errors import VinetwinError

    twins: list[Twin] = []
    broken: list[tuple[Path, str]] = []
    for r in paths:
        try:
            twins.append(Twin.load(r))
        except VinetwinError as exc:
            broken.append((r, str(exc)))
    return twins, broken


#: The tube mesh's triangle edge (m): below MIN_EDGE a 1.5 m vine's mesh passes 5 million
#: triangles; above MAX_EDGE a cane is a few flat facets.
MIN_EDGE, MAX_EDGE = 0.0005, 0.05


def twin_from_skeleton(
    root: str | Path,
    skeleton: Skeleton,
    *,
    name: str | None = None,
    edge: float = 0.002,
    caps: str = "round",
    camera: CameraModel | None = None,
    source: dict[str, Any] | None = None,
    cut_points: int = 0,
    overwrite: bool = False,
    progress: Callable[[str], None] | None = None,
) -> Twin:
    """Builds a tube mesh from a skeleton and writes a twin; the first `cut_points` candidates
    (spread over the vine) become cut points with default pruning poses."""
    from vinetwin.twin.skeleton import tube_mesh

    if not (isinstance(edge, int | float) and MIN_EDGE <= edge <= MAX_EDGE):
        raise InputError(
            f"edge must lie in [{MIN_EDGE:g}, {MAX_EDGE:g}] m (the tube mesh's triangle edge; "
            f"the bundled sample uses 0.002), got {edge}"
        )
    if cut_points < 0:
        raise InputError(f"cut_points must be >= 0, got {cut_points}")
    if progress:
        progress("meshing")
    V, F = tube_mesh(skeleton, edge=edge, caps=caps)  # type: ignore[arg-type]
    twin = Twin.create(
        root, V, F, name=name, camera=camera, skeleton=skeleton, source=source, overwrite=overwrite
    )
    if cut_points > 0 and skeleton.candidates:
        n = len(skeleton.candidates)
        picks = np.unique(np.linspace(0, n - 1, min(cut_points, n)).round().astype(int))
        for i in picks:
            c = skeleton.candidates[i]
            cut = twin.add_cut_point(c.point, c.cane_axis, name=c.label, source="candidate")
            twin.add_pose(cut.id)
        twin.save()
    return twin


def bundled_sample() -> Path:
    """The bundled sample twin: `samples/vine_bilateral.twin` of the source checkout."""
    here = Path(__file__).resolve()
    for parent in here.parents:
        cand = parent / "samples" / "vine_bilateral.twin"
        if (cand / TWIN_FILE).exists():
            return cand
    raise TwinError(
        "the bundled sample twin was not found (it ships in the source checkout under samples/); "
        "make one with: vinetwin sample --out vine.twin"
    )


def copy_bundled_sample(folder: str | Path, replace: bool = False) -> Path:
    """A copy of the bundled sample twin in `folder` (the sample itself is never modified): the
    copy already there unless `replace`. Returns the copy's path."""
    import shutil

    src = bundled_sample()
    dst = Path(folder) / src.name
    if dst.exists() and replace:
        shutil.rmtree(dst)
    if not dst.exists():
        Path(folder).mkdir(parents=True, exist_ok=True)
        shutil.copytree(src, dst)
    return dst
