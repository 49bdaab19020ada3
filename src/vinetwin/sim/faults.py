"""Fault injection in the simulated loop: what goes wrong on a real robot, each class seeded and
switchable, to check that the servo never sends more than its limits, never moves on an estimate
it does not trust, and recovers (`vinetwin campaign --faults ...`, `validate --faults ...`).

The classes (`FAULT_CLASSES`), each drawn per camera frame with probability `FaultConfig.rate`
(jerks at a fifth of it):

| class | what happens | what the servo must do |
|---|---|---|
| `drop` | the frame is lost: the camera delivers nothing this tick | stop the robot (no frame in time) |
| `stall` | the frame arrives `stall` s (200 ms) late, the robot holding its last twist meanwhile | refuse the stale frame; the robot's watchdog stops it |
| `zero` | every pixel reads 0 (no data: a covered lens, the dark) | refuse (empty frame) |
| `nan` | every pixel is NaN (a broken pipeline) | refuse (empty frame) |
| `half_nan` | the left half of the image is NaN | refuse the whole frame (corrupt depth image) |
| `stale` | the frame's stamp is 150 ms old | refuse (stale frame) |
| `duplicate` | the frame repeats the previous stamp | refuse (stale frame) |
| `jerk` | the vine jumps rigidly (`jerk_translation`, `jerk_rotation`) and stays there | refuse the jump, then re-acquire |
| `leaf` | a leaf 9 cm from the camera covers the cut's side of the view for `leaf_frames` frames | refuse or follow what is still trusted |
| `lost_command` | the next command never reaches the robot, which keeps its previous twist until that command expires (the watchdog time, as a Franka's do) | nothing to do: the expiry bounds it |

`FaultLog` keeps every injected event with its time; `fault_summary` turns a run's cycles into the
report's counts: commands above a limit, motion on an untrusted estimate (a non-zero twist sent
on a refused frame), recoveries (a trusted frame after the event) and recovery times.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from vinetwin.capture.sources import CameraFrame, CameraSource, quantize_depth
from vinetwin.frames import Array, invert, make_pose, so3_exp, transform_points
from vinetwin.sim.camera import SimCameraSource
from vinetwin.sim.config import FAULT_CLASSES, FaultConfig


@dataclass
class _InjectedFrame(CameraFrame):
    """A frame whose float depth is given (NaN can only exist there: counts are integers)."""

    depth_m: Any = None

    @property
    def depth(self) -> Any:
        return self.depth_m


@dataclass
class FaultLog:
    """The faults injected in one run: (simulated time, class) per event."""

    events: list[tuple[float, str]] = field(default_factory=list)


class FaultySource(CameraSource):
    """The simulator's camera with faults injected (`FaultConfig`); `cut_vine` is the cut point
    in the vine frame (a leaf covers it)."""

    def __init__(self, inner: SimCameraSource, config: FaultConfig, cut_vine: Array) -> None:
        self.inner = inner
        self.config = config
        self.cut_vine = np.asarray(cut_vine, float)
        self.camera = inner.camera
        self.depth_unit = inner.depth_unit
        self.description = f"{inner.description} with faults: {', '.join(config.classes)}"
        self.rng = np.random.default_rng([config.seed, 7])
        self.log = FaultLog()
        self._last_stamp: float | None = None
        self._leaf_left = 0

    # the simulated truth, read by the simulation's metrics
    @property
    def T(self) -> Array:
        return self.inner.T

    @property
    def T_rel(self) -> Array:
        return self.inner.T_rel

    def now(self) -> float:
        return self.inner.now()

    def _fires(self, cls: str) -> bool:
        if cls not in self.config.classes:
            return False
        p = self.config.rate / 5 if cls == "jerk" else self.config.rate
        return bool(self.rng.random() < p)

    def read(self, timeout: float = 1.0) -> CameraFrame | None:
        cfg = self.config
        fired = [c for c in FAULT_CLASSES if self._fires(c)]
        robot = self.inner.sim_robot
        t = robot.t
        if "jerk" in fired:
            d = self.rng.normal(size=3)
            a = self.rng.normal(size=3)
            jump = make_pose(
                so3_exp(cfg.jerk_rotation * a / np.linalg.norm(a)),
                cfg.jerk_translation * d / np.linalg.norm(d),
            )
            self.inner.vine_offset = jump @ self.inner.vine_offset
        if "lost_command" in fired:
            robot.lose_next_command = True
        if "leaf" in fired:
            self._leaf_left = cfg.leaf_frames
        frame = self.inner.read(timeout)
        for c in fired:
            self.log.events.append((t, c))
        if frame is None:
            return None
        if "drop" in fired:
            return None
        if "stall" in fired:  # the robot goes on meanwhile, in steps its watchdog sees
            steps = max(1, math.ceil(cfg.stall / 0.01))
            for _ in range(steps):
                robot.advance(cfg.stall / steps)
        if self._leaf_left > 0:
            self._leaf_left -= 1
            frame = replace(frame, counts=self._leaf(frame.counts))
        if "zero" in fired:
            frame = replace(frame, counts=np.zeros_like(frame.counts))
        if "stale" in fired:
            frame = replace(frame, stamp=frame.stamp - 0.15)
        if "duplicate" in fired and self._last_stamp is not None:
            frame = replace(frame, stamp=self._last_stamp)
        if "nan" in fired or "half_nan" in fired:
            depth = frame.depth.copy()
            if "nan" in fired:
                depth[:] = np.nan
            else:
                depth[:, : depth.shape[1] // 2] = np.nan
            frame = _InjectedFrame(
                frame.counts, frame.depth_unit, frame.stamp, frame.number, depth_m=depth
            )
        self._last_stamp = frame.stamp
        return frame

    def _leaf(self, counts: Any) -> Any:
        """A leaf 9 cm from the camera over a disc of a third of the image's height, centred
        beside the cut's image point (a leaf rarely covers the cut exactly)."""
        cam = self.camera
        p = transform_points(invert(self.inner.T_rel), self.cut_vine[None])[0]
        u, v = cam.cx, cam.cy
        if p[2] > 0:
            u = cam.fx * p[0] / p[2] + cam.cx
            v = cam.fy * p[1] / p[2] + cam.cy
        r = cam.height / 6
        yy, xx = np.mgrid[0 : cam.height, 0 : cam.width]
        disc = (xx - (u + r / 2)) ** 2 + (yy - v) ** 2 <= r * r
        out = counts.copy()
        out[disc] = quantize_depth(np.float32(0.09), self.depth_unit)
        return out


#: An event this long before the end of the run with no trusted frame after it never recovered
#: (later ones may just have run out of time).
NEVER_RECOVERED_S = 1.0


def fault_summary(
    log: FaultLog,
    cycles: list[dict[str, Any]],
    limits: Any,
    duration: float,
) -> dict[str, Any]:
    """Per fault class: events, recoveries (a trusted frame after the event, before the run
    ended), events never recovered (no trusted frame in the `NEVER_RECOVERED_S` or more left),
    the median and largest recovery time; and for the whole run: commands above a limit
    and non-zero twists sent on refused frames (both must be 0)."""
    over = sum(
        np.linalg.norm(c["sent"][:3]) > limits.max_linear + 1e-9
        or np.linalg.norm(c["sent"][3:]) > limits.max_angular + 1e-9
        for c in cycles
    )
    untrusted = sum((not c["trusted"] or c["overrun"]) and any(c["sent"]) for c in cycles)
    trusted_t = [c["t"] for c in cycles if c["trusted"]]
    per_class: dict[str, dict[str, Any]] = {}
    for t, cls in log.events:
        row = per_class.setdefault(
            cls, {"events": 0, "recovered": 0, "never_recovered": 0, "recovery_s": []}
        )
        row["events"] += 1
        after = next((x for x in trusted_t if x > t), None)
        if after is not None:
            row["recovered"] += 1
            row["recovery_s"].append(after - t)
        elif t < duration - NEVER_RECOVERED_S:
            row["never_recovered"] += 1
    for row in per_class.values():
        rs = row.pop("recovery_s")
        row["median_recovery_s"] = float(np.median(rs)) if rs else None
        row["max_recovery_s"] = float(max(rs)) if rs else None
    return {
        "commands_over_limit": int(over),
        "motion_on_untrusted": int(untrusted),
        "classes": per_class,
        "duration_s": duration,
    }
