"""What an import found (`ScanImport`), shared by the importer and its report."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from vinetwin.frames import Array
from vinetwin.scan.skeletonize import SkeletonResult
from vinetwin.twin.skeleton import Skeleton

#: Labels of removed points, in the order the report lists them.
REMOVED = ("stray", "ground", "clutter", "wire", "post", "apart", "others")


@dataclass
class ScanImport:
    """What an import found, before anything is written."""

    skeleton: Skeleton
    """In the vine frame, with kinds and cut candidates."""
    T_vine_scan: Array
    """Maps the file's points, converted to metres (`units`), into the vine frame."""
    units: str
    unit_note: str
    up_from: str
    """How the up axis was found: given, ground, trunk."""
    points: Array
    """The plant's points kept, in the vine frame."""
    removed: dict[str, Array] = field(default_factory=dict)
    """Removed points by reason (vine frame)."""
    read: int = 0
    spacing: float = 0.0
    result: SkeletonResult | None = None
    notes: list[str] = field(default_factory=list)
    mesh: tuple[Array, np.ndarray] | None = None
    """The scan's own mesh in the vine frame (mesh files)."""
    seconds: dict[str, float] = field(default_factory=dict)

    def counts(self) -> dict[str, int]:
        return {"read": self.read, "kept": len(self.points),
                **{k: len(self.removed.get(k, ())) for k in REMOVED}}  # fmt: skip

    def summary(self) -> dict[str, Any]:
        """What the twin's provenance and the report keep of the import."""
        r = self.result
        return {
            "units": self.units,
            "units_note": self.unit_note,
            "up_from": self.up_from,
            "T_vine_scan": np.round(self.T_vine_scan, 9).tolist(),
            "point_spacing_m": round(self.spacing, 6),
            "counts": self.counts(),
            "notes": self.notes,
            "skeleton": {
                "method": "geodesic level sets (vinetwin.scan.skeletonize)",
                "voxel_m": round(r.voxel, 6) if r else None,
                "bin_m": round(r.bin, 6) if r else None,
                "bridges": r.bridges if r else 0,
                "branches": len(self.skeleton.branches),
                "candidates": len(self.skeleton.candidates),
            },
            "seconds": {k: round(v, 3) for k, v in self.seconds.items()},
        }
