"""The settings of the simulation, declared once: one closed-loop run (`SimConfig`, which is a
`servo.config.ServoConfig` plus what only a simulation has), the vine's motion (`Disturbance`),
a campaign (`CampaignConfig`) and a per-pose validation (`ValidateConfig`). The command line
nests these dataclasses (their field docstrings are its `--help`), so a setting has one
default. Nothing heavy is imported here."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Literal, get_args

from vinetwin._config import JsonFields, check_at_most, check_counts, check_finite
from vinetwin.errors import InputError
from vinetwin.reconstruct.config import TSDF_VOXEL, VOXEL_RANGE
from vinetwin.servo.config import Law, Limits, ServoConfig, Variant
from vinetwin.sim.paper import PRESETS

#: The longest simulated run (s) a campaign, validation or run accepts: the paper's slowest
#: convergence took 125 s; an hour is a typo, not a run.
MAX_DURATION = 3600.0

if TYPE_CHECKING:
    from pathlib import Path

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


#: The field profile's error sources (`FieldProfile.sources`), each switchable on its own.
FieldSource = Literal[
    "twin", "registration", "hand_eye", "kinematics", "timing", "wind", "depth", "dynamics"
]
FIELD_SOURCES: tuple[str, ...] = get_args(FieldSource)


@dataclass(frozen=True, kw_only=True)
class FieldProfile(JsonFields):
    """The errors a field run adds to the ideal simulation, source by source (`docs/field.md`
    gives each default's source; `../shared/FIELD.md`'s "E" marks an engineering estimate). A
    profile is `ideal` (no source), `field` (every source) or a JSON file of these fields
    (`vinetwin campaign --profile FILE`); `sources` switches each source on or off. Every draw
    comes from the run's seed, one random stream per source."""

    sources: tuple[FieldSource, ...] = ()
    """Sources switched on: twin, registration, hand_eye, kinematics, timing, wind, depth,
    dynamics (the MuJoCo Panda only: joint velocities tracked through its actuators)."""
    twin_frames: int = 60
    """twin: the reference is rendered from a twin reconstructed (TSDF) from this many
    synthetic D405 frames of the true vine; the scene stays the true vine."""
    twin_pose_noise_translation: float = 0.001
    """twin: the capture's robot pose error (m, standard deviation per axis)."""
    twin_pose_noise_rotation: float = 0.002
    """twin: and its rotation (rad, per axis)."""
    twin_voxel: float = TSDF_VOXEL
    """twin: the fusion's TSDF voxel (m)."""
    twin_trajectory: Literal["grid", "poses"] = "grid"
    """twin: the capture's viewpoints: grid (a sweep over the whole vine from one side) or poses
    (around the twin's pruning poses; for vines too large to sweep whole at 0.3 m)."""
    registration_translation: float = 0.02
    """registration: where the robot believes the vine is, off by this much (m; the platform's
    stop after the arrival; replaces the ideal run's `registration_error_translation`)."""
    registration_rotation: float = 0.035
    """registration: and by this rotation (rad, 2 degrees)."""
    hand_eye_translation: float = 0.001
    """hand_eye: the calibrated T_flange_camera off by this much (m, per axis, fixed per run)."""
    hand_eye_rotation: float = 0.0087
    """hand_eye: and by this rotation (rad per axis, 0.5 degrees)."""
    encoder_translation: float = 0.00005
    """kinematics: noise of each reported camera pose (m per axis: repeatability, encoders)."""
    encoder_rotation: float = 0.0001
    """kinematics: and of its rotation (rad per axis)."""
    kinematic_scale: float = 0.005
    """kinematics: the reported motion's scale error (fraction; a calibrated arm's absolute
    accuracy over the servo's travel; an estimate)."""
    latency: float = 0.06
    """timing: from a frame's exposure to its delivery (s; D405 depth at 30 fps)."""
    stamp_jitter: float = 0.002
    """timing: error of each frame's time stamp (s, standard deviation)."""
    frame_drop: float = 0.02
    """timing: probability that a frame never arrives."""
    sway_amplitude: float = 0.001
    """wind: cane sway near the cut point (m, sinusoid along a random direction)."""
    sway_frequency: float = 3.0
    """wind: its frequency (Hz)."""
    base_amplitude: float = 0.0005
    """wind: the platform's vibration, engine on (m)."""
    base_frequency: float = 4.0
    """wind: its frequency (Hz)."""
    depth_bias: float = 0.005
    """depth: the D405's depth scale error (fraction of z, fixed per run; an estimate)."""
    depth_noise_factor: float = 1.5
    """depth: the stereo noise outdoors, relative to the model's indoor value (an estimate)."""
    depth_dropout: float = 0.05
    """depth: fraction of valid pixels lost at random (glare, thin canes)."""
    settled_translation: float = 0.005
    """How a field run is judged: converged when its final error is within this (m)..."""
    settled_rotation: float = 0.05
    """...and this (rad): the real robot's range in the paper (1.7-4.1 mm, <= 0.045 rad),
    since the ideal 2 mm / 0.01 rad band is out of reach by design once the twin is wrong."""

    def __post_init__(self) -> None:
        for src in self.sources:
            if src not in FIELD_SOURCES:
                raise InputError(
                    f"unknown field error source '{src}'; choose from: {', '.join(FIELD_SOURCES)}"
                )
        check_finite(
            self,
            tuple(f for f in self.__dataclass_fields__ if f not in ("sources", "twin_trajectory")),
        )
        if self.twin_trajectory not in ("grid", "poses"):
            raise InputError(f"twin_trajectory must be grid or poses, got {self.twin_trajectory!r}")
        if self.twin_frames < 10:
            raise InputError(f"twin_frames must be >= 10, got {self.twin_frames}")
        if not (0.0 <= self.frame_drop < 1.0 and 0.0 <= self.depth_dropout < 1.0):
            raise InputError("frame_drop and depth_dropout must lie in [0, 1)")
        if not VOXEL_RANGE[0] <= self.twin_voxel <= VOXEL_RANGE[1]:  # the fusion's own range
            raise InputError(f"twin_voxel must lie in [{VOXEL_RANGE[0]:g}, {VOXEL_RANGE[1]:g}] m, "
                             f"got {self.twin_voxel}")  # fmt: skip

    def on(self, source: str) -> bool:
        return source in self.sources


#: The named profiles of `--profile`.
PROFILES: dict[str, FieldProfile] = {
    "ideal": FieldProfile(),
    "field": FieldProfile(sources=get_args(FieldSource)),
}


def load_profile(name: str, sources: tuple[str, ...] | None = None) -> FieldProfile:
    """`ideal`, `field`, or a JSON file of `FieldProfile` fields (unknown keys are an error, so
    a typo does not silently leave a source at its default); `sources` replaces its sources."""
    from dataclasses import replace
    from pathlib import Path

    from vinetwin.files import read_json

    if name in PROFILES:
        profile = PROFILES[name]
    else:
        path = Path(name)
        if not path.is_file():
            raise InputError(
                f"unknown profile '{name}': give ideal, field or a JSON file of FieldProfile fields"
            )
        data = read_json(path, InputError)
        if not isinstance(data, dict):
            raise InputError(f"{path}: a profile is a JSON object of FieldProfile fields")
        unknown = sorted(set(data) - set(FieldProfile.__dataclass_fields__))
        if unknown:
            raise InputError(f"{path}: unknown profile fields: {', '.join(unknown)}")
        profile = FieldProfile.from_dict(data)
    return profile if sources is None else replace(profile, sources=tuple(sources))  # type: ignore[arg-type]


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
    profile: FieldProfile = field(default_factory=FieldProfile)
    """The field's errors added to the run (`FieldProfile`; default: none, the ideal run)."""

    def tolerances(self) -> tuple[float, float]:
        """How a run's "converged" is judged (m, rad): the servo's goal tolerance (2 mm / 0.01
        rad); under a field profile, its `settled_*` band (the real robot's range) where wider."""
        p = self.profile
        if not p.sources:
            return self.converged_translation, self.converged_rotation
        return (
            max(self.converged_translation, p.settled_translation),
            max(self.converged_rotation, p.settled_rotation),
        )

    def __post_init__(self) -> None:
        super().__post_init__()
        self._nested_from_dicts()
        check_finite(self, ("camera_rate", "duration"), positive=True)
        check_finite(self, ("fixed_period", "settle", "registration_error_translation",
                            "registration_error_rotation"))  # fmt: skip
        check_counts(self, ("seed",))
        check_at_most(self, {"duration": MAX_DURATION}, "s (the longest simulated run)")


def servo_settings(variant: str) -> dict[str, Any]:
    """The servo's own settings a simulated run uses beyond its config (`SafetyConfig` and the
    variant's `ICPConfig`, their defaults): part of what a stored run's result depends on
    (`validate`'s and the campaign's digests), so that a vinetwin whose servo decides
    differently runs it again instead of reusing the older result."""
    from dataclasses import asdict

    from vinetwin.registration.icp import ICPConfig
    from vinetwin.servo import config as servo_config

    return {
        "safety": servo_config.SafetyConfig().to_dict(),
        "icp": asdict(ICPConfig(variant=variant)),
    }


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
    profile: str = "ideal"
    """Error profile of the runs: ideal (the twin is the vine, calibration and kinematics
    exact), field (every source of `FieldProfile`: reconstructed twin, platform registration,
    hand-eye, kinematics, camera timing, wind, depth) or a JSON file of `FieldProfile` fields."""
    sources: tuple[FieldSource, ...] = ()
    """Only these of the profile's error sources (default: the profile's own)."""
    profile_comparison: bool = True
    """With a profile other than ideal: also run the grid under the ideal profile (the report
    shows both beside the paper's real robot)."""
    ablation: bool = False
    """With a profile other than ideal: add runs from the first start with each error source
    alone, per variant (the report's ablation table: which source costs what)."""
    seed: int = 0
    """Seed of the starts, the noise and the registration error."""
    workers: int = 0
    """Processes; 0: one per core. With --ray: the local Ray's CPUs (0: all)."""

    def field_profile(self) -> FieldProfile:
        """The profile the runs use (`load_profile` of `profile`, restricted to `sources`)."""
        return load_profile(self.profile, self.sources or None)

    def __post_init__(self) -> None:
        self._nested_from_dicts()
        self.field_profile()  # a bad profile name or file is an error before anything runs
        if self.preset not in PRESETS:
            raise InputError(f"unknown preset '{self.preset}'; choose one of: {', '.join(PRESETS)}")
        _check_variants(self.variants)
        check_finite(self, ("duration", "camera_rate"), positive=True)
        check_finite(self, ("fixed_period", "disturbance_time", "fault_rate"))
        check_counts(self, ("seed", "workers"))
        check_at_most(self, {"duration": MAX_DURATION}, "s (the longest simulated run)")
        if not all(map(math.isfinite, self.disturbance_translation + self.disturbance_rotation)):
            raise InputError("disturbance_translation and disturbance_rotation must be finite")
        if self.fault_rate > 1.0:
            raise InputError(f"fault_rate must lie in [0, 1], got {self.fault_rate}")
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
    profile: str = "ideal"
    """Error profile of the runs (see `campaign --profile`): ideal, field or a JSON file. A
    profile other than ideal keeps its results and map apart, in validation/PROFILE/ (PROFILE:
    the name, or the file's stem), and judges "converged" by its settled band."""
    sources: tuple[FieldSource, ...] = ()
    """Only these of the profile's error sources (default: the profile's own)."""
    world: str = ""
    """A mesh file (or a twin folder) of the vine the twin was made from, in the twin's vine
    frame: the simulated camera sees it instead of the twin's mesh, the reference stays
    rendered from the twin, and every final error is against it (a scanned or reconstructed
    twin judged against the true vine). The twin is then the reconstruction: a profile's twin
    source rebuilds nothing. Results are kept apart, in validation/PROFILE-world/."""

    def field_profile(self) -> FieldProfile:
        return load_profile(self.profile, self.sources or None)

    def profile_dir(self) -> str:
        """The sub-folder of validation/ for this profile ("" for ideal)."""
        import re
        from pathlib import Path

        if not self.field_profile().sources:
            return "world" if self.world else ""
        name = self.profile if self.profile in PROFILES else Path(self.profile).stem
        if self.sources:
            name += "-" + "-".join(self.sources)
        if self.world:
            name += "-world"
        return re.sub(r"[^A-Za-z0-9_.-]", "_", name)

    def world_mesh(self) -> Path | None:
        """The world's mesh file (`world` names a mesh, or a twin folder: its mesh); None
        without a world. Raises InputError when it is missing."""
        from pathlib import Path

        if not self.world:
            return None
        path = Path(self.world).expanduser()
        if path.is_dir():
            from vinetwin.twin.model import Twin

            return Twin.load(path).mesh_path
        if not path.is_file():
            raise InputError(f"world {self.world}: no such mesh file or twin folder")
        return path

    def __post_init__(self) -> None:
        self._nested_from_dicts()
        self.field_profile()
        _check_variants(self.variants)
        if self.starts < 1:
            raise InputError(f"starts must be >= 1, got {self.starts}")
        check_finite(self, ("radius_translation", "radius_rotation", "fault_rate"))
        check_finite(self, ("duration",), positive=True)
        check_counts(self, ("seed", "workers"))
        check_at_most(self, {"duration": MAX_DURATION}, "s (the longest simulated run)")
        if self.fault_rate > 1.0:
            raise InputError(f"fault_rate must lie in [0, 1], got {self.fault_rate}")


@dataclass(frozen=True, kw_only=True)
class FidelityConfig(JsonFields):
    """`vinetwin fidelity`: how good must a twin be? The whole chain against a truth, over a sweep
    of the twin's quality."""

    frames: tuple[int, ...] = (20, 60, 120)
    """Capture sizes swept (frames of the synthetic capture), at the middle pose noise."""
    pose_noise: tuple[float, ...] = (0.0, 0.001, 0.003)
    """Capture pose errors swept (m per axis; the rotation error is 2 rad per m of it, e.g.
    1 mm with 2 mrad), at the middle capture size."""
    voxels: tuple[float, ...] = (TSDF_VOXEL,)
    """Fusion voxels swept (m), at the middle capture size and pose noise."""
    trajectory: Literal["grid", "poses"] = "grid"
    """The captures' viewpoints: grid (the whole vine from one side) or poses (around the
    pruning poses; for large vines)."""
    profile: str = "field"
    """The servo runs' error profile (the twin source is always on; its settings are the
    sweep's): field (every source), ideal (the twin alone), or a JSON file."""
    preset: Literal["table1", "table2", "quick"] = "table1"
    """Starts of each sweep point."""
    variants: tuple[Variant, ...] = ALL_VARIANTS
    """ICP variants."""
    ablation: bool = True
    """At the middle point, also each error source alone (the ablation table)."""
    duration: float = 30.0
    """Longest simulated time per run (s)."""
    seed: int = 0
    """Seed of the captures, the starts and the noise."""
    workers: int = 0
    """Processes; 0: one per core."""

    def __post_init__(self) -> None:
        load_profile(self.profile)
        _check_variants(self.variants)
        if not self.frames or not self.pose_noise or not self.voxels:
            raise InputError("give at least one value for each of frames, pose_noise and voxels")
        if min(self.frames) < 10:
            raise InputError("a capture needs at least 10 frames")
        if min(self.pose_noise) < 0 or min(self.voxels) <= 0:
            raise InputError("pose_noise must be >= 0 and voxels > 0")
