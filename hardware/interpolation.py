"""Stretched table axes and 4- and 3-point Lagrange interpolation weights (numba).

An axis is a float64 array ``[kind, origin, scale, s_min, step, n]``: node i sits
at the position x whose stretched coordinate s(x) equals s_min + i * step, with
s(x) = x (uniform), asinh((x - origin) / scale) (sinh: dense near ``origin``,
spacing growing exponentially away from it) or log(x / scale) (log-uniform).
"""

from __future__ import annotations

import math

import numba
import numpy as np

AXIS_UNIFORM = 0
AXIS_SINH = 1
AXIS_LOG = 2
_KIND = 0
_ORIGIN = 1
_SCALE = 2
_S_MIN = 3
_STEP = 4
_COUNT = 5


def _stretch(kind: int, origin: float, scale: float, x: np.ndarray) -> np.ndarray:
    if kind == AXIS_UNIFORM:
        return np.asarray(x, dtype=float)
    if kind == AXIS_SINH:
        return np.arcsinh((np.asarray(x) - origin) / scale)
    if kind == AXIS_LOG:
        return np.log(np.asarray(x) / scale)
    raise ValueError(f"axis kind = {kind!r}: must be AXIS_UNIFORM, AXIS_SINH or AXIS_LOG")


def make_axis(kind: int, x_min: float, x_max: float, step: float,
              scale: float = 1.0, origin: float = 0.0) -> np.ndarray:
    """An axis from x_min to x_max (both nodes) with about ``step`` in s.

    ``step`` is shrunk so that an integer number of steps spans the range.
    """
    s_min, s_max = (float(s) for s in _stretch(kind, origin, scale, np.array([x_min, x_max])))
    if not s_max > s_min:
        raise ValueError(f"axis range [{x_min}, {x_max}]: must be increasing")
    count = int(math.ceil((s_max - s_min) / step - 1e-9)) + 1
    return np.array([kind, origin, scale, s_min, (s_max - s_min) / (count - 1), count],
                    dtype=float)


def axis_nodes(axis: np.ndarray) -> np.ndarray:
    """Node positions x_i of ``axis`` [axis units]."""
    kind, origin, scale, s_min, step, count = axis
    s = s_min + step * np.arange(int(count))
    if kind == AXIS_UNIFORM:
        return s
    if kind == AXIS_SINH:
        return origin + scale * np.sinh(s)
    return scale * np.exp(s)


@numba.njit(cache=True, inline="always")
def axis_position(axis, x):
    """Fractional node index of x on ``axis`` (unclamped)."""
    kind = axis[_KIND]
    if kind == AXIS_SINH:
        s = math.asinh((x - axis[_ORIGIN]) / axis[_SCALE])
    elif kind == AXIS_LOG:
        s = math.log(x / axis[_SCALE])
    else:
        s = x
    return (s - axis[_S_MIN]) / axis[_STEP]


@numba.njit(cache=True, inline="always")
def clamped_position(axis, x):
    """Fractional node index of x on ``axis``, clamped to the axis."""
    return min(max(axis_position(axis, x), 0.0), axis[_COUNT] - 1.0)


@numba.njit(cache=True, inline="always")
def beyond_end(axis, t):
    """Whether fractional index t lies past the last node of ``axis``."""
    return t > axis[_COUNT] - 1.0


@numba.njit(cache=True, inline="always")
def stencil_start(t, axis):
    """First node of the 4-node stencil for fractional index t: centred on the
    interval holding t, one-sided at the ends of ``axis``."""
    start = int(math.floor(t)) - 1
    return min(max(start, 0), int(axis[_COUNT]) - 4)


@numba.njit(cache=True, inline="always")
def nearest_stencil_start(t, axis):
    """First node of the 3-node stencil for fractional index t: centred on the
    node nearest t, one-sided at the ends of ``axis``."""
    start = int(math.floor(t + 0.5)) - 1
    return min(max(start, 0), int(axis[_COUNT]) - 3)


@numba.njit(cache=True, inline="always")
def lagrange4_weights(u):
    """Cubic Lagrange weights of nodes 0..3 at local position u (nodes at 0..3)."""
    return (-(u - 1.0) * (u - 2.0) * (u - 3.0) / 6.0,
            u * (u - 2.0) * (u - 3.0) / 2.0,
            -u * (u - 1.0) * (u - 3.0) / 2.0,
            u * (u - 1.0) * (u - 2.0) / 6.0)


@numba.njit(cache=True, inline="always")
def lagrange3_weights(u):
    """Quadratic Lagrange weights of nodes 0..2 at local position u (nodes at 0..2)."""
    return ((u - 1.0) * (u - 2.0) / 2.0,
            -u * (u - 2.0),
            u * (u - 1.0) / 2.0)
