"""Every setting of the servo, declared once: the camera's speed and acceleration limits
(`Limits`, which the servo law saturates to and ramps by, and `CommandLimits`, which adds the
robot's watchdog and is what the command guard enforces), when an alignment is trusted
(`SafetyConfig`), the law and the ICP variant (`ServoConfig`), and how the loop runs
(`LoopConfig`).

The defaults of `Limits` are the safety limits `docs/hardware.md` states; the command line, the
web app, the simulation and the hardware adapters all read them from here. This module imports
nothing heavy, so `vinetwin --help` stays instant.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal, get_args

from vinetwin._config import (
    JsonFields,
    check_at_most,
    check_counts,
    check_finite,
)
from vinetwin.errors import InputError

#: The ICP variants (the paper's four).
Variant = Literal["point_to_point", "lm", "point_to_plane", "symmetric"]
#: The control law: eq8 (the paper's PBVS, the camera's centre on a straight line) or target
#: (PBVS on the cut point and theta*u, the cut's image on a straight line: `pbvs.target_twist`).
Law = Literal["eq8", "target"]
LAWS: tuple[str, ...] = get_args(Law)
#: The variants that pair their final level against a dense reference (`dense_reference`; how
#: much denser: `cloud.DENSE_FACTOR`). LM measures its distances to
#: the reference surface (`ICPConfig.lm_model`), which the lattice does not hold.
DENSE_VARIANTS = frozenset({"point_to_point"})
#: Where each frame's ICP starts (see `servo.step.Servo`).
Guess = Literal["kinematic", "previous", "identity"]
GUESSES: tuple[str, ...] = get_args(Guess)
#: Every ICP variant, in the paper's order (the same list as `cloud.ICP_VARIANTS`, which core
#: modules use; a test keeps them equal).
VARIANTS: tuple[str, ...] = get_args(Variant)


@dataclass(frozen=True)
class Envelope:
    """The safe envelope of every setting that moves a robot while it servos near a vine,
    declared once (`docs/hardware.md`, "The envelope"). A `Limits` above it is refused, naming
    the envelope, unless `override_envelope` is set; nothing, override or not, goes above
    `ARM_CEILING`. A gain or a stop time outside it is always refused."""

    max_linear: float = 0.25
    """m/s: the camera near canes, a person within reach. ISO 10218-1's reduced speed (the
    teaching speed of an industrial arm) is 250 mm/s; five times the default."""
    max_angular: float = 1.0
    """rad/s: the blade, about 0.25 m from the flange, then moves at most about 0.25 m/s."""
    max_linear_acceleration: float = 2.5
    """m/s^2: the envelope's speed in 0.1 s; five times the default."""
    max_angular_acceleration: float = 10.0
    """rad/s^2: the envelope's angular speed in 0.1 s."""
    max_gain: float = 5.0
    """1/s, the PBVS gain lambda: the loop is a discrete proportional law, stable for
    lambda * T < 2 and without overshoot for lambda * T < 1 with T the outer loop's period; the
    paper's outer loop ran at about 15 Hz (T = 0.067 s): lambda * T = 0.33 at 5."""
    min_watchdog: float = 0.001
    """s: the Franka's control period (1 kHz); a shorter watchdog cannot be kept."""
    max_watchdog: float = 0.5
    """s: a command outlives the process that sent it by at most this long. At the default
    5 cm/s the camera then coasts at most 2.5 cm before the robot brakes; a Franka stops in
    well under a second from there."""
    max_stop_time: float = 1.0
    """s: the ceiling of every other timer that stops the robot (`LoopConfig.frame_timeout`,
    `max_cycle`, `SafetyConfig.max_frame_age`): a larger one is a stop switched off."""


#: The envelope (`Envelope`): the one instance the configs check against.
ENVELOPE = Envelope()


@dataclass(frozen=True)
class ArmCeiling:
    """The Franka Panda's own Cartesian limits (Franka's FCI documentation, "Limits for
    Panda": 1.7 m/s, 2.5 rad/s, 13 m/s^2, 25 rad/s^2). Never exceeded, even with
    `Limits.override_envelope`: a value above them is a typo (cm/s for m/s), not a choice."""

    max_linear: float = 1.7
    max_angular: float = 2.5
    max_linear_acceleration: float = 13.0
    max_angular_acceleration: float = 25.0


ARM_CEILING = ArmCeiling()
_LIMIT_FIELDS = ("max_linear", "max_angular", "max_linear_acceleration", "max_angular_acceleration")


def check_gain(config: object, names: tuple[str, ...]) -> None:
    """Gains must be positive, finite and within `ENVELOPE.max_gain` (a negative gain drives
    the camera away from the goal; NaN stops every command without saying why)."""
    check_finite(config, names, positive=True)
    check_at_most(
        config, dict.fromkeys(names, ENVELOPE.max_gain), "(the envelope's largest gain, 1/s)"
    )


@dataclass(frozen=True, kw_only=True)
class Limits(JsonFields):
    """The camera's speed and acceleration limits. The servo law saturates its twist to the
    speeds (direction kept) and ramps its growth by the accelerations; the robot's command guard
    (`CommandLimits`) enforces the same numbers on what leaves for the arm."""

    max_linear: float = 0.05
    """Camera speed limit, m/s."""
    max_angular: float = 0.25
    """Camera angular speed limit, rad/s."""
    max_linear_acceleration: float = 0.5
    """Ramp on increases of the linear speed, m/s^2; 0: none. Stops are never ramped."""
    max_angular_acceleration: float = 2.5
    """Ramp on increases of the angular speed, rad/s^2; 0: none."""

    override_envelope: bool = False
    """Allow speeds and accelerations above the envelope for servoing near a vine
    (`ENVELOPE`, `docs/hardware.md`), up to the arm's own limits (`ARM_CEILING`), never above.
    For a cleared cell, not for a vineyard with people in it."""

    def __post_init__(self) -> None:
        check_finite(self, ("max_linear", "max_angular"), positive=True)
        check_finite(self, ("max_linear_acceleration", "max_angular_acceleration"))
        check_at_most(
            self, {k: getattr(ARM_CEILING, k) for k in _LIMIT_FIELDS},
            "(the Panda's own Cartesian limit; m/s, rad/s, m/s^2, rad/s^2: a value in cm/s?)",
        )  # fmt: skip
        if not self.override_envelope:
            check_at_most(
                self, {k: getattr(ENVELOPE, k) for k in _LIMIT_FIELDS},
                "(the envelope for servoing near a vine, docs/hardware.md; --override-envelope "
                "allows up to the arm's own limits)",
            )  # fmt: skip


@dataclass(frozen=True, kw_only=True)
class CommandLimits(Limits):
    """What may leave a robot adapter: the speed and acceleration limits, and the watchdog."""

    watchdog: float = 0.2
    """Stop the robot when no command has come for this long (s)."""

    def __post_init__(self) -> None:
        super().__post_init__()
        check_finite(self, ("watchdog",), positive=True)
        if not ENVELOPE.min_watchdog <= self.watchdog <= ENVELOPE.max_watchdog:
            raise InputError(
                f"watchdog must lie in [{ENVELOPE.min_watchdog:g}, {ENVELOPE.max_watchdog:g}] s "
                f"(the robot's control period to the envelope's ceiling, docs/hardware.md), "
                f"got {self.watchdog:g}"
            )

    def speeds(self) -> Limits:
        """The limits without the watchdog (what the servo law uses)."""
        return Limits(**{k: v for k, v in self.to_dict().items() if k != "watchdog"})


@dataclass(frozen=True, kw_only=True)
class SafetyConfig(JsonFields):
    """When an alignment is trusted enough to move the arm."""

    min_overlap: float = 0.3
    """Smallest share of the smaller cloud (frame or reference) paired (`ICPResult.overlap`)."""
    min_correspondences: int = 60
    """Fewest pairs."""
    max_rmse: float = 0.003
    """Largest inlier RMSE (m)."""
    max_jump_translation: float = 0.01
    """Largest distance (m) between the estimate and its prediction. Without robot kinematics
    the distance the camera may have covered at `Limits.max_linear` since the last trusted frame
    is added."""
    max_jump_rotation: float = 0.05
    """Largest angle (rad) between the estimate and its prediction (same allowance)."""
    jump_fraction: float = 0.1
    """Both limits grow by this fraction of the predicted distance (m) and angle (rad) to the
    goal: far from the vine a view holds more of it and its estimate wanders more from frame to
    frame, while a slip matters most near the cut, where the limits are tight."""
    max_frame_age: float = 0.1
    """A frame older than this (s) when `step` is called with `now` is stale."""
    reacquire_frames: int = 5
    """A pose jump seen consistently in this many consecutive frames (estimates within
    `reacquire_translation` / `reacquire_rotation` of each other) is accepted as the scene having
    moved; 0: never."""
    reacquire_translation: float = 0.002
    """m."""
    reacquire_rotation: float = 0.01
    """rad."""
    max_guess_translation: float = 0.05
    """Before the first trusted frame: an estimate farther than this (m) from the believed pose
    (the caller's initial guess) is refused (ICP slid to another part of the vine)."""
    max_guess_rotation: float = 0.25
    """rad (same rule)."""
    search_after: float = 0.3
    """After refusals for this long (s, by frame stamps), each frame is also registered by the
    wide search (`servo.reacquire`): coarse-to-fine from several hypotheses around the
    prediction; its answer is trusted once the same pose is found in `reacquire_frames`
    consecutive frames and no other hypothesis fits as well. 0: from the first refusal."""
    search_translation: float = 0.05
    """The wide search's hypotheses lie this far (m) from the prediction, along each axis of
    the reference camera..."""
    search_rotation: float = 0.15
    """...and turned this far (rad) about each axis through the reference cloud's centre."""
    lost_after: float = 2.0
    """After refusals for this long (s, by frame stamps) without a trusted frame the servo stops
    for good with the named reason "lost the vine" (the loop ends; `Servo.reset` starts again).
    0: never."""
    doubt_overlap: float = 0.7
    """A trusted alignment pairing less than this share of the frame (`ICPResult.overlap`) is
    doubted: the wide search looks around it, on the first trusted frame and then every
    `doubt_every` s while the overlap stays low, for a pose that pairs clearly more (ICP settled
    in a basin beside the right one, fitting part of the canes: from a 5 cm / 0.15 rad start on
    a rebuilt twin, 50-60% paired where the right pose pairs 75-90%). 0: never."""
    doubt_margin: float = 0.15
    """A pose of the wide search pairing at least this much more than the estimate, beyond the
    pose-jump limits from it, makes the estimate untrusted ("ambiguous alignment": zero
    twist); that pose is trusted once `reacquire_frames` consecutive frames find it."""
    doubt_every: float = 0.5
    """s between two looks while the overlap stays low (each costs a wide search)."""
    track_translation: float = 0.003
    """Steady tracking (the last frame trusted): ICP first runs only its final level from the
    prediction, and that answer is used, without the wider levels, when it is trusted, moved
    the prediction less than this (m) and `track_rotation`, and pairs at least
    `track_overlap` of the last trusted frame's overlap; otherwise the full schedule runs on the
    same frame. 0: always the full schedule. (On 2 mm views of two vines, predictions 2-5 mm /
    0.5-1 deg off, the final level alone ended within 0.01 mm of the full schedule for
    point-to-plane and symmetric, 0.13 mm for point-to-point up to 3 mm: docs/servo.md.)"""
    track_rotation: float = 0.0175
    """rad (same rule)."""
    track_overlap: float = 0.9
    """Fraction of the last trusted frame's `ICPResult.overlap` (same rule)."""
    track_tolerance: float = 1e-4
    """The final-level pass from the prediction (steady tracking, and the second opinion after
    a refusal) stops when an update moves less than this (m) and turns less than this (rad),
    if that is looser than the ICP's own tolerances: from a prediction a few millimetres off
    its last iterations move the estimate by hundredths of a millimetre, below the D405's noise
    (2 mm views of three vines, 2 mm / 0.5 deg predictions: 4-9 iterations instead of 6-15;
    median and p90 errors within 0.005 mm of the exact tolerance's for point-to-plane,
    symmetric and LM, 0.015 and 0.04 mm for point-to-point; docs/servo.md). 0: the ICP's own."""

    def __post_init__(self) -> None:
        floats = tuple(f for f, v in self.__dataclass_fields__.items() if v.type == "float")
        check_finite(self, floats)
        check_at_most(self, {"max_frame_age": ENVELOPE.max_stop_time}, "s (a stop switched off)")
        if self.jump_fraction > 1.0:  # (an overlap above 1 only refuses more: allowed)
            raise InputError(f"jump_fraction must lie in [0, 1], got {self.jump_fraction}")
        for name in ("doubt_overlap", "doubt_margin"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise InputError(f"{name} must lie in [0, 1], got {getattr(self, name)}")
        if self.doubt_every < 0:
            raise InputError(f"doubt_every must be >= 0, got {self.doubt_every}")
        for name in ("min_correspondences", "reacquire_frames"):
            if getattr(self, name) < 0:
                raise InputError(f"{name} must be >= 0, got {getattr(self, name)}")


@dataclass(frozen=True, kw_only=True)
class ServoConfig(JsonFields):
    """The servo law and its registration: which ICP variant, the gains, where ICP starts, and
    when the goal is reached."""

    variant: Variant = "point_to_plane"
    """ICP variant."""
    gain: float = 1.0
    """lambda at the goal (adaptive gain, ViSP's law)."""
    gain_far: float = 0.4
    """lambda far from the goal."""
    guess: Guess = "kinematic"
    """Where ICP starts each frame: kinematic (eq. 11), previous or identity."""
    dense_reference: bool = True
    """Point-to-point (`DENSE_VARIANTS`): pair the final ICP level against the reference depth
    seen through the perception chain at a quarter of its voxel (`DENSE_FACTOR`), so it is not
    held to the voxel lattice (about 1-2 mm at 4 mm voxels; measured in `docs/servo.md`)."""
    law: Law = "eq8"
    """Control law: eq8 (the paper's) or target (keeps the cut in view: its image moves on a
    straight line)."""
    converged_translation: float = 0.002
    """At the goal when the error is within this (m)..."""
    converged_rotation: float = 0.01
    """...and this (rad)."""

    def __post_init__(self) -> None:
        if self.variant not in VARIANTS:
            raise InputError(
                f"unknown ICP variant '{self.variant}'; choose one of: {', '.join(VARIANTS)}"
            )
        if self.guess not in GUESSES:
            raise InputError(f"unknown guess '{self.guess}'; choose one of: {', '.join(GUESSES)}")
        if self.law not in LAWS:
            raise InputError(f"unknown law '{self.law}'; choose one of: {', '.join(LAWS)}")
        check_gain(self, ("gain", "gain_far"))
        check_finite(self, ("converged_translation", "converged_rotation"), positive=True)


@dataclass(frozen=True, kw_only=True)
class LoopConfig(JsonFields):
    """How the loop runs and when it ends."""

    dry_run: bool = False
    """Compute and log twists, send none."""
    duration: float = 0.0
    """End after this many seconds of frames (stamp clock); 0: no limit."""
    max_frames: int = 0
    """End after this many frames; 0: no limit."""
    settle: float = 2.0
    """End once the servo has reported being at its goal for this long (s); 0: never."""
    frame_timeout: float = 0.2
    """Stop the robot when no frame came for this long (s)."""
    camera_lost: float = 2.0
    """End the run when no frame came for this long (s)."""
    max_cycle: float = 0.1
    """A frame whose command comes later than this after its capture (stamp) sends zero
    instead (s, > 0). The simulation, whose time is simulated, does not check it."""
    follow_window: float = 2.0
    """The arm must follow its commands: when, over this long (s), the camera (as the robot's
    kinematics report it) moved less than `follow_fraction` of the motion sent to it, the run
    ends with the named stop "the arm does not follow" (a joint limit, a singularity, a
    collision or a reflex would otherwise hold it still while the servo keeps asking). 0: no
    check."""
    follow_fraction: float = 0.3
    """See `follow_window`."""
    follow_min_translation: float = 0.005
    """Commanded motion below which a window is not judged (m)..."""
    follow_min_rotation: float = 0.03
    """...and its rotation (rad): the arm may lag a small command."""

    def __post_init__(self) -> None:
        check_finite(self, ("frame_timeout", "camera_lost", "max_cycle"), positive=True)
        check_at_most(
            self, dict.fromkeys(("frame_timeout", "max_cycle"), ENVELOPE.max_stop_time),
            "s (the envelope's ceiling on a timer that stops the robot, docs/hardware.md)",
        )  # fmt: skip
        check_finite(self, ("duration", "settle"))
        check_finite(self, ("follow_window", "follow_min_translation", "follow_min_rotation"))
        if not 0.0 < self.follow_fraction < 1.0:
            raise InputError(f"follow_fraction must be in (0, 1), got {self.follow_fraction}")
        if self.max_frames < 0:
            raise InputError(f"max_frames must be >= 0, got {self.max_frames}")
        if self.camera_lost < self.frame_timeout:
            raise InputError("camera_lost must be >= frame_timeout")


@dataclass(frozen=True, kw_only=True)
class ArrivalConfig(JsonFields):
    """Settings of the arrival registration (`servo.arrival`), set from the command line of
    `vinetwin servo` and `check-arrival`-style callers by their `arrival_*` names."""

    voxel: float = 0.004
    """Voxel of the registration clouds (m)."""
    feature_radius: float = 0.02
    """FPFH radius (m)."""
    max_translation: float = 0.15
    """Largest correction of the belief accepted (m): the platform's error bound."""
    max_rotation: float = 0.35
    """Largest rotation correction accepted (rad)."""
    search_translation: float = 0.10
    """Radius of the grid of translation candidates (m)."""
    grid_step: float = 0.02
    """Spacing of the translation candidates (m): within the refinement's reach (5 voxels)."""
    rotation_step: float = 0.13
    """Spacing of the rotation candidates (rad, 7.5 degrees); two steps each way per axis."""
    screen_points: int = 200
    """Live points used to screen the candidates."""
    refine: int = 16
    """Candidates refined by ICP and scored by rendering."""
    final_threshold: float = 0.003
    """Pairing distance of the final ICP level and of the score (m)."""
    min_score: float = 0.5
    """Below this F-score of the live view against the view expected from the best pose:
    "too little agreement"."""
    ambiguity: float = 0.9
    """A second candidate at a different pose scoring at least this share of the best:
    "ambiguous"."""
    distinct_translation: float = 0.01
    """Candidates further apart than this (m)..."""
    distinct_rotation: float = 0.05
    """...or turned more than this (rad) are different poses."""
    score_scale: float = 0.5
    """Resolution of the expected views rendered for the score, as a share of the camera's."""
    ransac_iterations: int = 100_000
    """RANSAC iterations of the feature-matching candidate; 0: no feature candidate."""
    seed: int = 0
    """Seed of RANSAC."""

    def __post_init__(self) -> None:
        if not (0 < self.min_score <= 1 and 0 < self.ambiguity <= 1):
            raise InputError("min_score and ambiguity must lie in (0, 1]")
        if self.voxel <= 0 or self.final_threshold <= 0 or not 0 < self.score_scale <= 1:
            raise InputError("voxel and final_threshold must be positive, score_scale in (0, 1]")


@dataclass(frozen=True, kw_only=True)
class RunnerConfig(JsonFields):
    """One `vinetwin servo` run: which camera and robot, the servo, the limits, the loop, and
    the settings of the live camera, the Franka and the simulated start."""

    pose: str = ""
    """Pruning pose id (default: the twin's first)."""
    camera: str = "sim"
    """realsense[:SERIAL] (a live D405), bag:FILE (a RealSense recording), folder:DIR (a capture
    folder), sim (rendered from the twin, simulated time), or render (rendered from the twin at
    a real robot's pose, in real time: the robot link without a camera)."""
    robot: str = "sim"
    """franka:HOST (franky-control), sim (a free-flying camera), mujoco (the MuJoCo Panda) or
    none (compute and log only)."""
    robot_model: str = ""
    """With --robot mujoco: a Panda model folder or MJCF file (default: vinetwin's own)."""
    servo: ServoConfig = field(default_factory=ServoConfig)
    limits: CommandLimits = field(default_factory=CommandLimits)
    loop: LoopConfig = field(default_factory=lambda: LoopConfig(duration=30.0))
    width: int = 848
    """Live camera: depth width (848 or 1280 for the twin's D405 presets)."""
    height: int = 480
    """Live camera: depth height."""
    fps: int = 30
    """Live or rendered camera: frames per second (30, 60 or 90)."""
    rate: float | None = None
    """Playback pacing in frames per second. folder: default as fast as read; bag: default the
    recorded rate, 0 as fast as read."""
    color: bool = False
    """Also stream colour aligned to depth (live or bag; kept by --record)."""
    camera_rate: float = 30.0
    """Simulation: camera frames per second."""
    start_translation: float = 0.04
    """Simulation: start this far from the pruning pose (m)."""
    start_rotation: float = 0.1
    """Simulation: and this angle (rad)."""
    arrival: bool = False
    """Before moving, register the first frame against the whole twin (`servo.arrival`) and
    start from its answer instead of where the robot believes the vine is; a refusal (too
    little agreement, ambiguous) stops the run before any motion. Needs a robot pose (franka,
    the simulation, or a capture folder's recorded poses)."""
    profile: str = "ideal"
    """Simulation: error profile (ideal, field or a JSON file of the simulator's FieldProfile;
    see `vinetwin campaign --help`). Its twin source reconstructs the twin once (about a
    minute; cached in TWIN/field_twins/)."""
    dynamics_factor: float = 0.2
    """franka: fraction of the robot's velocity, acceleration and jerk limits."""
    realtime: bool = True
    """franka: demand a real-time kernel (libfranka's default); --no-realtime for a simulated
    Franka or bench tests."""
    seed: int = 0
    """Seed of the simulated start, noise and registration error."""

    def __post_init__(self) -> None:
        self._nested_from_dicts()
        check_finite(self, ("start_translation", "start_rotation"))
        check_finite(self, ("camera_rate", "dynamics_factor"), positive=True)
        if self.rate is not None:
            check_finite(self, ("rate",))
        if not 0.0 < self.dynamics_factor <= 1.0:
            raise InputError(f"dynamics_factor must lie in (0, 1], got {self.dynamics_factor}")
        for name in ("width", "height", "fps"):
            if getattr(self, name) < 1:
                raise InputError(f"{name} must be >= 1, got {getattr(self, name)}")
        check_counts(self, ("seed",))
        if self.profile != "ideal" and self.camera != "sim":
            raise InputError(
                f"--profile {self.profile} is a simulation setting: it needs --camera sim (a real "
                "camera and robot bring their own errors)"
            )


@dataclass(frozen=True, kw_only=True)
class CheckConfig(JsonFields):
    """`vinetwin check-reference`: live frames at a pruning pose against its reference."""

    pose: str = ""
    """Pruning pose id (default: the twin's first). The camera must be at that pose."""
    camera: str = "sim"
    """realsense[:SERIAL] (a live D405), bag:FILE, folder:DIR, or sim (rendered from the twin at
    the pose, to try the check; see --sim-offset)."""
    frames: int = 5
    """Frames to align (the verdict takes their medians)."""
    variant: Variant | Literal[""] = ""
    """ICP variant of the alignment ("": the pose's own, the one its servo uses)."""
    max_translation: float = 0.003
    """A live view that fits the reference further than this from the pose (m)..."""
    max_rotation: float = 0.02
    """...or turned more than this (rad) means "vine moved"."""
    min_coverage: float = 0.6
    """A live view covering less of the reference than this means "vine changed here"."""
    max_rmse: float = 0.002
    """A residual above this after alignment (m) means "vine changed here"."""
    sim_offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """camera sim: move the vine by this (m, vine frame) before rendering."""
    seed: int = 0
    """camera sim: seed of the D405 noise."""

    def __post_init__(self) -> None:
        if self.frames < 1:
            raise InputError(f"frames must be >= 1, got {self.frames}")
        if self.variant and self.variant not in VARIANTS:
            raise InputError(f"unknown ICP variant '{self.variant}'; choose one of: "
                             f"{', '.join(VARIANTS)}")  # fmt: skip
        if not all(math.isfinite(v) for v in self.sim_offset) or self.seed < 0:
            raise InputError(f"sim_offset must be finite and seed >= 0, got {self.sim_offset}")
        check_finite(self, ("max_translation", "max_rotation", "max_rmse"), positive=True)
        if not 0.0 < self.min_coverage <= 1.0:
            raise InputError(f"min_coverage must lie in (0, 1], got {self.min_coverage}")
