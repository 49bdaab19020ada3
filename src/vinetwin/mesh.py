"""Triangle meshes in and out: read any format trimesh reads, and check what a renderer, a
ray caster or a twin needs (finite vertices, triangle faces, indices in range), naming the
problem in a `MeshError`."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from vinetwin.errors import MeshError

if TYPE_CHECKING:
    import trimesh


def check_mesh_arrays(V: Any, F: Any, where: str) -> None:
    """Raises MeshError naming the problem: bad shapes, no faces, non-finite vertices, faces
    indexing missing vertices."""
    V = np.asarray(V)
    F = np.asarray(F)
    if F.ndim != 2 or F.shape[1] != 3 or len(F) == 0:
        raise MeshError(f"{where}: mesh has no triangle faces (faces shape {F.shape})")
    if V.ndim != 2 or V.shape[1] != 3 or len(V) == 0:
        raise MeshError(f"{where}: mesh vertices must have shape (V, 3) with V > 0, got {V.shape}")
    if not np.all(np.isfinite(V)):
        raise MeshError(
            f"{where}: mesh has {int((~np.isfinite(V)).any(1).sum())} non-finite vertices"
        )
    if F.min() < 0 or F.max() >= len(V):
        raise MeshError(f"{where}: mesh faces index vertices out of range 0..{len(V) - 1}")


def load_mesh(path: str | Path) -> trimesh.Trimesh:
    """Reads a triangle mesh (PLY, OBJ, STL, GLB...) and checks it; raises MeshError naming the
    problem (missing, unreadable, no faces, non-finite vertices)."""
    import trimesh

    path = Path(path)
    if not path.exists():
        raise MeshError(f"{path}: mesh file does not exist")
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types on corrupt input
        raise MeshError(f"{path}: cannot read mesh: {type(exc).__name__}: {exc}") from exc
    if not isinstance(mesh, trimesh.Trimesh):
        raise MeshError(f"{path}: not a triangle mesh")
    check_mesh_arrays(mesh.vertices, mesh.faces, str(path))
    return mesh


def mesh_ply_bytes(vertices: Any, faces: Any, where: str) -> bytes:
    """A checked mesh as binary PLY (float32 vertices, metres)."""
    import trimesh

    V = np.asarray(vertices)
    check_mesh_arrays(V, faces, where)
    data = trimesh.Trimesh(V.astype(np.float32), np.asarray(faces), process=False).export(
        file_type="ply", encoding="binary"
    )
    if not isinstance(data, bytes):
        raise MeshError(f"{where}: trimesh returned {type(data).__name__}, not PLY bytes")
    return data
