"""The settings of `vinetwin propose`: the pruning rule and its options, the tool and camera body
the pose search keeps clear of the vine, and the search itself. Each range below is the one place
it is declared: the command line, the web app and the docs read it from here."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Literal

from vinetwin._config import JsonFields, check_counts, check_finite
from vinetwin.errors import InputError
from vinetwin.twin.model import TOOL_REACH
from vinetwin.twin.poses import DEFAULT_STANDOFF, STANDOFF_RANGE
from vinetwin.twin.skeleton import DEFAULT_INTERNODE

Rule = Literal["spur", "cane"]
RULES: tuple[Rule, ...] = ("spur", "cane")

#: Buds a spur keeps (Silwal et al. 2022 cut between the Nth and (N+1)th bud; two is the
#: common spur), buds a kept cane keeps (8-15 in cane-pruned vineyards, Botterill et al. 2017),
#: and the internode lengths (m) a rule accepts: the generator's canes are 5-9 cm, hydroshoot's
#: shoots 6-10 cm; below 3 cm or above 15 cm is no grapevine.
SPUR_BUDS_RANGE = (1, 4)
CANE_BUDS_RANGE = (4, 20)
INTERNODE_RANGE = (0.03, 0.15)


@dataclass(frozen=True, kw_only=True)
class RuleConfig(JsonFields):
    """Which cuts a pruning rule proposes on a twin's skeleton."""

    rule: Rule = "spur"
    """spur: each spur keeps its best-placed cane shortened to `buds` buds, its other canes are
    cut at their base. cane: the `canes` canes nearest the head (the trunk's top) keep
    `cane_buds` buds, the next one is a renewal spur of `buds` buds, every other cane or spur is
    cut at its base."""
    buds: int = 2
    """Buds a spur keeps (the spur rule's spurs and the cane rule's renewal spur)."""
    cane_buds: int = 10
    """Buds each kept cane keeps (cane rule)."""
    canes: int = 2
    """Canes kept (cane rule): 1 or 2."""
    internode: float = 0.0
    """Distance between buds (m). 0: the skeleton's own nodes where it knows them (the generator,
    hydroshoot), else `DEFAULT_INTERNODE` (7 cm); a value: buds every that far on every cane,
    counted from the permanent wood's surface (what a scan allows)."""
    spur_radius: float = 0.03
    """Canes leaving the permanent wood within this distance (m) of each other belong to one
    spur."""

    def __post_init__(self) -> None:
        if self.rule not in RULES:
            raise InputError(f"unknown rule {self.rule!r}; choose one of: {', '.join(RULES)}")
        for name, (lo, hi) in (("buds", SPUR_BUDS_RANGE), ("cane_buds", CANE_BUDS_RANGE),
                               ("canes", (1, 2))):  # fmt: skip
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
                raise InputError(f"{name} must be an integer from {lo} to {hi}, got {v!r}")
        check_finite(self, ("internode", "spur_radius"))
        lo, hi = INTERNODE_RANGE
        if self.internode != 0.0 and not lo <= self.internode <= hi:
            raise InputError(
                f"internode must be 0 (the skeleton's nodes) or {lo}-{hi} m, got {self.internode}"
            )
        if not 0.005 <= self.spur_radius <= 0.1:
            raise InputError(f"spur_radius must be 0.005-0.1 m, got {self.spur_radius}")

    def bud_spacing(self) -> float:
        """The internode used where the skeleton does not know its nodes."""
        return self.internode or DEFAULT_INTERNODE


@dataclass(frozen=True, kw_only=True)
class BodyConfig(JsonFields):
    """What must clear the vine, in the camera frame (OpenCV: z along the optical axis).

    - The camera: a D405 body, 42 x 42 x 23 mm (Intel's datasheet), its front face at the
      optical centre, grown by `margin`, swept along the optical axis from the pruning pose to
      where the tool closes (the tool moves straight in).
    - The tool: a capsule of `tool_radius` on the optical axis from the camera to the cut point
      (the line the blade travels); vine within `jaw_zone` of the cut point is the cane the jaws
      close on and is not an obstacle.
    - The tool's blade is `tool_reach` ahead of the camera: the camera stops that far from the
      cut point.
    - The arm's wrist (link 7, the tool mount, the camera's housing as the planner models
      them) is not set here: it comes from the twin's hand-eye transform (`search.Wrist`).
    """

    camera_size: tuple[float, float, float] = (0.042, 0.042, 0.023)
    """Camera body (m): width, height, depth."""
    tool_radius: float = 0.010
    """Radius (m) of the tool along its straight approach."""
    tool_reach: float = TOOL_REACH
    """From the camera to the blade (m) along the optical axis."""
    jaw_zone: float = 0.025
    """Vine within this distance (m) of the cut point is the cane being cut."""
    margin: float = 0.005
    """Clearance (m) every body part keeps from the vine; below it a pose is refused."""

    def __post_init__(self) -> None:
        self._nested_from_dicts()
        object.__setattr__(self, "camera_size", tuple(float(v) for v in self.camera_size))
        check_finite(self, ("tool_radius", "tool_reach", "jaw_zone", "margin"))
        if len(self.camera_size) != 3 or not all(0.0 < v <= 0.3 for v in self.camera_size):
            raise InputError(f"camera_size must be 3 sizes in (0, 0.3] m, got {self.camera_size}")
        for name, lo, hi in (("tool_radius", 0.0, 0.05), ("tool_reach", 0.0, STANDOFF_RANGE[1]),
                             ("jaw_zone", 0.005, 0.1), ("margin", 0.0, 0.05)):  # fmt: skip
            v = getattr(self, name)
            if not lo <= v <= hi:
                raise InputError(f"{name} must lie in [{lo}, {hi}] m, got {v}")


@dataclass(frozen=True, kw_only=True)
class SearchConfig(JsonFields):
    """The approach directions tried for each cut and how the best is chosen."""

    standoff: float = DEFAULT_STANDOFF
    """Camera to cut point (m)."""
    azimuths: int = 13
    """Approach azimuths tried, evenly over `azimuth_range`."""
    azimuth_range: tuple[float, float] = (15.0, 165.0)
    """Approach azimuths (deg; 90: looking along +Y, from the robot's side of the row). From the
    row's far side the same range half a turn on (`side`)."""
    side: Literal["near", "far", "auto"] = "auto"
    """Which side of the row each cut is approached from: near (the robot's, -Y), far (+Y: the
    platform's pass along the next aisle; `vinetwin prune --sides both`), or auto: far for a
    cut more than `far_beyond` on the far side of the trunk's foot (a divided canopy's far
    curtain: the GDC's lie 1.2 m apart, past the arm's reach from the near aisle)."""
    far_beyond: float = 0.3
    """With side auto: how far (m, +Y) past the trunk's foot a cut is taken from the far side."""
    elevations: int = 7
    """Approach elevations tried, evenly over `elevation_range`."""
    elevation_range: tuple[float, float] = (-30.0, 60.0)
    """Approach elevations (deg; positive looks down)."""
    rolls: tuple[float, ...] = (0.0, 180.0)
    """Image rolls (deg) tried in turn, each over the whole grid, until one has a passing
    direction: 0 puts the cane across the image with the arm's wrist toward the cane's base,
    180 the same image turned over, the wrist toward its tip."""
    min_cross: float = 50.0
    """Smallest angle (deg) between the approach and the cane: shears cut across it."""
    min_visible: float = 0.5
    """Share of the cane within 5 cm of the cut the camera must see."""
    min_points: int = 1500
    """Fewest vine points (full-resolution estimate) the camera must see for a reference."""
    body: BodyConfig = field(default_factory=BodyConfig)

    def __post_init__(self) -> None:
        self._nested_from_dicts()
        for name in ("azimuth_range", "elevation_range", "rolls"):
            object.__setattr__(self, name, tuple(float(v) for v in getattr(self, name)))
        if not 1 <= len(self.rolls) <= 8 or not all(-180.0 <= r <= 180.0 for r in self.rolls):
            raise InputError(
                f"rolls must be 1 to 8 angles within [-180, 180] deg, got {self.rolls}"
            )
        lo, hi = STANDOFF_RANGE
        if not (math.isfinite(self.standoff) and lo <= self.standoff <= hi):
            raise InputError(f"standoff must lie in [{lo}, {hi}] m, got {self.standoff}")
        if self.body.tool_reach >= self.standoff:
            raise InputError(
                f"tool_reach {self.body.tool_reach} m must be below the standoff {self.standoff} m"
            )
        for name, top in (("azimuths", 72), ("elevations", 37)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= top:
                raise InputError(f"{name} must be an integer from 1 to {top}, got {v!r}")
        a0, a1 = self.azimuth_range
        e0, e1 = self.elevation_range
        if not (-180.0 <= a0 <= a1 <= 360.0 and -89.0 <= e0 <= e1 <= 89.0):
            raise InputError(
                f"azimuth_range {self.azimuth_range} must be increasing degrees within "
                f"[-180, 360] and elevation_range {self.elevation_range} within [-89, 89]"
            )
        if self.side not in ("near", "far", "auto"):
            raise InputError(f"side must be near, far or auto, got {self.side!r}")
        if not (math.isfinite(self.far_beyond) and 0.05 <= self.far_beyond <= 5.0):
            raise InputError(f"far_beyond must lie in [0.05, 5] m, got {self.far_beyond}")
        if not 0.0 <= self.min_cross <= 90.0 or not 0.0 <= self.min_visible <= 1.0:
            raise InputError("min_cross must lie in [0, 90] deg and min_visible in [0, 1]")
        if isinstance(self.min_points, bool) or not 0 <= self.min_points <= 1_000_000:
            raise InputError(f"min_points must be 0-1000000, got {self.min_points}")

    def far_for(self, point: Any) -> bool:
        """Whether a cut at `point` (vine frame) is approached from the row's far side."""
        return self.side == "far" or (self.side == "auto" and float(point[1]) > self.far_beyond)

    def azimuths_for(self, far: bool) -> tuple[float, float]:
        """The azimuth range (deg) from the near side, or from the far one: half a turn on."""
        a0, a1 = self.azimuth_range
        return (a0 + 180.0, a1 + 180.0) if far else (a0, a1)


@dataclass(frozen=True, kw_only=True)
class ServoCheckConfig(JsonFields):
    """Whether each proposed pose is checked by the servo before it is proposed: `vinetwin
    validate`'s closed-loop runs (point-to-plane ICP) from `check_starts` starts up to the
    radii; a pose that does not converge from every start is replaced by the search's next
    directions, best score first, and the one converging from the most starts is kept (a tie:
    the better score). The checks are written into the twin as `vinetwin validate` writes them."""

    check_profile: str = ""
    """Error profile of the check: ideal, field or a JSON file (see `campaign --profile`);
    empty: no check (validate later). The check runs the simulation (`sim.servo_check`)."""
    check_starts: int = 4
    """Runs per pose, from 1/N to N/N of the radii away."""
    check_translation: float = 0.05
    """Farthest start (m)."""
    check_rotation: float = 0.15
    """Farthest start (rad)."""
    check_alternatives: int = 3
    """Other directions tried for a pose that does not converge from every start."""
    check_seed: int = 0
    """Seed of the starts and the noise."""
    check_workers: int = 0
    """Processes of the check's runs; 0: one per core."""

    def __post_init__(self) -> None:
        check_finite(self, ("check_translation", "check_rotation"))
        check_counts(self, ("check_seed", "check_workers"))  # as `validate`'s seed and workers
        for name, lo, top in (("check_starts", 1, 24), ("check_alternatives", 0, 10)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= top:
                raise InputError(f"{name} must be an integer from {lo} to {top}, got {v!r}")
        if not (0.0 < self.check_translation <= 0.3 and 0.0 < self.check_rotation <= 1.0):
            raise InputError("check_translation must lie in (0, 0.3] m and check_rotation in "
                             f"(0, 1] rad, got {self.check_translation}, {self.check_rotation}")  # fmt: skip


@dataclass(frozen=True, kw_only=True)
class ProposeConfig(JsonFields):
    """`vinetwin propose`: a rule, the pose search, the servo's check of each pose, and what
    happens to earlier proposals."""

    rule: RuleConfig = field(default_factory=RuleConfig)
    search: SearchConfig = field(default_factory=SearchConfig)
    servo: ServoCheckConfig = field(default_factory=ServoCheckConfig)
    replace: bool = False
    """Replace the earlier proposals not yet accepted (never a person's own cuts). Without it a
    proposal within 1 cm of a cut point already there is not added again."""

    def __post_init__(self) -> None:
        self._nested_from_dicts()
