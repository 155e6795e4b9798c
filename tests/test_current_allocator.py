"""Current allocation: exact when within limits, never over a limit, shortfall reported;
the thermal allocation against a general QP solver (Clarabel, through Drake)."""

import numpy as np
import pytest
from pydrake.math import RigidTransform, RollPitchYaw
from pydrake.solvers import ClarabelSolver, MathematicalProgram
from scipy.optimize import lsq_linear

from maglev_haptics.hardware import DeviceConfig
from maglev_haptics.hardware.magnetics import load_magnetics
from maglev_haptics.systems.current_allocator import (
    TORQUE_WEIGHT_PER_M, allocate_currents, bounded_minimum_power_currents)

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
    currents, shortfall = bounded_minimum_power_currents(
        A, wrench, np.full(A.shape[1], 6.5), np.full(A.shape[1], LIMIT_A), TORQUE_WEIGHT_PER_M)
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


def reference_minimum_power(A, wrench, resistance_ohm, bound_a):
    """Clarabel's interior-point answer to the thermal allocation's QP; None if it
    finds the wrench out of reach."""
    program = MathematicalProgram()
    currents = program.NewContinuousVariables(A.shape[1])
    program.AddQuadraticCost(np.diag(resistance_ohm), np.zeros(A.shape[1]), currents)
    program.AddLinearEqualityConstraint(A, wrench, currents)
    program.AddBoundingBoxConstraint(-bound_a, bound_a, currents)
    result = ClarabelSolver().Solve(program)
    if not result.is_success():
        return None
    solution = result.GetSolution(currents)
    return solution if np.linalg.norm(A @ solution - wrench) < 1e-7 else None


def random_thermal_problems(magnetics, rng, count):
    """(A, wrench, resistances [ohm], bounds [A]): random_allocation_problems with each
    winding between 20 and 100 C and each coil's bound between 0.5 A and the limit."""
    for A, wrench, _ in random_allocation_problems(magnetics, rng, count):
        resistance = 6.5 * (1 + 0.00393 * rng.uniform(0.0, 80.0, A.shape[1]))
        bound = np.minimum(LIMIT_A, rng.uniform(0.5, 2 * LIMIT_A, A.shape[1]))
        yield A, wrench, resistance, bound


def test_thermal_allocation_is_the_minimum_power_optimum_or_the_nearest_wrench(magnetics):
    """Reachable: the wrench exactly, at Clarabel's minimum power (to its tolerance) and
    never below it. Out of reach: within 1e-6 (relative) of the least-squares optimum
    (BVLS) of the shortfall with its torque rows weighted, over the same bounds. Never a coil
    past its bound."""
    rng = np.random.default_rng(11)
    reachable = out_of_reach = 0
    weight = np.diag([1.0, 1.0, 1.0] + [TORQUE_WEIGHT_PER_M] * 3)
    for A, wrench, resistance, bound in random_thermal_problems(magnetics, rng, 300):
        currents, shortfall = bounded_minimum_power_currents(A, wrench, resistance, bound,
                                                             TORQUE_WEIGHT_PER_M)
        assert np.all(np.abs(currents) <= bound)
        np.testing.assert_allclose(shortfall, wrench - A @ currents, rtol=0, atol=1e-12)
        reference = reference_minimum_power(A, wrench, resistance, bound)
        if reference is not None:
            reachable += 1
            assert np.linalg.norm(shortfall) <= 1e-9 * max(1.0, np.linalg.norm(wrench))
            power, optimum = resistance @ currents**2, resistance @ reference**2
            assert optimum * (1 - 1e-6) <= power <= optimum * (1 + 1e-6)
        else:
            out_of_reach += 1
            nearest = lsq_linear(weight @ A, weight @ wrench, bounds=(-bound, bound),
                                 method="bvls", tol=1e-14)
            best = np.linalg.norm(weight @ (wrench - A @ nearest.x))
            assert np.linalg.norm(weight @ shortfall) <= best * (1 + 1e-6) + 1e-6
    assert reachable > 30 and out_of_reach > 30


def test_thermal_allocation_spreads_the_load_off_a_bounded_coil(magnetics):
    """Bounding the busiest coil of the unbounded answer moves its share onto the others:
    the same wrench, that coil at its bound, more power in all."""
    A = hover_matrix(magnetics)
    wrench = np.array([0.0, 0.0, 0.125 * 9.81, 0.0, 0.0, 0.0])
    resistance = np.full(A.shape[1], 6.5)
    free, _ = bounded_minimum_power_currents(A, wrench, resistance, np.full(A.shape[1], LIMIT_A),
                                             TORQUE_WEIGHT_PER_M)
    np.testing.assert_allclose(free, np.linalg.pinv(A) @ wrench, atol=1e-9)  # equal R: min norm
    busiest = np.argmax(np.abs(free))
    bound = np.full(A.shape[1], LIMIT_A)
    bound[busiest] = 0.5 * abs(free[busiest])
    spread, shortfall = bounded_minimum_power_currents(A, wrench, resistance, bound,
                                                       TORQUE_WEIGHT_PER_M)
    assert np.linalg.norm(shortfall) < 1e-9
    assert abs(spread[busiest]) == pytest.approx(bound[busiest], rel=1e-12)
    assert resistance @ spread**2 > resistance @ free**2


def test_out_of_reach_the_thermal_allocation_keeps_the_attitude_first(magnetics):
    """A wrench far out of reach (a hard shove's PD force) with a small torque: the
    allocation keeps the torque and gives up force; weighting force and torque alike,
    it would give up the torque and spin the instrument."""
    A = hover_matrix(magnetics)
    wrench = np.array([4.0, -10.0, 1.2, 0.004, 0.0, 0.0])
    resistance, bound = np.full(A.shape[1], 6.5), np.full(A.shape[1], LIMIT_A)
    first, _ = bounded_minimum_power_currents(A, wrench, resistance, bound, TORQUE_WEIGHT_PER_M)
    alike, _ = bounded_minimum_power_currents(A, wrench, resistance, bound, 1.0)
    torque_error = [np.linalg.norm((A @ currents)[3:6] - wrench[3:6]) for currents in (first, alike)]
    assert torque_error[0] < 1e-4 < 0.1 * torque_error[1]
