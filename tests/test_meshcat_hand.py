"""Meshcat hand input: the smoothing filter, slider-driven target, button-toggled grip."""

import math

import numpy as np
import pytest
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import VectorLogSink

from maglev_haptics.systems.meshcat_hand import (
    GRIP_BUTTON, SLIDERS, MeshcatHandInput, critically_damped_response, grip_from_clicks)

START = np.array([0.01, -0.02, 0.025, 0.0, 0.05, 0.3])  # [x, y, z, roll, pitch, yaw] (m, rad)
TIME_CONSTANT_S = 0.1
PERIOD_S = 1 / 30
LOG_PERIOD_S = 1e-3


def test_filter_starts_where_it_is_and_settles_on_the_goal():
    value, rate, goal = np.array([1.0, -2.0]), np.array([0.5, 0.0]), np.array([3.0, 1.0])
    at_zero = critically_damped_response(value, rate, goal, 4.0, 0.0)
    np.testing.assert_allclose(at_zero[0], value)
    np.testing.assert_allclose(at_zero[1], rate)
    late = critically_damped_response(value, rate, goal, 4.0, 10.0)
    np.testing.assert_allclose(late[0], goal, atol=1e-12)
    np.testing.assert_allclose(late[1], 0.0, atol=1e-12)


def test_filter_rate_is_the_derivative_and_obeys_the_equation():
    value, rate, goal, omega = np.array([0.2]), np.array([-1.0]), np.array([0.7]), 5.0
    h = 1e-6
    for t in (0.05, 0.2, 0.6):
        before = critically_damped_response(value, rate, goal, omega, t - h)
        at = critically_damped_response(value, rate, goal, omega, t)
        after = critically_damped_response(value, rate, goal, omega, t + h)
        np.testing.assert_allclose(at[1], (after[0] - before[0]) / (2 * h), rtol=1e-6)
        acceleration = (after[1] - before[1]) / (2 * h)
        np.testing.assert_allclose(acceleration,
                                   omega**2 * (goal - at[0]) - 2 * omega * at[1], rtol=1e-5)


def test_filtered_step_peaks_at_d_omega_over_e():
    _, rate = critically_damped_response(np.zeros(1), np.zeros(1), np.array([0.05]), 5.0, 0.2)
    np.testing.assert_allclose(rate, 0.05 * 5.0 / math.e)


def test_each_click_toggles_the_grip():
    assert [grip_from_clicks(c, False) for c in range(4)] == [0.0, 1.0, 0.0, 1.0]
    assert [grip_from_clicks(c, True) for c in range(4)] == [1.0, 0.0, 1.0, 0.0]


def build(meshcat, grip_at_start=False):
    builder = DiagramBuilder()
    hand_input = builder.AddSystem(MeshcatHandInput(
        meshcat, start_pose=START, filter_time_constant_s=TIME_CONSTANT_S, period_s=PERIOD_S,
        grip_at_start=grip_at_start))
    target_log = builder.AddSystem(VectorLogSink(12, LOG_PERIOD_S))
    grip_log = builder.AddSystem(VectorLogSink(1, LOG_PERIOD_S))
    builder.Connect(hand_input.GetOutputPort("hand_target"), target_log.get_input_port())
    builder.Connect(hand_input.GetOutputPort("grip"), grip_log.get_input_port())
    diagram = builder.Build()
    simulator = Simulator(diagram)
    simulator.Initialize()
    return hand_input, simulator, target_log, grip_log


def test_controls_are_added_at_the_start_pose_and_deleted(meshcat):
    hand_input, simulator, _, _ = build(meshcat)
    try:
        assert set(meshcat.GetSliderNames()) >= {name for name, *_ in SLIDERS}
        assert GRIP_BUTTON in meshcat.GetButtonNames()
        for (name, scale, _, _, step), value in zip(SLIDERS, START):
            assert abs(meshcat.GetSliderValue(name) * scale - value) <= step * scale / 2
        context = hand_input.GetMyContextFromRoot(simulator.get_context())
        np.testing.assert_allclose(hand_input.GetOutputPort("hand_target").Eval(context),
                                   np.concatenate((START, np.zeros(6))))
        assert hand_input.GetOutputPort("grip").Eval(context)[0] == 0.0
    finally:
        hand_input.Delete()
    assert not set(meshcat.GetSliderNames()) & {name for name, *_ in SLIDERS}
    assert GRIP_BUTTON not in meshcat.GetButtonNames()


def test_target_follows_the_sliders_smoothly(meshcat):
    hand_input, simulator, target_log, _ = build(meshcat)
    try:
        simulator.AdvanceTo(0.1)
        meshcat.SetSliderValue("Hand x (mm)", 1e3 * START[0] + 40.0)
        meshcat.SetSliderValue("Hand yaw (deg)", math.degrees(START[5]) - 20.0)
        simulator.AdvanceTo(0.3)
        context = hand_input.GetMyContextFromRoot(simulator.get_context())
        target = hand_input.GetOutputPort("hand_target").Eval(context)
        assert START[0] < target[0] < START[0] + 0.040 and target[6] > 0.0
        assert START[5] - math.radians(20) < target[5] < START[5] and target[11] < 0.0
        simulator.AdvanceTo(1.5)
        target = hand_input.GetOutputPort("hand_target").Eval(context)
        # The goal is what the sliders show: the start pose rounded to their steps.
        goal = np.array([meshcat.GetSliderValue(name) * scale for name, scale, *_ in SLIDERS])
        np.testing.assert_allclose(goal, START + [0.040, 0, 0, 0, 0, -math.radians(20)],
                                   atol=math.radians(0.05))
        np.testing.assert_allclose(target[0:6], goal, atol=1e-5)
        np.testing.assert_allclose(target[6:12], 0.0, atol=1e-4)
        # Smooth: no jump between 1 ms samples beyond what the peak rate allows, and the
        # logged rate is the derivative of the logged target.
        log = target_log.FindLog(simulator.get_context())
        t, data = log.sample_times(), log.data()
        peak_rate = 0.040 / TIME_CONSTANT_S / math.e
        assert np.max(np.abs(np.diff(data[0]))) <= 1.01 * peak_rate * LOG_PERIOD_S
        assert np.max(data[6]) == pytest.approx(peak_rate, rel=0.02)
        midpoint_rate = (data[6:12, 1:] + data[6:12, :-1]) / 2
        np.testing.assert_allclose(np.diff(data[0:6], axis=1) / np.diff(t), midpoint_rate,
                                   atol=1e-3)
    finally:
        hand_input.Delete()


def test_button_clicks_toggle_the_grip(meshcat, click_button):
    hand_input, simulator, _, grip_log = build(meshcat)
    try:
        context = hand_input.GetMyContextFromRoot(simulator.get_context())
        simulator.AdvanceTo(0.1)
        assert hand_input.GetOutputPort("grip").Eval(context)[0] == 0.0
        click_button(meshcat, GRIP_BUTTON)
        simulator.AdvanceTo(0.2)
        assert hand_input.GetOutputPort("grip").Eval(context)[0] == 1.0
        click_button(meshcat, GRIP_BUTTON)
        simulator.AdvanceTo(0.3)
        assert hand_input.GetOutputPort("grip").Eval(context)[0] == 0.0
        log = grip_log.FindLog(simulator.get_context())
        assert np.count_nonzero(np.diff(log.data()[0])) == 2
    finally:
        hand_input.Delete()


def test_grip_at_start_grips_before_any_click(meshcat, click_button):
    hand_input, simulator, _, _ = build(meshcat, grip_at_start=True)
    try:
        context = hand_input.GetMyContextFromRoot(simulator.get_context())
        assert hand_input.GetOutputPort("grip").Eval(context)[0] == 1.0
        click_button(meshcat, GRIP_BUTTON)
        simulator.AdvanceTo(0.1)
        assert hand_input.GetOutputPort("grip").Eval(context)[0] == 0.0
    finally:
        hand_input.Delete()
