"""The simulated tracker: marker kinematics, latency, noise, quantization, occlusion."""

import dataclasses
import math

import numpy as np
import pytest
from pydrake.common.eigen_geometry import Quaternion
from pydrake.math import RigidTransform
from pydrake.systems.analysis import Simulator
from scipy.spatial.transform import Rotation

from maglev_haptics.hardware import TrackerSpec, default_instrument
from maglev_haptics.systems.marker_sensor import (
    MarkerSensor, Occlusion, extrapolate_pose, marker_positions_W, quantize)

INSTRUMENT = default_instrument("two_magnet")
P_IK = INSTRUMENT.p_IK
RATE_HZ = 860.0
TICK_S = 1e-3  # the plant's step (s)


def pose_vector(rotation: Rotation, p_WI) -> np.ndarray:
    return np.concatenate([rotation.as_quat(scalar_first=True), p_WI])


def constant_velocity_state(t, R0=Rotation.from_euler("ZYX", [120, 45, 0], degrees=True),
                            p0=(0.01, -0.02, 0.04), w=(0.5, -0.3, 3.0), v=(0.04, -0.02, 0.01)):
    """Free-body state (13,) at t [s] for constant V_WI = [w; v] in W."""
    w, v = np.asarray(w, float), np.asarray(v, float)
    pose = pose_vector(Rotation.from_rotvec(w * t) * R0, np.asarray(p0) + v * t)
    return np.concatenate([pose, w, v])


def sample(sensor, t, instrument_state):
    """The sensor's output read just after the sample published at t [s] (the state
    ``instrument_state`` held since the tick before it)."""
    context = sensor.CreateDefaultContext()
    sensor.GetInputPort("instrument_state").FixValue(context, instrument_state)
    context.SetTime(t + 0.1 / RATE_HZ)
    assert sensor.GetOutputPort("markers_sample_time_s").Eval(context)[0] == \
        pytest.approx(t, abs=1e-12)
    return sensor.GetOutputPort("markers_measured").Eval(context)


def noiseless(**changes):
    return TrackerSpec(**{"noise_m": 0.0, **changes})


def test_marker_positions_match_drake_rigid_transform():
    x = pose_vector(Rotation.from_euler("ZYX", [250, -30, 45], degrees=True), [0.1, -0.05, 0.03])
    X_WI = RigidTransform(Quaternion(x[:4]), x[4:])
    expected = (X_WI.rotation().matrix() @ P_IK.T).T + X_WI.translation()
    np.testing.assert_allclose(marker_positions_W(x, P_IK), expected, atol=1e-15)


def test_ports_and_initial_output():
    sensor = MarkerSensor(INSTRUMENT, TrackerSpec(), TICK_S)
    assert sensor.get_input_port().get_name() == "instrument_state"
    assert sensor.get_input_port().size() == 13
    assert sensor.GetOutputPort("markers_measured").size() == 3 * len(P_IK)
    assert sensor.GetOutputPort("markers_sample_time_s").size() == 1
    context = sensor.CreateDefaultContext()
    sensor.get_input_port().FixValue(context, constant_velocity_state(0.0))
    # At t = 0 the first sample is due, not yet published: nothing measured yet.
    assert np.all(np.isnan(sensor.GetOutputPort("markers_measured").Eval(context)))
    assert sensor.GetOutputPort("markers_sample_time_s").Eval(context)[0] == -np.inf
    assert sensor.sample_period_s == 1 / 860.0


def test_noise_free_sample_shows_the_pose_latency_ago():
    latency = 1.5e-3
    sensor = MarkerSensor(INSTRUMENT, noiseless(latency_s=latency), TICK_S)
    t = 37 / RATE_HZ
    measured = sample(sensor, t, constant_velocity_state(t)).reshape(-1, 3)
    expected = marker_positions_W(constant_velocity_state(t - latency)[:7], P_IK)
    np.testing.assert_allclose(measured, expected, rtol=0, atol=1e-15)
    # The lag is real: the markers moved ~0.1 mm meanwhile.
    now = marker_positions_W(constant_velocity_state(t)[:7], P_IK)
    assert np.abs(now - measured).max() > 5e-5


def test_latency_is_first_order_under_acceleration():
    latency, a = 1.5e-3, np.array([0.0, 0.0, -9.81])  # falling freely [m/s^2]
    t = 0.2
    state = np.concatenate([[1, 0, 0, 0], 0.5 * a * t**2, np.zeros(3), a * t])
    x_then = extrapolate_pose(state[:7], state[7:], -latency)
    error = x_then[4:] - 0.5 * a * (t - latency) ** 2
    np.testing.assert_allclose(error, -0.5 * a * latency**2, atol=1e-15)


def test_each_sample_sees_the_state_held_over_its_tick_and_is_held_after():
    sensor = MarkerSensor(INSTRUMENT, noiseless(latency_s=0.0), TICK_S)
    simulator = Simulator(sensor)
    context = simulator.get_mutable_context()
    x = constant_velocity_state(0.0, w=(0, 0, 0), v=(0, 0, 0))

    def hold_state(dx):
        """The plant steps to a state moved dx (m) along x: returns its markers."""
        moved = x.copy()
        moved[4] += dx
        sensor.get_input_port().FixValue(context, moved)
        return marker_positions_W(moved[:7], P_IK).ravel()

    def read():
        return (sensor.GetOutputPort("markers_sample_time_s").Eval(context)[0],
                sensor.GetOutputPort("markers_measured").Eval(context))

    # The plant's step at k ms is emulated by a new fixed state just after the tick at k
    # ms was processed: the state then holds until the step at k + 1 ms.
    before = hold_state(0.0)  # held over [0, 1) ms: sample 0 (at 0 ms)
    simulator.AdvanceTo(0.5 * TICK_S)
    published_s, markers = read()
    assert published_s == 0.0
    np.testing.assert_allclose(markers, before, atol=1e-15)
    simulator.AdvanceTo(1.05 * TICK_S)
    after = hold_state(0.01)  # held over [1, 2) ms: sample 1 (at 1.16 ms)
    published_s, markers = read()  # sample 1 not yet published: sample 0 held
    assert published_s == 0.0
    np.testing.assert_allclose(markers, before, atol=1e-15)
    simulator.AdvanceTo(1.5 * TICK_S)
    published_s, markers = read()
    assert published_s == 1 / RATE_HZ
    np.testing.assert_allclose(markers, after, atol=1e-15)
    simulator.AdvanceTo(2.05 * TICK_S)
    hold_state(0.02)  # held over [2, 3) ms; nothing published until 2.33 ms
    simulator.AdvanceTo(2.2 * TICK_S)
    published_s, markers = read()
    assert published_s == 1 / RATE_HZ  # sample 1, as it was taken
    np.testing.assert_allclose(markers, after, atol=1e-15)


def test_a_sample_due_at_a_ticks_instant_is_read_at_the_next_tick():
    # 43 samples at 860 Hz are 50 ticks at 1 kHz: sample 43 falls on the tick at 50 ms.
    sensor = MarkerSensor(INSTRUMENT, noiseless(latency_s=0.0), TICK_S)
    simulator = Simulator(sensor)
    context = simulator.get_mutable_context()
    x = constant_velocity_state(0.0, w=(0, 0, 0), v=(0, 0, 0))
    sensor.get_input_port().FixValue(context, x)
    simulator.AdvanceTo(50 * TICK_S)
    published = sensor.GetOutputPort("markers_sample_time_s")
    assert round(published.Eval(context)[0] * RATE_HZ) == 42
    moved = x.copy()
    moved[4] += 0.01  # the plant's step at 50 ms
    sensor.get_input_port().FixValue(context, moved)
    simulator.AdvanceTo(51 * TICK_S)
    assert round(published.Eval(context)[0] * RATE_HZ) == 43
    np.testing.assert_allclose(sensor.GetOutputPort("markers_measured").Eval(context),
                               marker_positions_W(moved[:7], P_IK).ravel(), atol=1e-15)


def test_noise_statistics_and_reproducibility():
    sigma = 1e-5
    sensor = MarkerSensor(INSTRUMENT, TrackerSpec(noise_m=sigma, latency_s=0.0), TICK_S, seed=7)
    x = constant_velocity_state(0.0, w=(0, 0, 0), v=(0, 0, 0))
    exact = marker_positions_W(x[:7], P_IK).ravel()
    errors = np.array([sensor.measure(k / RATE_HZ, x) - exact for k in range(3000)])
    assert abs(errors.std() / sigma - 1) < 0.03  # 9000 values: std error 0.7 %
    assert abs(errors.mean()) < 4 * sigma / math.sqrt(errors.size)
    # Noise of sample k depends on (seed, k) only: order of calls and Contexts do not matter.
    np.testing.assert_array_equal(sensor.measure(5 / RATE_HZ, x), errors[5] + exact)
    np.testing.assert_array_equal(sample(sensor, 2999 / RATE_HZ, x), errors[2999] + exact)
    again = MarkerSensor(INSTRUMENT, TrackerSpec(noise_m=sigma, latency_s=0.0), TICK_S, seed=7)
    np.testing.assert_array_equal(again.measure(1234 / RATE_HZ, x), errors[1234] + exact)
    other = MarkerSensor(INSTRUMENT, TrackerSpec(noise_m=sigma, latency_s=0.0), TICK_S, seed=8)
    assert not np.allclose(other.measure(1234 / RATE_HZ, x), errors[1234] + exact)


def test_measure_takes_a_strided_state():
    sensor = MarkerSensor(INSTRUMENT, TrackerSpec(), TICK_S, seed=1)
    x = constant_velocity_state(0.1)
    strided = np.repeat(x, 2)[::2]  # a non-contiguous view of the same values
    np.testing.assert_array_equal(sensor.measure(0.1, strided), sensor.measure(0.1, x))


def test_quantization():
    step = 1e-4
    sensor = MarkerSensor(INSTRUMENT, TrackerSpec(latency_s=0.0), TICK_S, quantization_m=step)
    x = constant_velocity_state(0.0)
    measured = sensor.measure(0.0, x)
    np.testing.assert_allclose(measured / step, np.round(measured / step), atol=1e-9)
    exact = marker_positions_W(x[:7], P_IK).ravel()
    assert np.abs(measured - exact).max() <= step / 2 + 5e-5  # + 5 sigma of noise
    np.testing.assert_array_equal(quantize(np.array([0.123456]), 0.0), [0.123456])


def test_scripted_occlusion_one_marker_and_lost_instrument():
    latency = 1.5e-3
    occlusions = [Occlusion(marker=1, start_s=0.10, end_s=0.20),
                  Occlusion(marker=None, start_s=0.50, end_s=0.60)]
    sensor = MarkerSensor(INSTRUMENT, TrackerSpec(latency_s=latency), TICK_S, occlusions, seed=3)
    x = constant_velocity_state(0.0)
    times = np.arange(0, 0.8, 1 / RATE_HZ)
    hidden = np.array([np.isnan(sensor.measure(t, x).reshape(-1, 3)).all(axis=1)
                       for t in times])
    # Partly NaN markers never occur.
    assert not np.any(np.isnan(np.array([sensor.measure(t, x) for t in times])).reshape(
        len(times), -1, 3).any(axis=2) & ~hidden)
    capture = times - latency  # occlusion applies at capture time
    in_one = (capture >= 0.10) & (capture < 0.20)
    in_all = (capture >= 0.50) & (capture < 0.60)
    np.testing.assert_array_equal(hidden[:, 1], in_one | in_all)
    np.testing.assert_array_equal(hidden[:, 0], in_all)
    np.testing.assert_array_equal(hidden[:, 2], in_all)
    assert in_one.sum() > 80 and in_all.sum() > 80
    # Through the system too, and with the intervals given as tuples.
    as_tuples = MarkerSensor(INSTRUMENT, TrackerSpec(latency_s=latency), TICK_S,
                             [(1, 0.10, 0.20), (None, 0.50, 0.60)], seed=3)
    t = times[np.argmax(in_all)]
    assert np.all(np.isnan(sample(as_tuples, t, x)))
    t = times[np.argmax(in_one)]
    np.testing.assert_array_equal(sample(as_tuples, t, x), sensor.measure(t, x))


def test_random_dropout():
    x = constant_velocity_state(0.0)
    times = np.arange(2000) / RATE_HZ
    for p in (0.0, 0.3, 1.0):
        sensor = MarkerSensor(INSTRUMENT, TrackerSpec(), TICK_S, seed=11, dropout_probability=p)
        hidden = np.array([np.isnan(sensor.measure(t, x)) for t in times])
        assert abs(hidden.mean() - p) < 0.02  # 6000 markers: std error 0.6 %


@pytest.mark.parametrize("kwargs, match", [
    (dict(tracker=TrackerSpec(rate_hz=0.0)), r"tracker.rate_hz = 0.0: must be .* > 0"),
    (dict(tracker=TrackerSpec(rate_hz=-860.0)), r"tracker.rate_hz = -860.0"),
    (dict(tracker=TrackerSpec(noise_m=-1e-5)), r"tracker.noise_m = -1e-05: must be .* >= 0"),
    (dict(tracker=TrackerSpec(latency_s=-1e-3)), r"tracker.latency_s = -0.001: must be .* >= 0"),
    (dict(tracker=TrackerSpec(noise_m=math.nan)), r"tracker.noise_m = nan"),
    (dict(dropout_probability=1.5), r"dropout_probability = 1.5: must be in \[0, 1\]"),
    (dict(dropout_probability=-0.1), r"dropout_probability = -0.1"),
    (dict(quantization_m=-1e-6), r"quantization_m = -1e-06: must be .* >= 0"),
    (dict(occlusions=[Occlusion(marker=3)]), r"occlusions\[0\].marker = 3: .* \[0, 2\]"),
    (dict(occlusions=[Occlusion(), Occlusion(marker=-1)]), r"occlusions\[1\].marker = -1"),
    (dict(occlusions=[Occlusion(marker=0, start_s=0.2, end_s=0.1)]),
     r"occlusions\[0\] = \(0.2, 0.1\) s: must satisfy start_s <= end_s"),
    (dict(seed=-1), r"seed = -1: must be a non-negative integer"),
    (dict(seed=1.5), r"seed = 1.5"),
    (dict(tick_s=0.002), r"tick_s = 0.002: .* at most the tracker's period"),
    (dict(tick_s=0.0), r"tick_s = 0.0: the plant's step must be > 0"),
])
def test_bad_input_is_named(kwargs, match):
    args = {"instrument": INSTRUMENT, "tracker": TrackerSpec(), "tick_s": TICK_S, **kwargs}
    with pytest.raises(ValueError, match=match):
        MarkerSensor(**args)


def test_bad_marker_model_is_named():
    flat = dataclasses.replace(INSTRUMENT, p_IK_m=[0.0, 0.0, 0.06])
    with pytest.raises(ValueError, match=r"instrument.p_IK_m has shape \(3,\)"):
        MarkerSensor(flat, TrackerSpec(), TICK_S)
