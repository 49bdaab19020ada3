"""Resumable batch results: a folder of JSON result files, each valid for one digest of its
job's inputs. A job whose file carries the digest of its current inputs (and whose companion
files, such as a reference's clouds, exist) is done; anything else runs again. Files are
written atomically and last, so a job killed mid-way leaves either no result or a whole one,
and the temporary files that killed writers leave are cleaned up. Export (`references/`),
campaigns (`runs/`) and validation (`validation/`) keep their results here."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from vinetwin._config import json_default
from vinetwin.files import atomic_write_text, parse_json, remove_orphan_temp_files


class JobStore:
    """Result files `NAME.json` in `folder`, each carrying `format_key: version` and
    `digest_key: digest` beside the job's own fields."""

    def __init__(
        self,
        folder: str | Path,
        version: int,
        *,
        format_key: str = "format",
        digest_key: str = "digest",
        indent: int | None = 1,
        sync: bool = True,
    ) -> None:
        self.folder = Path(folder)
        self.version = version
        self.format_key = format_key
        self.digest_key = digest_key
        self.indent = indent
        self.sync = sync
        """False: results are written without fsync (`files.atomic_write_bytes`); for stores
        whose records are checked before use and flushed by the caller."""

    def path(self, name: str) -> Path:
        return self.folder / f"{name}.json"

    def open(self) -> JobStore:
        """Creates the folder and removes what writers killed in an earlier run left there."""
        self.folder.mkdir(parents=True, exist_ok=True)
        self.clean()
        return self

    def clean(self) -> list[Path]:
        """Removes the temporary files of dead writers (a pool that broke mid-write)."""
        return remove_orphan_temp_files(self.folder)

    def read(self, name: str) -> dict[str, Any] | None:
        """The result file of `name`, or None when it is missing, unreadable or of another
        format version."""
        try:
            record = parse_json(self.path(name).read_bytes())
        except (OSError, ValueError):  # missing, not UTF-8, not JSON, too deep: run it again
            return None
        if not isinstance(record, dict) or record.get(self.format_key) != self.version:
            return None
        return record

    def current(
        self, name: str, digest: str, companions: Sequence[str | Path] = ()
    ) -> dict[str, Any] | None:
        """The result of `name` if it was made from inputs with this digest and its
        `companions` (other files it stands for) exist; else None: run it (again)."""
        if not all(Path(c).exists() for c in companions):
            return None
        record = self.read(name)
        if record is None or record.get(self.digest_key) != digest:
            return None
        return record

    def put(self, name: str, digest: str, result: dict[str, Any]) -> dict[str, Any]:
        """Writes the result (atomically) with its digest; returns it as a reader reads it."""
        record = {**result, self.format_key: self.version, self.digest_key: digest}
        text = json.dumps(record, indent=self.indent, default=json_default)
        atomic_write_text(self.path(name), text + "\n", sync=self.sync)
        return json.loads(text)
