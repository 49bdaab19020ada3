"""The twin's store, below the entities (`twin.model`, which imports it): twin.json read
(`read_twin_file`) and its fields checked (`FieldReader`: every error names the field and its
bad value), written atomically one revision up under the folder's lock (`write_twin_json`), and
concurrent saves merged entity by entity (`merge_twin_json`)."""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import re
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from vinetwin.errors import (
    InputError,
    TwinConflictError,
    TwinError,
    TwinFieldError,
)
from vinetwin.files import atomic_write_text, parse_json, remove_orphan_temp_files
from vinetwin.frames import Array, check_pose, unit_vector

#: The twin folder's description file.
TWIN_FILE = "twin.json"
#: The entry names twin.json's ids must match: safe as file names.
ID_RE = re.compile(r"[A-Za-z0-9_-]{1,64}")

T = TypeVar("T")

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


def read_twin_file(root: str | Path) -> tuple[Path, Any, Path]:
    """The twin folder, twin.json's parsed content (not yet validated: `Twin.from_json` does)
    and its path; TwinError naming what is wrong when it cannot be read or parsed."""
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
    return root, data, path


def write_twin_json(
    json_path: Path,
    ours: dict[str, Any],
    base: dict[str, Any] | None,
    revision: int,
    load: Callable[[Any], T],
) -> tuple[dict[str, Any], T | None]:
    """Writes `ours` (twin.json's content, this copy's `revision`, read as `base`) atomically,
    one revision up, under the folder's lock. When another writer saved since `base` was read,
    the two are merged against `base` (`merge_twin_json`) and the merge must `load` (twin.json's
    content to a twin; a twin that would not load is not written). Returns what was written and,
    after a merge, the merged twin (None when nothing was merged)."""
    root = json_path.parent
    remove_orphan_temp_files(root)
    with _save_lock(root):
        theirs = read_saved(root, load)
        merged, fresh = ours, None
        if theirs is not None and theirs.get("revision") != revision:
            merged = merge_twin_json(base or {}, ours, theirs, str(json_path))
        merged["revision"] = max(revision, int((theirs or {}).get("revision", 0))) + 1
        if merged is not ours:  # the merge must still be a twin
            fresh = load(merged)
        try:
            atomic_write_text(json_path, json.dumps(merged, indent=1) + "\n")
        except OSError as exc:
            raise TwinError(f"{json_path}: cannot save: {exc}") from exc
    return merged, fresh


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


def read_saved(root: Path, load: Callable[[Any], Any]) -> dict[str, Any] | None:
    """twin.json as saved now, normalised by `load` (its content to a twin, whose `to_json` is
    taken); None when there is none or it cannot be read (nothing to merge with: it is
    replaced)."""
    if not (root / TWIN_FILE).exists():
        return None
    try:
        return load(read_twin_file(root)[1]).to_json()
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
