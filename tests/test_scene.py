"""The virtual scene: models built from the config, ports, contact sensing, and the
physics of the three scenes with the tool held by the virtual coupling."""

import re
from dataclasses import dataclass, field

import numpy as np
import pytest
from pydrake.common.eigen_geometry import Quaternion
from pydrake.common.yaml import yaml_load_typed
from pydrake.geometry import Box, HalfSpace, Role, TriangleSurfaceMesh, VolumeMesh
from pydrake.math import RigidTransform, RollPitchYaw
from pydrake.multibody.parsing import Parser
from pydrake.multibody.plant import AddMultibodyPlant, MultibodyPlantConfig
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import Adder, ConstantVectorSource, Demultiplexer, VectorLogSink

from maglev_haptics.diagrams.scene import (
    ContactProperties, HangingBall, PaddleBall, PegInHole, SceneConfig, hanging_drop_m,
    table_top_z)
from maglev_haptics.diagrams.scene_builder import (
    AddScene, start_overlap, wrench_to_generalized_force)
from maglev_haptics.hardware.constants import GRAVITY_M_S2
from maglev_haptics.plant_models.scene_geometry import (
    box_inertia, box_overlaps_box, hole_block_boxes, sphere_overlaps_box)
from maglev_haptics.plant_models.scene_sdf import TABLE_RGBA, TABLE_SIZE_M, TABLE_SLAB_M
from maglev_haptics.systems.haptic_coupling import CouplingConfig, HapticCoupling
from maglev_haptics.systems.tool_contact import ToolContactSensor, wrench_about_point

STEP_S = 1e-3
HOVER = RigidTransform([0.0, 0.0, 0.025])  # X_WI of an instrument hovering 25 mm up (m)


def pose_vector(X: RigidTransform):
    q = X.rotation().ToQuaternion()
    return np.array([q.w(), q.x(), q.y(), q.z(), *X.translation()])


def tool_centre_pose(X_WT, scene):
    """X_WA: the tool's centre frame, at ``tool_offset_m`` in T with T's axes, for a
    logged pose vector X_WT [qw, qx, qy, qz, x, y, z] (m)."""
    q = np.asarray(X_WT[0:4])
    return (RigidTransform(Quaternion(q / np.linalg.norm(q)), X_WT[4:7])
            @ RigidTransform(scene.tool_offset_m))


class HeldScene:
    """A scene whose tool is held by the virtual coupling to a fixed instrument pose,
    plus a constant extra wrench on the tool (``force`` in W, N, and ``torque`` in W
    about T, N*m); logs the tool, the ball and the contact wrench every step. The
    coupling's gains are the scene's design values (5 N*s/m; 0.25 N*m/rad,
    3.1e-3 N*m*s/rad); ``k_t = 0`` leaves only its damping and its rotational spring,
    so the extra wrench is what presses the tool."""

    def __init__(self, scene, X_WI, *, force=(0.0, 0.0, 0.0), torque=(0.0, 0.0, 0.0),
                 k_t=400.0):
        builder = DiagramBuilder()
        self.parts = AddScene(builder, scene=scene, time_step_s=STEP_S, X_WI_start=X_WI)
        coupling = builder.AddNamedSystem("coupling", HapticCoupling(
            config=CouplingConfig(translational_stiffness=[k_t] * 3,
                                  translational_damping=[5.0] * 3,
                                  rotational_stiffness=[0.25] * 3,
                                  rotational_damping=[3.125e-3] * 3,
                                  ramp_s=0.0, max_force_n=100.0, max_torque_nm=100.0),
            period_s=STEP_S, X_IT=self.parts.X_IT))
        push = builder.AddSystem(ConstantVectorSource(np.concatenate((force, torque))))
        total = builder.AddSystem(Adder(2, 6))
        builder.Connect(coupling.GetOutputPort("wrench_on_tool_W"), total.get_input_port(0))
        builder.Connect(push.get_output_port(), total.get_input_port(1))
        builder.Connect(total.get_output_port(), self.parts.wrench_on_tool_input)
        builder.Connect(self.parts.X_WT_output, coupling.GetInputPort("X_WT"))
        builder.Connect(self.parts.V_WT_output, coupling.GetInputPort("V_WT"))
        sources = {"X_WT": self.parts.X_WT_output, "contact": self.parts.contact_wrench_output,
                   "in_contact": self.parts.in_contact_output}
        if self.parts.ball_body is not None:
            ball_state = builder.AddSystem(Demultiplexer([7, 6]))
            builder.Connect(self.parts.plant.get_state_output_port(
                self.parts.ball_body.model_instance()), ball_state.get_input_port())
            sources["X_WB"] = ball_state.get_output_port(0)
        self._logs = {}
        for name, port in sources.items():
            self._logs[name] = builder.AddSystem(VectorLogSink(port.size(), STEP_S))
            builder.Connect(port, self._logs[name].get_input_port())
        self.diagram = builder.Build()
        self.simulator = Simulator(self.diagram)
        context = self.simulator.get_mutable_context()
        coupling.GetInputPort("X_WI_measured").FixValue(
            coupling.GetMyMutableContextFromRoot(context), pose_vector(X_WI))
        coupling.GetInputPort("V_WI_measured").FixValue(
            coupling.GetMyMutableContextFromRoot(context), np.zeros(6))
        coupling.GetInputPort("haptics_enable").FixValue(
            coupling.GetMyMutableContextFromRoot(context), [1.0])

    def run(self, duration_s):
        self.simulator.AdvanceTo(duration_s)
        return self

    def log(self, name):
        """(times (n,), samples (n, size))."""
        log = self._logs[name].FindLog(self.simulator.get_context())
        return log.sample_times(), log.data().T


# --- numeric cores ----------------------------------------------------------------------

def test_wrench_about_point_moves_forces_and_couples_to_the_origin():
    forces = np.array([[0.0, 0.0, 2.0], [1.0, 0.0, 0.0]])
    couples = np.array([[0.0, 0.0, 0.1], [0.0, 0.0, 0.0]])
    points = np.array([[0.01, 0.0, -0.02], [0.0, 0.0, 0.0]])
    p_WO = np.array([0.0, 0.0, -0.02])
    wrench = wrench_about_point(forces, couples, points, p_WO)
    # (0.01, 0, 0) x (0, 0, 2) = (0, -0.02, 0); (0, 0, 0.02) x (1, 0, 0) = (0, 0.02, 0)
    np.testing.assert_allclose(wrench, [1.0, 0.0, 2.0, 0.0, 0.0, 0.1], atol=1e-15)
    none = np.zeros((0, 3))
    np.testing.assert_array_equal(wrench_about_point(none, none, none, p_WO), np.zeros(6))


def test_wrench_maps_to_the_free_body_generalized_forces():
    D = wrench_to_generalized_force(velocity_start=6, num_velocities=12)
    tau = D @ np.array([1.0, 2.0, 3.0, 4.0, 5.0, 6.0])
    np.testing.assert_array_equal(tau, [0, 0, 0, 0, 0, 0, 4, 5, 6, 1, 2, 3])


def test_the_four_walls_fill_the_plate_except_the_hole():
    scene = PegInHole(hole_center_m=[0.01, -0.02, -0.015])
    boxes = hole_block_boxes(scene.block_size_m, scene.hole_size_m, scene.hole_center_m)
    assert len(boxes) == 4
    bx, by = scene.block_size_m
    hx, hy, depth = scene.hole_size_m
    cx, cy, top = scene.hole_center_m
    # Points in the plate's outer box, as thick as the hole is deep (m).
    points = np.random.default_rng(0).uniform(
        [cx - bx / 2, cy - by / 2, top - depth], [cx + bx / 2, cy + by / 2, top], (20000, 3))
    inside = np.zeros(len(points), dtype=int)
    for _, centre, size in boxes:
        inside += np.all(np.abs(points - centre) < size / 2, axis=1)
    in_hole = (np.abs(points[:, 0] - cx) < hx / 2) & (np.abs(points[:, 1] - cy) < hy / 2)
    np.testing.assert_array_equal(inside, np.where(in_hole, 0, 1))
    # The hole goes through the plate: its floor is the table's top.
    assert table_top_z(scene) == pytest.approx(top - depth)


# --- models and ports ---------------------------------------------------------------------

def build(scene, X_WI=HOVER):
    builder = DiagramBuilder()
    parts = AddScene(builder, scene=scene, time_step_s=STEP_S, X_WI_start=X_WI)
    return builder, parts


def table_geometry(parts, role):
    """(shape, X_WG, properties of ``role``) of the table's geometry on the world body."""
    inspector = parts.scene_graph.model_inspector()
    (geometry,) = [g for g in inspector.GetGeometries(inspector.world_frame_id(), role)
                   if inspector.GetName(g) == "table"]
    properties = (inspector.GetProximityProperties(geometry) if role == Role.kProximity
                  else inspector.GetIllustrationProperties(geometry))
    return inspector.GetShape(geometry), inspector.GetPoseInFrame(geometry), properties


def proximity_shapes(parts, model_name):
    """{geometry name: (shape, X_WG, ProximityProperties, GeometryId)} of a model's
    collision geometry."""
    plant, inspector = parts.plant, parts.scene_graph.model_inspector()
    context = plant.CreateDefaultContext()
    shapes = {}
    for body_index in plant.GetBodyIndices(plant.GetModelInstanceByName(model_name)):
        body = plant.get_body(body_index)
        X_WB = plant.EvalBodyPoseInWorld(context, body)
        for geometry in plant.GetCollisionGeometriesForBody(body):
            shapes[inspector.GetName(geometry).split("::")[-1]] = (
                inspector.GetShape(geometry), X_WB @ inspector.GetPoseInFrame(geometry),
                inspector.GetProximityProperties(geometry), geometry)
    return shapes


def test_peg_scene_models_follow_the_config():
    scene = PegInHole(contact=ContactProperties(hydroelastic_modulus_pa=2e6, friction=0.3))
    _, parts = build(scene)
    inspector = parts.scene_graph.model_inspector()
    peg = proximity_shapes(parts, "tool")["peg"]
    assert isinstance(peg[0], Box)
    np.testing.assert_allclose(peg[0].size(), scene.peg_size_m)
    # The peg hangs at tool_offset_m below the grip, level.
    assert peg[1].IsNearlyEqualTo(HOVER @ RigidTransform(scene.tool_offset_m), 1e-12)
    assert not peg[2].HasProperty("hydroelastic", "hydroelastic_modulus")  # rigid
    assert isinstance(inspector.maybe_get_hydroelastic_mesh(peg[3]), TriangleSurfaceMesh)
    block = proximity_shapes(parts, "block")
    assert sorted(block) == ["wall_back", "wall_front", "wall_left", "wall_right"]
    for name, centre, size in hole_block_boxes(scene.block_size_m, scene.hole_size_m,
                                               scene.hole_center_m):
        shape, X_WG, props, geometry = block[name]
        np.testing.assert_allclose(shape.size(), size)
        np.testing.assert_allclose(X_WG.translation(), centre, atol=1e-12)
        assert isinstance(inspector.maybe_get_hydroelastic_mesh(geometry), VolumeMesh)
        assert props.GetProperty("hydroelastic", "hydroelastic_modulus") == 2e6
        assert props.GetProperty("material", "coulomb_friction").static_friction() == 0.3
        assert props.GetProperty("material", "coulomb_friction").dynamic_friction() == 0.3
    # The table: a compliant half-space whose top is the hole's floor, drawn as a box.
    floor_z = scene.hole_center_m[2] - scene.hole_size_m[2]
    table, X_WG, props = table_geometry(parts, Role.kProximity)
    assert isinstance(table, HalfSpace)
    np.testing.assert_allclose(X_WG.rotation().col(2), [0.0, 0.0, 1.0], atol=1e-12)  # its normal
    np.testing.assert_allclose(X_WG.translation(), [0.0, 0.0, floor_z], atol=1e-12)
    assert props.GetProperty("hydroelastic", "hydroelastic_modulus") == 2e6
    assert props.GetProperty("hydroelastic", "slab_thickness") == TABLE_SLAB_M
    assert props.GetProperty("material", "coulomb_friction").static_friction() == 0.3
    assert props.GetProperty("material", "hunt_crossley_dissipation") == pytest.approx(
        scene.contact.hunt_crossley_dissipation_s_per_m)
    box, X_WG, props = table_geometry(parts, Role.kIllustration)
    np.testing.assert_allclose(box.size(), TABLE_SIZE_M)
    assert X_WG.translation()[2] + box.size()[2] / 2 == pytest.approx(floor_z)
    np.testing.assert_allclose(props.GetProperty("phong", "diffuse").rgba, TABLE_RGBA)

    # About T (the grip) Drake holds the spatial inertia; the centre of mass is the
    # peg's centre, and the floored moments are about it.
    M_TTo_T = parts.tool_body.default_spatial_inertia()
    assert M_TTo_T.get_mass() == pytest.approx(scene.peg_mass_kg)
    np.testing.assert_allclose(M_TTo_T.get_com(), scene.tool_offset_m, atol=1e-12)
    I_TCm_T = M_TTo_T.Shift(M_TTo_T.get_com()).CalcRotationalInertia().CopyToFullMatrix3()
    moments = np.diag(I_TCm_T)
    np.testing.assert_allclose(
        moments, np.maximum(box_inertia(scene.peg_mass_kg, scene.peg_size_m),
                            scene.min_inertia_kg_m2), rtol=1e-6)
    np.testing.assert_allclose(I_TCm_T - np.diag(moments), 0.0, atol=1e-15)  # principal axes
    assert min(moments) >= 5e-6


def test_every_visual_has_its_own_colour():
    for scene in (PegInHole(), HangingBall(), PaddleBall()):
        _, parts = build(scene)
        inspector = parts.scene_graph.model_inspector()
        colours = [tuple(inspector.GetIllustrationProperties(g).GetProperty("phong", "diffuse")
                         .rgba) for g in inspector.GetAllGeometryIds(Role.kIllustration)]
        block_walls = 3 if isinstance(scene, PegInHole) else 0  # the 4 walls share a colour
        assert len(set(colours)) == len(colours) - block_walls


def test_default_poses_and_ports():
    X_WI = RigidTransform(RollPitchYaw(0.1, -0.2, 0.3), [0.01, 0.02, 0.06])
    # The second hanging ball's anchor sits off the grip, so its spring's end shows.
    for scene in (PegInHole(), HangingBall(), HangingBall(tool_offset_m=[0.004, -0.003, -0.010]),
                  PaddleBall()):
        builder, parts = build(scene, X_WI)
        assert parts.wrench_on_tool_input.size() == 6
        assert parts.X_WT_output.size() == 7 and parts.V_WT_output.size() == 6
        assert parts.contact_wrench_output.size() == 6 and parts.in_contact_output.size() == 1
        diagram = builder.Build()
        context = diagram.CreateDefaultContext()
        # T is I when relaxed: the tool starts at X_WI itself, its shape at tool_offset_m in T.
        assert parts.X_IT.IsExactlyEqualTo(RigidTransform())
        np.testing.assert_allclose(
            np.abs(parts.X_WT_output.Eval(parts.X_WT_output.get_system()
                                          .GetMyContextFromRoot(context))),
            np.abs(pose_vector(X_WI)), atol=1e-12)
        X_WA = X_WI @ RigidTransform(scene.tool_offset_m)
        (shape_pose,) = [X_WG for _, X_WG, _, _ in proximity_shapes(parts, "tool").values()]
        assert shape_pose.IsNearlyEqualTo(X_WA, 1e-12)
        plant_context = parts.plant.GetMyContextFromRoot(context)
        if isinstance(scene, HangingBall):
            p_WB = parts.plant.EvalBodyPoseInWorld(plant_context, parts.ball_body).translation()
            np.testing.assert_allclose(p_WB, X_WA.translation() - [0, 0, hanging_drop_m(scene)],
                                       atol=1e-12)
        elif isinstance(scene, PaddleBall):
            p_WB = parts.plant.EvalBodyPoseInWorld(plant_context, parts.ball_body).translation()
            np.testing.assert_allclose(p_WB, scene.ball_start_m)
        else:
            assert parts.ball_body is None


def test_scene_plant_is_its_own_plant_and_the_tool_has_no_weight():
    builder = DiagramBuilder()
    station_plant, _ = AddMultibodyPlant(MultibodyPlantConfig(time_step=STEP_S), builder)
    Parser(station_plant).AddModelsFromString(
        '<sdf version="1.9"><model name="instrument"><link name="instrument"/></model></sdf>',
        "sdf")
    station_plant.Finalize()
    parts = AddScene(builder, scene=HangingBall(), time_step_s=STEP_S, X_WI_start=HOVER)
    assert parts.plant is not station_plant
    assert parts.plant.get_name() == "scene_plant"
    assert parts.scene_graph.get_name() == "scene_graph"
    assert not parts.plant.HasModelInstanceNamed("instrument")
    assert parts.plant.time_step() == STEP_S
    assert not parts.plant.is_gravity_enabled(parts.tool_body.model_instance())
    assert parts.plant.is_gravity_enabled(parts.ball_body.model_instance())

    # Unheld and undriven, the weightless peg stays exactly where it started.
    builder, parts = build(PegInHole(), RigidTransform([0.0, 0.0, 0.06]))
    diagram = builder.Build()
    simulator = Simulator(diagram)
    parts.wrench_on_tool_input.FixValue(
        parts.wrench_on_tool_input.get_system().GetMyMutableContextFromRoot(
            simulator.get_mutable_context()), np.zeros(6))
    simulator.AdvanceTo(0.1)
    context = parts.X_WT_output.get_system().GetMyContextFromRoot(simulator.get_context())
    np.testing.assert_allclose(parts.X_WT_output.Eval(context), [1, 0, 0, 0, 0, 0, 0.06],
                               atol=1e-12)


def test_the_wrench_input_pushes_and_turns_the_tool_in_W():
    """One step from rest of the free paddle, tilted so that W and T differ, under a
    wrench about T (the grip, 30 mm above the paddle's centre of mass Cm): its centre
    of mass speeds up by h f / m, it turns by h I_Cm^-1 (tau + p_CmT x f) and T moves
    with v_WCm + w x p_CmT."""
    scene = PaddleBall(ball_start_m=[0.3, 0.0, 0.0], table_z_m=None)  # the ball falls away
    X_WI = RigidTransform(RollPitchYaw(0.1, -0.2, 0.3), [0.0, 0.0, 0.06])
    builder, parts = build(scene, X_WI)
    diagram = builder.Build()
    simulator = Simulator(diagram)
    wrench = np.array([0.01, -0.02, 0.03, 2e-4, -1e-4, 3e-4])  # N, N*m
    parts.wrench_on_tool_input.FixValue(
        parts.wrench_on_tool_input.get_system().GetMyMutableContextFromRoot(
            simulator.get_mutable_context()), wrench)
    simulator.AdvanceTo(STEP_S)
    context = parts.V_WT_output.get_system().GetMyContextFromRoot(simulator.get_context())
    V_WT = parts.V_WT_output.Eval(context)
    R_WT = X_WI.rotation().matrix()
    moments = np.maximum(box_inertia(scene.paddle_mass_kg, scene.paddle_size_m),
                         scene.min_inertia_kg_m2)  # about Cm, along T's axes (kg*m^2)
    I_Cm_W = R_WT @ np.diag(moments) @ R_WT.T
    p_CmT_W = -R_WT @ scene.tool_offset_m
    w_WT = STEP_S * np.linalg.solve(I_Cm_W, wrench[3:6] + np.cross(p_CmT_W, wrench[0:3]))
    v_WCm = STEP_S * wrench[0:3] / scene.paddle_mass_kg
    np.testing.assert_allclose(V_WT[0:3], w_WT, rtol=1e-9)
    np.testing.assert_allclose(V_WT[3:6], v_WCm + np.cross(w_WT, p_CmT_W), rtol=1e-9)


def test_scene_contact_stiffness_by_central_differences():
    builder = DiagramBuilder()
    # The peg starts level, 0.5 mm above the floor. (From 1 mm, the 2 N push lands its
    # bottom face exactly on the table's plane after 4 steps of 0.1, 0.2, 0.3, 0.4 mm, and
    # Drake 1.51's clipping of a rigid mesh by a half-space fails a check when two
    # vertices of one triangle lie exactly on the plane.)
    parts = AddScene(builder, scene=PegInHole(), time_step_s=STEP_S,
                     X_WI_start=peg_in_hole_at(0.0, -0.0245), use_sampled_output_ports=False)
    builder.ExportInput(parts.wrench_on_tool_input, "wrench_on_tool_W")
    builder.ExportOutput(parts.contact_wrench_output, "contact_wrench")
    diagram = builder.Build()
    simulator = Simulator(diagram)
    context = simulator.get_mutable_context()
    push = [0.0, 0.0, -2.0, 0.0, 0.0, 0.0]
    diagram.GetInputPort("wrench_on_tool_W").FixValue(context, push)
    simulator.AdvanceTo(0.1)
    plant_context = parts.plant.GetMyMutableContextFromRoot(context)
    x = parts.plant.GetPositionsAndVelocities(plant_context)
    assert diagram.GetOutputPort("contact_wrench").Eval(context)[2] == pytest.approx(2.0, rel=0.02)

    def f_z(dz_m):
        """The contact force's z (N) with the peg moved dz_m (m) along z (entry 6 of [q; p])."""
        moved = x.copy()
        moved[6] += dz_m
        parts.plant.SetPositionsAndVelocities(plant_context, moved)
        return diagram.GetOutputPort("contact_wrench").Eval(context)[2]

    step_m = 1e-7
    assert (f_z(step_m) - f_z(-step_m)) / (2 * step_m) < -1e3  # deeper pushes back harder (N/m)


# --- contact sensing ------------------------------------------------------------------------

def test_point_contact_wrench_is_on_the_tool_and_about_its_origin():
    """A ball resting on a static box under point contact: the sensor sees its weight
    upward at the contact point, moved to an origin 2 cm off to the side."""
    builder = DiagramBuilder()
    plant, _ = AddMultibodyPlant(MultibodyPlantConfig(time_step=STEP_S, contact_model="point"),
                                 builder)
    proximity = ("<drake:proximity_properties><drake:point_contact_stiffness>1000"
                 "</drake:point_contact_stiffness><drake:hunt_crossley_dissipation>20"
                 "</drake:hunt_crossley_dissipation></drake:proximity_properties>")
    Parser(plant).AddModelsFromString(
        '<sdf version="1.9" xmlns:drake="http://drake.mit.edu"><model name="ball">'
        '<pose>0 0 0.0101 0 0 0</pose><link name="ball"><inertial><mass>0.05</mass>'
        '<inertia><ixx>2e-6</ixx><iyy>2e-6</iyy><izz>2e-6</izz></inertia></inertial>'
        f'<collision name="c"><geometry><sphere><radius>0.01</radius></sphere></geometry>'
        f'{proximity}</collision></link></model></sdf>', "sdf")
    Parser(plant).AddModelsFromString(
        '<sdf version="1.9" xmlns:drake="http://drake.mit.edu"><model name="floor">'
        '<static>true</static><link name="floor"><pose>0 0 -0.005 0 0 0</pose>'
        f'<collision name="c"><geometry><box><size>0.1 0.1 0.01</size></box></geometry>'
        f'{proximity}</collision></link></model></sdf>', "sdf")
    plant.Finalize()
    ball = plant.GetBodyByName("ball")
    sensor = builder.AddSystem(ToolContactSensor(plant, ball))
    builder.Connect(plant.get_contact_results_output_port(),
                    sensor.GetInputPort("contact_results"))
    diagram = builder.Build()
    simulator = Simulator(diagram)
    sensor_context = sensor.GetMyMutableContextFromRoot(simulator.get_mutable_context())
    sensor.GetInputPort("X_WT").FixValue(sensor_context, [1, 0, 0, 0, 0.02, 0, 0])
    simulator.AdvanceTo(0.5)
    weight = 0.05 * GRAVITY_M_S2
    wrench = sensor.GetOutputPort("wrench_on_tool_W").Eval(sensor_context)
    p_WC = plant.get_contact_results_output_port().Eval(
        plant.GetMyContextFromRoot(simulator.get_context())).point_pair_contact_info(0) \
        .contact_point()
    # tau = (p_WC - p_WO) x (0, 0, w): about y, -(x_C - 0.02) w.
    np.testing.assert_allclose(wrench, [0, 0, weight, 0, -(p_WC[0] - 0.02) * weight, 0],
                               atol=1e-4 * weight)
    assert wrench[4] == pytest.approx(0.02 * weight, rel=1e-3)
    assert sensor.GetOutputPort("in_contact").Eval(sensor_context)[0] == 1.0


# --- physics --------------------------------------------------------------------------------

def peg_in_hole_at(x_m, z_peg_bottom_m, scene=None):
    """X_WI that puts the peg's centre at x and its bottom at z (m), level."""
    scene = scene or PegInHole()
    return RigidTransform([x_m, 0.0, z_peg_bottom_m + scene.peg_size_m[2] / 2
                           - scene.tool_offset_m[2]])


def test_peg_pressed_into_the_hole_feels_the_push():
    scene = PegInHole()
    floor_z = table_top_z(scene)
    run = HeldScene(scene, peg_in_hole_at(0.0, floor_z + 0.002), force=(0.0, 0.0, -2.0),
                    k_t=0.0).run(0.5)
    _, contact = run.log("contact")
    _, X_WT = run.log("X_WT")
    # Pushed down at the grip, straight above the peg's centre: the floor pushes back
    # with the same force.
    np.testing.assert_allclose(contact[-100:, 0:3], np.tile([0.0, 0.0, 2.0], (100, 1)),
                               atol=0.02 * 2.0)
    assert np.ptp(contact[-100:, 2]) < 1e-3
    p_WA = tool_centre_pose(X_WT[-1], scene).translation()
    hx, hy, _ = scene.hole_size_m
    assert abs(p_WA[0]) < (hx - scene.peg_size_m[0]) / 2
    assert abs(p_WA[1]) < (hy - scene.peg_size_m[1]) / 2
    bottom = p_WA[2] - scene.peg_size_m[2] / 2
    assert floor_z - 2e-4 < bottom < floor_z  # pressed in by a fraction of a millimetre
    assert run.log("in_contact")[1][-1, 0] == 1.0
    # Only the table touches it, in few polygons: ~16 cost ~80 us a plant step, where
    # the 43 the peg made on a compliant box floor cost ~230 us.
    plant = run.parts.plant
    results = plant.get_contact_results_output_port().Eval(
        plant.GetMyContextFromRoot(run.simulator.get_context()))
    assert results.num_hydroelastic_contacts() == 1
    assert results.hydroelastic_contact_info(0).contact_surface().num_faces() <= 20


def test_peg_sliding_on_the_floor_feels_coulomb_friction():
    scene = PegInHole()
    floor_z = table_top_z(scene)
    left = -(scene.hole_size_m[0] - scene.peg_size_m[0]) / 2 + 0.0005
    # 0.45 N sideways against 0.15 * 2 N of friction; the coupling's 5 N*s/m damping
    # holds the slide at 0.03 m/s, which crosses the 29 mm of free floor in ~1 s.
    # Pushed at the grip, 45 mm above the floor, the peg leans ~0.5 deg.
    run = HeldScene(scene, peg_in_hole_at(left, floor_z + 0.001), force=(0.45, 0.0, -2.0),
                    k_t=0.0).run(0.4)
    t, contact = run.log("contact")
    _, X_WT = run.log("X_WT")
    sliding = t > 0.1
    x_A = [tool_centre_pose(X, scene).translation()[0] for X in X_WT]  # the peg's centre (m)
    speed = np.diff(x_A) / STEP_S
    assert np.all(speed[sliding[1:]] > 0.02)
    ratio = -contact[sliding, 0] / contact[sliding, 2]
    np.testing.assert_allclose(ratio, scene.contact.friction, rtol=0.2)
    np.testing.assert_allclose(contact[sliding, 2], 2.0, rtol=0.02)


def test_peg_pushed_against_the_side_wall_feels_it_in_x():
    scene = PegInHole()
    floor_z = table_top_z(scene)
    # The push acts at the peg's centre A: f at T with the couple p_TA x f (N*m; the peg
    # starts level, so p_TA in W is tool_offset_m). At the grip alone f would add
    # 0.025 N*m about y about A and tip the peg ~7 deg over the wall.
    force = np.array([1.0, 0.0, -1.0])  # N
    run = HeldScene(scene, peg_in_hole_at(0.010, floor_z + 0.001), force=force,
                    torque=np.cross(scene.tool_offset_m, force), k_t=0.0).run(0.4)
    _, contact = run.log("contact")
    _, X_WT = run.log("X_WT")
    np.testing.assert_allclose(contact[-1, 0:3], [-1.0, 0.0, 1.0], atol=0.02)
    # The peg's right face lies on the wall from its bottom edge up to the wall's top.
    X_WA = tool_centre_pose(X_WT[-1], scene)
    half_x, _, half_z = np.asarray(scene.peg_size_m) / 2
    wall_x = scene.hole_size_m[0] / 2
    for z_A in (-half_z, -half_z + scene.hole_size_m[2]):
        assert (X_WA @ [half_x, 0.0, z_A])[0] == pytest.approx(wall_x, abs=5e-4)


# The anchor at the grip, and 10 mm below it: the spring hangs from the anchor's centre.
@pytest.mark.parametrize("tool_offset_m", [[0.0, 0.0, 0.0], [0.0, 0.0, -0.010]])
def test_hanging_ball_hangs_at_the_static_deflection(tool_offset_m):
    scene = HangingBall(tool_offset_m=tool_offset_m)
    X_WI = RigidTransform([0.01, -0.02, 0.030])
    run = HeldScene(scene, X_WI).run(1.0)
    _, X_WT = run.log("X_WT")
    _, X_WB = run.log("X_WB")
    weight = scene.ball_mass_kg * GRAVITY_M_S2
    # The coupling holds the weightless anchor against the ball's weight: 0.25 mm of sag.
    np.testing.assert_allclose(X_WT[-1, 4:7], X_WI.translation() - [0, 0, weight / 400.0],
                               atol=2e-5)
    p_WA = tool_centre_pose(X_WT[-1], scene).translation()
    deflection = p_WA[2] - X_WB[-1, 6] - scene.spring_rest_length_m
    assert deflection == pytest.approx(weight / scene.spring_stiffness_n_per_m, rel=0.02)
    np.testing.assert_allclose(X_WB[-1, 4:6], p_WA[0:2], atol=1e-6)
    assert np.all(run.log("in_contact")[1] == 0.0)


def first_contact(run):
    """Step indices (first touching, first free again) of the ball's first contact."""
    _, touching = run.log("in_contact")
    start = int(np.argmax(touching[:, 0] > 0.5))
    assert touching[start, 0] > 0.5
    end = start + int(np.argmax(touching[start:, 0] < 0.5))
    assert end > start
    return start, end


def test_ball_dropped_on_the_paddle_bounces():
    scene = PaddleBall()
    run = HeldScene(scene, HOVER).run(0.2)
    start, end = first_contact(run)
    _, X_WB = run.log("X_WB")
    _, contact = run.log("contact")
    z = X_WB[:, 6]
    assert np.max(z[end:]) > z[end] + 0.003  # it rises again after leaving the paddle
    # The ball pushes the paddle down (so the paddle pushes the ball up).
    assert np.all(contact[start:end, 2] <= 1e-12)
    assert np.min(contact[start:end, 2]) < -0.5


def test_off_centre_hit_turns_the_paddle_about_y():
    scene = PaddleBall(ball_start_m=[0.025, 0.0, 0.050])
    run = HeldScene(scene, HOVER).run(0.15)
    start, end = first_contact(run)
    _, contact = run.log("contact")
    peak = start + int(np.argmin(contact[start:end, 2]))
    f_x, f_z, tau_y = contact[peak, 0], contact[peak, 2], contact[peak, 4]
    # About T (the grip), a downward force f_z < 0 at x = +25 mm on the paddle's top,
    # z = -27 mm, gives tau_y = z f_x - x f_z = -0.027 f_x - 0.025 f_z > 0 (the +x edge dips).
    z_top = scene.tool_offset_m[2] + scene.paddle_size_m[2] / 2
    assert f_z < -0.5
    assert tau_y > 0.0
    assert tau_y == pytest.approx(z_top * f_x - 0.025 * f_z, rel=0.1)


# --- configuration --------------------------------------------------------------------------

@pytest.mark.parametrize("scene, field_name", [
    (PegInHole(peg_size_m=[0.025, 0.03, 0.04]), "scene.peg_size_m[1]"),
    (PegInHole(peg_size_m=[0.06, 0.025, 0.04]), "scene.peg_size_m[0]"),
    (PegInHole(peg_mass_kg=-0.02), "scene.peg_mass_kg"),
    (PegInHole(hole_size_m=[0.054, 0.027, -0.01]), "scene.hole_size_m"),
    (PegInHole(block_size_m=[0.08, 0.06, 0.03]), "scene.block_size_m"),  # x, y only
    (PegInHole(block_size_m=[0.05, 0.08]), "scene.hole_size_m[0]"),
    (HangingBall(table_z_m=float("inf")), "scene.table_z_m"),
    (PegInHole(tool_offset_m=[0.0, 0.0]), "scene.tool_offset_m"),
    (PegInHole(contact=ContactProperties(friction=-0.1)), "scene.contact.friction"),
    (PegInHole(contact=ContactProperties(hydroelastic_modulus_pa=0.0)),
     "scene.contact.hydroelastic_modulus_pa"),
    (HangingBall(ball_radius_m=0.0), "scene.ball_radius_m"),
    (HangingBall(spring_stiffness_n_per_m=float("nan")), "scene.spring_stiffness_n_per_m"),
    (HangingBall(spring_rest_length_m=0.001, ball_mass_kg=0.001),
     "scene.spring_rest_length_m"),
    (PaddleBall(paddle_size_m=[0.08, -0.05, 0.006]), "scene.paddle_size_m"),
    (PaddleBall(ball_mass_kg=0.0), "scene.ball_mass_kg"),
    (PaddleBall(min_inertia_kg_m2=-1.0), "scene.min_inertia_kg_m2"),
])
def test_bad_config_names_the_field(scene, field_name):
    with pytest.raises(ValueError, match="^" + re.escape(field_name) + " = .+: .+"):
        scene.validate()
    with pytest.raises(ValueError, match="scene."):
        build(scene)


def test_box_overlap_separating_axes():
    size = [0.02, 0.02, 0.02]
    X_WA = RigidTransform()
    # Face to face: apart, touching, overlapping.
    assert not box_overlaps_box(X_WA, size, RigidTransform([0.021, 0, 0]), size)
    assert not box_overlaps_box(X_WA, size, RigidTransform([0.020, 0, 0]), size)
    assert box_overlaps_box(X_WA, size, RigidTransform([0.019, 0, 0]), size)
    # Turned 45 deg about z, the corner reaches 0.01 * sqrt(2) = 14.1 mm.
    turned = RollPitchYaw(0, 0, np.pi / 4)
    assert box_overlaps_box(X_WA, size, RigidTransform(turned, [0.024, 0, 0]), size)
    assert not box_overlaps_box(X_WA, size, RigidTransform(turned, [0.0242, 0, 0]), size)
    assert sphere_overlaps_box([0.0, 0.0, 0.019], 0.01, X_WA, size)
    # Beyond the corner: inside the box grown by the radius, but 10.4 mm from the corner.
    assert not sphere_overlaps_box([0.016, 0.016, 0.016], 0.01, X_WA, size)
    assert sphere_overlaps_box([0.015, 0.015, 0.015], 0.01, X_WA, size)


# With the defaults the hole's floor, the table's top, is at z = -25 mm; the peg's
# bottom is 45 mm below I, the paddle's 33 mm, and the paddle reaches 40 mm in x. The
# table is a half-space: at x = 0.30 m the peg is past its drawn box but still inside.
@pytest.mark.parametrize("scene, X_WI, what", [
    (PegInHole(), RigidTransform([0.0, 0.0, 0.007]), "the peg starts inside the table"),
    (PegInHole(), RigidTransform([0.0, 0.0, 0.021]), None),
    (PegInHole(), RigidTransform([0.03, 0.0, 0.025]), "the peg starts inside the block's wall"),
    (PegInHole(), RigidTransform([0.10, 0.0, 0.021]), None),  # beside the plate, on the table
    (PegInHole(), RigidTransform([0.10, 0.0, 0.0]), "the peg starts inside the table"),
    (PegInHole(), RigidTransform([0.30, 0.0, 0.0]), "the peg starts inside the table"),
    (HangingBall(), RigidTransform([0.0, 0.0, 0.005]), "the ball starts inside the table"),
    (PaddleBall(), RigidTransform([0.0, 0.0, 0.075]), "the ball starts inside the paddle"),
    (PaddleBall(), RigidTransform([0.0, 0.0, -0.008]), "the paddle starts inside the table"),
    # Pitched 0.5 rad, the paddle's centre is 10 mm above the table but an edge dips 12 mm in.
    (PaddleBall(), RigidTransform(RollPitchYaw(0.0, 0.5, 0.0), [0.0, 0.0, -0.004]),
     "the paddle starts inside the table"),
    (PaddleBall(table_z_m=None), RigidTransform([0.0, 0.0, -0.5]), None),
])
def test_start_inside_the_scene_is_refused(scene, X_WI, what):
    found = start_overlap(scene, X_WI @ RigidTransform(scene.tool_offset_m))
    if what is None:
        assert found is None
        build(scene, X_WI)
    else:
        assert (found or "").startswith(what)
        with pytest.raises(ValueError, match=r"^X_WI_start \(p_WI = .*\): " + what):
            build(scene, X_WI)


def test_bad_time_step_is_refused():
    with pytest.raises(ValueError, match="time_step_s = 0"):
        AddScene(DiagramBuilder(), scene=PegInHole(), time_step_s=0, X_WI_start=HOVER)


@dataclass
class _Holder:
    scene: SceneConfig = field(default_factory=PegInHole)


def test_scenes_load_from_yaml_by_tag():
    holder = yaml_load_typed(schema=_Holder, data="""
scene: !HangingBall
  ball_mass_kg: 0.02
  table_z_m: null
  contact: {friction: 0.4}
""", defaults=_Holder())
    assert isinstance(holder.scene, HangingBall)
    assert holder.scene.ball_mass_kg == 0.02 and holder.scene.table_z_m is None
    assert holder.scene.contact.friction == 0.4
    assert holder.scene.contact.resolution_hint_m == ContactProperties().resolution_hint_m
    holder.scene.validate()
    holder = yaml_load_typed(schema=_Holder, data="scene: !PaddleBall {}", defaults=_Holder())
    assert holder.scene == PaddleBall()
