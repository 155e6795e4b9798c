"""Smooth 0 -> 1 blends shared by the scripted trajectories and the supervisor."""

LANDING_PRESS_M = 0.001  # a landing setpoint ends this far below the rest height (m)
# Hermite samples per second of a minimum-jerk move: the cubic Hermite fit of
# the quintic then errs by < 1e-7 of the move's amplitude.
SAMPLES_PER_S = 200


def minimum_jerk(s):
    """Blend 0 -> 1 and its derivative for s in [0, 1] (zero rate and acceleration at both ends)."""
    return 10 * s**3 - 15 * s**4 + 6 * s**5, 30 * s**2 - 60 * s**3 + 30 * s**4


def clipped_minimum_jerk(elapsed_s: float, duration_s: float):
    """(blend, d blend / dt in 1/s) ``elapsed_s`` into a move of ``duration_s`` (s);
    1 and 0 once it is over, 0 and 0 before it starts."""
    if duration_s <= 0.0 or elapsed_s >= duration_s:
        return 1.0, 0.0
    s = max(elapsed_s, 0.0) / duration_s
    blend, rate = minimum_jerk(s)
    return blend, rate / duration_s
