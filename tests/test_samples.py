"""The sample programs run (in quick mode) so that they never rot."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

SAMPLES = sorted((Path(__file__).resolve().parents[1] / "samples").glob("[0-9][0-9]_*.py"))


@pytest.mark.parametrize("script", SAMPLES, ids=[s.name for s in SAMPLES])
def test_sample_runs(script: Path, tmp_path: Path) -> None:
    args = [sys.executable, str(script), "--quick"]
    args += ["--out", str(tmp_path / ("out.png" if "reference" in script.name else "copy.twin"))]
    proc = subprocess.run(args, capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.strip(), "a sample should say what it did"
