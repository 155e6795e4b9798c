"""The virtual coupling: spring-damper law, momentum balance, potential, ramp, clamp, the
compiled law against Drake's rotations and central differences."""

import numpy as np
import pytest
from pydrake.math import RigidTransform, RollPitchYaw, RotationMatrix
from scipy.spatial.transform import Rotation

from maglev_haptics.analysis.haptic_metrics import clamped_in_haptics_s
from maglev_haptics.systems.haptic_coupling import (
    CouplingConfig, HapticCoupling, clamp_scale, coupling_gains, coupling_wrenches,
    passivity_step, resolved_rotational_gains, spring_potential, velocity_filter_gain)
from maglev_haptics.systems.haptic_supervisor import HAPTIC

PERIOD_S = 1e-3
# What the diagram builder fills in for a device: limits and rotational gains.
RESOLVED = dict(max_force_n=4.0, max_torque_nm=0.08, rotational_stiffness=[0.03, 0.18, 0.19],
                rotational_damping=[3e-4, 2.2e-3, 2.4e-3])
# Distinct per-axis gains so a mixed-up axis shows.
GAINS = CouplingConfig(translational_stiffness=[300.0, 400.0, 500.0],
                       translational_damping=[3.0, 4.0, 5.0],
                       rotational_stiffness=[0.1, 0.2, 0.3],
                       rotational_damping=[1e-3, 2e-3, 3e-3],
                       ramp_s=0.0, max_force_n=1e3, max_torque_nm=1e3)
X_IT_OFFSET = RigidTransform(RollPitchYaw(0.2, -0.1, 0.5), [0.01, -0.02, 0.05])  # a tool tip


def pose_vector(X: RigidTransform):
    q = X.rotation().ToQuaternion()
    return np.array([q.w(), q.x(), q.y(), q.z(), *X.translation()])


def random_pose(rng, scale_m=0.05):
    return RigidTransform(RollPitchYaw(rng.uniform(-np.pi, np.pi, 3)), rng.normal(0, scale_m, 3))


def make(config=GAINS, X_IT=RigidTransform()):
    coupling = HapticCoupling(config=config, period_s=PERIOD_S, X_IT=X_IT)
    return coupling, coupling.CreateDefaultContext()


def fix(coupling, context, *, X_WI, X_WT, V_WI=np.zeros(6), V_WT=np.zeros(6), enable=1.0,
        ramp=1.0):
    coupling.GetInputPort("X_WI_measured").FixValue(context, pose_vector(X_WI))
    coupling.GetInputPort("V_WI_measured").FixValue(context, V_WI)
    coupling.GetInputPort("X_WT").FixValue(context, pose_vector(X_WT))
    coupling.GetInputPort("V_WT").FixValue(context, V_WT)
    coupling.GetInputPort("haptics_enable").FixValue(context, [enable])
    # The damper uses the low-passed velocity: start the filter settled at V_WI.
    context.SetDiscreteState(0, [ramp])
    context.SetDiscreteState(1, V_WI)


def step(system, context):
    """Apply one periodic update to ``context``."""
    update = system.EvalUniquePeriodicDiscreteUpdate(context)
    for group in range(update.num_groups()):
        context.SetDiscreteState(group, update.get_vector(group).CopyToVector())


def outputs(coupling, context):
    return (coupling.GetOutputPort("wrench_on_tool_W").Eval(context),
            coupling.GetOutputPort("wrench_feedforward_W").Eval(context),
            coupling.GetOutputPort("coupling_clamped").Eval(context)[0])


def test_zero_wrench_when_aligned_and_at_rest():
    rng = np.random.default_rng(0)
    for X_IT in (RigidTransform(), X_IT_OFFSET):
        coupling, context = make(X_IT=X_IT)
        X_WI = random_pose(rng)
        fix(coupling, context, X_WI=X_WI, X_WT=X_WI @ X_IT)
        on_tool, feedforward, clamped = outputs(coupling, context)
        np.testing.assert_allclose(on_tool, 0.0, atol=1e-14)
        np.testing.assert_allclose(feedforward, 0.0, atol=1e-14)
        assert clamped == 0.0


def test_spring_law_per_axis():
    k, _ = coupling_gains(GAINS)
    coupling, context = make()
    # Yawed by 90 deg, so the instrument's x axis is W's y: rotational gains follow I.
    X_WI = RigidTransform(RollPitchYaw(0, 0, np.pi / 2), [0.01, 0.02, 0.03])
    for axis in range(3):
        offset = np.zeros(3)
        offset[axis] = 0.002
        fix(coupling, context, X_WI=X_WI,
            X_WT=RigidTransform(X_WI.rotation(), X_WI.translation() + offset))
        expected = np.zeros(6)
        expected[axis] = -k[axis] * 0.002
        np.testing.assert_allclose(outputs(coupling, context)[0], expected, atol=1e-15)
        # The tool turned by 0.6 rad about I's axis: torque -k sin(angle) about that axis,
        # exact at a large angle.
        axis_I = np.eye(3)[axis]
        R_WT = X_WI.rotation() @ RotationMatrix(RollPitchYaw(0.6 * axis_I))
        fix(coupling, context, X_WI=X_WI, X_WT=RigidTransform(R_WT, X_WI.translation()))
        torque = outputs(coupling, context)[0][3:6]
        np.testing.assert_allclose(torque, -k[3 + axis] * np.sin(0.6) *
                                   (X_WI.rotation().matrix() @ axis_I), atol=1e-15)


def test_damping_per_axis():
    _, b = coupling_gains(GAINS)
    coupling, context = make()
    X_WI = RigidTransform(RollPitchYaw(0, 0, np.pi / 2), [0.0, 0.0, 0.03])
    R_WI = X_WI.rotation().matrix()
    for axis in range(3):
        v = np.zeros(3)
        v[axis] = 0.1
        w_I = 0.5 * np.eye(3)[axis]
        fix(coupling, context, X_WI=X_WI, X_WT=X_WI, V_WT=np.concatenate([R_WI @ w_I, v]))
        on_tool = outputs(coupling, context)[0]
        np.testing.assert_allclose(on_tool[0:3], -b[0:3] * v, atol=1e-15)
        np.testing.assert_allclose(on_tool[3:6], -b[3 + axis] * (R_WI @ w_I), atol=1e-15)


def test_equal_and_opposite_with_zero_net_moment():
    rng = np.random.default_rng(1)
    coupling, context = make(X_IT=X_IT_OFFSET)
    for _ in range(5):
        X_WI = random_pose(rng)
        X_WT = X_WI @ X_IT_OFFSET @ RigidTransform(RollPitchYaw(rng.normal(0, 0.2, 3)),
                                                    rng.normal(0, 0.01, 3))
        fix(coupling, context, X_WI=X_WI, X_WT=X_WT, V_WI=rng.normal(0, 0.1, 6),
            V_WT=rng.normal(0, 0.1, 6))
        on_tool, on_instrument, _ = outputs(coupling, context)
        np.testing.assert_allclose(on_instrument[0:3], -on_tool[0:3], atol=1e-15)
        p_WO = rng.normal(0, 0.1, 3)  # any common point
        moment_O = (on_tool[3:6] + np.cross(X_WT.translation() - p_WO, on_tool[0:3])
                    + on_instrument[3:6] + np.cross(X_WI.translation() - p_WO, on_instrument[0:3]))
        np.testing.assert_allclose(moment_O, 0.0, atol=1e-15)


def rotated_moved(X, dphi_W, dp_W):
    """X turned by the rotation vector dphi_W (rad, in W) about its origin and moved by dp_W (m)."""
    R = RotationMatrix(Rotation.from_rotvec(dphi_W).as_matrix())
    return RigidTransform(R @ X.rotation(), X.translation() + dp_W)


def test_potential_decreases_along_the_spring_wrench():
    """Finite differences: dU = -(f . dp + tau . dphi) for a small motion of the tool,
    with different gains per axis, large deflections and an offset tool."""
    rng = np.random.default_rng(2)
    k, b = coupling_gains(GAINS)
    R_IT, p_IT = X_IT_OFFSET.rotation().matrix(), X_IT_OFFSET.translation()
    h = 1e-6  # finite-difference step (rad, m)
    for _ in range(5):
        X_WI = random_pose(rng)
        X_WT = X_WI @ X_IT_OFFSET @ RigidTransform(RollPitchYaw(rng.normal(0, 0.7, 3)),
                                                    rng.normal(0, 0.01, 3))
        on_tool, _ = coupling_wrenches(pose_vector(X_WI), np.zeros(6), pose_vector(X_WT),
                                       np.zeros(6), R_IT, p_IT, k, b)

        def energy(X):
            return spring_potential(pose_vector(X_WI), pose_vector(X), R_IT, p_IT, k)

        for _ in range(4):
            d = rng.normal(size=6)  # [dp; dphi], ordered like the wrench
            dU = (energy(rotated_moved(X_WT, h * d[3:6], h * d[0:3]))
                  - energy(rotated_moved(X_WT, -h * d[3:6], -h * d[0:3]))) / (2 * h)
            assert dU == pytest.approx(-(on_tool @ d), rel=1e-6, abs=1e-9)
        step = 1e-4 * on_tool / np.linalg.norm(on_tool)
        assert energy(rotated_moved(X_WT, step[3:6], step[0:3])) < energy(X_WT)


def test_ramp_from_enable():
    config = CouplingConfig(ramp_s=0.01, **RESOLVED)
    k, _ = coupling_gains(config)
    coupling, context = make(config)
    X_WI = RigidTransform([0, 0, 0.03])
    fix(coupling, context, X_WI=X_WI, X_WT=RigidTransform([0.001, 0, 0.03]), ramp=0.0)
    forces = []
    for _ in range(15):
        forces.append(outputs(coupling, context)[1][0])
        step(coupling, context)
    # Feed-forward (on the instrument) pulls it toward the tool: +x, ramping in over 10 periods.
    expected = k[0] * 0.001 * np.minimum(np.arange(15) / 10, 1.0)
    np.testing.assert_allclose(forces, expected, rtol=1e-12, atol=1e-15)
    # Disabling cuts the user's wrench at once; the next enable ramps again from zero.
    # The tool keeps following the instrument throughout.
    coupling.GetInputPort("haptics_enable").FixValue(context, [0.0])
    assert np.all(outputs(coupling, context)[1] == 0.0)
    assert outputs(coupling, context)[0][0] == pytest.approx(-k[0] * 0.001)
    step(coupling, context)
    coupling.GetInputPort("haptics_enable").FixValue(context, [1.0])
    assert np.all(outputs(coupling, context)[1] == 0.0)


def test_clamp_preserves_direction_and_limits():
    config = CouplingConfig(ramp_s=0.0, **RESOLVED)
    coupling, context = make(config)
    rng = np.random.default_rng(3)
    for _ in range(10):
        X_WI = random_pose(rng)
        X_WT = X_WI @ RigidTransform(RollPitchYaw(rng.normal(0, 1.0, 3)),
                                     rng.normal(0, 0.02, 3))
        fix(coupling, context, X_WI=X_WI, X_WT=X_WT, V_WT=rng.normal(0, 0.5, 6))
        on_tool, feedforward, clamped = outputs(coupling, context)
        assert np.linalg.norm(feedforward[0:3]) <= 4.0 * (1 + 1e-12)
        assert np.linalg.norm(feedforward[3:6]) <= 0.08 * (1 + 1e-12)
        unclamped = coupling_wrenches(
            pose_vector(X_WI), np.zeros(6), pose_vector(X_WT),
            coupling.GetInputPort("V_WT").Eval(context), np.eye(3), np.zeros(3),
            *coupling_gains(config))
        scale = clamp_scale(unclamped[1], 4.0, 0.08)
        assert clamped == (1.0 if scale < 1.0 else 0.0)
        # One factor for all six components of both wrenches: direction kept.
        np.testing.assert_allclose(feedforward, scale * unclamped[1], rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(on_tool, scale * unclamped[0], rtol=1e-12, atol=1e-15)
    assert clamp_scale(np.array([3.0, 0, 0, 0, 0, 0.01]), 4.0, 0.08) == 1.0
    assert clamp_scale(np.array([0, 8.0, 0, 0, 0.02, 0]), 4.0, 0.08) == 0.5
    assert clamp_scale(np.array([0, 1.0, 0, 0, 0.16, 0]), 4.0, 0.08) == 0.5


def test_stiffness_by_central_differences_through_the_system():
    coupling, context = make(CouplingConfig(ramp_s=0.0, **RESOLVED))
    k, _ = coupling_gains(CouplingConfig(**RESOLVED))
    step_m = 1e-7

    def forces(dx_WI, dx_WT):
        """(f_x on the tool, f_x on the instrument) with I and T moved along x (m)."""
        fix(coupling, context, X_WI=RigidTransform([dx_WI, 0.0, 0.03]),
            X_WT=RigidTransform([0.001 + dx_WT, 0.0, 0.03]))
        step(coupling, context)
        on_tool, feedforward, _ = outputs(coupling, context)
        return np.array([on_tool[0], feedforward[0]])

    assert forces(0.0, 0.0)[0] == pytest.approx(-k[0] * 0.001)
    d_dx_WT = (forces(0.0, step_m) - forces(0.0, -step_m)) / (2 * step_m)
    d_dx_WI = (forces(step_m, 0.0) - forces(-step_m, 0.0)) / (2 * step_m)
    np.testing.assert_allclose(d_dx_WT, [-k[0], k[0]], rtol=1e-6)
    np.testing.assert_allclose(d_dx_WI, [k[0], -k[0]], rtol=1e-6)


def test_compiled_law_matches_its_matrix_form_with_drakes_rotations():
    """coupling_wrenches against the module docstring's law written with Drake's
    RigidTransform: f_T = k_t (p_WD - p_WT) + b_t (v_WD - v_WT), tau_T_I =
    -2 vee(skew(R_E G)) + b_r R_WI^T (w_WI - w_WT), the instrument's the opposite."""
    rng = np.random.default_rng(4)
    k, b = coupling_gains(GAINS)
    G = np.diag(0.5 * k[3:6].sum() - k[3:6])
    for _ in range(5):
        X_WI, X_WT = random_pose(rng), random_pose(rng)
        V_WI, V_WT = rng.normal(0, 0.1, 6), rng.normal(0, 0.1, 6)
        R_WI = X_WI.rotation().matrix()
        X_WD = X_WI @ X_IT_OFFSET
        p_ID_W = X_WD.translation() - X_WI.translation()
        v_WD = V_WI[3:6] + np.cross(V_WI[0:3], p_ID_W)
        force = k[0:3] * (X_WD.translation() - X_WT.translation()) + b[0:3] * (v_WD - V_WT[3:6])
        R_E = (X_WI.rotation().inverse() @ X_WT.rotation()
               @ X_IT_OFFSET.rotation().inverse()).matrix()
        skew = 0.5 * (R_E @ G - (R_E @ G).T)
        spring_I = -2 * np.array([skew[2, 1], skew[0, 2], skew[1, 0]])
        torque = R_WI @ (spring_I + b[3:6] * (R_WI.T @ (V_WI[0:3] - V_WT[0:3])))
        moment_arm = X_WT.translation() - X_WI.translation()
        on_tool, on_instrument = coupling_wrenches(
            pose_vector(X_WI), V_WI, pose_vector(X_WT), V_WT, X_IT_OFFSET.rotation().matrix(),
            X_IT_OFFSET.translation(), k, b)
        np.testing.assert_allclose(on_tool, np.concatenate((force, torque)), rtol=1e-12,
                                   atol=1e-15)
        np.testing.assert_allclose(
            on_instrument, np.concatenate((-force, -torque - np.cross(moment_arm, force))),
            rtol=1e-12, atol=1e-15)


def test_damper_uses_the_low_passed_velocity():
    config = CouplingConfig(ramp_s=0.0, **RESOLVED)
    k, b = coupling_gains(config)
    coupling, context = make(config)
    X_WI = RigidTransform([0, 0, 0.03])
    fix(coupling, context, X_WI=X_WI, X_WT=X_WI)
    # A step in the measured velocity reaches the damper through the first-order filter.
    coupling.GetInputPort("V_WI_measured").FixValue(context, [0, 0, 0, 0.01, 0, 0])
    alpha = velocity_filter_gain(config.velocity_filter_hz, PERIOD_S)
    assert outputs(coupling, context)[0][0] == 0.0  # no direct feedthrough
    forces = []
    for _ in range(50):
        step(coupling, context)
        forces.append(outputs(coupling, context)[0][0])
    expected = b[0] * 0.01 * (1 - (1 - alpha) ** np.arange(1, 51))
    np.testing.assert_allclose(forces, expected, rtol=1e-9)


def test_rotational_gains_follow_the_instrument_inertia():
    config = resolved_rotational_gains(CouplingConfig(), 0.125, [8e-6, 5.6e-5, 6e-5])
    k, b = coupling_gains(config)
    # Every axis has the translation's natural frequency and damping ratio.
    np.testing.assert_allclose(k[3:6] / [8e-6, 5.6e-5, 6e-5], k[0] / 0.125)
    np.testing.assert_allclose(b[3:6] / [8e-6, 5.6e-5, 6e-5], b[0] / 0.125)
    given = resolved_rotational_gains(CouplingConfig(rotational_stiffness=[1.0, 2.0, 3.0]),
                                      0.125, [8e-6, 5.6e-5, 6e-5])
    assert given.rotational_stiffness == [1.0, 2.0, 3.0]
    with pytest.raises(ValueError, match="rotational_stiffness is None"):
        HapticCoupling(config=CouplingConfig(max_force_n=1.0, max_torque_nm=0.1),
                       period_s=PERIOD_S)


def test_the_passivity_observer_leaves_a_passive_port_alone_and_scales_an_axis_in_debt():
    """Energy is counted from the wrench sent d samples ago against this sample's
    velocity; an axis in debt has its wrench scaled by 1 / (1 + debt / reference)."""
    period_s, reference = 1e-3, np.full(6, 1e-3)
    sent = np.zeros((3, 6))
    sent[0] = [2.0, 0.0, 0.0, 0.0, 0.0, 0.0]  # pushed +x three samples ago
    wrench = np.array([1.0, -1.0, 0.5, 0.01, 0.0, 0.0])
    # The instrument moves -x into the push: the user did work on the device (+2 mJ).
    moving_into = np.array([0.0, 0.0, 0.0, -1.0, 0.0, 0.0])
    out, energy, new_sent, withheld = passivity_step(
        wrench, moving_into, np.zeros(6), sent, period_s, reference)
    np.testing.assert_array_equal(out, wrench)
    assert energy[0] == pytest.approx(2e-3) and withheld == 0.0
    np.testing.assert_array_equal(new_sent[-1], wrench)
    np.testing.assert_array_equal(new_sent[0:2], sent[1:3])
    # Moving +x with the push: the device did 2 mJ of work it never received.
    out, energy, _, withheld = passivity_step(
        wrench, -moving_into, np.zeros(6), sent, period_s, reference)
    assert energy[0] == pytest.approx(-2e-3)
    assert out[0] == pytest.approx(wrench[0] / 3.0)  # 1 / (1 + 2 mJ / 1 mJ)
    np.testing.assert_array_equal(out[1:], wrench[1:])
    assert withheld == pytest.approx((wrench[0] - out[0]) * 1.0 * period_s)


def test_clamped_time_counts_only_what_the_hand_could_feel():
    """The summary's coupling_clamped_s: the samples clamped in haptic mode only (the
    coupling runs, clamped or not, before haptics engages and after it ends)."""
    t = np.arange(10) * 1e-3
    clamped = np.array([1, 1, 1, 0, 1, 1, 0, 0, 1, 1], float)
    mode = np.array([0, 0, HAPTIC, HAPTIC, HAPTIC, HAPTIC, HAPTIC, 0, 0, 0], float)
    log = {"t": t, "coupling_clamped": clamped, "haptic_mode": mode}
    assert clamped_in_haptics_s(log) == pytest.approx(3e-3)
