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
import re
import socket
import tempfile
import time
from pathlib import Path
from typing import Any

from vinetwin._faults import fault_point

#: Temporary files of `atomic_write_bytes`: `.NAME.HOST-PID.RANDOM.tmp`.
_TEMP_RE = re.compile(r"^\..+\.(?P<host>[A-Za-z0-9-]+)-(?P<pid>[0-9]+)\.[^.]+\.tmp$")
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
    sidecars, which `sync_to_disk` flushes together at the end of the export)."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(
        prefix=f".{path.name}.{_host_tag()}-{os.getpid()}.", suffix=".tmp", dir=path.parent
    )
    try:
        os.fchmod(fd, _mode_for(path))
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            if sync:
                os.fsync(fh.fileno())
        fault_point(str(path), "write")  # tests: a writer killed before the rename
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def _mode_for(path: Path) -> int:
    """The mode the file gets: the one it has, else what the umask leaves of rw-rw-rw- (as
    `open` would give it; mkstemp's temporary files are rw------- whatever the umask)."""
    try:
        return path.stat().st_mode & 0o777
    except OSError:
        return 0o666 & ~_umask()


def _umask() -> int:
    """The process's umask, read without changing it (Linux: /proc; elsewhere set and reset)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    umask = os.umask(0o022)
    os.umask(umask)
    return umask


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
    older than `ORPHAN_AGE_S`. Files being written by a live process are kept. Returns what
    was removed."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    host, now, removed = _host_tag(), time.time(), []
    for p in folder.glob(".*.tmp"):
        m = _TEMP_RE.match(p.name)
        try:
            old = now - p.stat().st_mtime > ORPHAN_AGE_S
        except OSError:
            continue
        dead = m is not None and m["host"] == host and not _pid_alive(int(m["pid"]))
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
