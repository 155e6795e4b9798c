"""Heat in the loop: the thermal allocation keeps the Fig. 3 hover under its winding
limit for as long as it is held, and a hold the coils cannot keep is flown only as
long as the forecast says, then landed."""

import numpy as np
import pytest
from pydrake.math import RollPitchYaw

from maglev_haptics.analysis.run_results import run_scenario
from maglev_haptics.cli import main
from maglev_haptics.diagrams.motion import flight_plan
from maglev_haptics.diagrams.scenario import ScenarioError, load_scenario
from maglev_haptics.diagrams.thermal_forecast import forecast_holds, thermal_outlook
from maglev_haptics.hardware.constants import GRAVITY_M_S2
from maglev_haptics.hardware.magnetics import load_magnetics
from maglev_haptics.hardware.thermal import coil_thermal, steady_state_temperature_c
from maglev_haptics.systems.device_supervisor import FAULT_COIL_OVER_TEMPERATURE

LIMIT_A = 4.0
LIMIT_C = 100.0
TARGET_C = 95.0  # the budget's target: the limit less the default 5 K margin
# The Fig. 3 tilt held for ten minutes.
LONG_TILT = ("{motion: {waypoints: [{pose: [0.0, 0.0, 0.020, 0.349066, 0.0, 0.0], "
             "move_s: 1.5, hold_s: 600.0}]}}")
# Coils that heat in seconds (0.5 J/K: a 1.25 s time constant, the budget's horizon
# scaled with it), so that a few seconds of flight are many time constants.
FAST_HEATING = "device: {thermal: {heat_capacity_j_per_k: 0.5}}"
FAST_HORIZON = "thermal_horizon_s: 0.2"
# Magnets 46 mm above the coils: past what the coils can carry for ever.
HIGH_HOLD = ("{motion: {waypoints: [{pose: [0.0, 0.0, 0.036, 0.0, 0.0, 0.0], move_s: 1.0, "
             "hold_s: 6.0}]}, device: {thermal: {heat_capacity_j_per_k: 2.0}}, "
             "controller: {thermal_horizon_s: 1.0}}")


def forecast(name, text):
    scenario = load_scenario("levitate", name, text)
    plan = flight_plan(scenario.motion, scenario.device.instrument_spec().rest_height_m)
    return scenario, forecast_holds(scenario, plan, load_magnetics(scenario.device))


def test_the_fig3_tilt_is_sustainable_where_minimum_norm_currents_overheat():
    """Ten minutes at the paper's Fig. 3 pose (four magnets, 30 mm, 20 deg): the
    thermal allocation's hottest winding stays under the budget's target, where the
    minimum-norm currents would settle the busiest coil far past the limit."""
    scenario, (tilt,) = forecast("four_magnet_tilt", LONG_TILT)
    assert tilt.sustainable and tilt.allowed_s is None
    assert 80.0 < tilt.hottest_c <= TARGET_C + 0.1
    device = scenario.device
    magnetics = load_magnetics(device)
    pose = np.array([0.0, 0.0, 0.020, 0.349066, 0.0, 0.0])
    A = magnetics.wrench_matrix_from(pose[0:3] - device.p_WA,
                                     RollPitchYaw(pose[3:6]).ToRotationMatrix().matrix())
    weight = np.r_[0.0, 0.0, device.instrument_spec().mass_kg * GRAVITY_M_S2, 0.0, 0.0, 0.0]
    minimum_norm = np.linalg.pinv(A) @ weight
    assert np.max(steady_state_temperature_c(coil_thermal(device), minimum_norm)) > 180.0


def run(name, text):
    scenario = load_scenario("levitate", name, text)
    return run_scenario(scenario, label=f"levitate:{name}", progress=False)


@pytest.mark.parametrize("allocation", ["thermal", "pseudoinverse"])
def test_the_fig3_tilt_flown_hot(allocation):
    """The Fig. 3 flight with coils that heat in a second: the thermal allocation holds
    the tilt with every winding under its target; the pseudoinverse overheats a coil
    and the supervisor lands on the over-temperature fault."""
    result = run("four_magnet_tilt", "{%s, controller: {allocation: %s, %s}}"
                 % (FAST_HEATING, allocation, FAST_HORIZON))
    summary, log = result.summary, result.log
    assert summary["max_coil_current_a"] <= LIMIT_A
    over_temperature = (log["fault_bits"] & FAULT_COIL_OVER_TEMPERATURE) != 0
    if allocation == "thermal":
        assert summary["max_coil_temperature_c"] <= TARGET_C + 0.5
        assert not over_temperature.any()
        tilted = summary["holds"][-1]
        assert tilted["position_error_rms_mm"] < 0.05 and tilted["angle_error_rms_deg"] < 0.1
    else:
        assert summary["max_coil_temperature_c"] > LIMIT_C
        assert over_temperature.any()
        assert summary["touchdown"] is not None and summary["touchdown"]["speed_m_s"] < 0.1


def test_a_hold_the_coils_cannot_keep_is_flown_as_long_as_forecast_then_landed():
    _, (hold,) = forecast("takeoff_hover_land", HIGH_HOLD)
    assert not hold.sustainable and hold.cut_short and 1.0 < hold.allowed_s < hold.hold_s
    result = run("takeoff_hover_land", HIGH_HOLD)
    summary, log = result.summary, result.log
    over_temperature = (log["fault_bits"] & FAULT_COIL_OVER_TEMPERATURE) != 0
    assert over_temperature.any()
    fault_s = log["t"][np.argmax(over_temperature)]
    # The forecast flies the setpoints; the loop's PD and noise move the moment a little.
    assert fault_s == pytest.approx(hold.start_s + hold.allowed_s, abs=0.5)
    assert summary["max_coil_temperature_c"] <= TARGET_C + 0.5
    assert summary["max_coil_current_a"] <= LIMIT_A
    touchdown = summary["touchdown"]
    assert touchdown is not None and touchdown["time_s"] > fault_s
    assert touchdown["speed_m_s"] < 0.1


def test_maglev_run_says_how_long_the_coils_allow_before_it_flies(capsys, tmp_path):
    def run_for(duration_s):
        code = main(["run", "levitate", "--name", "takeoff_hover_land", "--no-meshcat",
                     "--duration", f"{duration_s:.3f}", "--out", str(tmp_path),
                     "--scenario-text", HIGH_HOLD])
        return code, capsys.readouterr().out.splitlines()[0]

    _, (hold,) = forecast("takeoff_hover_land", HIGH_HOLD)
    # Past the moment the budget ends the hold (the loop moves it by at most 0.5 s).
    code, first = run_for(hold.start_s + hold.allowed_s + 1.0)
    assert code == 5  # the fault it foretold latched: coil over-temperature
    assert first.startswith("levitate:takeoff_hover_land: motion.waypoints[0]: held 6 s, but "
                            "the coils allow ")
    assert "device then lands (coil over-temperature)" in first
    # A run that ends before the budget would is told nothing of it.
    code, first = run_for(0.05)
    assert code == 0 and first == "{"  # the summary comes first


def test_the_outlook_speaks_only_of_holds_the_budget_would_end():
    """square's corners cannot be held for ever but are held for 0.8 s of the 20 s the
    coils allow: nothing to say. A hold past what they allow is one line."""
    _, holds = forecast("square", "{}")
    assert any(not hold.sustainable for hold in holds)
    assert not any(hold.cut_short for hold in holds)
    assert thermal_outlook(load_scenario("levitate", "square"), "square") == []
    high = load_scenario("levitate", "takeoff_hover_land", HIGH_HOLD)
    (line,) = thermal_outlook(high, "high")
    assert line.startswith("high: motion.waypoints[0]: held 6 s, but the coils allow ")
    # A run that ends before the budget would: nothing to say.
    (hold,) = forecast_holds(high, flight_plan(high.motion, high.device.instrument_spec()
                                               .rest_height_m), load_magnetics(high.device))
    assert thermal_outlook(high, "high", duration_s=hold.start_s + hold.allowed_s - 0.1) == []


def test_an_unreachable_waypoint_is_refused_before_any_forecast():
    scenario = load_scenario("levitate", "takeoff_hover_land", "{motion: {waypoints: [{pose: "
                             "[0, 0, 0.05, 0, 0, 0], move_s: 1.0, hold_s: 1.0}]}}")
    with pytest.raises(ScenarioError, match=r"^high: motion.waypoints\[0\].pose = .*unreachable"):
        thermal_outlook(scenario, "high")
