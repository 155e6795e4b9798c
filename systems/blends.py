"""Smooth 0 -> 1 blends shared by the scripted trajectories and the supervisor."""

import math

import numba
import numpy as np
from numba.extending import register_jitable
from pydrake.trajectories import PiecewisePolynomial

from maglev_haptics.hardware.exact_arithmetic import libm_pow

LANDING_PRESS_M = 0.001  # a landing setpoint ends this far below the rest height (m)
# Hermite samples per second of a minimum-jerk move: the cubic Hermite fit of
# the quintic then errs by < 1e-7 of the move's amplitude.
SAMPLES_PER_S = 200


# Python (numpy's powers, of arrays or floats) and the kernels (the C library's) share it.
@register_jitable
def minimum_jerk_of_powers(s2, s3, s4, s5):
    """``minimum_jerk`` from s^2, s^3, s^4 and s^5."""
    return 10 * s3 - 15 * s4 + 6 * s5, 30 * s2 - 60 * s3 + 30 * s4


def minimum_jerk(s):
    """Blend 0 -> 1 and its derivative for s in [0, 1] (zero rate and acceleration at both ends)."""
    return minimum_jerk_of_powers(s**2, s**3, s**4, s**5)


def minimum_jerk_samples(pose_from, pose_to, t_from_s: float, duration_s: float):
    """A minimum-jerk move sampled for a cubic Hermite fit: (times (s) (n,), values
    (n, d), rates (per s) (n, d)) after ``t_from_s``, at SAMPLES_PER_S, the move's end
    included. Vectorized: a fault's landing is planned inside a tick (~0.5 ms)."""
    n = max(2, math.ceil(duration_s * SAMPLES_PER_S))
    s = np.arange(1, n + 1) / n
    blend, blend_rate = minimum_jerk(s)
    pose_from = np.asarray(pose_from, dtype=float)
    step = np.asarray(pose_to, dtype=float) - pose_from
    return (t_from_s + s * duration_s, pose_from + blend[:, None] * step,
            (blend_rate / duration_s)[:, None] * step)


def minimum_jerk_plan(start, start_s: float, moves, tail_s: float):
    """A cubic Hermite fit of a scripted motion: hold ``start`` until ``start_s``, then
    for each (goal, move_s, hold_s) of ``moves`` a minimum-jerk move into the goal and a
    hold there; the last pose is held ``tail_s`` more, so the plan always has a segment.
    Exact rates at the samples (values in the units of ``start``, time in s)."""
    pose = np.asarray(start, dtype=float)
    times, values, rates = [0.0], [pose], [np.zeros_like(pose)]

    def hold_until(t):
        if t > times[-1]:
            times.append(t)
            values.append(pose)
            rates.append(np.zeros_like(pose))

    t = start_s
    for goal, move_s, hold_s in moves:
        hold_until(t)
        goal = np.asarray(goal, dtype=float)
        for samples, new in zip((times, values, rates),
                                minimum_jerk_samples(pose, goal, t, move_s)):
            samples.extend(new)
        pose = goal
        t += move_s + hold_s
    hold_until(max(t, times[-1]) + tail_s)
    return PiecewisePolynomial.CubicHermite(np.array(times), np.array(values).T,
                                            np.array(rates).T)


def minimum_jerk_moves(start, goals, move_s: float, times_s):
    """Exact minimum-jerk moves from ``start`` through each of ``goals`` in turn, each
    taking ``move_s`` (s) from time 0, at ``times_s`` (s, (n,)): (values (n, d), rates
    (per s) (n, d)); the last goal holds after. Vectorized: a fault's landing is
    planned inside a tick (~0.2 ms for 2000 ticks)."""
    times_s = np.asarray(times_s, dtype=float)
    start = np.asarray(start, dtype=float)
    values = np.tile(start, (len(times_s), 1))
    rates = np.zeros_like(values)
    for k, goal in enumerate(goals):
        blend, blend_rate = minimum_jerk(np.clip(times_s / move_s - k, 0.0, 1.0))
        step = np.asarray(goal, dtype=float) - start
        values += blend[:, None] * step
        rates += (blend_rate / move_s)[:, None] * step
        start = goal
    return values, rates


@numba.njit(cache=True)
def clipped_minimum_jerk(elapsed_s: float, duration_s: float):
    """(blend, d blend / dt in 1/s) ``elapsed_s`` into a move of ``duration_s`` (s);
    1 and 0 once it is over, 0 and 0 before it starts."""
    if duration_s <= 0.0 or elapsed_s >= duration_s:
        return 1.0, 0.0
    s = max(elapsed_s, 0.0) / duration_s
    # The C library's pow, as numpy's power of a float calls it.
    blend, rate = minimum_jerk_of_powers(libm_pow(s, 2.0), libm_pow(s, 3.0), libm_pow(s, 4.0),
                                         libm_pow(s, 5.0))
    return blend, rate / duration_s
