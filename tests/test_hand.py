"""The simulated hand: arm and grip laws, latching, the plan, the schema, and the hand
gripping real instrument models in a discrete plant."""

import math
import re
from dataclasses import dataclass, field
from typing import Union

import numpy as np
import pytest
from llvmlite import binding
from pydrake.common.yaml import yaml_load_typed
from pydrake.math import RigidTransform, RollPitchYaw
from pydrake.multibody.math import SpatialVelocity
from pydrake.multibody.parsing import Parser
from pydrake.multibody.plant import AddMultibodyPlant, MultibodyPlantConfig
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import Adder, ConstantVectorSource, MatrixGain, TrajectorySource
from pydrake.trajectories import PiecewisePolynomial

from maglev_haptics.diagrams.hand_script import (
    GripEvent, MeshcatHand, ScriptedHand, hand_plan)
from maglev_haptics.diagrams.station import generalized_force_placement
from maglev_haptics.diagrams.waypoints import Waypoint
from maglev_haptics.hardware.constants import GRAVITY_M_S2
from maglev_haptics.plant_models import PACKAGE_XML
from maglev_haptics.systems.hand import (
    HAND_BODY_NAME, HAND_MODEL_URL, HandImpedanceConfig, SimulatedHand, arm_wrench,
    explicit_step_spectral_radius, grip_update, grip_wrenches, hand_spatial_inertia,
    hand_wrenches, impedance_gains, latch_X_HI)
from maglev_haptics.systems.rotations import rigid_transform
from maglev_haptics.systems.waiting_hand_script import WaitingHandScript

CONFIG = HandImpedanceConfig()
# Distinct per-axis gains so a mixed-up axis shows.
UNEVEN = HandImpedanceConfig(
    arm_translational_stiffness=[200.0, 300.0, 400.0], arm_translational_damping=[6.0, 7.0, 8.0],
    arm_rotational_stiffness=[0.8, 1.0, 1.2], arm_rotational_damping=[0.01, 0.02, 0.03],
    grip_translational_stiffness=[1500.0, 2000.0, 2500.0],
    grip_translational_damping=[10.0, 12.0, 14.0],
    grip_rotational_stiffness=[0.4, 0.5, 0.6], grip_rotational_damping=[2e-3, 3e-3, 4e-3])
INSTRUMENTS = {  # model URL, mass (kg), inertia diagonal about I (kg*m^2)
    "two_magnet": ("package://maglev_haptics/two_magnet_instrument.sdf", 0.125,
                   [7.790118e-06, 5.589197e-05, 6.015717e-05]),
    "four_magnet": ("package://maglev_haptics/four_magnet_instrument.sdf", 0.075,
                    [2.929768e-05, 2.929768e-05, 5.736824e-05]),
}
START = np.array([0.01, -0.02, 0.025, 0.0, 0.0, 0.3])  # the instrument's hover pose in W (m, rad)
TIME_STEP_S = 1e-3


def pose_vector(X: RigidTransform) -> np.ndarray:
    q = X.rotation().ToQuaternion()
    return np.array([q.w(), q.x(), q.y(), q.z(), *X.translation()])


def random_pose(rng, scale_m=0.05) -> RigidTransform:
    return RigidTransform(RollPitchYaw(rng.uniform(-np.pi, np.pi, 3)), rng.normal(0, scale_m, 3))


def target_vector(X_WD: RigidTransform, rates=np.zeros(6)) -> np.ndarray:
    return np.concatenate((X_WD.translation(), RollPitchYaw(X_WD.rotation()).vector(), rates))


# --- the numeric core ---------------------------------------------------------

def test_arm_wrench_at_target_carries_only_the_weight():
    rng = np.random.default_rng(0)
    k, b, _, _ = impedance_gains(UNEVEN)
    for _ in range(5):
        X_WD = random_pose(rng)
        wrench = arm_wrench(pose_vector(X_WD), np.zeros(6), target_vector(X_WD), k, b, 0.25)
        np.testing.assert_allclose(wrench, [0, 0, 0.25 * GRAVITY_M_S2, 0, 0, 0], atol=1e-12)


def test_arm_wrench_pulls_toward_the_target_with_the_per_axis_gains():
    k, b, _, _ = impedance_gains(UNEVEN)
    X_WD = RigidTransform(RollPitchYaw(0.1, -0.2, 0.7), [0.01, 0.02, 0.03])
    offset = np.array([1e-3, -2e-3, 3e-3])
    X_WH = RigidTransform(X_WD.rotation(), X_WD.translation() + offset)
    V_WH = np.array([0.0, 0.0, 0.0, 0.01, 0.02, -0.01])
    wrench = arm_wrench(pose_vector(X_WH), V_WH, target_vector(X_WD), k, b, 0.0)
    np.testing.assert_allclose(wrench[0:3], -k[0:3] * offset - b[0:3] * V_WH[3:6], atol=1e-12)
    np.testing.assert_allclose(wrench[3:6], 0.0, atol=1e-12)
    # A small twist about the target's own y axis is resisted by the y gain.
    angle = 1e-4
    R_WH = X_WD.rotation() @ RollPitchYaw(0.0, angle, 0.0).ToRotationMatrix()
    wrench = arm_wrench(pose_vector(RigidTransform(R_WH, X_WD.translation())), np.zeros(6),
                        target_vector(X_WD), k, b, 0.0)
    tau_D = X_WD.rotation().matrix().T @ wrench[3:6]
    np.testing.assert_allclose(tau_D, [0.0, -k[4] * angle, 0.0], atol=1e-3 * k[4] * angle)


def test_arm_damping_acts_on_the_velocity_relative_to_the_target():
    k, b, _, _ = impedance_gains(UNEVEN)
    X_WD = RigidTransform(RollPitchYaw(0.2, 0.1, -0.4), [0.0, 0.01, 0.02])
    rpy_rates = np.array([0.3, -0.2, 0.5])
    target = target_vector(X_WD, np.concatenate(([0.05, -0.02, 0.01], rpy_rates)))
    rpy = RollPitchYaw(X_WD.rotation())
    w_WD = rpy.CalcAngularVelocityInParentFromRpyDt(rpy_rates)
    V_WH = np.concatenate((w_WD, [0.05, -0.02, 0.01]))
    wrench = arm_wrench(pose_vector(X_WD), V_WH, target, k, b, 0.0)
    np.testing.assert_allclose(wrench, 0.0, atol=1e-12)


def random_state(rng):
    return np.concatenate((pose_vector(random_pose(rng)), rng.normal(0, 1, 6)))


def test_grip_wrench_pair_has_zero_net_force_and_moment():
    rng = np.random.default_rng(1)
    _, _, k, b = impedance_gains(UNEVEN)
    for _ in range(20):
        hand, instrument = random_state(rng), random_state(rng)
        X_HI = pose_vector(random_pose(rng, 0.02))
        on_hand, on_instrument = grip_wrenches(hand[0:7], hand[7:13], instrument[0:7],
                                               instrument[7:13], X_HI, k, b)
        assert np.linalg.norm(on_hand[0:3]) > 1.0  # the test is not vacuous
        np.testing.assert_allclose(on_hand[0:3] + on_instrument[0:3], 0.0, atol=1e-9)
        moment_W = (on_hand[3:6] + np.cross(hand[4:7], on_hand[0:3])
                    + on_instrument[3:6] + np.cross(instrument[4:7], on_instrument[0:3]))
        np.testing.assert_allclose(moment_W, 0.0, atol=1e-9)


def test_latching_makes_the_grip_relaxed_even_in_rigid_motion():
    rng = np.random.default_rng(2)
    _, _, k, b = impedance_gains(UNEVEN)
    for _ in range(10):
        X_WH, X_WI = random_pose(rng), random_pose(rng)
        X_HI = latch_X_HI(pose_vector(X_WH), pose_vector(X_WI))
        np.testing.assert_allclose(pose_vector(X_WH.inverse() @ X_WI)[4:7], X_HI[4:7],
                                   atol=1e-12)
        w = rng.normal(0, 2, 3)
        v_WH = rng.normal(0, 0.1, 3)
        v_WI = v_WH + np.cross(w, X_WI.translation() - X_WH.translation())
        on_hand, on_instrument = grip_wrenches(
            pose_vector(X_WH), np.concatenate((w, v_WH)), pose_vector(X_WI),
            np.concatenate((w, v_WI)), X_HI, k, b)
        np.testing.assert_allclose(on_hand, 0.0, atol=1e-9)
        np.testing.assert_allclose(on_instrument, 0.0, atol=1e-9)


# Drake composes poses with fused multiply-adds where the CPU has AVX2 (and FMA), as
# the compiled latch does; elsewhere its products round one by one.
FUSED_COMPOSITION = all(binding.get_host_cpu_features().get(name, False)
                        for name in ("avx2", "fma"))


def test_latch_is_drakes_relative_pose():
    rng = np.random.default_rng(5)
    for _ in range(500):
        X_WH = np.concatenate((rng.normal(size=4), rng.normal(0, 0.05, 3)))
        X_WI = np.concatenate((rng.normal(size=4), rng.normal(0, 0.05, 3)))
        expected = pose_vector(rigid_transform(X_WH).InvertAndCompose(rigid_transform(X_WI)))
        if FUSED_COMPOSITION:
            np.testing.assert_array_equal(latch_X_HI(X_WH, X_WI), expected)
        else:
            np.testing.assert_allclose(latch_X_HI(X_WH, X_WI), expected, atol=1e-15)


def test_grip_update_latches_on_the_rising_edge_and_releases_on_the_falling_edge():
    rng = np.random.default_rng(3)
    X_WH, X_WI = pose_vector(random_pose(rng)), pose_vector(random_pose(rng))
    old = pose_vector(random_pose(rng))
    gripped, X_HI = grip_update(0.0, old, 1.0, X_WH, X_WI)
    assert gripped == 1.0
    np.testing.assert_allclose(X_HI, latch_X_HI(X_WH, X_WI))
    # Held: the latched pose is kept although the bodies moved.
    gripped, kept = grip_update(1.0, X_HI, 1.0, old, X_WI)
    assert gripped == 1.0 and np.array_equal(kept, X_HI)
    gripped, _ = grip_update(1.0, X_HI, 0.0, X_WH, X_WI)
    assert gripped == 0.0


def test_released_hand_puts_no_force_on_the_instrument():
    rng = np.random.default_rng(4)
    gains = impedance_gains(UNEVEN)
    hand, instrument = random_state(rng), random_state(rng)
    target = rng.normal(0, 0.1, 12)
    X_HI = pose_vector(random_pose(rng, 0.02))
    on_hand, on_instrument = hand_wrenches(hand, instrument, target, 0.0, X_HI, *gains, 0.25)
    np.testing.assert_array_equal(on_instrument, 0.0)
    np.testing.assert_allclose(on_hand, arm_wrench(hand[0:7], hand[7:13], target, gains[0],
                                                   gains[1], 0.25))


@pytest.mark.parametrize("kind", INSTRUMENTS)
def test_default_gains_are_explicitly_stable_at_the_plant_step(kind):
    _, mass, inertia = INSTRUMENTS[kind]
    assert explicit_step_spectral_radius(CONFIG, mass, inertia, TIME_STEP_S) < 1.0
    assert explicit_step_spectral_radius(CONFIG, mass, inertia, 2 * TIME_STEP_S) < 1.0
    # The check does find instability: a step four times longer is unstable.
    assert explicit_step_spectral_radius(CONFIG, mass, inertia, 4 * TIME_STEP_S) > 1.0


def test_hand_model_matches_the_config():
    plant_config = MultibodyPlantConfig(time_step=TIME_STEP_S)
    plant, _ = AddMultibodyPlant(plant_config, DiagramBuilder())
    parser = Parser(plant)
    parser.package_map().AddPackageXml(str(PACKAGE_XML))
    model = parser.AddModels(url=HAND_MODEL_URL)[0]
    plant.Finalize()
    assert plant.GetModelInstanceName(model) == "hand"
    body = plant.GetBodyByName(HAND_BODY_NAME, model)
    assert body.is_floating_base_body()
    assert body.default_mass() == CONFIG.mass_kg
    np.testing.assert_allclose(
        body.default_rotational_inertia().CopyToFullMatrix3(),
        hand_spatial_inertia(CONFIG.mass_kg).CalcRotationalInertia().CopyToFullMatrix3(),
        rtol=1e-12)
    np.testing.assert_array_equal(body.default_com(), 0.0)


# --- the hand in a discrete plant --------------------------------------------

class Bench:
    """Hand and a real instrument model in a discrete 1 ms plant, gravity on, the
    instrument's weight carried by a constant generalized force (as levitation would)."""

    def __init__(self, kind: str, script: ScriptedHand, *, V_WI0=np.zeros(6),
                 config=CONFIG):
        url, mass, _ = INSTRUMENTS[kind]
        builder = DiagramBuilder()
        plant, _ = AddMultibodyPlant(MultibodyPlantConfig(time_step=TIME_STEP_S), builder)
        parser = Parser(plant)
        parser.package_map().AddPackageXml(str(PACKAGE_XML))
        hand_model = parser.AddModels(url=HAND_MODEL_URL)[0]
        instrument_model = parser.AddModels(url=url)[0]
        plant.Finalize()
        hand_body = plant.GetBodyByName(HAND_BODY_NAME, hand_model)
        instrument_body = plant.GetBodyByName("instrument", instrument_model)
        X_W0 = RigidTransform(RollPitchYaw(START[3:6]), START[0:3])
        plant.SetDefaultFloatingBaseBodyPose(hand_body, X_W0)
        plant.SetDefaultFloatingBaseBodyPose(instrument_body, X_W0)
        weight = np.zeros(plant.num_velocities())
        plant.SetVelocitiesInArray(instrument_model, [0, 0, 0, 0, 0, mass * GRAVITY_M_S2],
                                   weight)
        lift = builder.AddSystem(ConstantVectorSource(weight))
        total = builder.AddSystem(Adder(2, plant.num_velocities()))
        builder.Connect(lift.get_output_port(), total.get_input_port(0))
        builder.Connect(total.get_output_port(), plant.get_applied_generalized_force_input_port())

        target, grip = hand_plan(script, START)
        self.target = target
        target_source = builder.AddSystem(TrajectorySource(target, output_derivative_order=1))
        grip_source = builder.AddSystem(TrajectorySource(grip))
        self.hand = builder.AddNamedSystem("hand", SimulatedHand(
            config=config, period_s=TIME_STEP_S))
        builder.Connect(plant.get_state_output_port(hand_model),
                        self.hand.GetInputPort("hand_state"))
        builder.Connect(plant.get_state_output_port(instrument_model),
                        self.hand.GetInputPort("instrument_state"))
        builder.Connect(target_source.get_output_port(), self.hand.GetInputPort("hand_target"))
        builder.Connect(grip_source.get_output_port(), self.hand.GetInputPort("grip"))
        placement = builder.AddSystem(MatrixGain(
            generalized_force_placement(plant, hand_body, instrument_body)))
        builder.Connect(self.hand.GetOutputPort("generalized_forces"),
                        placement.get_input_port())
        builder.Connect(placement.get_output_port(), total.get_input_port(1))
        self.diagram = builder.Build()
        self.plant, self.hand_body, self.instrument_body = plant, hand_body, instrument_body
        self.simulator = Simulator(self.diagram)
        self.context = self.simulator.get_mutable_context()
        self.plant_context = plant.GetMyMutableContextFromRoot(self.context)
        plant.SetFreeBodySpatialVelocity(self.plant_context, instrument_body,
                                         SpatialVelocity(w=V_WI0[0:3], v=V_WI0[3:6]))
        self.simulator.Initialize()

    def advance(self, t: float):
        self.simulator.AdvanceTo(t)

    def X_W(self, body) -> RigidTransform:
        return self.plant.EvalBodyPoseInWorld(self.plant_context, body)

    def V_W(self, body) -> np.ndarray:
        return self.plant.EvalBodySpatialVelocityInWorld(self.plant_context, body).get_coeffs()

    def gripped(self) -> float:
        hand_context = self.hand.GetMyContextFromRoot(self.context)
        return self.hand.GetOutputPort("handle_gripped").Eval(hand_context)[0]


MOVED = np.array([START[0] + 0.030, START[1], START[2] + 0.005, 0.0, 0.0, START[5] + 0.2])


def moving_script(events):
    return ScriptedHand(start_s=0.3, waypoints=[Waypoint(pose=list(MOVED), move_s=0.5,
                                                             hold_s=1.0)], events=events)


@pytest.mark.parametrize("kind", INSTRUMENTS)
def test_gripped_instrument_follows_the_hand_and_settles(kind):
    bench = Bench(kind, moving_script([GripEvent(at_s=0.1, grip=True)]))
    bench.advance(0.2)
    assert bench.gripped() == 1.0
    worst = 0.0
    for t in np.arange(0.3, 0.9, 0.01):
        bench.advance(t)
        worst = max(worst, np.linalg.norm(bench.X_W(bench.instrument_body).translation()
                                          - bench.target.value(t).ravel()[0:3]))
    assert worst < 0.005  # within a few mm during the 30 mm move
    bench.advance(1.8)
    X_WI = bench.X_W(bench.instrument_body)
    np.testing.assert_allclose(X_WI.translation(), MOVED[0:3], atol=1e-4)
    np.testing.assert_allclose(RollPitchYaw(X_WI.rotation()).vector(), MOVED[3:6], atol=1e-3)
    np.testing.assert_allclose(bench.V_W(bench.instrument_body), 0.0, atol=1e-3)
    # Held at rest, the grip carries nothing (the weight is carried elsewhere).
    hand_context = bench.hand.GetMyContextFromRoot(bench.context)
    wrench = bench.hand.GetOutputPort("wrench_on_instrument_W").Eval(hand_context)
    np.testing.assert_allclose(wrench, 0.0, atol=1e-3)


def test_an_open_hand_leaves_the_instrument_and_hovers_at_its_target():
    bench = Bench("two_magnet", moving_script([]))
    bench.advance(1.8)
    assert bench.gripped() == 0.0
    np.testing.assert_allclose(bench.X_W(bench.instrument_body).translation(), START[0:3],
                               atol=1e-9)
    np.testing.assert_allclose(bench.X_W(bench.hand_body).translation(), MOVED[0:3], atol=1e-4)


def test_released_instrument_is_no_longer_pulled():
    script = ScriptedHand(
        start_s=0.3,
        waypoints=[Waypoint(pose=list(MOVED), move_s=0.5, hold_s=1.0),
                   Waypoint(pose=list(START), move_s=0.5, hold_s=0.5)],
        events=[GripEvent(at_s=0.1, grip=True), GripEvent(at_s=1.5, grip=False)])
    bench = Bench("two_magnet", script)
    bench.advance(1.55)
    assert bench.gripped() == 0.0
    p_released = bench.X_W(bench.instrument_body).translation()
    np.testing.assert_allclose(p_released, MOVED[0:3], atol=2e-4)
    bench.advance(2.8)
    np.testing.assert_allclose(bench.X_W(bench.hand_body).translation(), START[0:3], atol=1e-4)
    np.testing.assert_allclose(bench.X_W(bench.instrument_body).translation(), p_released,
                               atol=1e-4)


@pytest.mark.parametrize("kind", INSTRUMENTS)
def test_gripped_hand_and_instrument_are_stable_with_the_default_gains(kind):
    # Gripped from t = 0 with the instrument knocked: the motion must die out.
    V_WI0 = np.array([3.0, -2.0, 4.0, 0.05, -0.03, 0.02])
    bench = Bench(kind, ScriptedHand(events=[GripEvent(at_s=0.0, grip=True)]), V_WI0=V_WI0)
    peaks = []
    for t_end in (0.25, 0.5, 0.75, 1.0):
        peak = 0.0
        for t in np.arange(t_end - 0.25, t_end, 0.005) + 0.005:
            bench.advance(t)
            peak = max(peak, np.max(np.abs(bench.V_W(bench.instrument_body))))
        peaks.append(peak)
    assert all(later < 0.5 * earlier for earlier, later in zip(peaks, peaks[1:]))
    assert peaks[-1] < 1e-3 * np.max(np.abs(V_WI0))
    p_WI = bench.X_W(bench.instrument_body).translation()
    np.testing.assert_allclose(bench.X_W(bench.hand_body).translation(), START[0:3], atol=1e-4)
    assert np.linalg.norm(p_WI - START[0:3]) < 0.005


# --- the plan ---------------------------------------------------------------

def test_hand_plan_holds_moves_and_holds():
    script = moving_script([])
    target, _ = hand_plan(script, START)
    rate = target.derivative(1)
    for t in (0.0, 0.15, 0.3):
        np.testing.assert_allclose(target.value(t).ravel(), START, atol=1e-12)
        np.testing.assert_allclose(rate.value(t).ravel(), 0.0, atol=1e-12)
    # Halfway through the minimum-jerk move: half way, at its peak rate 15/8 d / T.
    np.testing.assert_allclose(target.value(0.55).ravel(), (START + MOVED) / 2, atol=1e-9)
    np.testing.assert_allclose(rate.value(0.55).ravel(), 1.875 * (MOVED - START) / 0.5,
                               atol=1e-9)
    for t in (0.8, 1.3, 1.8, 10.0):
        np.testing.assert_allclose(target.value(t).ravel(), MOVED, atol=1e-12)
        np.testing.assert_allclose(rate.value(t).ravel(), 0.0, atol=1e-12)


def test_hand_plan_without_waypoints_holds_the_start_pose():
    target, grip = hand_plan(ScriptedHand(), START)
    for t in (0.0, 0.5, 5.0):
        np.testing.assert_allclose(target.value(t).ravel(), START)
        assert grip.value(t)[0, 0] == 0.0


def test_hand_plan_grip_steps_at_the_events():
    events = [GripEvent(at_s=2.0, grip=False), GripEvent(at_s=0.5, grip=True),
              GripEvent(at_s=3.0, grip=True), GripEvent(at_s=3.0, grip=False)]
    _, grip = hand_plan(ScriptedHand(events=events), START)
    expected = {0.0: 0.0, 0.49: 0.0, 0.5: 1.0, 1.99: 1.0, 2.0: 0.0, 2.99: 0.0, 3.0: 0.0,
                10.0: 0.0}
    for t, value in expected.items():
        assert grip.value(t)[0, 0] == value, t
    _, grip = hand_plan(ScriptedHand(events=[GripEvent(at_s=0.0, grip=True)]), START)
    assert grip.value(0.0)[0, 0] == 1.0 and grip.value(10.0)[0, 0] == 1.0


def test_a_waiting_script_holds_its_start_then_runs_the_script_at_its_own_time():
    """device-sim's hand: its start target (rates zero) and grip until ``start``, then
    exactly what a TrajectorySource of the script gives at t - the start time (rates
    zero past the script's end); a second start changes nothing."""
    target, grip = hand_plan(moving_script([GripEvent(at_s=0.1, grip=True)]), START)
    script = WaitingHandScript(target=target, grip=grip)
    context = script.CreateDefaultContext()
    references = (TrajectorySource(target, output_derivative_order=1), TrajectorySource(grip))
    reference_contexts = [source.CreateDefaultContext() for source in references]

    def outputs(t):
        context.SetTime(t)
        return [script.GetOutputPort(name).Eval(context) for name in ("hand_target", "grip")]

    def script_outputs(script_s):
        for reference_context in reference_contexts:
            reference_context.SetTime(script_s)
        return [source.get_output_port().Eval(reference_context)
                for source, reference_context in zip(references, reference_contexts)]

    for t in (0.0, 0.55, 5.0):
        held_target, held_grip = outputs(t)
        np.testing.assert_array_equal(held_target, np.r_[START, np.zeros(6)])
        assert held_grip[0] == 0.0
    started_at_s = 2.0173
    script.start(started_at_s)
    script.start(3.0)
    assert script.started_at_s == started_at_s
    for script_s in (0.0, 0.1, 0.3, 0.4179, 0.55, 0.8, 1.7, 10.0):
        t = started_at_s + script_s
        for value, expected in zip(outputs(t), script_outputs(t - started_at_s)):
            np.testing.assert_array_equal(value, expected)
    assert np.any(outputs(started_at_s + 0.55)[0][6:] != 0.0)  # moving: rates shown
    np.testing.assert_array_equal(outputs(started_at_s + 10.0)[0][6:], 0.0)


def test_starting_a_waiting_script_builds_no_trajectory(monkeypatch):
    """``start`` runs inside a device tick (the application's first command): it records
    the time and leaves the script's trajectories as they were, neither shifted, copied
    nor differentiated, and no source's trajectory replaced (~10 ms for peg_in_hole's)."""
    target, grip = hand_plan(moving_script([GripEvent(at_s=0.1, grip=True)]), START)
    script = WaitingHandScript(target=target, grip=grip)
    times = [trajectory.get_segment_times() for trajectory in (target, grip)]

    def built(*args):
        raise AssertionError("start built or replaced a trajectory")

    for name in ("shiftRight", "Clone", "derivative", "MakeDerivative"):
        monkeypatch.setattr(PiecewisePolynomial, name, built)
    monkeypatch.setattr(TrajectorySource, "UpdateTrajectory", built)
    script.start(2.0)
    monkeypatch.undo()
    assert script.started_at_s == 2.0
    assert [trajectory.get_segment_times() for trajectory in (target, grip)] == times


# --- the schema ---------------------------------------------------------------

@dataclass
class HandHolder:
    hand: Union[ScriptedHand, MeshcatHand] = field(default_factory=ScriptedHand)


def test_hand_variants_load_from_yaml_by_tag():
    loaded = yaml_load_typed(schema=HandHolder, data="""
hand: !ScriptedHand
  impedance: {mass_kg: 0.3, arm_translational_stiffness: [100, 200, 300]}
  start_s: 0.5
  waypoints: [{pose: [0.01, 0, 0.03, 0, 0, 0], move_s: 0.4, hold_s: 0.2}]
  events: [{at_s: 0.2, grip: true}]
""")
    assert isinstance(loaded.hand, ScriptedHand)
    assert loaded.hand.impedance.mass_kg == 0.3
    assert loaded.hand.impedance.arm_translational_stiffness == [100, 200, 300]
    assert loaded.hand.impedance.grip_translational_stiffness == [2000.0] * 3
    assert loaded.hand.waypoints[0].move_s == 0.4 and loaded.hand.events[0].grip
    loaded = yaml_load_typed(schema=HandHolder, data="""
hand: !MeshcatHand {filter_time_constant_s: 0.5, grip_at_start: true}
""")
    assert isinstance(loaded.hand, MeshcatHand)
    assert loaded.hand.filter_time_constant_s == 0.5 and loaded.hand.grip_at_start
    loaded.hand.validate("test: hand")


@pytest.mark.parametrize("hand, message", [
    (ScriptedHand(impedance=HandImpedanceConfig(mass_kg=-1.0)),
     "test: hand.impedance.mass_kg = -1.0: must be a finite number > 0"),
    (ScriptedHand(impedance=HandImpedanceConfig(grip_rotational_damping=[1.0, -1.0, 1.0])),
     "test: hand.impedance.grip_rotational_damping = [1.0, -1.0, 1.0]: must be 3 finite"),
    (ScriptedHand(impedance=HandImpedanceConfig(arm_rotational_stiffness=[1.0])),
     "test: hand.impedance.arm_rotational_stiffness = [1.0]: must be 3"),
    (ScriptedHand(start_s=float("nan")), "test: hand.start_s = nan: must be a finite"),
    (ScriptedHand(waypoints=[Waypoint(), Waypoint(pose=[0.0] * 5)]),
     "test: hand.waypoints[1].pose = [0.0, 0.0, 0.0, 0.0, 0.0]: must be 6 finite numbers"),
    (ScriptedHand(waypoints=[Waypoint(move_s=0.0)]),
     "test: hand.waypoints[0].move_s = 0.0: must be a finite number > 0"),
    (ScriptedHand(waypoints=[Waypoint(hold_s=-1.0)]),
     "test: hand.waypoints[0].hold_s = -1.0: must be a finite number >= 0"),
    (ScriptedHand(events=[GripEvent(at_s=-0.1)]),
     "test: hand.events[0].at_s = -0.1: must be a finite number >= 0"),
    (MeshcatHand(filter_time_constant_s=0.0),
     "test: hand.filter_time_constant_s = 0.0: must be a finite number > 0"),
    (MeshcatHand(input_rate_hz=float("inf")),
     "test: hand.input_rate_hz = inf: must be a finite number > 0"),
])
def test_validate_hand_names_the_field_the_value_and_what_is_allowed(hand, message):
    with pytest.raises(ValueError) as error:
        hand.validate("test: hand")
    assert str(error.value).startswith(message)


# A hand with one ">= 0" bound at value v, by the field its message names.
ZERO_EDGES = {
    "hand.start_s": lambda v: ScriptedHand(start_s=v),
    "hand.waypoints[0].hold_s": lambda v: ScriptedHand(waypoints=[Waypoint(hold_s=v)]),
    "hand.events[0].at_s": lambda v: ScriptedHand(events=[GripEvent(at_s=v)]),
    "hand.impedance.arm_translational_damping": lambda v: ScriptedHand(
        impedance=HandImpedanceConfig(arm_translational_damping=[v] * 3)),
}


def test_validate_hand_accepts_the_defaults_and_each_bound_up_to_its_edge():
    for hand in (ScriptedHand(), moving_script([GripEvent()]), MeshcatHand()):
        assert hand.validate("test: hand") is None
    for field_name, hand_with in ZERO_EDGES.items():
        assert hand_with(0.0).validate("test: hand") is None  # the edge itself is allowed
        with pytest.raises(ValueError, match=re.escape(f"test: {field_name} = ")):
            hand_with(math.nextafter(0.0, -1.0)).validate("test: hand")  # one step below
