"""Shared fixtures. Real data from ../shared/data is read where it exists; tests that need it are
skipped (with the reason) on a checkout without it."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
os.environ.setdefault("MUJOCO_GL", "egl")

ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = ROOT.parent / "shared" / "data"
SAMPLES = ROOT / "samples"


def shared(*parts: str) -> Path:
    p = SHARED_DATA.joinpath(*parts)
    if not p.exists():
        pytest.skip(f"shared data not present: {p}")
    return p


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(1234)


@pytest.fixture(scope="session")
def sample_twin_dir() -> Path:
    p = SAMPLES / "vine_bilateral.twin"
    assert (p / "twin.json").exists(), "bundled sample twin missing; run samples/make_samples.py"
    return p
