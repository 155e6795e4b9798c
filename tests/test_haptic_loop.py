"""The exactly discretized 1-DOF haptic loop: against closed forms in their limits
and against a fine-step simulation of the same continuous-discrete loop."""

import math
from dataclasses import replace

import numpy as np
import pytest

from maglev_haptics.analysis.haptic_loop import (
    LoopParameters, closed_loop_matrix, critical_stiffness, environment_impedance,
    filter_coefficient, is_stable, plant_matrices)
from maglev_haptics.analysis.passivity import passivity_margin


@pytest.mark.parametrize("T", [1e-3, 1 / 860, 2e-3])
@pytest.mark.parametrize("delay_s", [0.0, 1e-3, 2.5e-3])
@pytest.mark.parametrize("B", [-0.5, 0.0, 2.0])
def test_critical_stiffness_reproduces_the_closed_form_for_a_heavy_mass(T, delay_s, B):
    """Gil et al. 2004 (no delay) and Diolaiti et al. 2006 (delay tau): a sampled
    virtual wall on a mass with damping b is stable iff K < 2 (b + B) / (T + 2 tau),
    in the limit where the mass's own dynamics are slow against the sampling."""
    p = LoopParameters(mass_kg=50.0, device_damping=1.0, hand_damping=0.0, hand_stiffness=0.0,
                       damping=B, period_s=T, delay_s=delay_s, velocity_filter_hz=math.inf)
    closed_form = 2 * (1.0 + B) / (T + 2 * delay_s)
    assert critical_stiffness(p) == pytest.approx(closed_form, rel=0.01)


def simulate_loop(p: LoopParameters, x0: float, periods: int, substeps: int = 2000):
    """The same loop by brute force: the plant integrated by classical Runge-Kutta
    with small steps, the force sequence computed each period and applied when its
    delay has passed. Returns the sampled positions."""
    T = p.period_s
    h = T / substeps
    a = filter_coefficient(p)
    A, B = plant_matrices(p)

    def derivative(state, force):
        return A @ state + B * force

    state = np.zeros(len(A))
    state[0] = x0
    x_previous, filtered = x0, 0.0
    forces = []  # (time it starts acting, value)
    positions = []
    for k in range(periods):
        x = state[0]
        positions.append(x)
        filtered = a * filtered + (1 - a) * (x - x_previous) / T
        x_previous = x
        forces.append((k * T + p.delay_s, -(p.stiffness * x + p.damping * filtered)))
        for i in range(substeps):
            t = k * T + i * h
            acting = [f for start, f in forces if start <= t + 1e-12]
            force = acting[-1] if acting else 0.0
            k1 = derivative(state, force)
            k2 = derivative(state + h / 2 * k1, force)
            k3 = derivative(state + h / 2 * k2, force)
            k4 = derivative(state + h * k3, force)
            state = state + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return np.array(positions)


@pytest.mark.parametrize("grip", [False, True])
@pytest.mark.parametrize("delay_s", [0.0, 0.4e-3, 2.5e-3])
def test_one_period_map_matches_a_fine_step_simulation(delay_s, grip):
    p = replace(LoopParameters(), delay_s=delay_s, period_s=1e-3)
    if grip:  # the instrument on the grip, the hand on the arm
        p = replace(p, mass_kg=0.125, grip_stiffness=2000.0, grip_damping=12.0)
    periods = 40
    simulated = simulate_loop(p, x0=0.01, periods=periods, substeps=400)
    M = closed_loop_matrix(p)
    state = np.zeros(len(M))
    previous = len(plant_matrices(p)[0])
    state[0] = state[previous] = 0.01  # at rest at x0: x_{k-1} = x0, no velocity or force yet
    mapped = []
    for _ in range(periods):
        mapped.append(state[0])
        state = M @ state
    np.testing.assert_allclose(mapped, simulated, rtol=0, atol=1e-9)


def test_the_coupling_defaults_are_stable_with_a_hand_and_not_without():
    p = LoopParameters()
    assert is_stable(p)
    # Let go: the instrument alone (no hand damping or stiffness) has only the
    # coupling's damper, which the delay and filter turn against it at high K.
    free = replace(p, mass_kg=0.125, hand_damping=0.0, hand_stiffness=0.0)
    assert critical_stiffness(free) < critical_stiffness(p)


def test_environment_impedance_is_the_wall_without_filter_or_delay():
    p = LoopParameters(damping=2.0, delay_s=0.0, velocity_filter_hz=math.inf)
    H = environment_impedance(p)
    margin = passivity_margin(H, 0.0)
    assert margin == pytest.approx(-(p.stiffness * p.period_s / 2 + 2.0), rel=1e-3)
