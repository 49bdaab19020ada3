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


#: PLY scalar types (names and their aliases) as numpy type codes
_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip


def _binary_ply_triangles(path: Path) -> tuple[np.ndarray, np.ndarray] | None:
    """Vertices (float64) and faces (int64) of a binary PLY of vertices with x, y, z and
    triangle faces, the form vinetwin writes (`mesh_ply_bytes`); None for any other file
    (ASCII, other elements, polygons, a size that does not add up), which trimesh then reads.
    It reads what trimesh reads, without importing it (0.8-1 s, paid by each export worker)."""
    with open(path, "rb") as f:
        head = f.read(65536)
        end = head.find(b"end_header")
        if not head.startswith(b"ply") or end < 0:
            return None
        stop = head.find(b"\n", end)
        if stop < 0:
            return None
        lines = head[:stop].decode("ascii", "replace").splitlines()[1:]
        order = ""
        elements: list[tuple[str, int, list[list[str]]]] = []
        for line in lines:
            w = line.split()
            if not w or w[0] in ("comment", "obj_info", "end_header"):
                continue
            if w[0] == "format" and len(w) >= 2:
                order = {"binary_little_endian": "<", "binary_big_endian": ">"}.get(w[1], "")
            elif w[0] == "element" and len(w) == 3 and w[2].isdigit():
                elements.append((w[1], int(w[2]), []))
            elif w[0] == "property" and elements:
                elements[-1][2].append(w[1:])
            else:
                return None
        if not order or [e[0] for e in elements] != ["vertex", "face"]:
            return None
        (_, nv, vprops), (_, nf, fprops) = elements
        try:
            vdtype = np.dtype([(p[1], order + _PLY_TYPES[p[0]]) for p in vprops])
        except (KeyError, IndexError, TypeError, ValueError):
            return None
        if len(fprops) != 1 or len(fprops[0]) != 4 or fprops[0][0] != "list":
            return None
        count_t, index_t = _PLY_TYPES.get(fprops[0][1]), _PLY_TYPES.get(fprops[0][2])
        names = vdtype.names or ()
        if count_t is None or index_t is None or not all(k in names for k in "xyz"):
            return None
        fdtype = np.dtype([("n", order + count_t), ("i", order + index_t, 3)])
        start = stop + 1
        if start + nv * vdtype.itemsize + nf * fdtype.itemsize != path.stat().st_size:
            return None  # polygons other than triangles, or a truncated or padded file
        f.seek(start)
        verts = np.fromfile(f, vdtype, nv)
        faces = np.fromfile(f, fdtype, nf)
    if len(verts) != nv or len(faces) != nf or not np.all(faces["n"] == 3):
        return None
    V = np.stack([verts["x"], verts["y"], verts["z"]], axis=1).astype(np.float64)
    return V, faces["i"].astype(np.int64)


def load_mesh_arrays(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """A checked mesh's vertices (V, 3) float64 and faces (F, 3) int64, as `load_mesh` reads
    them, for the processes that need only the arrays (export and campaign workers): binary
    PLY triangle meshes (what twins hold) are read without trimesh; anything else through it."""
    path = Path(path)
    if not path.exists():
        raise MeshError(f"{path}: mesh file does not exist")
    try:
        arrays = _binary_ply_triangles(path) if path.suffix.lower() == ".ply" else None
    except (OSError, ValueError):
        arrays = None
    if arrays is None:
        mesh = load_mesh(path)
        return np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64)
    check_mesh_arrays(*arrays, str(path))
    return arrays


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
