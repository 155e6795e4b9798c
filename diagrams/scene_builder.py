"""Add a rigid virtual scene (``diagrams/scene.py``) to a diagram: a tool coupled to
the instrument, and rigid objects it touches.

``AddScene`` adds the scene's own discrete MultibodyPlant ("scene_plant") and
SceneGraph ("scene_graph"): the physical world (instrument, display glass) lives
in the station's plant, so virtual and real bodies never collide.

Its models come from ``diagrams/scene_models.py`` (the tool first, then the
scene's model directives, a ``ModelScene``'s or those the paper scenes
generate); the paper scenes' table and spring are added here. What follows on
contact is the paper scenes'; a ``ModelScene`` takes what its models declare,
else its ``contact`` defaults (scene_models.py).

The tool is a free body driven only by an explicit external wrench (the virtual
coupling's ``wrench_on_tool_W``, [fx, fy, fz, tx, ty, tz] in W, N and N*m about
the tool's origin); its gravity is off, because the user should not feel the
virtual tool's weight. The balls keep gravity. Frame T is the tool body's frame:
it coincides with I when relaxed (X_IT is the identity), so the coupling acts at
the grip, and the tool's shape and centre of mass sit at ``tool_offset_m`` in T.
Coupling at the grip rather than at the tool's centre keeps the tracker's
rotational noise out of the coupling's force: about the 2-magnet instrument's
long axis the estimated angular velocity carries ~130 mrad/s of noise, which at a
25 mm lever would be ~3 mm/s of velocity noise in the damper.

Explicit coupling stability: the coupling's wrench is computed from the tool's
sampled state and held for one step h, so each tool needs k h^2 / m < 1 and
b h / m < 2 per axis. With the coupling's 400 N/m and 5 N*s/m at h = 1 ms that
means m >~ 10 g. Its rotational gains follow the instrument's inertia (for the
2-magnet instrument up to 0.19 N*m/rad and 2.4e-3 N*m*s/rad), so every principal
moment of inertia about T must be >~ 5e-6 kg*m^2 (b h / I = 0.48). Small tools
have smaller solid-body moments, so each tool's moments are raised to
``min_inertia_kg_m2``: added virtual inertia (the user feels it through the
coupling as a rotational resonance near 31 Hz at 0.19 N*m/rad).

Contact is hydroelastic ("hydroelastic_with_fallback", polygon surfaces, the
"lagged" discrete approximation, which uses the Hunt-Crossley dissipation; "sap"
costs about the same but ignores it, "similar" was no faster, triangle surfaces
cost a third more). The table is a compliant half-space (collision only; Meshcat
draws a finite thin box of TABLE_SIZE_M): Drake clips a rigid tool's surface mesh
against its plane, the cheapest hydroelastic contact, and no table edge is ever
reached. The plate's walls and the balls are compliant too (boxes get Drake's
coarse 40-44 tetrahedron meshes; a sphere's mesh follows ``resolution_hint_m``);
the tools are rigid. Drake has no hydroelastic contact between a compliant body
and a compliant half-space, so under the balls the table is a rigid half-space
(the ball is the soft side); a rigid tool pushed onto that table would meet it
in point contact (the "fallback"), which the scripts never do.

A scene plant step's cost follows its contact polygons (``maglev bench`` measures
the peg pushed onto the hole's floor): the peg pressed on the floor makes ~16 (the
compliant box floor this table replaced made 43, about three times the cost), on
the floor and against a wall ~19 from the wall's mesh against the peg's and ~10
from the table, the costliest case; free, a step costs a fraction of that.

That cost need not be the tick's: with ``stepping="worker"`` (the scenario's
default) a worker process steps the plant on the other core while the rest of
the tick runs (``systems/remote_scene.py``, ``diagrams/scene_process.py``),
bit for bit as in place. The diagram then holds the plant's state, and a copy of
the plant outside it poses the scene graph's geometry for Meshcat and the stereo
renderer; the contact results stay in the worker (no ContactVisualizer).
Measured on the 2-core machine with this process and its worker at real-time
priority (other users' processes pushed aside; `maglev run ... --duration 3`,
alternated): peg_in_hole 3.3-3.8x real time in place, 4.7-4.8x with the
worker; paddle_ball 2.2-2.3x and 4.0x. Without priority, on the machine loaded
by others (load 4-7 on 2 cores), the worker rarely finds a core in time, the
plant steps here instead (``RemoteScene``'s fallback), and alternated runs of
either kind scattered from 0.5x to 4x: the load, not the stepping, decided.

Drake 1.51's clipping of a rigid mesh by a half-space fails a check
("mesh_half_space_intersection.cc ... sgn(s_a) != sgn(s_b)") when two vertices
of one triangle lie exactly on the plane: a level tool, never perturbed, whose
bottom lands exactly on the table, which takes round numbers in a noiseless test
(the tracker's noise keeps the haptic runs off it).
"""

import time
from dataclasses import dataclass, field
from typing import List, Optional

import numpy as np
from pydrake.geometry import DefaultProximityProperties, SceneGraph, SceneGraphConfig
from pydrake.math import RigidTransform
from pydrake.multibody.plant import (
    AddMultibodyPlant, ApplyMultibodyPlantConfig, MultibodyPlant, MultibodyPlantConfig)
from pydrake.multibody.tree import LinearSpringDamper, RigidBody
from pydrake.systems.framework import DiagramBuilder, InputPort, OutputPort
from pydrake.systems.primitives import Demultiplexer, MatrixGain, ZeroOrderHold
from pydrake.systems.rendering import MultibodyPositionToGeometryPose

from maglev_haptics.diagrams.scene import (
    HangingBall, ModelScene, PaddleBall, PegInHole, SceneConfig, hanging_drop_m, table_top_z)
from maglev_haptics.diagrams.scene_models import add_scene_models
from maglev_haptics.hardware.config_checks import positive
from maglev_haptics.plant_models.scene_geometry import (
    Solid, hole_block_boxes, solid_bottom_z, solid_overlaps_box)
from maglev_haptics.plant_models.scene_sdf import register_table
from maglev_haptics.systems.remote_scene import RemoteScene
from maglev_haptics.systems.scene_worker import CONTACT, STEP, SceneWorker
from maglev_haptics.systems.tool_contact import ToolContactSensor


@dataclass
class SceneParts:
    """What ``AddScene`` added. Port shapes: wrenches [fx, fy, fz, tx, ty, tz] in W
    (N, N*m, about the tool's origin); ``X_WT`` [qw, qx, qy, qz, x, y, z] (m);
    ``V_WT`` [wx, wy, wz, vx, vy, vz] in W (rad/s, m/s)."""

    plant: MultibodyPlant
    scene_graph: SceneGraph
    tool_body: RigidBody
    X_IT: RigidTransform  # the tool's frame T in the instrument frame I
    ball_body: Optional[RigidBody]  # None for PegInHole
    wrench_on_tool_input: InputPort  # the coupling's wrench on the tool
    X_WT_output: OutputPort
    V_WT_output: OutputPort
    contact_wrench_output: OutputPort  # total contact wrench on the tool (sampled)
    in_contact_output: OutputPort  # 1.0 while anything touches the tool (sampled)
    surface: Optional[object] = None  # the DeformableSurface system of a deformable scene
    lattice: Optional[object] = None  # its Lattice at rest
    # The RemoteScene system when a worker process steps the plant: ``plant`` is then
    # a copy outside the diagram that only poses ``scene_graph``'s geometry.
    worker: Optional[object] = None
    # A model scene's tissue bodies (``tissue_scene.Tissue``), each its own system.
    tissue: List[object] = field(default_factory=list)



def start_overlap(scene: SceneConfig, X_WA: RigidTransform) -> Optional[str]:
    """What the tool's shape at X_WA (its centre frame, m) or the ball at its start
    would start inside, or None. The table is a half-space: anything reaching below
    its top starts inside it."""
    boxes = []
    if isinstance(scene, PegInHole):
        boxes = [Solid(f"the block's {name.replace('_', ' ')}", RigidTransform(centre), size)
                 for name, centre, size in hole_block_boxes(
                     scene.block_size_m, scene.hole_size_m, scene.hole_center_m)]
        moving = [Solid("peg", X_WA, scene.peg_size_m)]
    elif isinstance(scene, HangingBall):
        p_WB = X_WA.translation() - [0.0, 0.0, hanging_drop_m(scene)]
        moving = [Solid("anchor", X_WA, radius_m=scene.anchor_radius_m),
                  Solid("ball", RigidTransform(p_WB), radius_m=scene.ball_radius_m)]
    else:
        ball = Solid("ball", RigidTransform(np.asarray(scene.ball_start_m, dtype=float)),
                     radius_m=scene.ball_radius_m)
        if solid_overlaps_box(ball, Solid("the paddle", X_WA, scene.paddle_size_m)):
            return "the ball starts inside the paddle"
        moving = [Solid("paddle", X_WA, scene.paddle_size_m), ball]
    table_z = table_top_z(scene)
    for solid in moving:
        for box in boxes:
            if solid_overlaps_box(solid, box):
                return f"the {solid.name} starts inside {box.name}"
        if table_z is not None and solid_bottom_z(solid) < table_z:
            return f"the {solid.name} starts inside the table (its top at z = {table_z:.4g} m)"
    return None


def wrench_to_generalized_force(velocity_start: int, num_velocities: int) -> np.ndarray:
    """(num_velocities, 6) matrix mapping [f; tau] in W to the plant's generalized
    forces: a quaternion free body's velocities are [w_WB; v_WB] in W, so the
    conjugate forces are [tau; f] at ``velocity_start``."""
    D = np.zeros((num_velocities, 6))
    D[velocity_start:velocity_start + 3, 3:6] = np.eye(3)
    D[velocity_start + 3:velocity_start + 6, 0:3] = np.eye(3)
    return D



SCENE_STEPPING = ("worker", "in_place")


def _add_models(plant: MultibodyPlant, scene_graph: SceneGraph, scene: SceneConfig,
                X_WT: RigidTransform):
    """The scene's models in ``plant`` (registered with ``scene_graph``), which is
    then finalized, the tool at X_WT and the balls at their starts. Returns
    (tool body, ball body or None)."""
    tool_body = add_scene_models(plant, scene_graph, scene).tool_body
    ball_body = None
    if isinstance(scene, (HangingBall, PaddleBall)):
        ball_body = plant.GetBodyByName("body", plant.GetModelInstanceByName("ball"))
    table_z = table_top_z(scene)
    if table_z is not None:
        # The soft side against the table: the table itself under the rigid peg, the
        # compliant balls over a rigid table (Drake has no hydroelastic contact of a
        # compliant body with a compliant half-space).
        register_table(plant, table_z, scene.contact, compliant=isinstance(scene, PegInHole))
    if table_z is not None or isinstance(scene, ModelScene):
        # SceneGraph back-fills a resolution hint (0.02 m) into every geometry without
        # one, which enrols a half-space for deformable contact, where Drake warns it
        # cannot take part. Every other scene geometry states its own hint.
        scene_graph.set_config(SceneGraphConfig(
            default_proximity_properties=DefaultProximityProperties(resolution_hint=None)))
    p_TA = np.asarray(getattr(scene, "tool_offset_m", [0.0, 0.0, 0.0]), dtype=float)  # in T (m)
    if isinstance(scene, HangingBall):
        plant.AddForceElement(LinearSpringDamper(
            tool_body, p_TA, ball_body, np.zeros(3), scene.spring_rest_length_m,
            scene.spring_stiffness_n_per_m, scene.spring_damping_n_s_per_m))
    plant.Finalize()
    plant.SetDefaultFloatingBaseBodyPose(tool_body, X_WT)
    if isinstance(scene, HangingBall):
        p_WB = X_WT @ p_TA - [0.0, 0.0, hanging_drop_m(scene)]
        plant.SetDefaultFloatingBaseBodyPose(ball_body, RigidTransform(p_WB))
    elif isinstance(scene, PaddleBall):
        plant.SetDefaultFloatingBaseBodyPose(ball_body, RigidTransform(
            np.asarray(scene.ball_start_m, dtype=float)))
    return tool_body, ball_body


def AddScene(builder: DiagramBuilder, *, scene: SceneConfig, time_step_s: float,
             X_WI_start: RigidTransform, use_sampled_output_ports: bool = True,
             contact_sample_period_s: Optional[float] = None,
             stepping: str = "in_place") -> SceneParts:
    """Add the scene's plant and scene graph, its models and its ports to ``builder``.

    The tool starts at X_WI_start * X_IT (X_IT the identity); the hanging ball at its static hanging
    point below the anchor; the paddle's ball at ``ball_start_m``; all at rest.
    A ValueError names a bad config field, or X_WI_start if it would start the
    tool or the ball inside the scene. ``use_sampled_output_ports=False`` (for
    linearization: Drake otherwise linearizes a sampled output to the identity) makes
    the plant's outputs, the contact wrench among them, functions of the current
    state instead of the last step's.
    ``contact_sample_period_s`` (s), when given, samples the contact wrench and
    the contact flag at that period instead of every step.

    ``stepping="worker"`` steps the plant in a process of its own on the other core
    (``systems/remote_scene.py``), with the numbers of ``use_sampled_output_ports=False``
    bit for bit; it needs ``contact_sample_period_s``. The diagram then holds the
    plant's state in "scene_plant_worker" and poses the scene graph's geometry from
    it; ``SceneParts.plant`` is a copy outside the diagram that only does that.
    """
    scene.validate()
    positive("time_step_s", time_step_s)
    if stepping not in SCENE_STEPPING:
        raise ValueError(f"stepping = {stepping!r}: one of {', '.join(SCENE_STEPPING)}")
    X_IT = RigidTransform()
    X_WT = X_WI_start @ X_IT
    overlap = None if isinstance(scene, ModelScene) else start_overlap(
        scene, X_WT @ RigidTransform(np.asarray(scene.tool_offset_m, float)))
    if overlap is not None:
        raise ValueError(
            f"X_WI_start (p_WI = {np.round(X_WI_start.translation(), 6).tolist()} m): {overlap}; "
            "start the instrument where the tool and the ball are clear of the scene")
    config = MultibodyPlantConfig(time_step=time_step_s, discrete_contact_approximation="lagged",
                                  contact_model="hydroelastic_with_fallback",
                                  use_sampled_output_ports=use_sampled_output_ports)
    if stepping == "worker":
        if contact_sample_period_s is None:
            raise ValueError("stepping = 'worker' samples the contact: "
                             "give contact_sample_period_s")
        return _add_worker_scene(builder, scene=scene, config=config, X_WI_start=X_WI_start,
                                 X_IT=X_IT, contact_sample_period_s=contact_sample_period_s)
    plant, scene_graph = AddMultibodyPlant(config, builder)
    plant.set_name("scene_plant")
    scene_graph.set_name("scene_graph")
    tool_body, ball_body = _add_models(plant, scene_graph, scene, X_WT)

    gain = builder.AddNamedSystem("scene_tool_wrench", MatrixGain(
        wrench_to_generalized_force(tool_body.floating_velocities_start_in_v(),
                                    plant.num_velocities())))
    builder.Connect(gain.get_output_port(), plant.get_applied_generalized_force_input_port())
    split = builder.AddNamedSystem("scene_tool_state", Demultiplexer([7, 6]))
    builder.Connect(plant.get_state_output_port(tool_body.model_instance()), split.get_input_port())
    sensor = builder.AddNamedSystem("scene_tool_contact", ToolContactSensor(plant, tool_body))
    builder.Connect(plant.get_contact_results_output_port(), sensor.GetInputPort("contact_results"))
    builder.Connect(split.get_output_port(0), sensor.GetInputPort("X_WT"))
    contact_wrench = sensor.GetOutputPort("wrench_on_tool_W")
    in_contact = sensor.GetOutputPort("in_contact")
    if contact_sample_period_s is not None:
        # Sample-and-hold: the plant's contact results (about as costly as its step)
        # and the sensor then run only at this period.
        holds = [builder.AddNamedSystem(f"scene_tool_contact_hold_{i}", ZeroOrderHold(
            contact_sample_period_s, port.size())) for i, port in enumerate((contact_wrench,
                                                                            in_contact))]
        for hold, port in zip(holds, (contact_wrench, in_contact)):
            builder.Connect(port, hold.get_input_port())
        contact_wrench, in_contact = (hold.get_output_port() for hold in holds)
    return SceneParts(
        plant=plant, scene_graph=scene_graph, tool_body=tool_body, X_IT=X_IT, ball_body=ball_body,
        wrench_on_tool_input=gain.get_input_port(), X_WT_output=split.get_output_port(0),
        V_WT_output=split.get_output_port(1),
        contact_wrench_output=contact_wrench, in_contact_output=in_contact)


def _part(builder: DiagramBuilder, name: str, port: OutputPort, start: int,
          size: int) -> OutputPort:
    """Elements ``start`` to ``start + size`` of ``port``."""
    if start == 0 and port.size() == size:
        return port
    sizes = [n for n in (start, size, port.size() - start - size) if n > 0]
    split = builder.AddNamedSystem(name, Demultiplexer(sizes))
    builder.Connect(port, split.get_input_port())
    return split.get_output_port(1 if start > 0 else 0)


def _add_worker_scene(builder: DiagramBuilder, *, scene: SceneConfig,
                      config: MultibodyPlantConfig, X_WI_start: RigidTransform,
                      X_IT: RigidTransform, contact_sample_period_s: float) -> SceneParts:
    """AddScene's ``stepping="worker"``: the plant's state stepped by a worker process
    (which builds the in-place plant with use_sampled_output_ports=False), and a
    copy of the plant outside the diagram that poses the scene graph's geometry."""
    scene_graph = builder.AddNamedSystem("scene_graph", SceneGraph())
    plant = MultibodyPlant(config.time_step)
    plant.set_name("scene_plant")
    ApplyMultibodyPlantConfig(config, plant)
    plant.RegisterAsSourceForSceneGraph(scene_graph)
    tool_body, ball_body = _add_models(plant, scene_graph, scene, X_WI_start @ X_IT)
    nq, nv = plant.num_positions(), plant.num_velocities()
    worker = SceneWorker("maglev_haptics.diagrams.scene_process",
                         (scene, config.time_step, X_WI_start.GetAsMatrix4()), nq + nv)
    remote = builder.AddNamedSystem("scene_plant_worker", RemoteScene(
        worker, SceneStepper(scene, config.time_step, X_WI_start),
        x0=plant.GetPositionsAndVelocities(plant.CreateDefaultContext()),
        period_s=config.time_step, contact_period_s=contact_sample_period_s))
    state = builder.AddNamedSystem("scene_state", Demultiplexer([nq, nv]))
    builder.Connect(remote.GetOutputPort("x"), state.get_input_port())
    to_pose = builder.AddNamedSystem("scene_geometry_pose", MultibodyPositionToGeometryPose(plant))
    builder.Connect(state.get_output_port(0), to_pose.get_input_port())
    builder.Connect(to_pose.get_output_port(), scene_graph.get_source_pose_port(
        plant.get_source_id()))
    return SceneParts(
        plant=plant, scene_graph=scene_graph, tool_body=tool_body, X_IT=X_IT, ball_body=ball_body,
        wrench_on_tool_input=remote.GetInputPort("wrench_on_tool_W"),
        # The tool's pose and velocity in q and v: first, but after any joints'
        # (Drake numbers the free bodies' joints last).
        X_WT_output=_part(builder, "scene_tool_pose", state.get_output_port(0),
                          tool_body.floating_positions_start(), 7),
        V_WT_output=_part(builder, "scene_tool_velocity", state.get_output_port(1),
                          tool_body.floating_velocities_start_in_v(), 6),
        contact_wrench_output=remote.GetOutputPort("contact_wrench_on_tool_W"),
        in_contact_output=remote.GetOutputPort("in_contact"), worker=remote)


class SceneStepper:
    """The scene's plant outside any simulated diagram, stepped on request: what a
    scene worker process computes (``systems/scene_worker.py``), and what
    ``RemoteScene`` computes itself when it does not wait for one. Built by
    AddScene (unsampled ports, the raw contact sensor), so its numbers are the
    in-place plant's bit for bit: the same plant, the same update handler, on the
    same state and input.

    ``stepper(kind, [x; u], result)`` writes x_next (STEP) and/or the contact
    sample [wrench on the tool (6), in contact] (CONTACT) at state x = [q; v]
    and tool wrench u into ``result`` [x_next; contact].
    """

    def __init__(self, scene, time_step_s: float, X_WI_start: RigidTransform):
        builder = DiagramBuilder()
        parts = AddScene(builder, scene=scene, time_step_s=time_step_s, X_WI_start=X_WI_start,
                         use_sampled_output_ports=False)
        self._diagram = builder.Build()
        context = self._diagram.CreateDefaultContext()
        self._plant = parts.plant
        self._plant_context = parts.plant.GetMyMutableContextFromRoot(context)
        gain = parts.wrench_on_tool_input.get_system()
        self._wrench = parts.wrench_on_tool_input.FixValue(
            gain.GetMyMutableContextFromRoot(context), np.zeros(6))
        self._contact_ports = [(port, port.get_system().GetMyContextFromRoot(context))
                               for port in (parts.contact_wrench_output, parts.in_contact_output)]
        self.n = parts.plant.num_positions() + parts.plant.num_velocities()
        self.x0 = parts.plant.GetPositionsAndVelocities(self._plant_context)  # at the start
        self._at = np.full(self.n + 6, np.nan)  # the (x, u) the context holds

    def __call__(self, kind: int, request: np.ndarray, result: np.ndarray) -> None:
        n = self.n
        # The same (x, u) again (the contact sample after its tick's step) keeps the
        # context, and with it the contact solver's cached results.
        if not np.array_equal(request.view(np.int64), self._at.view(np.int64)):
            self._at[:] = request
            self._plant.SetPositionsAndVelocities(self._plant_context, request[:n])
            self._wrench.GetMutableData().get_mutable_value().SetFromVector(request[n:])
        if kind & STEP:
            result[:n] = self._plant.EvalUniquePeriodicDiscreteUpdate(
                self._plant_context).get_vector(0).value()
        if kind & CONTACT:
            (wrench, wrench_context), (flag, flag_context) = self._contact_ports
            result[n:n + 6] = wrench.Eval(wrench_context)
            result[n + 6] = flag.Eval(flag_context)[0]


COST_STEPS = 300  # steps timed at load (0.3 s of scene time at 1 kHz)


def measure_step_cost_s(scene: SceneConfig, time_step_s: float,
                        X_WI_start: RigidTransform) -> float:
    """What one tick of the scene's plant costs here (s): the median time of a step
    with its contact sample, over COST_STEPS steps from the start, the tool left
    where it starts (free bodies fall onto what holds them). Contact the tool makes
    later costs more (``maglev bench`` measures the shipped scenes in contact)."""
    stepper = SceneStepper(scene, time_step_s, X_WI_start)
    request = np.concatenate([stepper.x0, np.zeros(6)])
    result = np.zeros(stepper.n + 7)
    costs = np.empty(COST_STEPS)
    for k in range(COST_STEPS):
        # A 1 uN push on the tool, alternating in sign, so that every step is computed
        # (the stepper keeps its result for the same state and input) and none moves it.
        request[stepper.n + 2] = 1e-6 * (-1) ** k
        start = time.perf_counter()
        stepper(STEP | CONTACT, request, result)
        costs[k] = time.perf_counter() - start
        request[:stepper.n] = result[:stepper.n]
    return float(np.median(costs))
