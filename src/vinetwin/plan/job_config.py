"""The settings of the whole pruning job (`vinetwin prune`): where the platform carries the arm,
what the arm may reach, how transits are planned and timed, and how the tool cuts. Each range
below is declared once, here: the command line, the web app and the docs read it. A setting that
moves the robot outside its range is refused by name."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from vinetwin._config import JsonFields, check_finite
from vinetwin.errors import InputError

Planner = Literal["RRTConnect", "RRT", "KPIECE1", "PRM"]
PLANNERS: tuple[Planner, ...] = ("RRTConnect", "RRT", "KPIECE1", "PRM")


def _ranges(obj: object, table: tuple[tuple[str, float, float], ...]) -> None:
    check_finite(obj, tuple(name for name, _, _ in table))
    for name, lo, hi in table:
        v = getattr(obj, name)
        if not lo <= v <= hi:
            raise InputError(f"{type(obj).__name__}.{name} must lie in [{lo}, {hi}], got {v}")


#: The automatic platform placement: the base this far (m) behind the camera nearest it (-Y)...
AUTO_REACH = 0.4
#: ... and this far (m) below the poses' median camera height (the Panda's shoulder is 0.333 m
#: above its base).
AUTO_DROP = 0.3


@dataclass(frozen=True, kw_only=True)
class PlatformConfig(JsonFields):
    """The platform that carries the Panda along the row (the vine frame's +X), on the robot's
    side (-Y). Its deck is a box under the base, an obstacle for the arm."""

    offset: float = 0.0
    """From the row (the vine frame's X axis) to the robot base (m), on the -Y side; 0: from
    the poses (`AUTO_REACH` behind the camera nearest the robot)."""
    height: float = 0.0
    """Robot base above the vine's foot (m): the deck's top; 0: from the poses (`AUTO_DROP`
    below their median camera height, so the shoulder faces the cuts)."""
    spacing: float = 0.10
    """Candidate stops along the row every this far (m)."""
    drive_speed: float = 0.25
    """Platform speed between stops (m/s); a tracked orchard platform drives 0.2-0.5 m/s."""
    stop_settle: float = 1.0
    """Time (s) the platform needs to come to rest at a stop before the arm moves."""
    deck: tuple[float, float] = (0.8, 0.6)
    """The deck's length along the row and width across it (m), centred under the base."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "deck", tuple(float(v) for v in self.deck))
        for name, lo, hi in (("offset", 0.2, 2.0), ("height", 0.05, 1.8)):
            v = getattr(self, name)
            if v != 0.0 and not lo <= v <= hi:
                raise InputError(f"PlatformConfig.{name} must be 0 (from the poses) or lie in "
                                 f"[{lo}, {hi}] m, got {v}")  # fmt: skip
        _ranges(self, (("spacing", 0.02, 0.5),
                       ("drive_speed", 0.01, 1.0), ("stop_settle", 0.0, 10.0)))  # fmt: skip
        check_finite(self, ("offset", "height"))
        if len(self.deck) != 2 or not all(0.1 <= v <= 3.0 for v in self.deck):
            raise InputError(f"PlatformConfig.deck must be 2 sizes in [0.1, 3] m, got {self.deck}")


@dataclass(frozen=True, kw_only=True)
class ReachConfig(JsonFields):
    """What counts as reaching a pruning pose and its straight approach to the cut."""

    min_manipulability: float = 0.02
    """Yoshikawa's manipulability floor for the camera frame (the Panda's is about 0.1 in the
    middle of its workspace, 0 at a singularity)."""
    limit_margin: float = 0.05
    """Every joint stays this far (rad) inside its limits at a pose and along the approach."""
    clearance: float = 0.02
    """The arm's links keep this far (m) from the vine, deck and ground at the poses and along
    planned transits: the twin, the platform's localisation and the arm's calibration are each
    a few millimetres off in the field (FIELD.md). The hand (mount, camera, tool), which must
    come close to the cut, keeps the pose search's margin (`BodyConfig.margin`)."""
    seeds: int = 6
    """Random IK seeds tried per pose after the warm ones."""
    approach_steps: int = 6
    """Poses checked along the straight approach (IK continuity and collisions)."""
    max_reach: float = 0.7
    """A stop farther (m) than this from a cut along the row is not tried (the Panda reaches
    0.855 m)."""

    def __post_init__(self) -> None:
        _ranges(self, (("min_manipulability", 0.0, 0.2), ("limit_margin", 0.0, 0.5),
                       ("clearance", 0.0, 0.1), ("max_reach", 0.2, 2.0)))  # fmt: skip
        for name, lo, hi in (("seeds", 0, 200), ("approach_steps", 2, 50)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
                raise InputError(f"ReachConfig.{name} must be an integer in [{lo}, {hi}], got {v}")


@dataclass(frozen=True, kw_only=True)
class TransitConfig(JsonFields):
    """Collision-free joint-space transits: planned with OMPL, timed with ruckig within the
    Panda's velocity, acceleration and jerk limits scaled by `speed_scale`."""

    planner: Planner = "RRTConnect"
    timeout: float = 1.0
    """Planning time allowed per search (s)."""
    attempts: int = 2
    """Searches per transit, each with its own random seed, before the cut is skipped with the
    reason: a search that times out in a narrow passage is seldom slow again with other random
    samples (each of the field benchmark's three timeouts at 1 s was found by the next seed)."""
    resolution: float = 0.01
    """Joint-space step (rad, the largest joint's motion) between collision checks along a
    motion."""
    speed_scale: float = 0.8
    """Share of the joint velocity, acceleration and jerk limits a transit uses."""

    def __post_init__(self) -> None:
        if self.planner not in PLANNERS:
            raise InputError(
                f"unknown planner {self.planner!r}; choose one of: {', '.join(PLANNERS)}"
            )
        _ranges(self, (("timeout", 0.01, 60.0), ("resolution", 0.001, 0.1),
                       ("speed_scale", 0.01, 1.0)))  # fmt: skip
        a = self.attempts
        if isinstance(a, bool) or not isinstance(a, int) or not 1 <= a <= 10:
            raise InputError(f"TransitConfig.attempts must be an integer in [1, 10], got {a}")


@dataclass(frozen=True, kw_only=True)
class CutConfig(JsonFields):
    """The cut: the tool moves straight in from the pruning pose until its blade is on the cut
    point, closes, and retreats along the same line."""

    approach_speed: float = 0.05
    """Tool speed along the straight approach and retreat (m/s); the arm's command guard holds
    it within the servo's envelope near a vine (`servo.config.Limits`, 5 cm/s by default): a
    faster setting is refused when the job runs."""
    close_time: float = 0.5
    """Time (s) the shears take to close and open."""
    aim_window: float = 0.35
    """The cut is aimed at the mean of where the servo's trusted frames of this last window (s)
    put the cut point in the robot's base frame: it averages the alignment's noise and about one
    period of a cane's sway (1-5 Hz in wind; `../shared/FIELD.md`). 0: the last frame alone."""
    max_blade_error: float = 0.005
    """A cut counts as done right when the blade closes within this distance (m) of the true
    cut point."""

    def __post_init__(self) -> None:
        _ranges(self, (("approach_speed", 0.005, 0.25), ("close_time", 0.0, 5.0),
                       ("aim_window", 0.0, 2.0), ("max_blade_error", 0.0005, 0.05)))  # fmt: skip


@dataclass(frozen=True, kw_only=True)
class JobConfig(JsonFields):
    """`vinetwin prune`'s plan settings."""

    platform: PlatformConfig = field(default_factory=PlatformConfig)
    reach: ReachConfig = field(default_factory=ReachConfig)
    transit: TransitConfig = field(default_factory=TransitConfig)
    cut: CutConfig = field(default_factory=CutConfig)
    sides: Literal["near", "both"] = "both"
    """near: the platform works the robot's side of the row only (a pose looking at the row from
    its far side is skipped by name); both: those poses are pruned in a second pass from the
    far side's aisle (`plan.sides`, `sim.prune_sides`), the vine's time the sum of both passes."""

    def __post_init__(self) -> None:
        self._nested_from_dicts()
        if self.sides not in ("near", "both"):
            raise InputError(f"sides must be near or both, got {self.sides!r}")


def placed(platform: PlatformConfig, cameras: list[tuple[float, float, float]]) -> PlatformConfig:
    """The platform with its automatic offset and height (those given as 0) set from the pruning
    poses' camera positions (vine frame), clamped to their ranges."""
    from dataclasses import replace

    if not cameras:
        return platform
    ys = [c[1] for c in cameras]
    zs = sorted(c[2] for c in cameras)
    offset = platform.offset or min(max(AUTO_REACH - min(ys), 0.2), 2.0)
    height = platform.height or min(max(zs[len(zs) // 2] - AUTO_DROP, 0.05), 1.8)
    return replace(platform, offset=round(offset, 3), height=round(height, 3))
