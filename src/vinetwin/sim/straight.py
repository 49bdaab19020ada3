"""The cut's straight move (`sim.prune`): where it is aimed, its speed profile and its
control period; the robot's straight move ends on the reported pose within
`STRAIGHT_TOLERANCE`."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from vinetwin.frames import Array

#: A straight move ends within this distance (m) of its end, as the robot reads it (above the
#: encoders' noise).
STRAIGHT_TOLERANCE = 5e-4
#: The straight move's feedback gain (1/s) on the reported pose's lag behind its profile: slow
#: enough for an arm that lags its command.
STRAIGHT_GAIN = 4.0
#: The straight cut ends only once the camera, as the robot reads it, moves slower than this
#: (m/s) on its end: an arm that lags its command would otherwise overshoot as it stops.
SETTLED_SPEED = 0.01
#: Control period (s) of the straight cut and retreat.
CUT_DT = 1.0 / 30.0


def straight_profile(
    length: float, speed: float, accel: float
) -> tuple[Callable[[float], tuple[float, float]], float]:
    """A trapezoidal (or, when too short to reach `speed`, triangular) profile over `length`
    (m): the function of time giving (distance, speed) along it, and its duration (s)."""
    v = min(speed, math.sqrt(max(length, 0.0) * accel))
    if v <= 0:
        return (lambda t: (0.0, 0.0)), 0.0
    ta = v / accel
    cruise = length / v - ta  # the time at full speed (>= 0)
    total = cruise + 2 * ta

    def at(t: float) -> tuple[float, float]:
        if t <= 0:
            return 0.0, 0.0
        if t < ta:
            return 0.5 * accel * t * t, accel * t
        if t < ta + cruise:
            return 0.5 * v * ta + v * (t - ta), v
        if t < total:
            r = total - t
            return length - 0.5 * accel * r * r, accel * r
        return length, 0.0

    return at, total


def aimed_cut(believed: list[tuple[float, Array]], window: float) -> Array | None:
    """Where the robot aims the cut, in its base frame: the mean of the cut point as its trusted
    frames of the last `window` seconds put it (each by the frame's reported pose and the
    servo's alignment; `SimRun.believed_cut`), or the last frame's alone when `window` is 0;
    None without a trusted frame."""
    if not believed:
        return None
    last = believed[-1][0]
    return np.mean([p for t, p in believed if t >= last - window - 1e-9], axis=0)
