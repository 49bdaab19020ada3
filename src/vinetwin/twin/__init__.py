"""The twin folder format, pruning poses, vine skeletons, importers and the sample generator.

Imports only numpy (trimesh when a mesh is read or written)."""

from vinetwin.twin.model import (
    FORMAT_VERSION,
    CutPoint,
    PruningPose,
    Twin,
    load_mesh,
    twin_from_skeleton,
)
from vinetwin.twin.poses import Approach, pruning_pose
from vinetwin.twin.skeleton import Branch, CutCandidate, Skeleton, tube_mesh

__all__ = [
    "FORMAT_VERSION",
    "Approach",
    "Branch",
    "CutCandidate",
    "CutPoint",
    "PruningPose",
    "Skeleton",
    "Twin",
    "load_mesh",
    "pruning_pose",
    "tube_mesh",
    "twin_from_skeleton",
]
