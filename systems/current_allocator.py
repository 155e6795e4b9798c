"""Current allocation: 27 coil currents that produce a wanted wrench.

The minimum-norm (minimum-power, all coils alike) solution ``I = A^+ w`` of
``A(X) I = w`` is used while no coil exceeds its limit. When some would, the
redistributed pseudoinverse (Durham's control-allocation scheme) pins those
coils at their limit and re-solves for the rest; if the wrench is still out of
reach, the direction-preserving scaled solution is kept when it misses by less.
Either way no coil ever exceeds its limit and the shortfall ``w - A I`` is
reported.

The levitation controller allocates in the same computation as its wrench law
(``systems/levitation_controller.py``): one Python call a tick instead of several.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg.lapack import dposv


def minimum_norm_currents(A: np.ndarray, wrench: np.ndarray) -> np.ndarray:
    """Minimum-norm I with A I = w (least squares where A (6 x n) loses rank).

    Full rank: I = A^T (A A^T)^-1 w by Cholesky. Out of the coils' reach (A
    near zero, e.g. an instrument lifted far away) the Cholesky fails and the
    SVD's minimum-norm least-squares answer is used instead.
    """
    _, solution, info = dposv(A @ A.T, wrench)
    if info == 0:
        return A.T @ solution
    return np.linalg.lstsq(A, wrench, rcond=1e-10)[0]


def allocate_currents(A: np.ndarray, wrench: np.ndarray, current_limit_a: float):
    """(currents [A], shortfall [N, N*m], n_saturated) for wrench [f; tau].

    ``A`` is the (6, n) wrench matrix at the instrument's pose. ``shortfall``
    is ``wrench - A @ currents``: zero (to rounding) unless the wrench is out of
    reach with every coil within ``current_limit_a``.
    """
    n = A.shape[1]
    currents = minimum_norm_currents(A, wrench)
    if np.max(np.abs(currents)) <= current_limit_a:
        return currents, wrench - A @ currents, 0
    # Rounding can leave a coil a hair past its limit; the limit is a hard one.
    scaled = np.clip(currents * (current_limit_a / np.max(np.abs(currents))),
                     -current_limit_a, current_limit_a)
    # Not scipy's lsq_linear(method="bvls"): the same currents within limits and in 323 of 326
    # reachable saturating cases, but ~900 us a saturated call (p95 1.9 ms) against ~65 us here.
    free = np.ones(n, dtype=bool)
    pinned = np.zeros(n)
    while free.sum() >= A.shape[0]:
        remaining = wrench - A[:, ~free] @ pinned[~free]
        trial = minimum_norm_currents(A[:, free], remaining)
        over = np.abs(trial) > current_limit_a
        if not over.any():
            pinned[free] = trial
            break
        indices = np.flatnonzero(free)[over]
        pinned[indices] = np.sign(trial[over]) * current_limit_a
        free[indices] = False
    redistributed = np.clip(pinned, -current_limit_a, current_limit_a)
    shortfall_redistributed = wrench - A @ redistributed
    shortfall_scaled = wrench - A @ scaled
    if np.linalg.norm(shortfall_scaled) < np.linalg.norm(shortfall_redistributed):
        redistributed, shortfall_redistributed = scaled, shortfall_scaled
    n_saturated = int(np.sum(np.abs(redistributed) >= current_limit_a * (1 - 1e-12)))
    return redistributed, shortfall_redistributed, n_saturated
