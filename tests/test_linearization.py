"""The period map's Jacobian of a diagram (AutoDiff and central differences) against
the hand-derived 1-DOF haptic loop, and the multirate machinery at equal rates."""

import math
from dataclasses import replace

import numpy as np
import pytest
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import LinearSystem, ZeroOrderHold

from maglev_haptics.analysis.haptic_loop import LoopParameters, closed_loop_matrix, filter_coefficient
from maglev_haptics.analysis.linearization import (
    hyperperiod_s, modes, monodromy_autodiff, monodromy_central, state_names)


def loop_diagram(p: LoopParameters):
    """The 1-DOF loop built from Drake's own systems, not from the derivation: a
    continuous mass-spring-damper (the instrument in the hand), a discrete controller
    (the sampled position, its filtered backward-difference velocity, the wall's
    force), and zero-order holds offset to apply the force ``delay_s`` after its sample."""
    builder = DiagramBuilder()
    c = p.device_damping + p.hand_damping
    plant = builder.AddNamedSystem("plant", LinearSystem(
        A=np.array([[0.0, 1.0], [-p.hand_stiffness / p.mass_kg, -c / p.mass_kg]]),
        B=np.array([[0.0], [1.0 / p.mass_kg]]), C=np.array([[1.0, 0.0]]), D=np.zeros((1, 1))))
    T, a = p.period_s, filter_coefficient(p)
    # state [x held, v]: x' = x(kT), v' = a v + (1 - a)(x(kT) - x held) / T; f = -(K x + B v)
    controller = builder.AddNamedSystem("controller", LinearSystem(
        A=np.array([[0.0, 0.0], [-(1 - a) / T, a]]), B=np.array([[1.0], [(1 - a) / T]]),
        C=np.array([[-p.stiffness, -p.damping]]), D=np.zeros((1, 1)), time_period=T))
    builder.Connect(plant.get_output_port(), controller.get_input_port())
    whole = math.floor(p.delay_s / T + 1e-9)
    fraction = p.delay_s / T - whole
    # A hold at the controller's own instants adds a period (it samples the force
    # before that instant's update); offset by the fraction, the first adds only it.
    holds = whole + (1 if fraction > 1e-9 else 0)
    port = controller.get_output_port()
    for i in range(holds):
        hold = builder.AddNamedSystem(f"delay_{i}", ZeroOrderHold(T, 1, fraction * T))
        builder.Connect(port, hold.get_input_port())
        port = hold.get_output_port()
    builder.Connect(port, plant.get_input_port())
    return builder.Build()


def accurate(simulator):
    """Fifth-order Runge-Kutta at 1e-13 accuracy: the continuous plant to round-off."""
    integrator = simulator.get_mutable_integrator()
    integrator.set_requested_minimum_step_size(1e-9)
    integrator.set_target_accuracy(1e-13)
    integrator.set_maximum_step_size(1e-4)


def power_traces(M, count=8):
    """tr(M^k), k = 1..count: the sums of the k-th powers of the eigenvalues. Two maps
    of different state bases and sizes share them iff their nonzero spectra agree, and
    unlike the small eigenvalues of a delay chain (nearly defective: an error e moves
    them by e^(1/3)) they are well conditioned."""
    return np.array([np.trace(np.linalg.matrix_power(M, k)) for k in range(1, count + 1)])


def dominant(M, floor=0.5):
    values = np.linalg.eigvals(M)
    values = values[np.abs(values) > floor]
    return values[np.lexsort((values.imag, values.real))]


@pytest.mark.parametrize("delay_s", [0.0, 1e-3, 2.5e-3, 0.4e-3])
def test_period_map_of_the_drake_loop_matches_the_hand_derivation(delay_s):
    p = replace(LoopParameters(), delay_s=delay_s)
    diagram = loop_diagram(p)
    context = diagram.CreateDefaultContext()
    context.SetContinuousState([0.002, 0.01])
    derived = closed_loop_matrix(p)
    for method, tolerance in ((monodromy_autodiff, 1e-9), (monodromy_central, 1e-7)):
        M = method(diagram, context, p.period_s, configure=accurate)
        np.testing.assert_allclose(power_traces(M), power_traces(derived), rtol=0,
                                   atol=tolerance)
        np.testing.assert_allclose(dominant(M), dominant(derived), rtol=0, atol=tolerance)


def test_hyperperiod_and_equal_rates():
    assert hyperperiod_s([1 / 860, 1e-3]) == pytest.approx(0.05)
    assert hyperperiod_s([1e-3, 1 / 200, 1 / 100]) == pytest.approx(0.01)
    # The multirate machinery with every rate equal is the single-rate map: over
    # five periods it is the fifth power of one.
    p = LoopParameters()
    diagram = loop_diagram(p)
    context = diagram.CreateDefaultContext()
    one = monodromy_autodiff(diagram, context, p.period_s, configure=accurate)
    five = monodromy_autodiff(diagram, context, 5 * p.period_s, configure=accurate)
    np.testing.assert_allclose(five, np.linalg.matrix_power(one, 5), atol=1e-9)


def test_modes_name_their_states():
    p = LoopParameters()
    diagram = loop_diagram(p)
    M = monodromy_autodiff(diagram, diagram.CreateDefaultContext(), p.period_s,
                           configure=accurate)
    names = state_names(diagram)
    assert names[0:2] == ["plant/x[0]", "plant/x[1]"]
    table = modes(M, p.period_s, names)
    assert abs(table[0].multiplier) < 1
    # The hand-held instrument on the coupling: ~ sqrt((300 + 400) / 0.375) / 2 pi = 6.9 Hz.
    oscillatory = [m for m in table if m.frequency_hz > 1]
    assert oscillatory and 5 < oscillatory[0].frequency_hz < 9
    assert any("plant" in name for name in oscillatory[0].states)
