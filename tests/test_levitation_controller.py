"""The levitation controller: PD law, gravity compensation, blind landing, the compiled law
against Drake's rotations."""

import numpy as np
import pytest
from pydrake.common.eigen_geometry import Quaternion
from pydrake.math import RollPitchYaw, RotationMatrix

from maglev_haptics.hardware import DeviceConfig
from maglev_haptics.hardware.constants import GRAVITY_M_S2
from maglev_haptics.hardware.magnetics import load_magnetics
from maglev_haptics.hardware.thermal import coil_thermal
from maglev_haptics.systems.levitation_controller import (
    ControllerConfig, LevitationController, pd_gains, pd_wrench)
from maglev_haptics.systems.rotations import (
    angular_velocity_from_rpy_rates, rotation_error_W, rotation_from_rpy)

MASS_KG = 0.125
INERTIA = np.array([8e-6, 5.6e-5, 6e-5])
LIMIT_A = 4.0
DEVICE = DeviceConfig()


@pytest.fixture(scope="module")
def magnetics():
    return load_magnetics(DEVICE)


def make(magnetics, config=ControllerConfig()):
    controller = LevitationController(config=config, mass_kg=MASS_KG, inertia_diag=INERTIA,
                                      magnetics=magnetics, p_WA=DEVICE.p_WA,
                                      current_limit_a=LIMIT_A, thermal=coil_thermal(DEVICE))
    context = controller.CreateDefaultContext()
    controller.GetInputPort("coil_temperature_c").FixValue(
        context, np.full(magnetics.n_coils, DEVICE.thermal.ambient_temperature_c))
    controller.GetInputPort("coil_currents").FixValue(context, np.zeros(magnetics.n_coils))
    controller.GetInputPort("coils_stuck").FixValue(context, np.zeros(magnetics.n_coils))
    return controller, context


def fix(controller, context, *, setpoint, pose, velocity=np.zeros(6), ok=1.0, enable=1.0,
        feedforward=np.zeros(6), pd_gain=1.0, brake_gain=0.0, lost_s=0.0):
    controller.GetInputPort("setpoint").FixValue(context, setpoint)
    controller.GetInputPort("X_WI_measured").FixValue(context, pose)
    controller.GetInputPort("V_WI_measured").FixValue(context, velocity)
    controller.GetInputPort("tracking_ok").FixValue(context, [ok])
    controller.GetInputPort("enable").FixValue(context, [enable])
    controller.GetInputPort("pd_gain").FixValue(context, [pd_gain])
    controller.GetInputPort("brake_gain").FixValue(context, [brake_gain])
    controller.GetInputPort("wrench_feedforward_W").FixValue(context, feedforward)
    controller.GetInputPort("tracking_lost_s").FixValue(context, [lost_s])


def pose_vector(rpy, p):
    q = RollPitchYaw(rpy).ToQuaternion()
    return np.array([q.w(), q.x(), q.y(), q.z(), *p])


def test_rotation_helpers_match_drake():
    rpy = np.array([0.3, -0.4, 2.5])
    np.testing.assert_allclose(rotation_from_rpy(rpy), RollPitchYaw(rpy).ToRotationMatrix().matrix(),
                               atol=1e-14)
    rates = np.array([0.2, -0.7, 1.1])
    expected = RollPitchYaw(rpy).CalcAngularVelocityInParentFromRpyDt(rates)
    np.testing.assert_allclose(angular_velocity_from_rpy_rates(rpy, rates), expected, atol=1e-14)
    small = RotationMatrix.MakeXRotation(1e-3).matrix()
    np.testing.assert_allclose(rotation_error_W(small, np.eye(3)), [1e-3, 0, 0], atol=1e-9)


def test_at_the_setpoint_it_carries_the_weight_only(magnetics):
    controller, context = make(magnetics)
    setpoint = np.array([0.01, -0.02, 0.018, 0.1, -0.2, 4.0, *np.zeros(6)])
    fix(controller, context, setpoint=setpoint, pose=pose_vector(setpoint[3:6], setpoint[0:3]))
    wrench = controller.GetOutputPort("wrench_commanded_W").Eval(context)
    np.testing.assert_allclose(wrench, [0, 0, MASS_KG * GRAVITY_M_S2, 0, 0, 0], atol=1e-12)


def test_pd_law_per_axis():
    kp, kd = pd_gains(ControllerConfig(), MASS_KG, INERTIA)
    omega = 2 * np.pi * 10
    np.testing.assert_allclose(kp, np.concatenate([[MASS_KG] * 3, INERTIA]) * omega**2)
    np.testing.assert_allclose(kd, 2 * 0.7 * np.concatenate([[MASS_KG] * 3, INERTIA]) * omega)
    setpoint = np.zeros(12)
    velocity = np.array([0, 0, 0.5, 0.01, 0, 0])
    pose = pose_vector([0, 0, 0.0], [0.001, 0, 0])
    wrench = pd_wrench(setpoint, pose, velocity, kp, kd, MASS_KG)
    np.testing.assert_allclose(wrench[0:3], [-kp[0] * 0.001 - kd[0] * 0.01, 0,
                                             MASS_KG * GRAVITY_M_S2], rtol=1e-12)
    np.testing.assert_allclose(wrench[3:6], [0, 0, -kd[5] * 0.5], atol=1e-15)
    # A small roll error about the instrument's x axis is corrected with that axis' gain;
    # yawed by 90 deg, I's x axis is W's y axis.
    pose = pose_vector([0.002, 0, np.pi / 2], [0, 0, 0])
    setpoint[5] = np.pi / 2
    torque = pd_wrench(setpoint, pose, np.zeros(6), kp, kd, MASS_KG)[3:6]
    np.testing.assert_allclose(torque, [0, -kp[3] * np.sin(0.002), 0], rtol=1e-6, atol=1e-15)


def test_enable_ramp_and_feedforward(magnetics):
    controller, context = make(magnetics)
    setpoint = np.zeros(12)
    feedforward = np.array([0.1, 0, 0, 0, 0, 0.001])
    fix(controller, context, setpoint=setpoint, pose=pose_vector([0, 0, 0], [0, 0, 0]),
        enable=0.25, feedforward=feedforward)
    wrench = controller.GetOutputPort("wrench_commanded_W").Eval(context)
    np.testing.assert_allclose(wrench, [0.1, 0, 0.25 * MASS_KG * GRAVITY_M_S2, 0, 0, 0.001])


def test_lost_tracking_holds_weight_through_the_grace_then_cuts(magnetics):
    config = ControllerConfig(lost_grace_s=0.02)
    controller, context = make(magnetics, config)
    pose = pose_vector([0, 0, 0], [0.01, 0, 0.02])
    weight = MASS_KG * GRAVITY_M_S2
    # The first tick of a loss (the supervisor has not counted it yet), then the grace.
    for ok, lost_s, lift in ((0.0, 0.0, weight), (0.0, 0.001, weight), (0.0, 0.02, weight),
                             (0.0, 0.021, 0.0), (1.0, 0.021, 0.0)):  # the count latched
        fix(controller, context, setpoint=np.zeros(12), pose=pose, ok=ok, lost_s=lost_s)
        wrench = controller.GetOutputPort("wrench_commanded_W").Eval(context)
        np.testing.assert_allclose(wrench, [0, 0, lift, 0, 0, 0])  # no stale PD


def test_compiled_pd_law_matches_drakes_rotations_and_its_differences():
    """pd_wrench at a tilted, turning pose, against the law written with Drake's
    RotationMatrix, RollPitchYaw and AngleAxis; and d fz / d z by central differences."""
    kp, kd = pd_gains(ControllerConfig(), MASS_KG, INERTIA)
    setpoint = np.array([0.01, -0.02, 0.03, 0.2, -0.1, 1.3, 0.05, 0.0, -0.02, 0.3, -0.2, 0.7])
    pose = pose_vector([0.25, 0.05, 1.1], [0.012, -0.018, 0.027])
    velocity = np.array([0.4, -0.3, 0.2, 0.02, -0.01, 0.03])
    R_WI = RotationMatrix(Quaternion(pose[0:4])).matrix()
    rpy_WD = RollPitchYaw(setpoint[3:6])
    # sin(angle) * axis of the rotation from I to D, in W.
    error = RotationMatrix(rpy_WD.ToRotationMatrix().matrix() @ R_WI.T).ToAngleAxis()
    error_W = np.sin(error.angle()) * error.axis()
    rate_error_W = rpy_WD.CalcAngularVelocityInParentFromRpyDt(setpoint[9:12]) - velocity[0:3]
    force = (kp[0:3] * (setpoint[0:3] - pose[4:7]) + kd[0:3] * (setpoint[6:9] - velocity[3:6])
             + [0.0, 0.0, MASS_KG * GRAVITY_M_S2])
    torque = R_WI @ (kp[3:6] * (R_WI.T @ error_W) + kd[3:6] * (R_WI.T @ rate_error_W))
    wrench = pd_wrench(setpoint, pose, velocity, kp, kd, MASS_KG)
    np.testing.assert_allclose(wrench, np.concatenate((force, torque)), rtol=1e-12, atol=1e-15)
    step_m = 1e-6
    up, down = pose.copy(), pose.copy()
    up[6] += step_m
    down[6] -= step_m
    dfz_dz = (pd_wrench(setpoint, up, velocity, kp, kd, MASS_KG)[2]
              - pd_wrench(setpoint, down, velocity, kp, kd, MASS_KG)[2]) / (2 * step_m)
    assert dfz_dz == pytest.approx(-kp[2], rel=1e-8)


def test_haptic_mode_renders_only_the_feedforward_beyond_the_weight(magnetics):
    controller, context = make(magnetics)
    feedforward = np.array([0.3, -0.2, 0.1, 0.01, 0.0, -0.02])
    # Far from the setpoint and moving: with pd_gain 0 none of that matters.
    fix(controller, context, setpoint=np.array([0.0, 0.0, 0.018] + [0.0] * 9),
        pose=pose_vector([0.2, 0, 0], [0.01, 0.0, 0.03]), velocity=np.full(6, 0.1),
        feedforward=feedforward, pd_gain=0.0)
    commanded = controller.GetOutputPort("wrench_commanded_W").Eval(context)
    weight = np.array([0, 0, MASS_KG * 9.81, 0, 0, 0])
    np.testing.assert_allclose(commanded, weight + feedforward, atol=1e-12)
    np.testing.assert_allclose(controller.GetOutputPort("wrench_rendered_W").Eval(context),
                               feedforward, atol=1e-12)
    # Half way through the handover the PD part is halved.
    fix(controller, context, setpoint=np.array([0.0, 0.0, 0.018] + [0.0] * 9),
        pose=pose_vector([0, 0, 0], [0.0, 0.0, 0.017]), pd_gain=0.5)
    kp, _ = pd_gains(ControllerConfig(), MASS_KG, INERTIA)
    rendered = controller.GetOutputPort("wrench_rendered_W").Eval(context)
    assert rendered[2] == pytest.approx(0.5 * kp[2] * 0.001)


def test_brake_damps_toward_rest_without_a_spring(magnetics):
    controller, context = make(magnetics)
    _, kd = pd_gains(ControllerConfig(), MASS_KG, INERTIA)
    velocity = np.array([0.0, 0.0, 0.3, 0.01, -0.02, 0.0])
    fix(controller, context, setpoint=np.array([0.05, 0.0, 0.03] + [0.0] * 9),
        pose=pose_vector([0, 0, 0], [0.0, 0.0, 0.02]), velocity=velocity, pd_gain=0.0,
        brake_gain=1.0)
    rendered = controller.GetOutputPort("wrench_rendered_W").Eval(context)
    # Level instrument: I's axes are W's. No pull toward the far setpoint, only damping.
    expected = np.concatenate((-kd[0:3] * velocity[3:6], -kd[3:6] * velocity[0:3]))
    np.testing.assert_allclose(rendered, expected, atol=1e-12)


def test_currents_produce_the_commanded_wrench_within_the_limit(magnetics):
    """The allocation reads the same command as the wrench outputs: at hover the
    currents give the commanded wrench exactly; asked for far more, every coil stays
    within its limit and the shortfall is what is missing."""
    controller, context = make(magnetics)
    pose = pose_vector([0, 0, 0], [0.0, 0.0, 0.018])
    setpoint = np.array([0.0, 0.0, 0.018] + [0.0] * 9)
    fix(controller, context, setpoint=setpoint, pose=pose)
    currents = controller.GetOutputPort("coil_currents_commanded").Eval(context)
    commanded = controller.GetOutputPort("wrench_commanded_W").Eval(context)
    A = magnetics.wrench_matrix_from(pose[4:7] - DEVICE.p_WA, np.eye(3))
    np.testing.assert_allclose(A @ currents, commanded, atol=1e-9)
    assert commanded[2] == pytest.approx(MASS_KG * GRAVITY_M_S2)
    assert np.linalg.norm(controller.GetOutputPort("allocation_shortfall_W").Eval(context)) < 1e-9
    fix(controller, context, setpoint=setpoint, pose=pose,
        feedforward=np.array([0.0, 0.0, 100.0, 0.0, 0.0, 0.0]))
    currents = controller.GetOutputPort("coil_currents_commanded").Eval(context)
    assert np.max(np.abs(currents)) <= LIMIT_A
    shortfall = controller.GetOutputPort("allocation_shortfall_W").Eval(context)
    commanded = controller.GetOutputPort("wrench_commanded_W").Eval(context)
    np.testing.assert_allclose(shortfall, commanded - A @ currents, atol=1e-9)
    assert shortfall[2] > 1.0
