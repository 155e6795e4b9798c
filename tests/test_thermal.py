"""The coils' thermal RC: closed forms, the continuous limit, the sampled update."""

import dataclasses
import math

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from maglev_haptics.hardware import DeviceConfig
from maglev_haptics.hardware.device import ThermalSpec
from maglev_haptics.hardware.thermal import (
    COPPER_DENSITY_KG_M3, COPPER_SPECIFIC_HEAT_J_PER_KG_K, coil_thermal,
    continuous_current_limit_a, current_bounds_a, thermal_budget, steady_state_temperature_c, temperature_after_c,
    step_temperatures_c, time_to_temperature_s, winding_numbers, winding_resistance_ohm,
    winding_volume_m3)

MODEL = coil_thermal(DeviceConfig())


def rhs(model, current_a):
    """dT/dt [K/s] of the thermal ODE, written directly from its physics."""
    def f(_, temperature):
        power_w = current_a**2 * winding_resistance_ohm(model, temperature)
        return (power_w - (temperature - model.ambient_c) / model.thermal_resistance_k_per_w) \
            / model.heat_capacity_j_per_k
    return f


def test_defaults_are_the_copper_winding():
    config = DeviceConfig()
    copper_kg = winding_volume_m3(config.coil) * 0.65 * COPPER_DENSITY_KG_M3
    assert MODEL.heat_capacity_j_per_k == pytest.approx(copper_kg * COPPER_SPECIFIC_HEAT_J_PER_KG_K)
    # The fill factor agrees with 1000 turns of copper at 6.5 ohm (rho 1.724e-8 ohm m at 20 C).
    wire_m = config.coil.turns * math.pi * (config.coil.outer_diameter_m
                                            + config.coil.inner_diameter_m) / 2
    copper_m3 = 1.724e-8 * wire_m**2 / config.coil.resistance_ohm
    assert copper_m3 / winding_volume_m3(config.coil) == pytest.approx(0.65, rel=0.02)
    override = dataclasses.replace(config, thermal=ThermalSpec(heat_capacity_j_per_k=40.0))
    assert coil_thermal(override).heat_capacity_j_per_k == 40.0
    assert 20 < MODEL.time_constant_s < 200


def test_zero_current_time_constant_is_rc():
    hot = 80.0
    tau = MODEL.time_constant_s
    cooled = temperature_after_c(MODEL, hot, 0.0, tau)
    assert cooled - MODEL.ambient_c == pytest.approx((hot - MODEL.ambient_c) / math.e, rel=1e-12)


def test_steady_state_matches_closed_form_and_the_ode():
    current = 1.5
    rise = steady_state_temperature_c(MODEL, current) - MODEL.ambient_c
    power = current**2 * winding_resistance_ohm(MODEL, MODEL.ambient_c + rise)
    assert rise == pytest.approx(MODEL.thermal_resistance_k_per_w * power, rel=1e-12)
    # Far beyond the effective time constant the transient reaches it.
    late = temperature_after_c(MODEL, MODEL.ambient_c, current, 50 * MODEL.time_constant_s)
    assert late == pytest.approx(MODEL.ambient_c + rise, rel=1e-12)
    # The currents that run away have no steady state.
    runaway = 1 / math.sqrt(MODEL.thermal_resistance_k_per_w * MODEL.resistance_ref_ohm
                            * MODEL.alpha_per_k)
    assert np.isinf(steady_state_temperature_c(MODEL, 1.01 * runaway))


def test_continuous_limit_holds_exactly_t_max():
    limit = continuous_current_limit_a(MODEL)
    assert steady_state_temperature_c(MODEL, limit) == pytest.approx(MODEL.max_c, abs=1e-9)
    assert steady_state_temperature_c(MODEL, limit * (1 + 1e-6)) > MODEL.max_c
    assert np.isinf(time_to_temperature_s(MODEL, MODEL.ambient_c, limit * (1 - 1e-6)))


def test_exact_solution_and_time_to_t_max_match_the_ode():
    current = 3.0
    reach = time_to_temperature_s(MODEL, 40.0, current)
    solution = solve_ivp(rhs(MODEL, current), (0, reach), [40.0], rtol=1e-11, atol=1e-11,
                         dense_output=True)
    assert solution.y[0, -1] == pytest.approx(MODEL.max_c, abs=1e-6)
    times = np.linspace(0, reach, 7)
    assert np.allclose(temperature_after_c(MODEL, 40.0, current, times),
                       solution.sol(times)[0], atol=1e-6)
    assert time_to_temperature_s(MODEL, MODEL.max_c + 1, current) == 0.0
    # Beyond the runaway current and through lambda = 0 the formula stays exact.
    for current in (3.9, 3.96, 4.5):
        reach = time_to_temperature_s(MODEL, 30.0, current)
        assert temperature_after_c(MODEL, 30.0, current, reach) == pytest.approx(
            MODEL.max_c, abs=1e-9)


def test_sampled_update_matches_the_continuous_solution():
    period = 1e-3  # [s], the 1 kHz tick
    rng = np.random.default_rng(3)
    held = rng.uniform(-4.0, 4.0, size=(200, 27))  # currents held over each tick [A]
    temperatures = np.full(27, 60.0)
    history = [temperatures]
    for currents in held:
        temperatures = temperature_after_c(MODEL, temperatures, currents, period)
        history.append(temperatures)
    history = np.array(history)
    for coil in (0, 13):
        def f(t, temperature, coil=coil):
            k = min(int(t / period), len(held) - 1)
            return rhs(MODEL, held[k, coil])(t, temperature)
        solution = solve_ivp(f, (0, len(held) * period), [60.0], rtol=1e-12, atol=1e-12,
                             t_eval=np.arange(len(held) + 1) * period, max_step=period / 4)
        assert np.allclose(history[:, coil], solution.y[0], atol=1e-9)


def test_station_step_in_place_is_the_sampled_update():
    rng = np.random.default_rng(4)
    temperatures = rng.uniform(0.0, 150.0, 27)
    currents = rng.uniform(-4.0, 4.0, 27)
    currents[0] = 0.0  # no heat: the rate's small-x branch
    expected = temperature_after_c(MODEL, temperatures, currents, 0.01)
    step_temperatures_c(temperatures, currents, 0.01, *winding_numbers(MODEL, len(temperatures)))
    np.testing.assert_array_equal(temperatures, expected)


def test_bad_thermal_spec_names_the_field():
    config = DeviceConfig(thermal=ThermalSpec(thermal_resistance_k_per_w=-1.0))
    with pytest.raises(ValueError, match="thermal_resistance_k_per_w"):
        coil_thermal(config)
    config = DeviceConfig(thermal=ThermalSpec(max_winding_temperature_c=20.0))
    with pytest.raises(ValueError, match="max_winding_temperature_c"):
        coil_thermal(config)


@pytest.mark.parametrize("horizon_s", [1.0, 10.0, 60.0])
def test_the_thermal_budget_allows_the_target_no_sooner_than_its_horizon(horizon_s):
    """At each temperature the bound, held, reaches the target in the horizon (or never,
    at the amplifier's limit); it tightens as the winding warms, to the current that
    holds the target; a winding past the target may hold only that."""
    budget = thermal_budget(MODEL, horizon_s=horizon_s, margin_c=5.0, current_limit_a=4.0)
    assert budget.target_c == MODEL.max_c - 5.0
    temperature_c = np.linspace(0.0, budget.target_c - 0.5, 200)
    bound = current_bounds_a(budget, temperature_c)
    assert np.all(np.diff(bound) <= 1e-12) and np.all(bound <= 4.0)
    reach = time_to_temperature_s(MODEL, temperature_c, bound, budget.target_c)
    below_limit = bound < 4.0 - 1e-9
    assert below_limit.any()
    # Linear interpolation between table points errs by well under a percent of the
    # horizon, but where the bound leaves the amplifier's limit (on the safe side).
    np.testing.assert_allclose(np.median(reach[below_limit]), horizon_s, rtol=0.001)
    assert np.all(reach >= horizon_s * 0.999) and np.all(reach[below_limit] <= horizon_s * 1.02)
    holding = current_bounds_a(budget, np.array([budget.target_c, MODEL.max_c + 20.0]))
    np.testing.assert_allclose(steady_state_temperature_c(MODEL, holding[0]), budget.target_c,
                               atol=1e-6)
    assert holding[1] == pytest.approx(holding[0], rel=1e-12)


def test_a_margin_that_leaves_no_room_above_ambient_is_refused():
    with pytest.raises(ValueError, match="controller.thermal_margin_c = 80.0"):
        thermal_budget(MODEL, horizon_s=10.0, margin_c=80.0, current_limit_a=4.0)
