"""The device supervisor: the scripted flight as its first motion, the watchdogs'
fault bits, and the landing a new fault starts."""

import math

import numpy as np
import pytest
from pydrake.systems.analysis import Simulator
from pydrake.systems.primitives import TrajectorySource

from maglev_haptics.diagrams.lcm_station import (
    LcmStation, followed_command_s, measured_currents_lag_ticks)
from maglev_haptics.diagrams.motion import flight_plan, landing_planner
from maglev_haptics.diagrams.scenario import ScenarioError, load_scenario
from maglev_haptics.systems.blends import (
    LANDING_PRESS_M, minimum_jerk_moves, minimum_jerk_plan)
from maglev_haptics.systems.device_supervisor import (
    FAULT_COIL_OVER_CURRENT, FAULT_COIL_OVER_TEMPERATURE, FAULT_OVER_SPEED,
    FAULT_SENSOR_OUT_OF_RANGE, DeviceSupervisor, WatchLimits, detect_faults, make_motion,
    STUCK_PERSIST_S, tracking_lost_after)
from maglev_haptics.systems.station_messages import currents_message

N_COILS = 27
TICK_S = 1e-3
WATCHDOG_PERIOD_S = 0.005
LIMITS = WatchLimits(current_limit_a=4.0, temperature_limit_c=100.0, max_speed_m_s=0.5,
                     boundary_center_m=(0.0, 0.0, 0.02), boundary_radius_m=0.01)
LOST_GRACE_S = 0.02
HEALTHY = dict(position_m=[0.0, 0.0, 0.02], velocity_m_s=[0.0, 0.0, 0.1], tracking_lost=False,
               coil_currents_a=np.full(N_COILS, 1.0), coil_temperature_c=np.full(N_COILS, 40.0),
               thermally_limited=False, carrying=True, limits=LIMITS)


@pytest.mark.parametrize("change, bit", [
    ({"tracking_lost": True}, FAULT_SENSOR_OUT_OF_RANGE),  # past the controller's grace
    ({"position_m": [0.0, 0.011, 0.02]}, FAULT_SENSOR_OUT_OF_RANGE),  # out of the sphere
    ({"velocity_m_s": [0.4, 0.0, -0.4]}, FAULT_OVER_SPEED),
    ({"coil_currents_a": np.r_[np.zeros(26), -4.01]}, FAULT_COIL_OVER_CURRENT),
    ({"coil_temperature_c": np.r_[np.zeros(26), 100.5]}, FAULT_COIL_OVER_TEMPERATURE),
    ({"thermally_limited": True}, FAULT_COIL_OVER_TEMPERATURE),  # too warm to carry it
])
def test_each_watchdog_raises_its_bit(change, bit):
    assert detect_faults(**HEALTHY) == 0
    assert detect_faults(**(HEALTHY | change)) == bit


def test_the_instruments_faults_count_only_while_the_coils_carry_it():
    resting = HEALTHY | {"carrying": False, "tracking_lost": True, "thermally_limited": True,
                         "velocity_m_s": [0.0, 0.0, -1.0]}
    assert detect_faults(**resting) == 0
    # The coils' own faults count whatever they carry.
    assert detect_faults(**(resting | {"coil_currents_a": np.full(N_COILS, 4.5)})) == \
        FAULT_COIL_OVER_CURRENT


def build(scenario, measured_lag_ticks=1):
    spec = scenario.device.instrument_spec()
    plan = flight_plan(scenario.motion, spec.rest_height_m)
    supervisor = DeviceSupervisor(
        initial_motion=make_motion(plan.setpoint, plan.enable, 0.0, TICK_S), limits=LIMITS,
        lost_grace_s=LOST_GRACE_S,
        plan_landing=landing_planner(scenario.motion, spec.rest_height_m), n_coils=N_COILS,
        watchdog_period_s=WATCHDOG_PERIOD_S, weight_n=spec.mass_kg * 9.81,
        measured_lag_ticks=measured_lag_ticks)
    context = supervisor.CreateDefaultContext()
    pose = np.array([1.0, 0, 0, 0, 0.0, 0.0, 0.02])
    for port, value in (("X_WI_measured", pose), ("V_WI_measured", np.zeros(6)),
                        ("tracking_ok", [1.0]), ("coil_currents", np.zeros(N_COILS)),
                        ("coil_temperature_c", np.full(N_COILS, 25.0)),
                        ("thermally_limited", [0.0]),
                        ("coil_currents_commanded", np.zeros(N_COILS)),
                        ("allocation_shortfall_W", np.zeros(6)),
                        ("coil_currents_age_s", [TICK_S])):
        supervisor.GetInputPort(port).FixValue(context, value)
    return supervisor, context, plan, spec


def test_the_script_flies_as_the_trajectories_it_replaced():
    """The same setpoint and force gain, bit for bit, at every tick, as Drake's
    TrajectorySource of the flight plan (what `maglev run` flew before the supervisor)."""
    supervisor, context, plan, _ = build(load_scenario("levitate"))
    source = TrajectorySource(plan.setpoint, output_derivative_order=1)
    source_context = source.CreateDefaultContext()
    for k in range(int(plan.end_s / 1e-3) + 50):
        t_s = k * 1e-3
        source_context.SetTime(t_s)
        np.testing.assert_array_equal(supervisor.GetOutputPort("setpoint").Eval(context),
                                      source.get_output_port().Eval(source_context))
        assert supervisor.GetOutputPort("enable").Eval(context)[0] == plan.enable.value(t_s)[0, 0]
        context.SetTime(t_s)
        context.SetDiscreteState(supervisor.EvalUniquePeriodicDiscreteUpdate(context))


def test_a_run_started_late_flies_from_its_own_tick():
    supervisor, context, plan, _ = build(load_scenario("levitate"))
    simulator = Simulator(supervisor, context)
    context.SetTime(3.0)  # hovering by then: the default state is the resting start
    simulator.Initialize()
    np.testing.assert_array_equal(supervisor.GetOutputPort("setpoint").Eval(context)[0:6],
                                  plan.setpoint.value(3.0).ravel())
    simulator.AdvanceTo(3.0105)
    np.testing.assert_array_equal(supervisor.GetOutputPort("setpoint").Eval(context)[0:6],
                                  plan.setpoint.value(3.011).ravel())


def test_a_new_fault_latches_and_lands_from_the_setpoint():
    supervisor, context, plan, spec = build(load_scenario("levitate"))
    simulator = Simulator(supervisor, context)  # each tick's update at its time
    hold_start_s, _ = plan.holds[0]
    # Tracking lost while hovering, two ticks after a watchdog check (every 5 ms):
    # the lost time passes the controller's 20 ms grace at the 21st tick, the next
    # check raises the fault.
    t_lost = math.ceil((hold_start_s + 0.5) / WATCHDOG_PERIOD_S) * WATCHDOG_PERIOD_S + 2 * TICK_S
    simulator.AdvanceTo(t_lost)  # the update at t_lost still to come
    supervisor.GetInputPort("tracking_ok").FixValue(context, [0.0])
    t_fault = t_lost
    while True:
        hover = supervisor.GetOutputPort("setpoint").Eval(context).copy()  # at t_fault
        simulator.AdvanceTo(t_fault + TICK_S)  # the update at t_fault done
        if supervisor.faults(context):
            break
        t_fault += TICK_S
    assert t_fault - t_lost == pytest.approx(0.023)
    assert supervisor.faults(context) == FAULT_SENSOR_OUT_OF_RANGE
    assert supervisor.GetOutputPort("fault_bits").Eval(context)[0] == FAULT_SENSOR_OUT_OF_RANGE
    landing = supervisor.active_motion(context)
    assert landing.landing and landing.start_s == pytest.approx(t_fault, abs=1e-12)
    np.testing.assert_allclose(landing.at(t_fault)[0], hover, atol=1e-12)  # continuous
    np.testing.assert_array_equal(supervisor.GetOutputPort("setpoint").Eval(context),
                                  landing.at(t_fault + TICK_S)[0])
    # Another fault adds its bit at the next check; the landing under way goes on.
    supervisor.GetInputPort("coil_currents").FixValue(context, np.full(N_COILS, 5.0))
    simulator.AdvanceTo(t_fault + WATCHDOG_PERIOD_S)
    assert supervisor.faults(context) == FAULT_SENSOR_OUT_OF_RANGE
    simulator.AdvanceTo(t_fault + WATCHDOG_PERIOD_S + TICK_S)
    assert supervisor.faults(context) == FAULT_SENSOR_OUT_OF_RANGE | FAULT_COIL_OVER_CURRENT
    assert supervisor.active_motion(context) is landing
    # Down onto the glass (just below the rest height) and the force ramped to zero.
    simulator.AdvanceTo(landing.end_s + 1.0)
    setpoint = supervisor.GetOutputPort("setpoint").Eval(context)
    assert setpoint[2] == pytest.approx(spec.rest_height_m - LANDING_PRESS_M, abs=1e-12)
    assert supervisor.GetOutputPort("enable").Eval(context)[0] == 0.0
    # Reset: the bits clear, the landing stays what is flown.
    supervisor.reset_faults(context)
    assert supervisor.faults(context) == 0
    assert supervisor.active_motion(context) is landing
    assert supervisor.GetOutputPort("enable").Eval(context)[0] == 0.0


def test_the_lost_time_counts_each_tick_and_latches_past_the_grace():
    # Tracking back within the grace: the count starts again.
    assert tracking_lost_after(0.0, 1.0, LOST_GRACE_S, TICK_S) == 0.0
    assert tracking_lost_after(0.0, 0.0, LOST_GRACE_S, TICK_S) == TICK_S
    assert tracking_lost_after(LOST_GRACE_S, 1.0, LOST_GRACE_S, TICK_S) == 0.0
    # Past it the controller has cut the coils: tracking coming back does not undo it.
    assert tracking_lost_after(LOST_GRACE_S + TICK_S, 1.0, LOST_GRACE_S, TICK_S) == \
        pytest.approx(LOST_GRACE_S + 2 * TICK_S)
    supervisor, context, _, _ = build(load_scenario("levitate"))
    simulator = Simulator(supervisor, context)
    simulator.AdvanceTo(1.0)
    lost = supervisor.GetOutputPort("tracking_lost_s")
    supervisor.GetInputPort("tracking_ok").FixValue(context, [0.0])
    simulator.AdvanceTo(1.010)  # ten updates without tracking
    assert lost.Eval(context)[0] == pytest.approx(0.010)
    supervisor.GetInputPort("tracking_ok").FixValue(context, [1.0])
    simulator.AdvanceTo(1.011)
    assert lost.Eval(context)[0] == 0.0
    supervisor.GetInputPort("tracking_ok").FixValue(context, [0.0])
    simulator.AdvanceTo(1.041)
    supervisor.GetInputPort("tracking_ok").FixValue(context, [1.0])
    simulator.AdvanceTo(1.050)
    assert lost.Eval(context)[0] == pytest.approx(0.039)  # latched
    supervisor.reset_faults(context)
    assert lost.Eval(context)[0] == 0.0 and supervisor.faults(context) == 0


def test_a_landing_is_the_scripts_minimum_jerk_moves_sampled_at_the_ticks():
    """The landing's exact minimum-jerk samples against the cubic Hermite fit the
    motion script flies (which errs by < 1e-7 of a move's amplitude)."""
    start = np.array([0.01, -0.005, 0.03, 0.2, -0.1, 0.5])
    goals = [np.array([0.01, -0.005, 0.03, 0.0, 0.0, 0.5]),
             np.array([0.01, -0.005, 0.006, 0.0, 0.0, 0.5])]
    times_s = np.arange(0, 2200) * TICK_S
    values, rates = minimum_jerk_moves(start, goals, 1.0, times_s)
    fit = minimum_jerk_plan(start, 0.0, [(goal, 1.0, 0.0) for goal in goals], 0.2)
    np.testing.assert_allclose(values, fit.vector_values(times_s).T, rtol=0, atol=1e-7)
    np.testing.assert_allclose(rates, fit.MakeDerivative(1).vector_values(times_s).T,
                               rtol=0, atol=2e-6)
    np.testing.assert_array_equal(values[0], start)
    np.testing.assert_allclose(values[-1], goals[-1], rtol=0, atol=1e-15)
    assert not rates[0].any() and not rates[-1].any()


def test_a_bad_watchdog_names_its_field():
    with pytest.raises(ScenarioError, match=r"watchdog.boundary_radius_m = -0.01: must be > 0"):
        load_scenario("levitate", scenario_text="{watchdog: {boundary_radius_m: -0.01}}")
    with pytest.raises(ScenarioError, match=r"watchdog.max_speed_m_s = 0.0"):
        load_scenario("levitate", scenario_text="{watchdog: {max_speed_m_s: 0.0}}")


@pytest.mark.parametrize("age_s", [0.009, math.inf], ids=["an older command", "none"])
def test_currents_of_another_command_are_not_taken_for_a_stuck_coil(age_s):
    """Over LCM the measured currents may follow a command older than those compared (a
    stalled device), or none (the device's own zero once its commands timed out): no
    coil latches as stuck then; currents that follow a command compared and do not
    match it still latch."""
    supervisor, context, _, _ = build(load_scenario("levitate"), measured_lag_ticks=5)
    simulator = Simulator(supervisor, context)
    simulator.AdvanceTo(2.0)  # hovering, coils on
    commanded = np.zeros(N_COILS)
    commanded[3] = 2.0  # coil 3 asked for 2 A, still measured at 0 A
    supervisor.GetInputPort("coil_currents_commanded").FixValue(context, commanded)
    supervisor.GetInputPort("coil_currents_age_s").FixValue(context, [age_s])
    simulator.AdvanceTo(2.0 + 4 * STUCK_PERSIST_S)
    assert not np.any(supervisor.GetOutputPort("coils_stuck").Eval(context))
    assert supervisor.faults(context) == 0
    supervisor.GetInputPort("coil_currents_age_s").FixValue(context, [2 * TICK_S])
    simulator.AdvanceTo(2.0 + 8 * STUCK_PERSIST_S)
    stuck = supervisor.GetOutputPort("coils_stuck").Eval(context)
    assert stuck[3] == 1.0 and stuck.sum() == 1.0
    assert supervisor.faults(context) & FAULT_COIL_OVER_CURRENT


@pytest.mark.parametrize("lag_ticks, age_ticks, compared", [
    (1, 1, True), (1, 2, False),  # the simulated station's: the tick before's command
    (5, 5, True), (5, 6, False),  # over LCM: the link's round trip
    (7, 6, False)])  # capped at the ticks between two checks (5)
def test_currents_are_compared_while_their_command_is_among_those_compared(
        lag_ticks, age_ticks, compared):
    """A coil that does not follow latches as stuck while the command its currents
    follow (``age_ticks`` old) is one of the ``lag_ticks`` ticks' before the check."""
    supervisor, context, _, _ = build(load_scenario("levitate"), lag_ticks)
    simulator = Simulator(supervisor, context)
    simulator.AdvanceTo(2.0)  # hovering, coils on
    commanded = np.zeros(N_COILS)
    commanded[3] = 2.0  # coil 3 asked for 2 A, still measured at 0 A
    supervisor.GetInputPort("coil_currents_commanded").FixValue(context, commanded)
    supervisor.GetInputPort("coil_currents_age_s").FixValue(context, [age_ticks * TICK_S])
    simulator.AdvanceTo(2.0 + 4 * STUCK_PERSIST_S)
    assert supervisor.GetOutputPort("coils_stuck").Eval(context)[3] == float(compared)


def test_the_lcm_stations_currents_are_dated_by_the_command_they_follow():
    """The device reports the sequence of the command its currents follow; the
    application numbers tick k's command k + 1: 1001 was sent at 1 s. None (0: the
    device's command timeout turned the coils off) is never compared."""
    scenario = load_scenario("levitate")
    assert scenario.control_rate_hz == 1000.0
    dated = followed_command_s(scenario)
    message = currents_message(5, 7.0, np.r_[np.zeros(N_COILS), 1.0], command_sequence=1001)
    assert dated(message) == pytest.approx(1.0)
    message.command_sequence = 0
    assert dated(message) == -math.inf


def fly_lagging_currents(measured_lag_ticks: int, stuck_coil=None):
    """Hovering, coil 3 commanded 4 sin(2 pi k / 8) A at tick k (a step of more than
    STUCK_MISMATCH_A every tick, as a saturating allocation swings) and every current
    measured 2 ticks after its command, as over LCM; ``stuck_coil`` measured at +4 A
    whatever its 0.5 A command. Returns the coils latched stuck."""
    supervisor, context, _, _ = build(load_scenario("levitate"),
                                      measured_lag_ticks=measured_lag_ticks)
    supervisor.GetInputPort("coil_currents_age_s").FixValue(context, [2 * TICK_S])
    simulator = Simulator(supervisor, context)
    simulator.AdvanceTo(2.0)  # hovering, coils on
    commands = []
    for k in range(60):
        commanded = np.full(N_COILS, 0.5)
        commanded[3] = 4.0 * math.sin(2.0 * math.pi * k / 8)
        commands.append(commanded)
        measured = commands[max(0, k - 2)].copy()
        if stuck_coil is not None:
            measured[stuck_coil] = 4.0
        supervisor.GetInputPort("coil_currents_commanded").FixValue(context, commanded)
        supervisor.GetInputPort("coil_currents").FixValue(context, measured)
        simulator.AdvanceTo(2.0 + (k + 1) * TICK_S)
    return np.flatnonzero(supervisor.GetOutputPort("coils_stuck").Eval(context)).tolist()


def test_currents_measured_a_round_trip_late_are_not_taken_for_a_stuck_coil():
    """Over LCM a measured current follows its command 2-3 ticks late: compared with
    the tick before's command alone a healthy coil whose command swings latched as
    stuck (the device API's saturating step cut the power in flight), and a tick's span
    cannot check them at all (their command is not in it: a stuck coil goes unseen);
    against the span of the link's round trip a healthy coil does not latch, and a coil
    that follows no command does."""
    lcm_lag_ticks = measured_currents_lag_ticks(load_scenario("levitate"), LcmStation())
    assert lcm_lag_ticks == 6  # (1 ms + 2 ms) each way; the supervisor caps it at 5
    assert fly_lagging_currents(measured_lag_ticks=1, stuck_coil=20) == []
    assert fly_lagging_currents(measured_lag_ticks=lcm_lag_ticks) == []
    assert fly_lagging_currents(measured_lag_ticks=lcm_lag_ticks, stuck_coil=20) == [20]
