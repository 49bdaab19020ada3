"""What every benchmark does with its figures: write them as JSON where `--json` says, with the
machine and the code they were measured on (timings from two machines are not comparable)."""

from __future__ import annotations

import datetime as _dt
import json
import os
import platform
import subprocess
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]


def _cpu() -> tuple[str, str]:
    """The CPU's model name and the widest vector instructions it has (a virtual machine's
    model name can be as vague as "AMD EPYC")."""
    model, flags = "", set()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name") and not model:
                model = line.split(":", 1)[1].strip()
            elif line.startswith("flags") and not flags:
                flags = set(line.split(":", 1)[1].split())
    except OSError:
        pass
    simd = next((f for f in ("avx512f", "avx2", "avx", "neon", "asimd") if f in flags), "")
    return model or platform.processor() or platform.machine(), simd


def _commit() -> str:
    """The checkout's commit, with "+changes" where the code (`src/`, `benchmarks/` but for
    its results, `pyproject.toml`) differs from it ("" outside git)."""
    try:
        head = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True,
            check=True, timeout=10,
        ).stdout.strip()  # fmt: skip
        dirty = subprocess.run(  # the results a benchmark run rewrites are not the code
            ["git", "status", "--porcelain", "--untracked-files=no", "--", "src", "benchmarks",
             "pyproject.toml", ":!benchmarks/results"], cwd=ROOT, capture_output=True, text=True,
            timeout=10,
        ).stdout.strip()  # fmt: skip
    except (OSError, subprocess.SubprocessError):
        return ""
    return head + ("+changes" if dirty else "")


def machine() -> dict[str, Any]:
    """Where and when the figures were measured: the CPU and its vector width, the cores this
    process may use, the Python, the commit and the time (UTC)."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    model, simd = _cpu()
    return {
        "cpu": model,
        "simd": simd,
        "cores": cores,
        "python": platform.python_version(),
        "commit": _commit(),
        "measured": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
    }


def write_json(path: Path | None, data: Any) -> None:
    """Writes `data` to `path` (its folder made as needed) and says so; nothing when None. A
    dict gets a "machine" entry (`machine()`)."""
    if path is None:
        return
    if isinstance(data, dict):
        data = {**data, "machine": machine()}
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data, indent=1))
    print(f"wrote {path}")
