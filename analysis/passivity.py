"""Passivity of a sampled haptic loop (Colgate and Schenkel, "Passivity of a class
of sampled-data systems", 1997).

A device with physical damping b (N s/m) rendering a discrete environment of
impedance H(z) (force over displacement, sampled every T s, zero-order held)
is passive iff

    b > (T / 2) / (1 - cos wT) * Re{(1 - e^{-jwT}) H(e^{jwT})}   for 0 <= w <= pi / T.

For the virtual wall, a spring K and a backward-difference damper B,
H(z) = K + B (1 - 1/z) / T, this is b > K T / 2 + |B|.
"""

import math

import numpy as np
import scipy.optimize
import scipy.signal

GRID_POINTS = 4096  # frequencies sampled over (0, pi/T] before the maximum is refined
# Below this wT the bracket is evaluated by its limit: (1 - cos wT) vanishes as
# (wT)^2 / 2 while Re{(1 - e^{-jwT}) H} vanishes as fast, and in floating point
# their ratio is noise there.
SMALL_ANGLE = 1e-4


def passivity_bound(H: scipy.signal.dlti, angles: np.ndarray) -> np.ndarray:
    """(T/2) / (1 - cos theta) * Re{(1 - e^{-j theta}) H(e^{j theta})} at the
    normalized frequencies ``angles`` = wT (rad per sample, 0 < theta <= pi):
    the damping (N s/m) the device needs at each."""
    T = H.dt
    angles = np.asarray(angles, float)
    _, response = H.freqresp(angles)
    z_inverse = np.exp(-1j * angles)
    return (T / 2) / (1 - np.cos(angles)) * np.real((1 - z_inverse) * response)


def passivity_margin(H: scipy.signal.dlti, device_damping: float) -> float:
    """b minus the largest damping the environment H needs over 0 <= w <= pi / T
    (N s/m): positive iff the sampled loop is passive (Colgate and Schenkel's bound).

    ``H`` is the environment's impedance (force over displacement) with sample
    period ``H.dt``; delays and filters are simply part of H. The maximum is
    found on a grid of GRID_POINTS frequencies, then refined around the best.
    """
    if not isinstance(H, scipy.signal.dlti) or not H.dt or not math.isfinite(H.dt) or H.dt <= 0:
        raise ValueError(f"H = {H!r}: must be a discrete-time scipy.signal.dlti with a "
                         "positive, finite sample period dt (s)")
    if not math.isfinite(device_damping):
        raise ValueError(f"device_damping = {device_damping}: must be a finite number (N s/m)")
    poles = np.roots(np.ravel(H.den))
    if np.any(np.abs(poles) >= 1 - 1e-12):
        raise ValueError(
            f"H has poles {np.round(poles, 6).tolist()}: one on or outside the unit circle "
            "(an integrator, or an unstable environment); the condition holds only for a "
            "stable H, and no damping makes that passive")
    angles = np.linspace(SMALL_ANGLE, math.pi, GRID_POINTS)
    bound = passivity_bound(H, angles)
    best = int(np.argmax(bound))
    low, high = angles[max(best - 1, 0)], angles[min(best + 1, GRID_POINTS - 1)]
    refined = scipy.optimize.minimize_scalar(
        lambda theta: -passivity_bound(H, np.array([theta]))[0], bounds=(low, high),
        method="bounded", options={"xatol": 1e-12})
    needed = max(bound[best], -refined.fun)
    return float(device_damping - needed)
