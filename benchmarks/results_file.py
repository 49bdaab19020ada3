"""What every benchmark does with its figures: write them as JSON where `--json` says."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any


def write_json(path: Path | None, data: Any) -> None:
    """Writes `data` to `path` (its folder made as needed) and says so; nothing when None."""
    if path is None:
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data, indent=1))
    print(f"wrote {path}")
