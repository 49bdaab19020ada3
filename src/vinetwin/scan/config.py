"""The settings of `vinetwin import-scan`, each declared once (its docstring is its `--help`).

The plausibility ranges that decide the units and refuse what is no plant are named constants
here too: the unit detector, the refusals and `docs/scans.md` read them from this module."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from vinetwin._config import check_counts, check_finite
from vinetwin.errors import InputError
from vinetwin.twin.skeleton import DEFAULT_INTERNODE as DEFAULT_INTERNODE  # declared there
from vinetwin.twin.skeleton import FIRST_NODE as FIRST_NODE

Units = Literal["auto", "m", "cm", "mm", "in", "ft"]
UpAxis = Literal["auto", "x", "y", "z", "-x", "-y", "-z"]
PlantKind = Literal["vine", "tree"]
MeshSource = Literal["tubes", "scan"]

#: Metres per unit.
UNIT_SCALE: dict[str, float] = {"m": 1.0, "cm": 0.01, "mm": 0.001, "in": 0.0254, "ft": 0.3048}
#: Units `auto` chooses among (inches and feet only when named).
AUTO_UNITS = ("m", "cm", "mm")
#: A plant's largest extent (m), by kind: a dormant vine is 0.5-3 m (5 m for a long cordon),
#: the measured trees of `../shared/data` up to 18 m. Outside it the scale is refused by name.
PLANT_EXTENT: dict[str, tuple[float, float]] = {"vine": (0.15, 5.0), "tree": (0.15, 30.0)}
#: A scan of a row of plants (`scan.row`) may be this long (m) when its units are named: `auto`
#: judges the units by one plant's size and would take a long row for a plant in other units.
ROW_EXTENT = 100.0
#: The median distance between neighbouring points (m) of a scan of a plant: terrestrial and
#: handheld LiDAR, stereo and photogrammetry give 0.5-30 mm.
POINT_SPACING = (0.0002, 0.05)
#: A vine's scan sparser than this (m, median between neighbours) cannot hold its canes (5-15 mm
#: thick): at 20 mm, the sparsest simulated quality, the skeleton found 37-61% of the canes
#: (`docs/scans.md`); a tree's limbs are scanned coarser (WoodSKE's real LiDAR trees: 25 mm).
VINE_MAX_SPACING = 0.03
#: A vine's wood is mostly canes, spurs and cordons, 0.5-4 cm thick: a skeleton whose
#: length-weighted median thickness (m) is above this is no vine (a volume of scattered points).
VINE_MAX_THICKNESS = 0.05
#: Points read at most; a larger file is decimated while it is read (every k-th point, named
#: in the report), so memory stays bounded (about 100 bytes a point while importing).
MAX_POINTS = 5_000_000
#: Fewer points than this are no plant scan.
MIN_POINTS = 200


@dataclass(frozen=True, kw_only=True)
class CleanConfig:
    """What is removed from a scan before its skeleton is found; each switchable."""

    strays: bool = True
    """Remove stray points: statistical outliers and small clusters apart from the plant."""
    ground: bool = True
    """Remove the ground: a large plane under the plant (its normal also gives the up axis)."""
    clutter: bool = True
    """Remove ground clutter (grass, weeds): what stands below 0.3 m above the ground
    (`scan.clean.CLUTTER_HEIGHT`) but the trunks' and posts' columns; with the ground only."""
    wires: bool = True
    """Remove trellis wires: long (>= 1 m), thin, straight, horizontal lines of points."""
    posts: bool = True
    """Remove posts: straight vertical clusters (>= 1 m) apart from the plant."""
    outlier_neighbours: int = 16
    """Neighbours of the statistical outlier test."""
    outlier_std: float = 3.0
    """A point farther from its neighbours than the mean + this many deviations is a stray."""

    def __post_init__(self) -> None:
        check_finite(self, ("outlier_std",), positive=True)
        check_counts(self, ("outlier_neighbours",), 1000)
        if self.outlier_neighbours < 4:
            raise InputError(f"outlier_neighbours must be >= 4, got {self.outlier_neighbours}")


@dataclass(frozen=True, kw_only=True)
class SkeletonConfig:
    """How the skeleton is found (level sets of the geodesic distance from the trunk's foot)."""

    voxel: float = 0.0
    """Working resolution (m): the scan is thinned to one point per voxel; 0 chooses from the
    point spacing (at least 3 mm)."""
    bin: float = 0.0
    """Width (m) of the geodesic slices whose clusters become skeleton nodes; 0: 4 voxels for a
    vine, 3 for a tree (`skeletonize.BIN_VOXELS`)."""
    gap: float = 0.035
    """Largest hole (m) bridged between pieces of the plant (a cane hidden behind another)."""
    min_branch: float = 0.03
    """A side branch shorter than this (m) is noise at a junction and is dropped."""
    refine: int = 2
    """Passes re-fitting each branch's centres and radii to its own points (`scan.refine`:
    centres near a fork no longer lean towards the other branch); 0 leaves the level sets'."""

    def __post_init__(self) -> None:
        check_counts(self, ("refine",), 5)
        check_finite(self, ("voxel", "bin"))
        check_finite(self, ("gap", "min_branch"), positive=True)
        for name, hi in (("voxel", 0.05), ("bin", 0.2), ("gap", 0.2), ("min_branch", 0.5)):
            if getattr(self, name) > hi:
                raise InputError(f"{name} {getattr(self, name):g} m is above {hi:g} m: no plant")


@dataclass(frozen=True, kw_only=True)
class ScanImportConfig:
    """One import of a scan: units, frame, cleaning, skeleton, mesh, cut candidates."""

    units: Units = "auto"
    """Units of the file's coordinates; auto: from the plant's size and point spacing."""
    up: UpAxis = "auto"
    """The scan's up axis; auto: the ground plane's normal, else the trunk's direction (the
    direction from its foot to the plant's mass when the two disagree; the axis of its thickest
    stretch when that says the foot is reversed); name it for a tree scanned without ground,
    see docs/scans.md."""
    plant: PlantKind = "vine"
    """vine: trunk, cordons, spurs, canes; a cut candidate where each cane would be shortened to
    a two-bud spur. tree: a trunk and branches; a candidate where each shoot stands 3 cm off
    the wood it grows from."""
    mesh: MeshSource = "tubes"
    """The twin's mesh: tubes around the skeleton, or the scan's own mesh (a mesh file only)."""
    edge: float = 0.003
    """Target triangle edge length of the tube mesh, metres."""
    cut_points: int = 0
    """How many cut candidates become cut points with a pruning pose."""
    internode: float = DEFAULT_INTERNODE
    """Distance between buds on a cane (m), for the two-bud spur's cut on a scan."""
    max_points: int = MAX_POINTS
    """Points kept while reading; a larger file is decimated (every k-th point) and says so."""
    plant_number: int = 0
    """A scan of a row holds several plants: import the K-th along the row (1 = the first, as
    the refusal lists them; `scan.row`). 0: the scan holds one plant; several trunks are
    refused, with where they stand."""
    clean: CleanConfig = CleanConfig()
    skeleton: SkeletonConfig = SkeletonConfig()

    def __post_init__(self) -> None:
        check_finite(self, ("edge", "internode"), positive=True)
        check_counts(self, ("cut_points",), 10_000)
        check_counts(self, ("plant_number",), 1000)
        if not 0.02 <= self.internode <= 0.3:
            raise InputError(f"internode must lie in [0.02, 0.3] m, got {self.internode:g}")
        if not 10 * MIN_POINTS <= self.max_points <= 50_000_000:
            raise InputError(
                f"max_points must lie in [{10 * MIN_POINTS}, 50000000], got {self.max_points}"
            )
