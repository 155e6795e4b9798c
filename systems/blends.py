"""Smooth 0 -> 1 blends shared by the scripted trajectories and the supervisor."""

import math

LANDING_PRESS_M = 0.001  # a landing setpoint ends this far below the rest height (m)
# Hermite samples per second of a minimum-jerk move: the cubic Hermite fit of
# the quintic then errs by < 1e-7 of the move's amplitude.
SAMPLES_PER_S = 200


def minimum_jerk(s):
    """Blend 0 -> 1 and its derivative for s in [0, 1] (zero rate and acceleration at both ends)."""
    return 10 * s**3 - 15 * s**4 + 6 * s**5, 30 * s**2 - 60 * s**3 + 30 * s**4


def minimum_jerk_samples(pose_from, pose_to, t_from_s: float, duration_s: float):
    """A minimum-jerk move sampled for a cubic Hermite fit: (times (s), values,
    rates (per s)) after ``t_from_s``, at SAMPLES_PER_S, the move's end included."""
    n = max(2, math.ceil(duration_s * SAMPLES_PER_S))
    times, values, rates = [], [], []
    for i in range(1, n + 1):
        blend, blend_rate = minimum_jerk(i / n)
        times.append(t_from_s + i / n * duration_s)
        values.append(pose_from + blend * (pose_to - pose_from))
        rates.append(blend_rate / duration_s * (pose_to - pose_from))
    return times, values, rates


def clipped_minimum_jerk(elapsed_s: float, duration_s: float):
    """(blend, d blend / dt in 1/s) ``elapsed_s`` into a move of ``duration_s`` (s);
    1 and 0 once it is over, 0 and 0 before it starts."""
    if duration_s <= 0.0 or elapsed_s >= duration_s:
        return 1.0, 0.0
    s = max(elapsed_s, 0.0) / duration_s
    blend, rate = minimum_jerk(s)
    return blend, rate / duration_s
