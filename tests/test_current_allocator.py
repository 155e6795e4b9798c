"""Current allocation: exact when within limits, never over a limit, shortfall reported."""

import numpy as np
import pytest
from pydrake.math import RigidTransform, RollPitchYaw
from scipy.optimize import lsq_linear

from maglev_haptics.hardware import DeviceConfig
from maglev_haptics.hardware.magnetics import load_magnetics
from maglev_haptics.systems.current_allocator import allocate_currents

LIMIT_A = 4.0


@pytest.fixture(scope="module")
def magnetics():
    return load_magnetics(DeviceConfig())


def hover_matrix(magnetics, p_AI=(0.0, 0.0, 0.028), rpy=(0.0, 0.0, 0.0)):
    X_AI = RigidTransform(RollPitchYaw(*rpy), list(p_AI))
    return magnetics.wrench_matrix(X_AI)


@pytest.mark.parametrize("p_AI, rpy", [((0, 0, 0.028), (0, 0, 0)),
                                        ((0.03, -0.02, 0.035), (0.3, -0.2, 1.0)),
                                        ((-0.04, 0.03, 0.03), (0, 0.4, 3.0))])
def test_within_limits_the_wrench_is_exact(magnetics, p_AI, rpy):
    A = hover_matrix(magnetics, p_AI, rpy)
    wrench = np.array([0.1, -0.2, 1.2, 0.002, -0.001, 0.003])
    currents, shortfall, n_saturated = allocate_currents(A, wrench, LIMIT_A)
    assert n_saturated == 0
    assert np.max(np.abs(currents)) < LIMIT_A
    np.testing.assert_allclose(A @ currents, wrench, rtol=0, atol=1e-9 * np.linalg.norm(wrench))
    assert np.linalg.norm(shortfall) <= 1e-9 * np.linalg.norm(wrench)
    # Minimum norm: the solution is orthogonal to A's null space.
    null_space = np.linalg.svd(A)[2][6:]
    assert np.max(np.abs(null_space @ currents)) < 1e-9 * np.linalg.norm(currents)


def test_redistribution_reaches_wrenches_the_pseudoinverse_cannot(magnetics):
    A = hover_matrix(magnetics)
    unconstrained = np.linalg.pinv(A) @ np.array([0, 0, 1.0, 0, 0, 0])
    # Scale so the min-norm solution is 20 % over the limit.
    wrench = np.array([0, 0, 1.0, 0, 0, 0]) * 1.2 * LIMIT_A / np.max(np.abs(unconstrained))
    currents, shortfall, n_saturated = allocate_currents(A, wrench, LIMIT_A)
    assert np.max(np.abs(currents)) <= LIMIT_A
    assert n_saturated > 0
    assert np.linalg.norm(shortfall) <= 1e-9 * np.linalg.norm(wrench)


@pytest.mark.parametrize("scale", [3.0, 10.0, 100.0])
def test_out_of_reach_never_exceeds_the_limit_and_reports_the_shortfall(magnetics, scale):
    A = hover_matrix(magnetics)
    wrench = scale * np.array([0.5, 0.3, 1.5, 0.01, 0.0, 0.02])
    currents, shortfall, n_saturated = allocate_currents(A, wrench, LIMIT_A)
    assert np.max(np.abs(currents)) <= LIMIT_A
    np.testing.assert_allclose(shortfall, wrench - A @ currents, atol=1e-12)
    if scale >= 10:
        assert np.linalg.norm(shortfall) > 0.1 * np.linalg.norm(wrench)
        assert n_saturated > 0


def test_out_of_the_coils_reach_gives_zero_currents_not_an_error(magnetics):
    A = hover_matrix(magnetics, p_AI=(0.0, 0.0, 0.5))  # half a metre up: beyond the table
    wrench = np.array([0, 0, 1.2, 0, 0, 0])
    currents, shortfall, _ = allocate_currents(A, wrench, LIMIT_A)
    assert np.all(np.isfinite(currents)) and np.max(np.abs(currents)) <= LIMIT_A
    np.testing.assert_allclose(shortfall, wrench - A @ currents)


def random_allocation_problems(magnetics, rng, count):
    """(A, wrench, limit) at random hovering poses: the weight plus a random wrench of
    0.3 to 10 N (and N*m / 50), under the peak or the thermal coil limit (A)."""
    for _ in range(count):
        X_AI = RigidTransform(
            RollPitchYaw(rng.uniform(-0.4, 0.4), rng.uniform(-0.4, 0.4), rng.uniform(-np.pi, np.pi)),
            [rng.uniform(-0.04, 0.04), rng.uniform(-0.03, 0.03), rng.uniform(0.024, 0.045)])
        scale = 10 ** rng.uniform(-0.5, 1.0)
        wrench = np.r_[0.0, 0.0, 0.125 * 9.81, 0.0, 0.0, 0.0] + scale * np.r_[
            rng.normal(0.0, 1.0, 3), rng.normal(0.0, 0.02, 3)]
        yield magnetics.wrench_matrix(X_AI), wrench, rng.choice([LIMIT_A, 1.874])


def test_matches_bounded_least_squares_within_limits_and_never_beats_it(magnetics):
    """The allocator against scipy's lsq_linear (BVLS), which it is kept over for speed:
    the same currents while the minimum-norm ones fit the limits, and beyond them never
    a smaller shortfall than BVLS's optimum, nor a coil over its limit."""
    rng = np.random.default_rng(7)
    within = saturated = 0
    for A, wrench, limit in random_allocation_problems(magnetics, rng, 300):
        currents, shortfall, n_saturated = allocate_currents(A, wrench, limit)
        optimum = lsq_linear(A, wrench, bounds=(-limit, limit), method="bvls", tol=1e-12)
        assert np.max(np.abs(currents)) <= limit
        if n_saturated == 0:
            within += 1
            np.testing.assert_allclose(currents, optimum.x, rtol=0, atol=1e-9)
        else:
            saturated += 1
            assert np.linalg.norm(shortfall) >= np.linalg.norm(wrench - A @ optimum.x) - 1e-9
    assert within > 10 and saturated > 10
