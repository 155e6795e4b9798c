"""The simulated station's amplifiers: a clamp at the current limit and a sampled
lag, on a supply the device supervisor can cut."""

import numpy as np
import pytest
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder

from maglev_haptics.diagrams.station import AddAmplifiers, amplifier_lag_coefficient
from maglev_haptics.hardware import AmplifierSpec
from maglev_haptics.systems.device_supervisor import cut_coil_power

N_COILS = 27
PERIOD_S = 1e-3


def amplifiers(spec):
    builder = DiagramBuilder()
    amplifiers = AddAmplifiers(builder, spec=spec, n_coils=N_COILS, period_s=PERIOD_S)
    builder.ExportInput(amplifiers.GetInputPort("coil_currents_commanded"), "commanded")
    builder.ExportInput(amplifiers.GetInputPort("coil_power"), "power")
    builder.ExportOutput(amplifiers.GetOutputPort("coil_currents"), "currents")
    diagram = builder.Build()
    return diagram, Simulator(diagram)


@pytest.mark.parametrize("power", [1.0, 0.0])
def test_the_currents_follow_the_clamped_command_with_the_supply_on_and_decay_to_zero_cut(power):
    spec = AmplifierSpec()
    diagram, simulator = amplifiers(spec)
    context = simulator.get_mutable_context()
    commanded = np.linspace(-1.5 * spec.current_limit_a, 1.5 * spec.current_limit_a, N_COILS)
    diagram.GetInputPort("commanded").FixValue(context, commanded)
    diagram.GetInputPort("power").FixValue(context, [1.0])
    simulator.AdvanceTo(0.02)  # settled on the clamped command
    diagram.GetInputPort("power").FixValue(context, [power])
    a = amplifier_lag_coefficient(spec.bandwidth_hz, PERIOD_S)
    expected = diagram.GetOutputPort("currents").Eval(context).copy()
    target = power * np.clip(commanded, -spec.current_limit_a, spec.current_limit_a)
    for k in range(1, 6):
        simulator.AdvanceTo(0.02 + k * PERIOD_S)
        expected = a * expected + (1 - a) * target
        np.testing.assert_allclose(diagram.GetOutputPort("currents").Eval(context), expected,
                                   rtol=0, atol=1e-9)


@pytest.mark.parametrize("stuck, carrying, shortfall_n, cut", [
    (False, False, 5.0, False),  # healthy coils: nothing to cut, whatever happens
    (True, True, 0.05, False),  # the others carry it against the stuck one: land
    (True, True, 0.2, True),  # they cannot (over 10% of its 1.2 N weight): cut now
    (True, False, 0.0, True),  # on the glass the stuck coil would push it along
])
def test_the_power_is_cut_for_a_stuck_coil_once_it_rests_or_cannot_be_carried(
        stuck, carrying, shortfall_n, cut):
    assert cut_coil_power(coils_stuck=stuck, carrying=carrying, force_shortfall_n=shortfall_n,
                          weight_n=1.2) is cut
