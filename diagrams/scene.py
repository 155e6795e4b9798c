"""The virtual scene: a tool coupled to the instrument, and rigid objects it touches.

``AddScene`` adds the scene's own discrete MultibodyPlant ("scene_plant") and
SceneGraph ("scene_graph"): the physical world (instrument, display glass) lives
in the station's plant, so virtual and real bodies never collide.

Three scenes, picked by the config's type:

- ``PegInHole``: a square peg (the tool) and a static plate lying on a table,
  with a rectangular hole through it, so the hole's floor is the table;
- ``HangingBall``: a small anchor sphere (the tool) with a ball hung from it by a
  ``LinearSpringDamper``, over a table;
- ``PaddleBall``: a paddle (the tool) and a ball dropped onto it, over a table.

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

Measured cost of one scene plant step on the 2-core reference machine (the
plant alone, best of several runs): ~15 us free; the peg pressed on the hole's
floor ~80 us (16 contact polygons; the compliant box floor this table replaced
made 43 and cost ~230 us), sliding on it ~105 us (11), on the floor and against a
wall ~230 us (the wall's mesh against the peg's makes ~19 polygons, the table
~10); the ball on the table ~65 us, on the paddle ~170 us.

Drake 1.51's clipping of a rigid mesh by a half-space fails a check
("mesh_half_space_intersection.cc ... sgn(s_a) != sgn(s_b)") when two vertices
of one triangle lie exactly on the plane: a level tool, never perturbed, whose
bottom lands exactly on the table, which takes round numbers in a noiseless test
(the tracker's noise keeps the haptic runs off it). Drake also warns once per
process that half-spaces take no part in deformable contact; the scene has no
deformable bodies.

Models are generated SDFormat text, so every size and contact property comes
from the scenario; nothing is read from files.
"""

from dataclasses import dataclass, field
from typing import List, NamedTuple, Optional, Sequence, Union

import numpy as np
from pydrake.geometry import (
    AddCompliantHydroelasticPropertiesForHalfSpace, AddContactMaterial,
    AddRigidHydroelasticProperties, Box, HalfSpace,
    ProximityProperties, SceneGraph)
from pydrake.math import RigidTransform
from pydrake.multibody.parsing import Parser
from pydrake.multibody.plant import (
    AddMultibodyPlant, CoulombFriction, MultibodyPlant, MultibodyPlantConfig)
from pydrake.multibody.tree import LinearSpringDamper, RigidBody
from pydrake.systems.framework import DiagramBuilder, InputPort, OutputPort
from pydrake.systems.primitives import Demultiplexer, MatrixGain, ZeroOrderHold

from maglev_haptics.systems.config_checks import finite, nonnegative, positive, require, vector
from maglev_haptics.systems.tool_contact import ToolContactSensor

GRAVITY_M_S2 = 9.81  # magnitude of the scene plant's default gravity (m/s^2)


@dataclass
class ContactProperties:
    """Hydroelastic contact properties shared by every collision geometry of a scene."""

    hydroelastic_modulus_pa: float = 1.0e6  # pressure at the deepest point of a compliant body (Pa)
    hunt_crossley_dissipation_s_per_m: float = 5.0  # (s/m); impacts barely bounce
    friction: float = 0.15  # Coulomb coefficient, static = dynamic (-)
    # Edge length of a sphere's mesh (m): 5 mm gives a 10 mm ball 128 tetrahedra
    # (faces ~0.6 mm inside the sphere); 10 mm, 32 (~2 mm inside, ~40 us a step less).
    resolution_hint_m: float = 0.005


@dataclass
class PegInHole:
    """A square peg to insert into a rectangular hole through a static plate lying on
    the table.

    The plate is as thick as the hole is deep, so the hole's floor is the table's
    top, at hole_center_m[2] - hole_size_m[2] in W (m). The hole is 2 mm wider than
    the peg in y (1 mm clearance a side) and 29 mm in x, so the peg can be slid
    along x inside the hole against the walls.
    """

    # x, y, length (m)
    peg_size_m: List[float] = field(default_factory=lambda: [0.025, 0.025, 0.040])
    peg_mass_kg: float = 0.020  # (kg); >= 10 g for the explicit coupling
    min_inertia_kg_m2: float = 5e-6  # floor of the peg's principal moments (kg*m^2)
    # Position of the peg's centre in I (m): the peg hangs below I.
    tool_offset_m: List[float] = field(default_factory=lambda: [0.0, 0.0, -0.025])
    # x, y, depth (m); the depth is also the plate's thickness.
    hole_size_m: List[float] = field(default_factory=lambda: [0.054, 0.027, 0.010])
    # Centre of the hole's opening in the plate's top surface, in W (m); the plate is
    # centred on it in x and y.
    hole_center_m: List[float] = field(default_factory=lambda: [0.0, 0.0, -0.015])
    # Outer x, y of the plate (m).
    block_size_m: List[float] = field(default_factory=lambda: [0.12, 0.08])
    contact: ContactProperties = field(default_factory=ContactProperties)


@dataclass
class HangingBall:
    """A ball hung from the tool (a small anchor sphere) by a linear spring-damper.

    The spring joins the anchor's centre to the ball's centre. With the defaults the
    ball hangs rest length + m g / k = 30 + 9.8 = 39.8 mm below the anchor, bobs at
    5 Hz (damping ratio 0.08) and swings as a 2.5 Hz pendulum.
    """

    anchor_radius_m: float = 0.008  # (m)
    anchor_mass_kg: float = 0.020  # (kg); >= 10 g for the explicit coupling
    min_inertia_kg_m2: float = 5e-6  # floor of the anchor's principal moments (kg*m^2)
    # The anchor's centre in I (m): at I's origin the spring exerts no torque on the user.
    tool_offset_m: List[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    ball_radius_m: float = 0.010  # (m)
    ball_mass_kg: float = 0.010  # (kg)
    spring_stiffness_n_per_m: float = 10.0  # (N/m)
    spring_damping_n_s_per_m: float = 0.05  # (N*s/m)
    spring_rest_length_m: float = 0.030  # (m)
    table_z_m: Optional[float] = -0.040  # top of the table in W (m); None: no table
    contact: ContactProperties = field(default_factory=ContactProperties)


@dataclass
class PaddleBall:
    """A light ball dropped from rest onto the paddle (the tool); it bounces.

    The 1 ms implicit contact step damps short impacts by itself, so the ball is
    soft (1e5 Pa; it sinks ~3 mm into the paddle at 1 m/s) with little Hunt-Crossley
    dissipation: dropped 5 cm, it rebounds at ~0.37 of its speed from the paddle
    held by the coupling (the paddle recoils; ~0.2 at 1e6 Pa), and at ~0.5 from the
    rigid table.
    """

    paddle_size_m: List[float] = field(default_factory=lambda: [0.08, 0.05, 0.006])  # x, y, z (m)
    paddle_mass_kg: float = 0.030  # (kg); >= 10 g for the explicit coupling
    min_inertia_kg_m2: float = 5e-6  # floor of the paddle's principal moments (kg*m^2)
    # Position of the paddle's centre (the tool body's origin) in I (m): below I.
    tool_offset_m: List[float] = field(default_factory=lambda: [0.0, 0.0, -0.030])
    ball_radius_m: float = 0.010  # (m)
    ball_mass_kg: float = 0.005  # (kg)
    # The ball's centre in W at t = 0, at rest (m).
    ball_start_m: List[float] = field(default_factory=lambda: [0.0, 0.0, 0.050])
    table_z_m: Optional[float] = -0.040  # top of the table in W (m); None: no table
    contact: ContactProperties = field(default_factory=lambda: ContactProperties(
        hydroelastic_modulus_pa=1.0e5, hunt_crossley_dissipation_s_per_m=0.1))


SceneConfig = Union[PegInHole, HangingBall, PaddleBall]


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


# The table's visual box, x, y, z (m), centred on W's z axis under the table's top;
# for contact the table is a half-space.
TABLE_SIZE_M = (0.24, 0.18, 0.010)
# Depth of the compliant half-space's slab (m): the pressure rises from 0 at the
# table's top to the modulus this deep, as in a 20 mm thick compliant box. At 1e6 Pa
# the peg's 25 x 25 mm face then meets 1e6 * 6.25e-4 / 0.010 = 62.5 N/mm.
TABLE_SLAB_M = 0.010

# Visual colours, RGBA.
PEG_RGBA = (0.20, 0.45, 0.85, 1.0)
PADDLE_RGBA = (0.90, 0.50, 0.10, 1.0)
ANCHOR_RGBA = (0.30, 0.30, 0.35, 1.0)
BALL_RGBA = (0.85, 0.15, 0.15, 1.0)
BLOCK_RGBA = (0.80, 0.65, 0.40, 1.0)
TABLE_RGBA = (0.35, 0.55, 0.40, 1.0)


# --- numeric core ---------------------------------------------------------------------

def box_inertia(mass_kg: float, size_m: Sequence[float]) -> np.ndarray:
    """Principal moments (3,) (kg*m^2) about its centre of a solid box of ``size_m``
    (x, y, z; m)."""
    x2, y2, z2 = np.square(np.asarray(size_m, dtype=float))
    return mass_kg / 12.0 * np.array([y2 + z2, x2 + z2, x2 + y2])


def sphere_inertia(mass_kg: float, radius_m: float) -> np.ndarray:
    """Principal moments (3,) (kg*m^2) of a solid sphere about its centre."""
    return np.full(3, 0.4 * mass_kg * radius_m**2)


def hole_block_boxes(block_size_m, hole_size_m, hole_center_m):
    """The plate with a hole through it as four boxes [(name, centre in W (3,),
    size (3,))] (m), each as thick as the hole is deep: the walls left and right of
    the hole (the plate's full y) and in front of and behind it (between those)."""
    bx, by = block_size_m
    hx, hy, depth = hole_size_m
    cx, cy, top = hole_center_m
    wall_z = top - depth / 2
    side_x = (bx - hx) / 2
    side_y = (by - hy) / 2
    x_wall = (hx + side_x) / 2  # wall centres' distance from the hole's centre (m)
    y_wall = (hy + side_y) / 2
    boxes = [
        ("wall_left", [cx - x_wall, cy, wall_z], [side_x, by, depth]),
        ("wall_right", [cx + x_wall, cy, wall_z], [side_x, by, depth]),
        ("wall_front", [cx, cy - y_wall, wall_z], [hx, side_y, depth]),
        ("wall_back", [cx, cy + y_wall, wall_z], [hx, side_y, depth]),
    ]
    return [(name, np.array(centre), np.array(size)) for name, centre, size in boxes]


def table_top_z(scene: SceneConfig) -> Optional[float]:
    """z of the table's top in W (m), None without a table. Under the peg's plate it
    is the hole's floor."""
    if isinstance(scene, PegInHole):
        return scene.hole_center_m[2] - scene.hole_size_m[2]
    return scene.table_z_m


def hanging_drop_m(scene: HangingBall) -> float:
    """Static distance (m) of the ball's centre below the anchor's: rest length + m g / k."""
    return (scene.spring_rest_length_m
            + scene.ball_mass_kg * GRAVITY_M_S2 / scene.spring_stiffness_n_per_m)


def box_overlaps_box(X_WA: RigidTransform, size_A, X_WB: RigidTransform, size_B) -> bool:
    """Whether two solid boxes (full sizes in m, centred on their frames) interpenetrate:
    the separating-axis test over both boxes' face normals and their edges' cross
    products. Boxes that only touch do not overlap."""
    R_A, R_B = X_WA.rotation().matrix(), X_WB.rotation().matrix()
    half_A, half_B = np.asarray(size_A) / 2, np.asarray(size_B) / 2
    p_AB_W = X_WB.translation() - X_WA.translation()
    axes = [R_A[:, i] for i in range(3)] + [R_B[:, j] for j in range(3)]
    axes += [np.cross(R_A[:, i], R_B[:, j]) for i in range(3) for j in range(3)]
    for axis in axes:
        norm = np.linalg.norm(axis)
        if norm < 1e-9:  # parallel edges: their face normals already cover this
            continue
        u = axis / norm
        reach = half_A @ np.abs(R_A.T @ u) + half_B @ np.abs(R_B.T @ u)
        if abs(p_AB_W @ u) >= reach:
            return False
    return True


def sphere_overlaps_box(p_WS, radius_m: float, X_WB: RigidTransform, size_B) -> bool:
    """Whether a solid sphere (centre p_WS, m) and a solid box (full size, m) interpenetrate."""
    p_BS = X_WB.inverse() @ np.asarray(p_WS, dtype=float)
    half = np.asarray(size_B) / 2
    return float(np.linalg.norm(p_BS - np.clip(p_BS, -half, half))) < radius_m


class Solid(NamedTuple):
    """A box of full extents ``size_m`` or, with ``radius_m``, a sphere, centred at X_WS (m)."""

    name: str
    X_WS: RigidTransform
    size_m: Optional[Sequence[float]] = None
    radius_m: Optional[float] = None


def solid_overlaps_box(solid: Solid, box: Solid) -> bool:
    if solid.radius_m is None:
        return box_overlaps_box(solid.X_WS, solid.size_m, box.X_WS, box.size_m)
    return sphere_overlaps_box(solid.X_WS.translation(), solid.radius_m, box.X_WS, box.size_m)


def solid_bottom_z(solid: Solid) -> float:
    """z in W of the solid's lowest point (m)."""
    if solid.radius_m is not None:
        return solid.X_WS.translation()[2] - solid.radius_m
    R_WS = solid.X_WS.rotation().matrix()
    return solid.X_WS.translation()[2] - np.abs(R_WS[2, :]) @ (np.asarray(solid.size_m) / 2)


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


# --- validation -----------------------------------------------------------------------

def _validate_contact(c: ContactProperties, path: str) -> None:
    positive(f"{path}.hydroelastic_modulus_pa", c.hydroelastic_modulus_pa)
    nonnegative(f"{path}.hunt_crossley_dissipation_s_per_m", c.hunt_crossley_dissipation_s_per_m)
    nonnegative(f"{path}.friction", c.friction)
    positive(f"{path}.resolution_hint_m", c.resolution_hint_m)


def validate_scene(scene: SceneConfig, label: str = "scene") -> None:
    """Range checks; a ValueError names ``label.field``, its value and what is allowed."""
    require(isinstance(scene, (PegInHole, HangingBall, PaddleBall)), label, scene,
            "must be a PegInHole, HangingBall or PaddleBall")
    nonnegative(f"{label}.min_inertia_kg_m2", scene.min_inertia_kg_m2)
    vector(f"{label}.tool_offset_m", scene.tool_offset_m)
    if not isinstance(scene, PegInHole) and scene.table_z_m is not None:
        require(finite(scene.table_z_m), f"{label}.table_z_m", scene.table_z_m,
                "must be a finite number or null")
    _validate_contact(scene.contact, f"{label}.contact")
    if isinstance(scene, PegInHole):
        vector(f"{label}.peg_size_m", scene.peg_size_m, positive=True)
        positive(f"{label}.peg_mass_kg", scene.peg_mass_kg)
        vector(f"{label}.hole_size_m", scene.hole_size_m, positive=True)
        vector(f"{label}.hole_center_m", scene.hole_center_m)
        vector(f"{label}.block_size_m", scene.block_size_m, positive=True, length=2,
               meaning=": the plate's outer x, y (its thickness is the hole's depth, "
               "hole_size_m[2])")
        for i, axis in enumerate("xy"):
            require(scene.peg_size_m[i] < scene.hole_size_m[i], f"{label}.peg_size_m[{i}]",
                    scene.peg_size_m[i], f"the peg must be narrower than the hole in {axis} "
                    f"(hole_size_m[{i}] = {scene.hole_size_m[i]})")
            require(scene.hole_size_m[i] < scene.block_size_m[i], f"{label}.hole_size_m[{i}]",
                    scene.hole_size_m[i], f"the hole must be narrower than the plate in {axis} "
                    f"(block_size_m[{i}] = {scene.block_size_m[i]})")
    elif isinstance(scene, HangingBall):
        positive(f"{label}.anchor_radius_m", scene.anchor_radius_m)
        positive(f"{label}.anchor_mass_kg", scene.anchor_mass_kg)
        positive(f"{label}.ball_radius_m", scene.ball_radius_m)
        positive(f"{label}.ball_mass_kg", scene.ball_mass_kg)
        positive(f"{label}.spring_stiffness_n_per_m", scene.spring_stiffness_n_per_m)
        nonnegative(f"{label}.spring_damping_n_s_per_m", scene.spring_damping_n_s_per_m)
        positive(f"{label}.spring_rest_length_m", scene.spring_rest_length_m)
        gap = scene.anchor_radius_m + scene.ball_radius_m
        require(hanging_drop_m(scene) > gap, f"{label}.spring_rest_length_m",
                scene.spring_rest_length_m, f"the ball must hang clear of the anchor: rest "
                f"length + m g / k = {hanging_drop_m(scene):.4g} m must exceed "
                f"anchor_radius_m + ball_radius_m = {gap:.4g} m")
    else:
        vector(f"{label}.paddle_size_m", scene.paddle_size_m, positive=True)
        positive(f"{label}.paddle_mass_kg", scene.paddle_mass_kg)
        positive(f"{label}.ball_radius_m", scene.ball_radius_m)
        positive(f"{label}.ball_mass_kg", scene.ball_mass_kg)
        vector(f"{label}.ball_start_m", scene.ball_start_m)


# --- SDFormat -------------------------------------------------------------------------

class Part(NamedTuple):
    """One visual + collision shape of a link: ``geometry`` is SDFormat
    <geometry> content, ``p_LP`` its centre in the link frame (m)."""

    name: str
    geometry: str
    p_LP: Sequence[float]
    rgba: Sequence[float]


def box_geometry(size_m) -> str:
    return "<box><size>{:.9g} {:.9g} {:.9g}</size></box>".format(*size_m)


def sphere_geometry(radius_m: float) -> str:
    return f"<sphere><radius>{radius_m:.9g}</radius></sphere>"


def proximity_properties_sdf(contact: ContactProperties, compliant: bool = True) -> str:
    """A hydroelastic <drake:proximity_properties> block, compliant or rigid."""
    kind = ("<drake:compliant_hydroelastic/><drake:hydroelastic_modulus>"
            f"{contact.hydroelastic_modulus_pa:.9g}</drake:hydroelastic_modulus>"
            if compliant else "<drake:rigid_hydroelastic/>")
    return (
        f"<drake:proximity_properties>{kind}"
        f"<drake:mesh_resolution_hint>{contact.resolution_hint_m:.9g}</drake:mesh_resolution_hint>"
        "<drake:hunt_crossley_dissipation>"
        f"{contact.hunt_crossley_dissipation_s_per_m:.9g}</drake:hunt_crossley_dissipation>"
        f"<drake:mu_static>{contact.friction:.9g}</drake:mu_static>"
        f"<drake:mu_dynamic>{contact.friction:.9g}</drake:mu_dynamic>"
        "</drake:proximity_properties>")


def model_sdf(name: str, parts: Sequence[Part], contact: ContactProperties, *,
              compliant: bool = True, mass_kg: Optional[float] = None, inertia_kg_m2=None,
              p_LCm=(0.0, 0.0, 0.0)) -> str:
    """An SDFormat model with one link "body" holding ``parts``. Static (welded to
    the world) when ``mass_kg`` is None, else a free body with that mass, its centre
    of mass at ``p_LCm`` (m) in the link frame, and the principal moments
    ``inertia_kg_m2`` (3,) about the centre of mass."""
    elements = []
    if mass_kg is None:
        elements.append("<static>true</static>")
    link = []
    if mass_kg is not None:
        ixx, iyy, izz = inertia_kg_m2
        link.append(
            "<inertial><pose>{:.9g} {:.9g} {:.9g} 0 0 0</pose>".format(*p_LCm) +
            f"<mass>{mass_kg:.9g}</mass><inertia><ixx>{ixx:.9g}</ixx>"
            f"<iyy>{iyy:.9g}</iyy><izz>{izz:.9g}</izz><ixy>0</ixy><ixz>0</ixz><iyz>0</iyz>"
            "</inertia></inertial>")
    properties = proximity_properties_sdf(contact, compliant)
    for part in parts:
        pose = "<pose>{:.9g} {:.9g} {:.9g} 0 0 0</pose>".format(*part.p_LP)
        link.append(
            f'<visual name="{part.name}">{pose}<geometry>{part.geometry}</geometry>'
            "<material><diffuse>{:.3g} {:.3g} {:.3g} {:.3g}</diffuse></material></visual>"
            .format(*part.rgba))
        link.append(f'<collision name="{part.name}">{pose}<geometry>{part.geometry}</geometry>'
                    f"{properties}</collision>")
    elements.append('<link name="body">' + "".join(link) + "</link>")
    return ('<?xml version="1.0"?><sdf version="1.9" xmlns:drake="http://drake.mit.edu">'
            f'<model name="{name}">' + "".join(elements) + "</model></sdf>")


def tool_sdf(scene: SceneConfig) -> str:
    """The tool's model "tool": its link's frame is T (at the grip, I's origin when
    relaxed); the tool's shape and centre of mass are at ``tool_offset_m`` in T."""
    p_TA = tuple(float(v) for v in scene.tool_offset_m)
    if isinstance(scene, PegInHole):
        mass, solid = scene.peg_mass_kg, box_inertia(scene.peg_mass_kg, scene.peg_size_m)
        part = Part("peg", box_geometry(scene.peg_size_m), p_TA, PEG_RGBA)
    elif isinstance(scene, HangingBall):
        mass = scene.anchor_mass_kg
        solid = sphere_inertia(mass, scene.anchor_radius_m)
        part = Part("anchor", sphere_geometry(scene.anchor_radius_m), p_TA, ANCHOR_RGBA)
    else:
        mass, solid = scene.paddle_mass_kg, box_inertia(scene.paddle_mass_kg, scene.paddle_size_m)
        part = Part("paddle", box_geometry(scene.paddle_size_m), p_TA, PADDLE_RGBA)
    inertia = np.maximum(solid, scene.min_inertia_kg_m2)
    return model_sdf("tool", [part], scene.contact, compliant=False, mass_kg=mass,
                     inertia_kg_m2=inertia, p_LCm=p_TA)


def ball_sdf(radius_m: float, mass_kg: float, contact: ContactProperties) -> str:
    part = Part("ball", sphere_geometry(radius_m), (0, 0, 0), BALL_RGBA)
    return model_sdf("ball", [part], contact, mass_kg=mass_kg,
                     inertia_kg_m2=sphere_inertia(mass_kg, radius_m))


def block_sdf(scene: PegInHole) -> str:
    """The static plate "block": its four walls on one body, placed in W."""
    parts = [Part(name, box_geometry(size), centre, BLOCK_RGBA)
             for name, centre, size in hole_block_boxes(scene.block_size_m, scene.hole_size_m,
                                                        scene.hole_center_m)]
    return model_sdf("block", parts, scene.contact)


def register_table(plant: MultibodyPlant, top_z_m: float, contact: ContactProperties, *,
                   compliant: bool) -> None:
    """The table "table", on the world body before Finalize: for contact a half-space
    with its top at ``top_z_m`` in W, compliant (a slab TABLE_SLAB_M deep) or rigid;
    to see, a TABLE_SIZE_M box under that top."""
    properties = ProximityProperties()
    if compliant:
        AddCompliantHydroelasticPropertiesForHalfSpace(
            TABLE_SLAB_M, contact.hydroelastic_modulus_pa, properties)
    else:
        AddRigidHydroelasticProperties(properties)
    AddContactMaterial(contact.hunt_crossley_dissipation_s_per_m, None,
                       CoulombFriction(contact.friction, contact.friction), properties)
    world = plant.world_body()
    plant.RegisterCollisionGeometry(world, HalfSpace.MakePose([0.0, 0.0, 1.0], [0.0, 0.0, top_z_m]),
                                    HalfSpace(), "table", properties)
    plant.RegisterVisualGeometry(world, RigidTransform([0.0, 0.0, top_z_m - TABLE_SIZE_M[2] / 2]),
                                 Box(*TABLE_SIZE_M), "table", np.array(TABLE_RGBA))


# --- builder --------------------------------------------------------------------------

def AddScene(builder: DiagramBuilder, *, scene: SceneConfig, time_step_s: float,
             X_WI_start: RigidTransform, use_sampled_output_ports: bool = True,
             contact_sample_period_s: Optional[float] = None) -> SceneParts:
    """Add the scene's plant and scene graph, its models and its ports to ``builder``.

    The tool starts at X_WI_start * X_IT (X_IT the identity); the hanging ball at its static hanging
    point below the anchor; the paddle's ball at ``ball_start_m``; all at rest.
    A ValueError names a bad config field, or X_WI_start if it would start the
    tool or the ball inside the scene. ``use_sampled_output_ports=False`` (for
    linearization, DESIGN.md section 6) makes the plant's outputs, the contact
    wrench among them, functions of the current state instead of the last step's.
    ``contact_sample_period_s`` (s), when given, samples the contact wrench and
    the contact flag at that period instead of every step.
    """
    validate_scene(scene)
    positive("time_step_s", time_step_s)
    X_IT = RigidTransform()
    X_WT = X_WI_start @ X_IT
    overlap = start_overlap(scene, X_WT @ RigidTransform(np.asarray(scene.tool_offset_m, float)))
    if overlap is not None:
        raise ValueError(
            f"X_WI_start (p_WI = {np.round(X_WI_start.translation(), 6).tolist()} m): {overlap}; "
            "start the instrument where the tool and the ball are clear of the scene")
    config = MultibodyPlantConfig(time_step=time_step_s, discrete_contact_approximation="lagged",
                                  contact_model="hydroelastic_with_fallback",
                                  use_sampled_output_ports=use_sampled_output_ports)
    plant, scene_graph = AddMultibodyPlant(config, builder)
    plant.set_name("scene_plant")
    scene_graph.set_name("scene_graph")
    parser = Parser(plant)
    tool = parser.AddModelsFromString(tool_sdf(scene), "sdf")[0]
    plant.set_gravity_enabled(tool, False)
    ball = None
    if isinstance(scene, PegInHole):
        parser.AddModelsFromString(block_sdf(scene), "sdf")
    else:
        ball = parser.AddModelsFromString(
            ball_sdf(scene.ball_radius_m, scene.ball_mass_kg, scene.contact), "sdf")[0]
    table_z = table_top_z(scene)
    if table_z is not None:
        # The soft side against the table: the table itself under the rigid peg, the
        # compliant balls over a rigid table (Drake has no hydroelastic contact of a
        # compliant body with a compliant half-space).
        register_table(plant, table_z, scene.contact, compliant=isinstance(scene, PegInHole))
    tool_body = plant.GetBodyByName("body", tool)
    ball_body = None if ball is None else plant.GetBodyByName("body", ball)
    p_TA = np.asarray(scene.tool_offset_m, dtype=float)  # the tool's centre in T (m)
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

    gain = builder.AddNamedSystem("scene_tool_wrench", MatrixGain(
        wrench_to_generalized_force(tool_body.floating_velocities_start_in_v(),
                                    plant.num_velocities())))
    builder.Connect(gain.get_output_port(), plant.get_applied_generalized_force_input_port())
    split = builder.AddNamedSystem("scene_tool_state", Demultiplexer([7, 6]))
    builder.Connect(plant.get_state_output_port(tool), split.get_input_port())
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
