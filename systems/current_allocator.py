"""Current allocation: 27 coil currents that produce a wanted wrench.

Two allocators, chosen by the scenario's ``controller.allocation``:

- ``"thermal"`` (the default): the minimum-power currents, sum R_j(T_j) I_j^2 with each
  winding's resistance at its temperature, subject to ``A(X) I = w`` and a bound on
  each coil: the amplifier's limit, tightened as the coil warms so that the current
  it holds could not take it past its temperature limit within a horizon
  (``hardware/thermal.py``, ``thermal_current_bounds``). The quadratic program is
  solved exactly by a semismooth Newton method on its 6 dual variables
  (``bounded_minimum_power_currents``). Out of reach, the currents within the bounds
  whose wrench is nearest ``w`` (least squares), of least power among those.
- ``"pseudoinverse"``: for comparison, the minimum-norm solution ``I = A^+ w`` while no
  coil exceeds the amplifier's limit; when some would, the redistributed
  pseudoinverse (Durham's control-allocation scheme) pins those coils at their limit
  and re-solves for the rest; if the wrench is still out of reach, the
  direction-preserving scaled solution is kept when it misses by less. Blind to heat.

Either way no coil ever exceeds its bound and the shortfall ``w - A I`` is reported.

The levitation controller allocates in the same computation as its wrench law
(``systems/levitation_controller.py``): one Python call a tick instead of several.
"""

from __future__ import annotations

import numba
import numpy as np
from scipy.linalg.lapack import dposv

from maglev_haptics.hardware.kernels import MATRIX, SCALAR, VECTOR, kernel

ALLOCATIONS = ("thermal", "pseudoinverse")


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


# Newton steps on the exact dual, and halvings of one step, before the wrench is taken
# to be out of reach (then the active-set method takes over, so failing early is cheap).
_EXACT_STEPS = 8
_EXACT_HALVINGS = 8
# Newton steps from the penalized optimum to the exact one.
_POLISH_STEPS = 3
# The penalty's weight 1/rho [(N or N*m)^2 / W]: out of reach, a watt of power weighs
# as much as a shortfall of sqrt(2e-12) ~ 1.4e-6 N (or N*m).
_INVERSE_PENALTY = 1e-12


@numba.njit(cache=True)
def _dual_value(A, wrench, resistance_ohm, bound_a, nu):
    """(q(nu), currents): the dual function of the allocation QP at ``nu``
    and the currents that minimize its Lagrangian, each clipped to its bound."""
    s = A.T @ nu
    currents = np.minimum(np.maximum(s / resistance_ohm, -bound_a), bound_a)
    value = np.sum(0.5 * resistance_ohm * currents**2 - s * currents) + wrench @ nu
    return value, currents


@numba.njit(cache=True)
def _dual_newton(A, wrench, resistance_ohm, bound_a, nu, max_steps, tolerance):
    """Maximize the concave, piecewise-quadratic dual from ``nu`` by Newton steps on
    its pieces with a backtracking line search; (nu, currents, converged)."""
    m = A.shape[0]
    # A whisker of regularization, on the scale of every coil's share of the Hessian,
    # keeps the step defined with fewer than 6 free coils.
    regularization = 1e-14 * np.sum(A**2 / resistance_ohm)
    value, currents = _dual_value(A, wrench, resistance_ohm, bound_a, nu)
    for _ in range(max_steps):
        gradient = wrench - A @ currents
        if np.max(np.abs(gradient)) <= tolerance:
            return nu, currents, True
        free = np.abs(A.T @ nu) < bound_a * resistance_ohm
        A_free = A[:, free]
        hessian = (A_free / resistance_ohm[free]) @ A_free.T
        for i in range(m):
            hessian[i, i] += regularization
        step = np.linalg.solve(hessian, gradient)
        slope = gradient @ step
        t = 1.0
        while True:
            trial_value, trial_currents = _dual_value(
                A, wrench, resistance_ohm, bound_a, nu + t * step)
            if trial_value >= value + 1e-4 * t * slope:
                break
            t *= 0.5
            if t < 0.5**_EXACT_HALVINGS:
                return nu, currents, False
        nu = nu + t * step
        value, currents = trial_value, trial_currents
    return nu, currents, False


@numba.njit(cache=True)
def _penalized_free_optimum(A, wrench, resistance_ohm, currents, free):
    """(nu = rho (w - A I), optimum of the free currents) of the penalized problem with
    the other currents held. With more free coils than rows, by Woodbury:
    I_F = R_F^-1 A_F^T nu with (1/rho + A_F R_F^-1 A_F^T) nu = w - A_H I_H, a 6 x 6
    system; with fewer, that system is nearly singular and its huge nu cancels in
    I_F, so the normal equations (A_F^T A_F + R_F / rho) I_F = A_F^T (w - A_H I_H)
    instead, at most 6 x 6."""
    held = ~free
    remaining = wrench - A[:, held] @ currents[held]
    A_free = A[:, free]
    resistance = resistance_ohm[free]
    if A_free.shape[1] > A.shape[0]:
        system = (A_free / resistance) @ A_free.T
        for i in range(A.shape[0]):
            system[i, i] += _INVERSE_PENALTY
        nu = np.linalg.solve(system, remaining)
        return nu, (A_free.T @ nu) / resistance
    optimum = np.zeros(A_free.shape[1])
    if A_free.shape[1] > 0:
        normal = A_free.T @ A_free
        for i in range(A_free.shape[1]):
            normal[i, i] += _INVERSE_PENALTY * resistance[i]
        optimum = np.linalg.solve(normal, A_free.T @ remaining)
    return (remaining - A_free @ optimum) / _INVERSE_PENALTY, optimum


@numba.njit(cache=True)
def _penalized_active_set(A, wrench, resistance_ohm, bound_a, currents):
    """The primal active-set method on the penalized problem, minimize
    sum R I^2 / 2 + rho |A I - w|^2 / 2 over the box, from feasible ``currents``
    (those at a bound start held there); (nu = rho (w - A I), currents)."""
    n = A.shape[1]
    currents = currents.copy()
    free = np.abs(currents) < bound_a
    nu = np.zeros(A.shape[0])
    for _ in range(4 * n):
        nu, optimum = _penalized_free_optimum(A, wrench, resistance_ohm, currents, free)
        indices = np.flatnonzero(free)
        current = currents[indices]
        # The longest step toward the free optimum that keeps every current in its box.
        step, blocking = 1.0, -1
        for k in range(indices.size):
            j = indices[k]
            change = optimum[k] - current[k]
            limit = bound_a[j] if change > 0 else -bound_a[j]
            if change != 0.0 and abs(optimum[k]) > bound_a[j]:
                reach = (limit - current[k]) / change
                if reach < step:
                    step, blocking = max(reach, 0.0), j
        currents[indices] = current + step * (optimum - current)
        if blocking >= 0:
            currents[blocking] = bound_a[blocking] if currents[blocking] > 0 else -bound_a[blocking]
            free[blocking] = False
            continue
        # At the free optimum: release the held current whose bound pushes back most.
        # Its gradient is R I - A^T nu: at +bound it must be <= 0, at -bound >= 0.
        gradient = resistance_ohm * currents - A.T @ nu
        worst, release = 0.0, -1
        for j in range(n):
            if not free[j]:
                push = gradient[j] if currents[j] > 0 else -gradient[j]
                if push > worst:
                    worst, release = push, j
        if release < 0:
            break
        free[release] = True
    return nu, currents


# Out of reach, a torque error of 1e-4 N*m counts as much as 1 N of force [1/m]: the
# attitude first. A lost attitude loses the instrument (it turns over, and the magnets'
# forces with it; the 2-magnet instrument turns about its magnet row with 8e-6 kg*m^2),
# while a position error is recovered. Without it the least squares gives up N*m for
# N, and a hard shove spins the instrument.
TORQUE_WEIGHT_PER_M = 1e4


@kernel((MATRIX, VECTOR, VECTOR, VECTOR, SCALAR))
def bounded_minimum_power_currents(A, wrench, resistance_ohm, bound_a, torque_weight):
    """(currents [A], shortfall [N, N*m]): minimize sum_j R_j I_j^2 subject to
    ``A @ I = wrench`` and ``|I_j| <= bound_a[j]``.

    ``A`` (6, n) is the wrench matrix at the instrument's pose, ``resistance_ohm`` (n,)
    the windings' resistances (> 0), ``bound_a`` (n,) each coil's bound (>= 0). The
    QP's dual has 6 variables: the currents are ``clip(A^T nu / R, -bound, bound)``
    and a Newton step on the dual solves a 6 x 6 system. When the wrench is out of
    reach the exact dual is unbounded; then the penalized problem (least squares on
    the shortfall with its torque rows times ``torque_weight`` (1/m:
    TORQUE_WEIGHT_PER_M in the loop), power weighted by 1e-12), solved by a primal
    active-set method on the currents (each step a 6 x 6 system, by Woodbury), gives
    the nearest wrench within the bounds.
    ``shortfall`` is ``wrench - A @ currents``: zero to ~1e-10 when reachable.
    """
    if not np.any(A):  # out of every coil's reach (beyond the field tables)
        return np.zeros(A.shape[1]), wrench.copy()
    tolerance = 1e-11 * max(1.0, np.max(np.abs(wrench)))
    _, currents, converged = _dual_newton(A, wrench, resistance_ohm, bound_a,
                                          np.zeros(A.shape[0]), _EXACT_STEPS, tolerance)
    if not converged:
        rows = np.ones(A.shape[0])
        rows[3:] = torque_weight
        nu, penalized = _penalized_active_set(A * rows.reshape(-1, 1), wrench * rows,
                                              resistance_ohm, bound_a, currents)
        currents = penalized
        # Reachable after all (many coils at their bounds)? Then the exact optimum is a
        # step or two from the penalized one.
        _, exact, converged = _dual_newton(A, wrench, resistance_ohm, bound_a,
                                           rows * nu, _POLISH_STEPS, tolerance)
        if converged:
            currents = exact
    return currents, wrench - A @ currents
