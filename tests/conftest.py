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


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(
        "--noise-stream", type=int, default=0, metavar="K",
        help="draw the D405 model's normal noise from stream K (0: numpy's, as seeded): a test "
        "that passes only for its seed's numbers sits on a threshold",
    )  # fmt: skip


def pytest_configure(config: pytest.Config) -> None:
    k = int(config.getoption("--noise-stream"))
    if k:
        from vinetwin.render import _sensor_kernels

        numpy_stream = _sensor_kernels.standard_normals

        def other_stream(rng: np.random.Generator, n: int) -> np.ndarray:
            numpy_stream(rng, n)  # the caller's generator ends where it would have
            return np.random.default_rng([int(rng.integers(2**62)), k]).standard_normal(n)

        _sensor_kernels.standard_normals = other_stream


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    if not config.getoption("--noise-stream"):
        return
    skip = pytest.mark.skip(reason="compares with numpy's noise stream or worker processes' noise")
    for item in items:
        if "numpy_noise" in item.keywords:
            item.add_marker(skip)


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


@pytest.fixture
def twin_dir(sample_twin_dir: Path, tmp_path: Path) -> Path:
    """A copy of the bundled sample to change (without references or validation results)."""
    import shutil

    dst = tmp_path / "vine.twin"
    shutil.copytree(sample_twin_dir, dst, ignore=shutil.ignore_patterns("references", "validation"))
    return dst


class VineViews:
    """The bilateral sample rendered like a servo sees it: a reference cloud per pruning pose and
    current clouds (depth and cloud) at known offsets from it, each with its own D405 noise."""

    def __init__(self, twin_dir: Path) -> None:
        from vinetwin.render.backends import get_backend
        from vinetwin.twin import Twin

        self.twin = Twin.load(twin_dir)
        mesh = self.twin.load_mesh()
        self.backend = get_backend("open3d", mesh.vertices, mesh.faces, self.twin.camera)
        self._refs: dict[str, object] = {}

    def depth(self, T_vine_camera: np.ndarray, seed: int) -> np.ndarray:
        from vinetwin.render.sensor import SensorConfig, apply_d405_model

        clean = self.backend.render(T_vine_camera)
        return apply_d405_model(
            clean, self.twin.camera, np.random.default_rng(seed), SensorConfig()
        )

    def cloud(self, T_vine_camera: np.ndarray, seed: int):  # type: ignore[no-untyped-def]
        from vinetwin.cloud import perceive

        return perceive(self.depth(T_vine_camera, seed), self.twin.camera, self.twin.perception)

    def reference(self, pose_id: str):  # type: ignore[no-untyped-def]
        if pose_id not in self._refs:
            self._refs[pose_id] = self.cloud(self.twin.pose(pose_id).T_vine_camera, 1)
        return self._refs[pose_id]

    def cases(self, offset_m: float, offset_deg: float, per_pose: int, seed: int = 7):  # type: ignore[no-untyped-def]
        """(pose id, reference, current cloud, T_ref_cur truth) at random offsets of the given size."""
        from vinetwin import frames as fr

        rng = np.random.default_rng(seed)
        out = []
        for pose in self.twin.poses:
            for k in range(per_pose):
                D = fr.random_pose(rng, offset_m, np.radians(offset_deg))
                cur = self.cloud(pose.T_vine_camera @ D, 100 + k)
                out.append((pose.id, self.reference(pose.id), cur, D))
        return out


@pytest.fixture(scope="session")
def vine_views(sample_twin_dir: Path) -> VineViews:
    return VineViews(sample_twin_dir)
