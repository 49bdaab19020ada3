"""The settings of the simulation, declared once: one closed-loop run (`SimConfig`, which is a
`servo.config.ServoConfig` plus what only a simulation has), the vine's motion (`Disturbance`),
a campaign (`CampaignConfig`) and a per-pose validation (`ValidateConfig`). The command line
nests these dataclasses (their field docstrings are its `--help`), so a setting has one
default. Nothing heavy is imported here."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Literal, get_args

from vinetwin._config import JsonFields
from vinetwin.errors import InputError
from vinetwin.servo.config import Law, Limits, ServoConfig, Variant, check_finite
from vinetwin.sim.paper import PRESETS

if TYPE_CHECKING:
    from vinetwin.frames import Array

#: Fault classes the simulation can inject (`sim.faults`).
FaultClass = Literal[
    "drop", "stall", "zero", "nan", "half_nan", "stale", "duplicate", "jerk", "leaf",
    "lost_command",
]  # fmt: skip
FAULT_CLASSES: tuple[str, ...] = get_args(FaultClass)

#: Every ICP variant, in the paper's order.
ALL_VARIANTS: tuple[Variant, ...] = get_args(Variant)


@dataclass(frozen=True, kw_only=True)
class Disturbance(JsonFields):
    """The vine moves rigidly by (translation, rotation vector) at `time`, in the vine frame
    (paper Fig. 6), and optionally vibrates sinusoidally along `vibration_axis`."""

    time: float = -1.0
    """When the vine moves (s); negative: never."""
    translation: tuple[float, float, float] = (0.03, 0.0, 0.0)
    """m."""
    rotation: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Rotation vector, rad."""
    vibration_amplitude: float = 0.0
    """m; 0: no vibration."""
    vibration_frequency: float = 2.0
    """Hz."""
    vibration_axis: tuple[float, float, float] = (1.0, 0.0, 0.0)

    def vine_motion(self, t: float) -> Array:
        """The vine's pose at time t in its original frame."""
        import numpy as np

        from vinetwin.frames import make_pose, so3_exp

        M = np.eye(4)
        if self.time >= 0 and t >= self.time:
            M = make_pose(so3_exp(self.rotation), self.translation)
        if self.vibration_amplitude > 0:
            axis = np.asarray(self.vibration_axis, dtype=np.float64)
            axis = axis / (np.linalg.norm(axis) or 1.0)
            s = self.vibration_amplitude * math.sin(2 * math.pi * self.vibration_frequency * t)
            M = make_pose(t=s * axis) @ M
        return M


@dataclass(frozen=True, kw_only=True)
class FaultConfig(JsonFields):
    """Faults injected into a simulated run (`sim.faults`), each class seeded and switchable."""

    classes: tuple[FaultClass, ...] = ()
    """Fault classes to inject: drop, stall, zero, nan, half_nan, stale, duplicate, jerk, leaf,
    lost_command (none: a clean run)."""
    rate: float = 0.03
    """Probability per camera frame of each class (jerks: a fifth of it)."""
    stall: float = 0.2
    """How late a stalled frame arrives (s)."""
    jerk_translation: float = 0.01
    """How far the vine jumps in a jerk (m)."""
    jerk_rotation: float = 0.02
    """How far it turns (rad)."""
    leaf_frames: int = 15
    """How many frames a leaf covers the view."""
    seed: int = 0
    """Seed of the faults (apart from the run's own)."""

    def __post_init__(self) -> None:
        for c in self.classes:
            if c not in FAULT_CLASSES:
                raise InputError(
                    f"unknown fault class '{c}'; choose from: {', '.join(FAULT_CLASSES)}"
                )
        if not (0.0 <= self.rate <= 1.0):
            raise InputError(f"fault rate must be within 0..1, got {self.rate}")


@dataclass(frozen=True, kw_only=True)
class SimConfig(ServoConfig):
    """One closed-loop run: the servo (`ServoConfig`: variant, gains, guess, goal tolerance),
    the camera's limits, and the simulated camera, time and registration error."""

    limits: Limits = field(default_factory=Limits)
    """Speed and acceleration limits of the servo law and of the simulated arm's guard."""
    camera_rate: float = 30.0
    """Camera frames per second (the D405 gives 30-90)."""
    fixed_period: float = 0.0
    """Hold each twist this long (s) instead of the measured processing time; 0: measured."""
    duration: float = 20.0
    """Longest simulated time per run (s)."""
    settle: float = 2.0
    """End the run once the servo has reported being at its goal for this long (s); 0: run the
    whole duration."""
    registration_error_translation: float = 0.005
    """Error (m) of where the robot believes the reference camera is (the twin's registration
    to the robot), which sets the first frame's guess."""
    registration_error_rotation: float = 0.02
    """rad."""
    seed: int = 0
    """Seed of the starts, the noise and the registration error."""
    faults: FaultConfig = field(default_factory=FaultConfig)
    """Faults injected into the run (none by default)."""

    def __post_init__(self) -> None:
        super().__post_init__()
        self._nested_from_dicts()
        check_finite(self, ("camera_rate", "duration"), positive=True)
        check_finite(self, ("fixed_period", "settle", "registration_error_translation",
                            "registration_error_rotation"))  # fmt: skip


def _check_variants(variants: tuple[str, ...]) -> None:
    for v in variants:
        if v not in ALL_VARIANTS:
            raise InputError(f"unknown ICP variant '{v}'; choose from: {', '.join(ALL_VARIANTS)}")


@dataclass(frozen=True, kw_only=True)
class CampaignConfig(JsonFields):
    """The paper's campaign in simulation."""

    preset: Literal["table1", "table2", "quick"] = "table1"
    """Starts: the paper's Table 1 (4), Table 2 (6), or one close start (quick)."""
    variants: tuple[Variant, ...] = ALL_VARIANTS
    """ICP variants to run."""
    pose: str = ""
    """Pruning pose to servo to (default: the twin's first)."""
    sim: Literal["kinematic", "mujoco"] = "kinematic"
    """Simulation: a free-flying camera (kinematic) or the D405 on a MuJoCo Panda (mujoco)."""
    robot: str = ""
    """With --sim mujoco: a Panda model folder (holding scene.xml, e.g. MuJoCo Menagerie's
    franka_emika_panda) or MJCF file; default: vinetwin's own Panda."""
    duration: float = 30.0
    """Longest simulated time per run (s)."""
    camera_rate: float = 30.0
    """Camera frames per second."""
    fixed_period: float = 0.0
    """Hold each twist this long (s) instead of the measured processing time; 0: measured."""
    limits: Limits = field(default_factory=Limits)
    """Speed and acceleration limits of every run."""
    disturbance: bool = True
    """Add a disturbance run per variant (the vine moves at --disturbance-time, paper Fig. 6)."""
    disturbance_time: float = 10.0
    """When the vine moves in those runs (s)."""
    disturbance_translation: tuple[float, float, float] = (0.03, 0.0, 0.01)
    """How far it moves (m, vine frame)."""
    disturbance_rotation: tuple[float, float, float] = (0.0, 0.0, 0.05)
    """How far it turns (rotation vector, rad)."""
    guess_comparison: bool = True
    """Add point-to-plane runs with and without the kinematic initial guess (paper Fig. 4)."""
    law: Law = "eq8"
    """Control law of the runs: eq8 (the paper's) or target (keeps the cut in view)."""
    law_comparison: bool = True
    """Add point-to-plane runs under the other law from every start (the report compares the
    laws: convergence, time, the cut's path in the image)."""
    faults: tuple[FaultClass, ...] = ()
    """Add a fault-injection run per listed class and variant (from the first start; classes:
    drop, stall, zero, nan, half_nan, stale, duplicate, jerk, leaf, lost_command)."""
    fault_rate: float = 0.03
    """Probability per frame of the injected fault."""
    seed: int = 0
    """Seed of the starts, the noise and the registration error."""
    workers: int = 0
    """Processes; 0: one per core. With --ray: the local Ray's CPUs (0: all)."""

    def __post_init__(self) -> None:
        self._nested_from_dicts()
        if self.preset not in PRESETS:
            raise InputError(f"unknown preset '{self.preset}'; choose one of: {', '.join(PRESETS)}")
        _check_variants(self.variants)
        check_finite(self, ("duration", "camera_rate"), positive=True)
        check_finite(self, ("fixed_period",))
        if self.sim not in ("kinematic", "mujoco"):
            raise InputError(f"unknown simulation '{self.sim}'; choose kinematic or mujoco")


@dataclass(frozen=True, kw_only=True)
class ValidateConfig(JsonFields):
    """Per-pose validation: closed-loop runs from stratified starts."""

    variants: tuple[Variant, ...] = ALL_VARIANTS
    """ICP variants to try."""
    poses: tuple[str, ...] = ()
    """Pose ids (default: all)."""
    starts: int = 6
    """Runs per pose and variant, from 1/N to N/N of the radii away."""
    radius_translation: float = 0.10
    """Farthest start (m)."""
    radius_rotation: float = 0.30
    """Farthest start (rad)."""
    duration: float = 20.0
    """Longest simulated time per run (s)."""
    limits: Limits = field(default_factory=Limits)
    """Speed and acceleration limits of every run."""
    faults: tuple[FaultClass, ...] = ()
    """Fault classes injected into every run (see `campaign --faults`)."""
    fault_rate: float = 0.03
    """Probability per frame of each injected fault."""
    seed: int = 0
    """Seed of the starts and the noise."""
    workers: int = 0
    """Processes; 0: one per core. With --ray: the local Ray's CPUs (0: all)."""
    force: bool = False
    """Run again what is already validated with the same inputs."""

    def __post_init__(self) -> None:
        self._nested_from_dicts()
        _check_variants(self.variants)
        if self.starts < 1:
            raise InputError(f"starts must be >= 1, got {self.starts}")
        check_finite(self, ("radius_translation", "radius_rotation", "duration"))
