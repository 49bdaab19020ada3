"""Files that survive a crash: atomic writes (a flushed temporary file renamed over the old
one), the clean-up of temporary files that killed writers leave behind, and content hashes.

Every file vinetwin writes (twin.json, meshes, references, capture frames, campaign runs,
validation results) goes through `atomic_write_bytes`, so a reader sees the old file or the new
one, never half of one.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import json
import os
import random
import re
import socket
import time
from pathlib import Path
from typing import Any

from vinetwin._faults import fault_point

#: Temporary files of `atomic_write_bytes`: `.NAME.vinetwin-HOST-PID.RANDOM.vttmp`, a name only
#: vinetwin makes; the clean-up removes nothing else (a user's `.notes.tmp` stays).
_TEMP_SUFFIX = ".vttmp"
_TEMP_RE = re.compile(
    r"^\..+\.vinetwin-(?P<host>[A-Za-z0-9-]+)-(?P<pid>[0-9]+)\.[0-9a-f]{10}\.vttmp$"
)
#: A temporary file this old is an orphan whoever wrote it (a write takes well under a second).
ORPHAN_AGE_S = 3600.0


@functools.cache
def _host_tag() -> str:
    return re.sub(r"[^A-Za-z0-9-]", "-", socket.gethostname())[:40] or "host"


def atomic_write_bytes(path: Path, data: bytes, *, sync: bool = True) -> None:
    """Writes `data` to `path` through a flushed temporary file and a rename.

    `sync=False` leaves out the fsync: other processes still see the old file or the new one,
    but after a power loss the file may be empty or old. Only for files whose content is
    checked against a hash recorded elsewhere before it is used (export's reference clouds and
    sidecars, which `sync_to_disk` flushes together at the end of the export).

    The new file gets the mode `open` would give it (rw-rw-rw- less the umask, applied by the
    system) or, when it replaces one, that file's mode. Plain `os` calls, not `tempfile` and a
    Python file object: an export writes three files per reference, and the extra system
    calls (the umask read from /proc, a chmod, a file object's stat, ioctl and seeks) cost
    about 0.5 ms of a worker's 17 ms per reference."""
    path = Path(path)
    try:
        keep: int | None = path.stat().st_mode & 0o777
    except OSError:
        keep = None
    prefix = f".{path.name}.vinetwin-{_host_tag()}-{os.getpid()}."
    for _ in range(100):
        tmp = path.parent / f"{prefix}{_TOKENS.getrandbits(40):010x}{_TEMP_SUFFIX}"
        try:
            fd = os.open(tmp, _CREATE, 0o666)
            break
        except FileExistsError:
            continue
    else:
        raise FileExistsError(f"{path.parent}: no free temporary name for {path.name}")
    try:
        _write_renamed(fd, tmp, path, data, keep, sync)
    except OSError as exc:
        if exc.filename is None and exc.strerror:  # os.write names no file: say where
            exc.filename = str(path)
        raise


def _write_renamed(
    fd: int, tmp: Path, path: Path, data: bytes, keep: int | None, sync: bool
) -> None:
    """`atomic_write_bytes`'s part after the temporary file is open: write, rename."""
    try:
        try:
            if keep is not None:
                os.fchmod(fd, keep)
            view = memoryview(data)
            while view:
                view = view[os.write(fd, view) :]
            if sync:
                os.fsync(fd)
        finally:
            os.close(fd)
        fault_point(str(path), "write")  # tests: a writer killed before the rename
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


#: How `atomic_write_bytes` creates its temporary file: new only, never through a link.
_CREATE = (
    os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_CLOEXEC", 0)
    | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_BINARY", 0)
)  # fmt: skip
#: Random parts of temporary names (with the host and pid, and created exclusively).
_TOKENS = random.Random()
if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_TOKENS.seed)


def save_figure(fig: Any, path: str | Path, dpi: int = 100) -> None:
    """A matplotlib figure as a PNG at `path`, atomically (a full disk names the file and
    leaves no half picture)."""
    import io

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    atomic_write_bytes(Path(path), buf.getvalue())


def atomic_write_text(path: Path, text: str, *, sync: bool = True) -> None:
    atomic_write_bytes(path, text.encode("utf-8"), sync=sync)


def sync_to_disk() -> None:
    """Flushes every written file to disk at once (after writes with `sync=False`): one
    journal commit for a whole batch instead of one fsync per file."""
    if hasattr(os, "sync"):
        os.sync()


def atomic_write_json(path: Path, data: Any, indent: int | None = 1) -> None:
    """`data` as JSON (numpy values as lists), atomically, with a final newline."""
    from vinetwin._config import json_default

    atomic_write_text(path, json.dumps(data, indent=indent, default=json_default) + "\n")


def refuse_existing(path: str | Path, flag: str, overwrite: bool = False) -> Path:
    """`path` as a Path, once it is known that writing there destroys nothing the user did not
    ask to replace: an existing file (or a folder that is not empty) raises InputError naming
    `flag` unless `overwrite`. A file where a folder goes, or the reverse, is refused anyway."""
    from vinetwin.errors import InputError

    path = Path(path)
    if not overwrite and (path.is_file() or path.is_symlink()):
        raise InputError(f"{flag} {path} exists; choose another name or pass --overwrite")
    if not overwrite and path.is_dir() and any(path.iterdir()):
        raise InputError(
            f"{flag} {path} is a folder that is not empty; choose another or pass --overwrite"
        )
    return path


def refuse_existing_json(path: Path | None, overwrite: bool) -> None:
    """A command's `--json PATH` (None: not asked for): `refuse_existing`, before the work."""
    if path is not None:
        refuse_existing(path, "--json", overwrite)


def refuse_existing_outputs(
    folder: Path, names: tuple[str, ...], flag: str, overwrite: bool
) -> None:
    """`refuse_existing` for the files `names` a command writes into `folder`; a `folder` that
    is a file is refused anyway."""
    from vinetwin.errors import InputError

    if folder.exists() and not folder.is_dir():
        raise InputError(f"{flag} {folder} is a file; name a folder (for {', '.join(names)})")
    for name in names:
        refuse_existing(folder / name, flag, overwrite)


def parse_json(text: str | bytes) -> Any:
    """`json.loads`, whose every refusal is a ValueError: besides malformed JSON, an integer
    of over 4300 digits (Python's own limit) and nesting deeper than the parser's recursion
    (`[[[[...` 100 000 deep: a RecursionError) are named as such."""
    try:
        return json.loads(text)
    except RecursionError:
        raise ValueError("nested too deeply to read") from None


def read_json(path: Path, error: type[Exception] = ValueError) -> Any:
    """The JSON file at `path`; any failure to read or parse it (missing, unreadable, not
    UTF-8, not JSON, too deep, too large a number) raises `error` naming the file and why."""
    try:
        return parse_json(Path(path).read_bytes())
    except (OSError, ValueError) as exc:  # UnicodeDecodeError and JSONDecodeError included
        why = exc.strerror if isinstance(exc, OSError) and exc.strerror else exc
        raise error(f"{path}: cannot read it as JSON: {why}") from None


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)  # signal 0: only asks whether the process exists
    except ProcessLookupError:
        return False
    except PermissionError:  # it exists, under another user
        pass
    return True


def remove_orphan_temp_files(folder: Path) -> list[Path]:
    """Removes the temporary files that writers killed in the middle of `atomic_write_bytes`
    left in `folder` (a worker killed by the OOM killer, or terminated by a pool that broke
    while it was writing): those written on this machine by a process that is gone, and any
    older than `ORPHAN_AGE_S`. Only names `atomic_write_bytes` makes (`_TEMP_RE`) are touched,
    never a link, and never through one: a `folder` that is a symbolic link (a twin's
    `references/` pointing elsewhere) is left alone. Files being written by a live process are
    kept. Returns what was removed."""
    folder = Path(folder)
    if folder.is_symlink() or not folder.is_dir():
        return []
    host, now, removed = _host_tag(), time.time(), []
    for p in folder.glob(f".*{_TEMP_SUFFIX}"):
        m = _TEMP_RE.match(p.name)
        if m is None or p.is_symlink():
            continue
        try:
            old = now - p.lstat().st_mtime > ORPHAN_AGE_S
        except OSError:
            continue
        dead = m["host"] == host and not _pid_alive(int(m["pid"]))
        if old or dead:
            with contextlib.suppress(OSError):
                p.unlink()
                removed.append(p)
    return removed


def file_sha256(path: Path) -> str:
    """The SHA-256 of a file's content (hex)."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def json_sha256(data: Any) -> str:
    """The SHA-256 of `data` as canonical JSON (sorted keys; numpy values as lists): the digest
    of a job's inputs."""
    from vinetwin._config import json_default

    blob = json.dumps(data, sort_keys=True, default=json_default)
    return hashlib.sha256(blob.encode()).hexdigest()
