"""The twin's store: twin.json read and validated (`load_twin`, `twin_from_json`, every error
naming its field and bad value; a newer format refused), written atomically one revision up
(`save_twin`), and concurrent saves merged entity by entity under a lock (`merge_twin_json`).
The entities themselves and their edits are in `twin.model`."""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

import vinetwin
from vinetwin.camera import CameraModel
from vinetwin.cloud import MAX_DECIMATION, OUTLIER_RULES, PerceptionConfig
from vinetwin.errors import (
    CameraError,
    InputError,
    TwinConflictError,
    TwinError,
    TwinFieldError,
    TwinVersionError,
)
from vinetwin.files import atomic_write_text, parse_json, remove_orphan_temp_files
from vinetwin.frames import Array, check_pose, unit_vector
from vinetwin.twin.model import (
    FORMAT_NAME,
    FORMAT_VERSION,
    ID_RE,
    TWIN_FILE,
    CutPoint,
    PruningPose,
    Twin,
)

log = logging.getLogger(__name__)


class FieldReader:
    """Typed getters over parsed JSON that raise TwinFieldError naming the field path."""

    def __init__(self, path: Path) -> None:
        self.path = str(path)

    def fail(self, where: str, message: str) -> TwinFieldError:
        return TwinFieldError(self.path, where, message)

    def obj(self, data: Any, where: str) -> dict[str, Any]:
        if not isinstance(data, dict):
            raise self.fail(where, f"must be an object, got {type(data).__name__}")
        return data

    def req(self, data: dict[str, Any], key: str, where: str) -> Any:
        if key not in data:
            raise self.fail(f"{where}{key}", "is missing")
        return data[key]

    def string(self, data: dict[str, Any], key: str, where: str, default: str | None = None) -> str:
        if default is not None and key not in data:
            return default
        v = self.req(data, key, where)
        if not isinstance(v, str):
            raise self.fail(f"{where}{key}", f"must be a string, got {v!r}")
        return v

    def ident(self, data: dict[str, Any], where: str) -> str:
        """The entry's `id`: a name that is safe as a file name."""
        v = self.string(data, "id", where)
        if not ID_RE.fullmatch(v):
            raise self.fail(f"{where}id", f"must match [A-Za-z0-9_-]{{1,64}}, got {v!r}")
        return v

    def number(
        self, data: dict[str, Any], key: str, where: str, default: float | None = None
    ) -> float:
        if default is not None and key not in data:
            return default
        v = self.req(data, key, where)
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
            raise self.fail(f"{where}{key}", f"must be a finite number, got {v!r}")
        return float(v)

    def seq(self, data: dict[str, Any], key: str) -> list[Any]:
        v = self.req(data, key, "")
        if not isinstance(v, list):
            raise self.fail(key, "must be a list")
        return v

    def unique(self, ids: list[str], where: str) -> None:
        seen: set[str] = set()
        for i, v in enumerate(ids):
            if v in seen:
                raise self.fail(f"{where}[{i}].id", f"must be unique, got {v!r} twice")
            seen.add(v)

    def vec3(self, data: dict[str, Any], key: str, where: str, unit: bool = False) -> Array:
        v = self.req(data, key, where)
        arr = self._numbers(v, f"{where}{key}", (3,))
        if unit:
            try:
                arr = unit_vector(arr)
            except InputError:
                raise self.fail(f"{where}{key}", "must be a non-zero direction") from None
        return arr

    def pose(self, data: dict[str, Any], key: str, where: str) -> Array:
        v = self.req(data, key, where)
        arr = self._numbers(v, f"{where}{key}", (4, 4))
        try:
            return check_pose(arr, f"{where}{key}", atol=1e-5)
        except InputError as exc:
            raise self.fail(f"{where}{key}", str(exc).split(" ", 1)[1]) from exc

    def _numbers(self, v: Any, where: str, shape: tuple[int, ...]) -> Array:
        try:
            arr = np.asarray(v, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise self.fail(where, f"must be numbers of shape {shape}, got {v!r:.80}") from exc
        if arr.shape != shape:
            raise self.fail(where, f"must have shape {shape}, got {arr.shape}")
        if not np.all(np.isfinite(arr)):
            raise self.fail(where, f"holds a non-finite value (NaN or inf): {arr.tolist()}")
        return arr


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
    "cut_points",
    "pruning_poses",
    "perception",
    "provenance",
    "revision",
}


def load_twin(root: str | Path) -> Twin:
    """Loads and validates a twin folder (the mesh is checked to exist, not read)."""
    root = Path(root)
    path = root / TWIN_FILE
    if root.is_file() and root.name == TWIN_FILE:
        root, path = root.parent, root
    if not path.exists():
        raise TwinError(f"{root}: no {TWIN_FILE} here; is this a twin folder?")
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise TwinError(f"{path}: cannot read: {exc}") from exc
    try:
        data = parse_json(text)
    except json.JSONDecodeError as exc:
        raise TwinError(
            f"{path}: not valid JSON (line {exc.lineno}, column {exc.colno}: {exc.msg}); "
            f"the file may be truncated"
        ) from exc
    except ValueError as exc:  # a number too long, nesting too deep
        raise TwinError(f"{path}: cannot read it: {exc}") from None
    return twin_from_json(root, data, path)


def twin_from_json(root: Path, data: Any, path: Path | None = None) -> Twin:
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
            if isinstance(val, bool) or not isinstance(val, int) or not 1 <= val <= MAX_DECIMATION:
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
            raise f.fail(f"pruning_poses[{i}].cut_point", f"names no cut point: {p.cut_point!r}")
    prov = data.get("provenance", {})
    if not isinstance(prov, dict):
        raise f.fail("provenance", "must be an object")
    twin = Twin(
        root=root,
        revision=revision,
        name=f.string(data, "name", "", default=root.name),
        mesh_file=mesh_file,
        skeleton_file=skel,
        T_world_vine=f.pose(data, "T_world_vine", ""),
        camera=camera,
        T_flange_camera=f.pose(data, "T_flange_camera", ""),
        cut_points=cut_points,
        poses=poses,
        perception=PerceptionConfig.from_dict(perc_data),
        provenance=prov,
        extra={k: v for k, v in data.items() if k not in _TOP_KEYS},
    )
    twin._base = twin.to_json()
    return twin


def save_twin(twin: Twin) -> None:
    """`Twin.save`: see there."""
    if not twin.root.is_dir():
        raise TwinError(f"{twin.root}: twin folder does not exist")
    ours = twin.to_json()
    twin_from_json(twin.root, ours, twin.json_path)  # refuse what would not load
    remove_orphan_temp_files(twin.root)
    with _save_lock(twin.root):
        theirs = read_saved(twin.root)
        merged, fresh = ours, None
        if theirs is not None and theirs.get("revision") != twin.revision:
            merged = merge_twin_json(twin._base or {}, ours, theirs, str(twin.json_path))
        merged["revision"] = max(twin.revision, int((theirs or {}).get("revision", 0))) + 1
        if merged is not ours:  # the merge must still be a twin
            fresh = twin_from_json(twin.root, merged, twin.json_path)
        try:
            atomic_write_text(twin.json_path, json.dumps(merged, indent=1) + "\n")
        except OSError as exc:
            raise TwinError(f"{twin.json_path}: cannot save: {exc}") from exc
    if fresh is not None:
        twin.__dict__.update(fresh.__dict__)
    else:
        twin.revision = merged["revision"]
    twin._base = twin.to_json()


# ----------------------------------------------------------------------------- concurrent saves
_MISSING: Any = object()


@contextlib.contextmanager
def _save_lock(root: Path) -> Iterator[None]:
    """An exclusive lock on the twin folder while it is read back and written (`flock` on
    `.twin.lock`: released by the kernel if the process dies)."""
    import fcntl

    path = root / ".twin.lock"
    try:  # created rw for everyone less the umask, as every file vinetwin writes
        fd = os.open(path, os.O_CREAT | os.O_RDWR, 0o666)
    except PermissionError:  # made by another user (or an older vinetwin, 0644): flock reads
        fd = os.open(path, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)


def read_saved(root: Path) -> dict[str, Any] | None:
    """twin.json as saved now, normalised like `Twin.to_json`; None when there is none or it
    cannot be read (nothing to merge with: it is replaced)."""
    if not (root / TWIN_FILE).exists():
        return None
    try:
        return Twin.load(root).to_json()
    except TwinError as exc:
        log.warning("%s: replacing a twin.json that does not load: %s", root, exc)
        return None


def merge_twin_json(
    base: dict[str, Any], ours: dict[str, Any], theirs: dict[str, Any], where: str = TWIN_FILE
) -> dict[str, Any]:
    """Three-way merge of twin.json contents: `ours` and `theirs` both derive from `base`.
    Cut points and pruning poses are matched by id and merged field by field; every other
    top-level field as a whole. A field changed on one side takes that side's value (a deleted
    entity stays deleted unless the other side changed it); the same field changed differently
    on both sides raises `TwinConflictError`."""
    out: dict[str, Any] = {}
    for key in dict.fromkeys([*theirs, *ours]):
        if key == "revision":
            continue
        if key in ("cut_points", "pruning_poses"):
            out[key] = _merge_entities(
                base.get(key, []), ours.get(key, []), theirs.get(key, []), f"{where}: {key}"
            )
            continue
        v = _pick(base.get(key, _MISSING), ours.get(key, _MISSING), theirs.get(key, _MISSING),
                  f"{where}: field '{key}'")  # fmt: skip
        if v is not _MISSING:
            out[key] = v
    return out


def _pick(b: Any, o: Any, t: Any, where: str) -> Any:
    if o == t:
        return o
    if o == b:
        return t
    if t == b:
        return o
    raise TwinConflictError(
        f"{where} was changed here and, differently, by another save since this copy was "
        "loaded; load the twin again and redo this change"
    )


def _merge_entities(
    base: list[dict[str, Any]], ours: list[dict[str, Any]], theirs: list[dict[str, Any]], where: str
) -> list[dict[str, Any]]:
    b, o, t = ({e["id"]: e for e in side} for side in (base, ours, theirs))
    merged = []
    for eid in dict.fromkeys([*t, *o]):
        be: Any = b.get(eid, _MISSING)
        oe: Any = o.get(eid, _MISSING)
        te: Any = t.get(eid, _MISSING)
        e: Any
        if _MISSING in (be, oe, te):  # added or deleted on one side
            e = _pick(be, oe, te, f"{where} '{eid}'")
        else:  # on both sides: field by field
            e = {}
            for key in dict.fromkeys([*te, *oe]):
                v = _pick(be.get(key, _MISSING), oe.get(key, _MISSING), te.get(key, _MISSING),
                          f"{where} '{eid}' field '{key}'")  # fmt: skip
                if v is not _MISSING:
                    e[key] = v
        if e is not _MISSING:
            merged.append(e)
    return merged
