"""The device's mode logic: engage in the hand, hand back on disable, land a free let-go
and an instrument let go when haptics ends."""

import numpy as np
import pytest
from pydrake.common.eigen_geometry import Quaternion
from pydrake.math import RollPitchYaw

from maglev_haptics.systems.blends import clipped_minimum_jerk, minimum_jerk
from maglev_haptics.systems.haptic_supervisor import (
    HAPTIC, LANDING, LANDING_PRESS_M, LEVITATE, HapticSupervisor, SupervisorConfig,
    initial_supervisor_state, measured_pose6, supervisor_gains, supervisor_parameters,
    supervisor_setpoint, supervisor_step)

PERIOD_S = 1e-3
REST_M = 0.007
CONFIG = SupervisorConfig()
PARAMETERS = supervisor_parameters(CONFIG)
HOVER = np.array([0.01, -0.02, 0.025, 0.0, 0.0, 0.3])


def pose_vector(xyz, rpy):
    q = RollPitchYaw(rpy).ToQuaternion()
    return np.array([q.w(), q.x(), q.y(), q.z(), *xyz])


def run(state, t0, n, *, X_WI, request, gripped, in_contact, tracking_ok=True, faulted=False):
    for k in range(n):
        state = supervisor_step(state, t0 + k * PERIOD_S, PERIOD_S, HOVER, X_WI, tracking_ok,
                                request, faulted, gripped, in_contact, PARAMETERS)
    return state, t0 + n * PERIOD_S


def test_measured_pose_unwraps_yaw_near_the_reference():
    pose = measured_pose6(pose_vector([0.01, 0.02, 0.03], [0.1, -0.2, 3.0]), 2 * np.pi + 3.0)
    np.testing.assert_allclose(pose, [0.01, 0.02, 0.03, 0.1, -0.2, 2 * np.pi + 3.0], atol=1e-12)


def test_compiled_pose_and_blend_round_as_drake_and_numpy_do():
    """The kernels stand in for Drake's RollPitchYaw and numpy's powers of a float: the
    same bits, so a run's log is what it was."""
    rng = np.random.default_rng(0)
    for k in range(2000):
        q = rng.normal(size=4) * rng.uniform(0.5, 2.0)
        if k % 4 == 0:  # near gimbal lock
            q = pose_vector([0, 0, 0], [rng.uniform(-3, 3), np.pi / 2 - 1e-9 * k, 0.0])[0:4]
        elif k % 4 == 1:  # near the identity
            q = np.array([1.0, 0.0, 0.0, 0.0]) + rng.normal(0, 1e-10, 4)
        X_WI = np.concatenate((q, rng.normal(0, 0.02, 3)))
        rpy = RollPitchYaw(Quaternion(q / np.linalg.norm(q))).vector()
        reference_yaw = rng.uniform(-10.0, 10.0)
        rpy[2] = reference_yaw + (rpy[2] - reference_yaw + np.pi) % (2 * np.pi) - np.pi
        np.testing.assert_array_equal(measured_pose6(X_WI, reference_yaw),
                                      np.concatenate((X_WI[4:7], rpy)))
    for elapsed in rng.uniform(-0.1, 0.6, 2000):
        s = np.float64(max(elapsed, 0.0) / 0.5)
        blend, rate = minimum_jerk(s)
        expected = (1.0, 0.0) if elapsed >= 0.5 else (blend, rate / 0.5)
        assert clipped_minimum_jerk(elapsed, 0.5) == expected


def test_engages_only_when_requested_and_gripped_and_hands_over_smoothly():
    X_WI = pose_vector(HOVER[0:3], HOVER[3:6])
    state = initial_supervisor_state()
    state, t = run(state, 0.0, 100, X_WI=X_WI, request=True, gripped=False, in_contact=False)
    assert state[0] == LEVITATE
    state, t = run(state, 0.0, 100, X_WI=X_WI, request=False, gripped=True, in_contact=False)
    assert state[0] == LEVITATE
    state, t = run(state, t, 1, X_WI=X_WI, request=True, gripped=True, in_contact=False)
    assert state[0] == HAPTIC
    # The PD fades out over the handover, linearly.
    state, t = run(state, t, int(CONFIG.handover_s / PERIOD_S / 2), X_WI=X_WI, request=True,
                   gripped=True, in_contact=False)
    assert state[14] == pytest.approx(0.5, abs=0.01)
    state, t = run(state, t, int(CONFIG.handover_s / PERIOD_S), X_WI=X_WI, request=True,
                   gripped=True, in_contact=False)
    assert state[14] == 0.0
    # In haptic mode the script passes through untouched.
    scripted = np.arange(12.0)
    assert supervisor_setpoint(state, t, scripted, REST_M, PARAMETERS) is scripted


def test_disable_blends_back_from_where_haptics_ended():
    X_WI_away = pose_vector([0.03, 0.0, 0.02], [0.0, 0.1, 0.3])
    state = initial_supervisor_state()
    state, t = run(state, 0.0, 10, X_WI=X_WI_away, request=True, gripped=True, in_contact=False)
    state, t = run(state, t, 1, X_WI=X_WI_away, request=False, gripped=True, in_contact=False)
    assert state[0] == LEVITATE
    scripted = np.concatenate((HOVER, np.zeros(6)))
    t = state[1]  # the switch
    start = supervisor_setpoint(state, t, scripted, REST_M, PARAMETERS)
    np.testing.assert_allclose(start[0:6], [0.03, 0.0, 0.02, 0.0, 0.1, 0.3], atol=1e-8)
    np.testing.assert_allclose(start[6:12], 0.0, atol=1e-9)
    end = supervisor_setpoint(state, t + CONFIG.handover_s, scripted, REST_M, PARAMETERS)
    np.testing.assert_allclose(end, scripted, atol=1e-12)
    middle = supervisor_setpoint(state, t + CONFIG.handover_s / 2, scripted, REST_M, PARAMETERS)
    assert middle[0] == pytest.approx((0.03 + HOVER[0]) / 2)
    assert middle[6] < 0.0  # moving back toward the script's x


def let_go_in_the_scene(X_WI):
    """A supervisor in haptic mode whose instrument the scene holds, let go."""
    state = initial_supervisor_state()
    state, t = run(state, 0.0, 10, X_WI=X_WI, request=True, gripped=True, in_contact=True)
    state, t = run(state, t, 200, X_WI=X_WI, request=True, gripped=False, in_contact=True)
    assert state[0] == HAPTIC
    return state, t


def test_disable_with_the_handle_let_go_lands_where_the_instrument_is():
    X_WI_in_hole = pose_vector([-0.01, 0.0, 0.0125], [0.0, 0.0, 0.3])
    state, t = let_go_in_the_scene(X_WI_in_hole)
    state, t = run(state, t, 1, X_WI=X_WI_in_hole, request=False, gripped=False,
                   in_contact=True)
    assert state[0] == LANDING
    scripted = np.concatenate((HOVER, np.zeros(6)))  # centimetres away: not followed
    for elapsed in np.linspace(0.0, CONFIG.landing_s, 7):
        setpoint = supervisor_setpoint(state, state[1] + elapsed, scripted, REST_M, PARAMETERS)
        np.testing.assert_allclose(setpoint[0:2], [-0.01, 0.0], atol=1e-9)  # straight down
        assert REST_M - LANDING_PRESS_M - 1e-12 <= setpoint[2] <= 0.0125 + 1e-12


def test_disable_during_a_let_go_shorter_than_the_debounce_hands_back_to_the_script():
    X_WI = pose_vector([-0.01, 0.0, 0.0125], [0.0, 0.0, 0.3])
    state = initial_supervisor_state()
    state, t = run(state, 0.0, 10, X_WI=X_WI, request=True, gripped=True, in_contact=True)
    state, t = run(state, t, int(CONFIG.release_debounce_s / PERIOD_S) - 5, X_WI=X_WI,
                   request=True, gripped=False, in_contact=True)  # a flicker of the grip
    state, t = run(state, t, 1, X_WI=X_WI, request=False, gripped=False, in_contact=True)
    assert state[0] == LEVITATE


def test_a_fault_with_the_handle_let_go_hands_back_to_the_supervisors_landing():
    X_WI = pose_vector([-0.01, 0.0, 0.0125], [0.0, 0.0, 0.3])
    state, t = let_go_in_the_scene(X_WI)
    state, t = run(state, t, 1, X_WI=X_WI, request=True, gripped=False, in_contact=True,
                   faulted=True)
    assert state[0] == LEVITATE  # the device supervisor's landing is the script now


def test_free_let_go_lands_level_and_then_ramps_the_force_down():
    X_WI = pose_vector([0.02, 0.01, 0.03], [0.05, 0.0, 0.3])
    state = initial_supervisor_state()
    state, t = run(state, 0.0, 10, X_WI=X_WI, request=True, gripped=True, in_contact=False)
    # A let-go shorter than the debounce is ridden through.
    state, t = run(state, t, int(CONFIG.release_debounce_s / PERIOD_S) - 5, X_WI=X_WI,
                   request=True, gripped=False, in_contact=False)
    assert state[0] == HAPTIC
    state, t = run(state, t, 1, X_WI=X_WI, request=True, gripped=True, in_contact=False)
    state, t = run(state, t, int(CONFIG.release_debounce_s / PERIOD_S) + 5, X_WI=X_WI,
                   request=True, gripped=False, in_contact=False)
    assert state[0] == LANDING
    assert state[14] == 1.0
    landing_start = state[1]
    scripted = np.concatenate((HOVER, np.zeros(6)))
    done = supervisor_setpoint(state, landing_start + CONFIG.landing_s, scripted, REST_M,
                               PARAMETERS)
    np.testing.assert_allclose(done[0:6], [0.02, 0.01, REST_M - LANDING_PRESS_M, 0, 0, 0.3],
                               atol=1e-9)
    state, t = run(state, t, int((CONFIG.landing_s + CONFIG.settle_s + CONFIG.force_ramp_s)
                                 / PERIOD_S) + 10,
                   X_WI=X_WI, request=True, gripped=False, in_contact=False)
    assert state[15] == 0.0


def test_let_go_while_touching_the_scene_stays_haptic():
    X_WI = pose_vector(HOVER[0:3], HOVER[3:6])
    state = initial_supervisor_state()
    state, t = run(state, 0.0, 10, X_WI=X_WI, request=True, gripped=True, in_contact=True)
    # Contact ends just after the let-go (the push relaxes): still within contact memory.
    state, t = run(state, t, 20, X_WI=X_WI, request=True, gripped=False, in_contact=True)
    state, t = run(state, t, 2000, X_WI=X_WI, request=True, gripped=False, in_contact=False)
    assert state[0] == HAPTIC


@pytest.mark.parametrize("share", [0.2, 0.7])
def test_the_scene_holds_a_let_go_instrument_braked_by_the_configured_share(share):
    parameters = supervisor_parameters(SupervisorConfig(let_go_brake=share))
    X_WI = pose_vector(HOVER[0:3], HOVER[3:6])
    state = initial_supervisor_state()
    state, t = run(state, 0.0, 10, X_WI=X_WI, request=True, gripped=True, in_contact=True)
    assert supervisor_gains(state, parameters)[1] == 0.0  # in the hand: no brake
    debounce = round(CONFIG.release_debounce_s / PERIOD_S) - 1
    state, t = run(state, t, debounce, X_WI=X_WI, request=True, gripped=False, in_contact=True)
    assert supervisor_gains(state, parameters)[1] == 0.0  # a let-go shorter than the debounce
    state, t = run(state, t, 2, X_WI=X_WI, request=True, gripped=False, in_contact=True)
    assert supervisor_gains(state, parameters)[1] == share
    state, t = run(state, t, 1, X_WI=X_WI, request=True, gripped=True, in_contact=True)
    assert supervisor_gains(state, parameters)[1] == 0.0


def test_a_brake_share_outside_0_to_1_is_refused():
    with pytest.raises(ValueError, match=r"supervisor\.let_go_brake.*1\.5.*0\.\.1"):
        SupervisorConfig(let_go_brake=1.5).validate()


def gripped_and_requested(scripted_enable: float):
    """A supervisor whose inputs hold the instrument gripped, haptics requested and no
    fault; and ``step()``, one update at the context's time, then the time a period on."""
    supervisor = HapticSupervisor(config=CONFIG, period_s=PERIOD_S, rest_height_m=REST_M)
    context = supervisor.CreateDefaultContext()
    values = {"scripted_setpoint": np.arange(12.0), "scripted_enable": [scripted_enable],
              "X_WI_measured": pose_vector(HOVER[0:3], HOVER[3:6]), "tracking_ok": [1.0],
              "haptics_request": [1.0], "handle_gripped": [1.0], "tool_in_contact": [0.0],
              "fault_bits": [0.0]}
    for name, value in values.items():
        supervisor.GetInputPort(name).FixValue(context, value)

    def step():
        update = supervisor.EvalUniquePeriodicDiscreteUpdate(context)
        for group in range(update.num_groups()):
            context.SetDiscreteState(group, update.get_vector(group).CopyToVector())
        context.SetTime(context.get_time() + PERIOD_S)

    return supervisor, context, step


def test_system_ports():
    supervisor, context, step = gripped_and_requested(scripted_enable=0.5)
    step()
    assert supervisor.GetOutputPort("mode").Eval(context)[0] == HAPTIC
    assert supervisor.GetOutputPort("enable").Eval(context)[0] == 0.5
    assert supervisor.GetOutputPort("haptics_enable").Eval(context)[0] == 1.0
    # Haptic: the script passes through to the controller untouched.
    np.testing.assert_array_equal(supervisor.GetOutputPort("setpoint").Eval(context),
                                  np.arange(12.0))


def test_a_latched_device_fault_ends_haptics_as_a_dropped_request_would():
    supervisor, context, step = gripped_and_requested(scripted_enable=1.0)
    step()
    assert supervisor.GetOutputPort("mode").Eval(context)[0] == HAPTIC
    supervisor.GetInputPort("fault_bits").FixValue(context, [4.0])  # over-current
    for _ in range(3):  # latched: still gripped and requested, it stays out
        step()
        assert supervisor.GetOutputPort("mode").Eval(context)[0] == LEVITATE
        assert supervisor.GetOutputPort("haptics_enable").Eval(context)[0] == 0.0
