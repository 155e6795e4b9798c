"""Faults injected into the simulated station: each does what it says, a bad one is
refused naming its field, and the loop copes (rides through or lands safely)."""

import numpy as np
import pytest
from pydrake.systems.analysis import Simulator

from maglev_haptics.analysis.run_results import run_scenario
from maglev_haptics.diagrams.scenario import ScenarioError, load_scenario
from maglev_haptics.hardware import DeviceConfig
from maglev_haptics.systems.device_supervisor import (
    FAULT_COIL_OVER_CURRENT, FAULT_OVER_SPEED, mismatched_coils)
from maglev_haptics.systems.fault_injection import (
    CorruptSample, LatencySpike, StuckAmplifier, corrupt, stalled, stuck_currents)
from maglev_haptics.systems.haptic_supervisor import HAPTIC, LEVITATE
from maglev_haptics.systems.marker_sensor import MarkerSensor

LIMIT_A = 4.0
TICK_S = 1e-3  # the plant's step (s)


def test_a_stuck_amplifier_delivers_its_stuck_current_from_its_time_on():
    faults = [StuckAmplifier(coil=2, at_s=1.0, stuck_at="zero"),
              StuckAmplifier(coil=5, at_s=2.0, stuck_at="negative_limit")]
    commanded = np.linspace(-1.0, 1.0, 27)
    np.testing.assert_array_equal(stuck_currents(0.5, commanded, faults, LIMIT_A), commanded)
    after = stuck_currents(2.0, commanded, faults, LIMIT_A)
    assert after[2] == 0.0 and after[5] == -LIMIT_A
    np.testing.assert_array_equal(np.delete(after, [2, 5]), np.delete(commanded, [2, 5]))


def test_a_stalled_tracker_holds_its_sample_and_a_corrupt_one_has_one_nan():
    spec = DeviceConfig().instrument_spec()
    tracker = DeviceConfig().tracker
    sensor = MarkerSensor(spec, tracker, TICK_S, latency_spikes=[LatencySpike(0.01, 0.02)],
                          corruptions=[CorruptSample(at_s=0.03, marker=1, coordinate=2)])
    simulator = Simulator(sensor)
    context = simulator.get_mutable_context()
    state = np.r_[1.0, 0, 0, 0, 0, 0, 0.02, np.zeros(6)]
    sensor.GetInputPort("instrument_state").FixValue(context, state)
    samples = {}
    for tick in range(1, 42):  # each sample is read at the tick after it
        simulator.AdvanceTo(tick * TICK_S)
        published_s = sensor.GetOutputPort("markers_sample_time_s").Eval(context)[0]
        samples[round(published_s * tracker.rate_hz)] = \
            sensor.GetOutputPort("markers_measured").Eval(context).copy()
    assert sorted(samples) == list(range(len(samples)))
    stall = [k for k in samples if stalled(k / tracker.rate_hz, [LatencySpike(0.01, 0.02)])]
    assert len(stall) >= 8
    for k in stall:  # the sample before the stall, again and again
        np.testing.assert_array_equal(samples[k], samples[stall[0] - 1])
    bad = samples[round(0.03 * tracker.rate_hz)]
    assert np.isnan(bad[5]) and np.isfinite(np.delete(bad, 5)).all()
    expected = samples[round(0.03 * tracker.rate_hz)].copy()
    corrupt(round(0.03 * tracker.rate_hz), expected, [], tracker.rate_hz)  # nothing to do
    np.testing.assert_array_equal(np.isnan(expected), np.isnan(bad))


@pytest.mark.parametrize("fault, message", [
    ("!StuckAmplifier {coil: 27}", "faults[0].coil = 27: must be a coil index 0..26"),
    ("!StuckAmplifier {stuck_at: sideways}", "faults[0].stuck_at = 'sideways': must be one of"),
    ("!CorruptSample {marker: 3}", "faults[0].marker = 3: must be a marker index 0..2"),
    ("!LatencySpike {start_s: 2.0, end_s: 1.0}", "faults[0].end_s = 1.0: must be finite"),
    ("!Shove {force_n: [1, 2]}", "faults[0].force_n = [1.0, 2.0]: must be a list of 3"),
])
def test_a_bad_fault_is_refused_naming_its_field(fault, message):
    with pytest.raises(ScenarioError, match=message.replace("[", r"\[")):
        load_scenario("levitate", None, f"{{faults: [{fault}]}}")


def run(text):
    scenario = load_scenario("levitate", None, text)
    return run_scenario(scenario, label="levitate", progress=False)


def test_a_stuck_amplifier_is_seen_by_its_mismatch_and_flown_around():
    measured = np.zeros(27)
    measured[14] = -4.0
    commanded = np.full(27, 0.5)
    commanded[3] = 5.0  # clamped to the limit: no mismatch
    measured[3] = 4.0
    assert np.flatnonzero(mismatched_coils(measured, commanded, commanded, LIMIT_A)).tolist() \
        == [14]


def test_a_coil_stuck_at_its_limit_under_the_hover_is_caught_and_landed_from_near_the_setpoint():
    """The centre coil stuck at -4 A: without the mismatch watchdog it threw the
    instrument off the coils' reach (the fault campaign's run 195)."""
    at_s = 2.37
    result = run("{faults: [!StuckAmplifier {coil: 14, at_s: %g, stuck_at: negative_limit}]}"
                 % at_s)
    log, summary = result.log, result.summary
    over_current = (log["fault_bits"] & FAULT_COIL_OVER_CURRENT) != 0
    assert over_current.any()
    assert at_s < log["t"][np.argmax(over_current)] <= at_s + 0.017
    touchdown = summary["touchdown"]
    assert touchdown is not None and touchdown["speed_m_s"] < 0.1
    flying = (log["t"] > at_s) & (log["t"] < touchdown["time_s"])
    assert np.max(np.linalg.norm(log["p_WI_true"][flying] - log["p_WI_desired"][flying],
                                 axis=1)) < 0.01
    assert summary["max_coil_current_a"] <= LIMIT_A
    # On the glass, the coils ramped down, the supervisor cuts the power: the stuck
    # coil no longer pushes the resting instrument aside (it did by 12 mm before).
    assert log["coil_power"][flying].min() == 1.0
    cut = np.argmax(log["coil_power"] < 0.5)
    assert log["t"][cut] > touchdown["time_s"]
    resting = log["t"] > log["t"][cut] + 0.05
    assert np.abs(log["coil_currents"][resting]).max() < 1e-3
    drift = log["p_WI_true"][resting] - log["p_WI_true"][cut]
    assert np.max(np.linalg.norm(drift[:, 0:2], axis=1)) < 1e-4


def test_a_stuck_coil_the_others_cannot_carry_against_cuts_the_power_and_it_falls_level():
    """The centre coil stuck at +4 A pulls the hovering instrument down harder than
    the other coils can hold it up (the fault campaign's run 105: a "controlled"
    landing touched down at 0.41 m/s): the supervisor cuts the power at the first
    check that sees the others fall short with the stuck coil's wrench taken as given
    (the one after it found it stuck: the allocation then still used the coil), and
    it falls level, no faster than free fall from its height and speed at the cut."""
    at_s = 2.9239
    result = run("{faults: [!StuckAmplifier {coil: 14, at_s: %g, stuck_at: positive_limit}]}"
                 % at_s)
    log, summary = result.log, result.summary
    cut = np.argmax(log["coil_power"] < 0.5)
    over_current = np.argmax((log["fault_bits"] & FAULT_COIL_OVER_CURRENT) != 0)
    assert log["t"][over_current] <= at_s + 0.017
    assert log["t"][over_current] < log["t"][cut] <= log["t"][over_current] + 0.005 + 1e-9
    height_m = log["p_WI_true"][cut, 2] - DeviceConfig().instrument_spec().rest_height_m
    sinking_m_s = -log["V_WI_true"][cut, 5]
    touchdown = summary["touchdown"]
    assert touchdown["tilt_deg"] < 5.0
    assert touchdown["speed_m_s"] <= np.sqrt(sinking_m_s**2 + 2 * 9.81 * height_m)
    assert np.abs(log["coil_currents"][log["t"] > log["t"][cut] + 0.01]).max() < 1e-3


def test_a_ten_newton_shove_raises_over_speed_and_lands():
    result = run("{faults: [!Shove {at_s: 2.5, duration_s: 0.01, force_n: [10, 0, 0]}]}")
    log = result.log
    over_speed = (log["fault_bits"] & FAULT_OVER_SPEED) != 0
    assert over_speed.any() and 2.5 < log["t"][np.argmax(over_speed)] < 2.53
    assert result.summary["touchdown"]["speed_m_s"] < 0.1


def test_a_fault_with_haptics_on_ends_haptics_and_the_device_lands_the_instrument():
    """A coil stuck while the hand holds the peg with haptics on: the latched fault
    ends haptics within a supervisor tick of its check, the device lands the
    instrument though the hand still grips it, and cuts the power on the glass."""
    scenario = load_scenario("peg_in_hole", "peg_release_outside", "{faults: [!StuckAmplifier "
                             "{coil: 10, at_s: 3.5, stuck_at: positive_limit}]}")
    log = run_scenario(scenario, label="peg_release_outside", progress=False)
    summary, log = log.summary, log.log
    t = log["t"]
    fault_s = t[np.argmax(log["fault_bits"] != 0)]
    assert 3.5 < fault_s <= 3.517
    mode = log["haptic_mode"].ravel()
    assert mode[(t > 2.6) & (t < fault_s)].min() == HAPTIC
    assert np.all(mode[t > fault_s + 0.01] == LEVITATE)
    touchdown = summary["touchdown"]
    assert touchdown["time_s"] < 4.5 + 1.0 and touchdown["speed_m_s"] < 0.1  # let go at 4.5 s
    assert t[np.argmax(log["coil_power"] < 0.5)] > touchdown["time_s"]
