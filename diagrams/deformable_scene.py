"""The deformable scene (the paper's Section V.D): a probe on the tool touches a
mass-spring-damper lattice built under a heightmap.

``AddDeformableScene`` gives the same ``SceneParts`` as ``AddScene``, so the
coupling, the supervisor, the log and the plots treat it like the rigid scenes:
the tool is a free body in its own MultibodyPlant (no collision geometry; its
weight is off, as for the rigid tools), driven by the coupling's wrench plus
the lattice's contact wrench; the lattice is a ``DeformableBody`` system stepped
at the control period by the lattice's tick (``lattice_dynamics``), reading the
tool's pose and velocity.
"""

from dataclasses import dataclass, field
from typing import List

import numpy as np
from pydrake.math import RigidTransform
from pydrake.multibody.parsing import Parser
from pydrake.multibody.plant import AddMultibodyPlant, MultibodyPlantConfig
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import Adder, Demultiplexer, MatrixGain

from maglev_haptics.diagrams.scene_builder import SceneParts, wrench_to_generalized_force
from maglev_haptics.hardware.config_checks import finite, nonnegative, positive, require, vector
from maglev_haptics.hardware.constants import GRAVITY_M_S2
from maglev_haptics.plant_models.scene_sdf import probe_tool_sdf
from maglev_haptics.systems.deformable_surface import (
    DeformableBody, DeformableDynamics)
from maglev_haptics.systems.heightmap import (
    Heightmap, ImageHeightmap, RandomHeightmap, heightmap_heights)
from maglev_haptics.systems.lattice_construction import Lattice, build_lattice
from maglev_haptics.systems.lattice_dynamics import (
    INTEGRATORS, LINEARLY_IMPLICIT, SYMPLECTIC_EULER, TICK_ARGUMENTS, LatticeModel, ProbeContact,
    implicit_workspace, lattice_model, max_stable_link_stiffness, state_contact, tick_from)
from maglev_haptics.systems.step_worker import tick_server

# The worker loop for the lattice's tick (its arguments after masses in, out and probe).
LATTICE_SERVER = tick_server(tick_from, TICK_ARGUMENTS[3:])


@dataclass
class DeformableSurface:
    """A jelly landscape: the lattice under a heightmap, and the probe that touches it.

    The lattice covers ``size_m`` (x, y) centred on ``center_m`` in W with
    columns every ``column_spacing_m``; its masses fill each column from
    ``base_z_m`` up to the surface at ``surface_z_m`` plus the heightmap, on
    levels ``level_spacing_m`` apart, respaced evenly (the paper's Fig. 7c).
    Bottom and edge masses are fixed. Every link has the same stiffness and
    damping. The defaults (33 x 25 columns, 5,357 masses, 58,715 links) are heavy
    enough for one symplectic Euler step a millisecond at 250 N/m links (the
    limit, ``max_stable_link_stiffness``, is ~320 N/m), and jiggle visibly.
    """

    size_m: List[float] = field(default_factory=lambda: [0.080, 0.060])  # x, y (m)
    center_m: List[float] = field(default_factory=lambda: [0.0, 0.0])  # x, y in W (m)
    column_spacing_m: float = 0.0025  # (m)
    level_spacing_m: float = 0.003  # (m)
    base_z_m: float = -0.030  # the fixed bottom layer, in W (m)
    surface_z_m: float = -0.015  # mean height of the surface in W (m)
    heightmap: Heightmap = field(default_factory=RandomHeightmap)
    # Every mass (kg): with explicit steps the node mass is a stability parameter (mass
    # scaling); the linearly implicit integrator allows lighter, stiffer lattices.
    node_mass_kg: float = 0.002
    link_stiffness_n_per_m: float = 250.0  # every link (N/m); explicit limit ~320 here
    link_damping_n_s_per_m: float = 0.07  # every link, along it (N*s/m)
    integrator: str = "symplectic_euler"  # or "linearly_implicit"
    substeps: int = 1  # symplectic Euler substeps per control tick
    cg_tolerance: float = 1e-4  # linearly implicit: relative CG residual
    cg_max_iterations: int = 40  # linearly implicit: CG iteration cap
    # Step the lattice one tick ahead on another core, while the rest of the diagram
    # computes (``systems/step_worker.py``); false: in the update itself. Same results.
    worker_thread: bool = True
    gravity_m_s2: List[float] = field(default_factory=lambda: [0.0, 0.0, -GRAVITY_M_S2])  # on the lattice
    probe: ProbeContact = field(default_factory=ProbeContact)
    # The probe sphere's centre in I (m): a tip below the instrument.
    tool_offset_m: List[float] = field(default_factory=lambda: [0.0, 0.0, -0.030])
    tool_mass_kg: float = 0.015  # (kg); >= 10 g for the explicit coupling
    min_inertia_kg_m2: float = 5e-6  # floor of the tool's principal moments (kg*m^2)

    def validate(self, path: str = "scene") -> None:
        """Range checks; a ValueError names ``path.field``, its value and what is allowed."""
        vector(f"{path}.size_m", self.size_m, positive=True, length=2)
        vector(f"{path}.center_m", self.center_m, length=2)
        positive(f"{path}.column_spacing_m", self.column_spacing_m)
        for i in range(2):
            require(self.size_m[i] >= 2 * self.column_spacing_m, f"{path}.size_m[{i}]",
                    self.size_m[i], f"at least 2 column spacings ({2 * self.column_spacing_m} m)")
        positive(f"{path}.level_spacing_m", self.level_spacing_m)
        require(finite(self.base_z_m), f"{path}.base_z_m", self.base_z_m, "a finite number")
        require(finite(self.surface_z_m) and self.surface_z_m > self.base_z_m,
                f"{path}.surface_z_m", self.surface_z_m,
                f"a finite height above base_z_m ({self.base_z_m} m)")
        self.heightmap.validate(f"{path}.heightmap")
        if isinstance(self.heightmap, ImageHeightmap):
            # Black lies at most height_m under the mean, surface_z_m: keep it above the base.
            depth_m = self.surface_z_m - self.base_z_m
            require(self.heightmap.height_m < depth_m, f"{path}.heightmap.height_m",
                    self.heightmap.height_m, f"must be below surface_z_m - base_z_m "
                    f"({depth_m:.4g} m), so black stays above the lattice's base")
        positive(f"{path}.node_mass_kg", self.node_mass_kg)
        positive(f"{path}.link_stiffness_n_per_m", self.link_stiffness_n_per_m)
        nonnegative(f"{path}.link_damping_n_s_per_m", self.link_damping_n_s_per_m)
        require(self.integrator in INTEGRATORS, f"{path}.integrator", self.integrator,
                f"one of {', '.join(INTEGRATORS)}")
        require(isinstance(self.substeps, int) and self.substeps >= 1, f"{path}.substeps",
                self.substeps, "an integer >= 1")
        positive(f"{path}.cg_tolerance", self.cg_tolerance)
        require(isinstance(self.cg_max_iterations, int) and self.cg_max_iterations >= 1,
                f"{path}.cg_max_iterations", self.cg_max_iterations, "an integer >= 1")
        vector(f"{path}.gravity_m_s2", self.gravity_m_s2)
        self.probe.validate(f"{path}.probe")
        vector(f"{path}.tool_offset_m", self.tool_offset_m)
        positive(f"{path}.tool_mass_kg", self.tool_mass_kg)
        nonnegative(f"{path}.min_inertia_kg_m2", self.min_inertia_kg_m2)


def lattice_dynamics(model: LatticeModel, *, probe: ProbeContact, period_s: float,
                     integrator: str, substeps: int = 1, cg_tolerance: float = 1e-4,
                     cg_max_iterations: int = 40) -> DeformableDynamics:
    """The lattice ``model`` stepped by ``tick_from`` each ``period_s`` (s) with
    ``integrator``: symplectic Euler in ``substeps``, or linearly implicit to the
    relative CG residual ``cg_tolerance`` in at most ``cg_max_iterations``."""
    implicit = integrator == LINEARLY_IMPLICIT
    n = len(model.mass_kg)
    contact_constants = probe.constants()
    constants = np.append(contact_constants, [period_s, cg_tolerance])

    def tick_arguments():
        # After the model's arrays: no external forces (N), the constants, the integrator's
        # flag and counts, then work space of both integrators (forces (N), implicit's).
        return (*model.topology, model.rest_lengths_m, model.stiffness_n_per_m,
                model.damping_n_s_per_m, model.mass_kg, model.inv_mass_per_kg,
                model.gravity_m_s2, model.surface, np.zeros((n, 3)), constants, implicit,
                int(substeps), int(cg_max_iterations), np.zeros((n, 3)),
                *implicit_workspace(n, len(model.links)))
    first_step_s = period_s if implicit else period_s / substeps

    def contact(state, p_TP):
        return state_contact(state, model.surface, p_TP, contact_constants, model.mass_kg,
                             first_step_s)
    return DeformableDynamics(
        node_mass_kg=model.mass_kg, surface_nodes=model.surface, tick=tick_from,
        tick_arguments=tick_arguments, server=LATTICE_SERVER, state_contact=contact)


def lattice_grid(scene: DeformableSurface):
    """(x_m (nx,), y_m (ny,)): the columns' positions in W (m)."""
    axes = []
    for i in range(2):
        count = int(round(scene.size_m[i] / scene.column_spacing_m)) + 1
        half = (count - 1) * scene.column_spacing_m / 2
        axes.append(scene.center_m[i] + np.linspace(-half, half, count))
    return axes[0], axes[1]


def build_scene_lattice(scene: DeformableSurface) -> Lattice:
    """The lattice of ``scene`` at rest."""
    x_m, y_m = lattice_grid(scene)
    heights = scene.surface_z_m + heightmap_heights(scene.heightmap, x_m, y_m)
    return build_lattice(heights, x_m, y_m, scene.base_z_m, scene.level_spacing_m)


def check_explicit_stability(scene: DeformableSurface, lattice: Lattice, time_step_s: float,
                             label: str = "haptics.scene") -> None:
    """A ValueError if symplectic Euler would blow this lattice up at ``time_step_s`` (s)."""
    if scene.integrator != SYMPLECTIC_EULER:
        return
    limit = max_stable_link_stiffness(
        lattice.positions_m, lattice.links, lattice.fixed, node_mass_kg=scene.node_mass_kg,
        link_damping_n_s_per_m=scene.link_damping_n_s_per_m, time_step_s=time_step_s,
        substeps=scene.substeps)
    if scene.link_stiffness_n_per_m >= limit:
        cause = (f"must be below {limit:.4g} N/m" if limit > 0 else
                 f"cannot be stable: link_damping_n_s_per_m = {scene.link_damping_n_s_per_m} "
                 "alone is too much")
        raise ValueError(
            f"{label}.link_stiffness_n_per_m = {scene.link_stiffness_n_per_m}: {cause} for "
            f"symplectic Euler with {scene.substeps} substep(s) of the {1e3 * time_step_s:g} ms "
            f"tick on this lattice ({scene.node_mass_kg} kg nodes); raise substeps or "
            "node_mass_kg, or use integrator: linearly_implicit")


def probe_start_overlap(scene: DeformableSurface, lattice: Lattice, X_WT: RigidTransform):
    """A message if the probe at X_WT starts touching or under the surface, else None."""
    p_WP = X_WT @ np.asarray(scene.tool_offset_m, dtype=float)
    surface = lattice.positions_m[lattice.surface.ravel()]
    near = np.hypot(surface[:, 0] - p_WP[0], surface[:, 1] - p_WP[1]) < scene.probe.radius_m
    x_m, y_m = lattice.x_m, lattice.y_m
    r = scene.probe.radius_m
    over = x_m[0] - r <= p_WP[0] <= x_m[-1] + r and y_m[0] - r <= p_WP[1] <= y_m[-1] + r
    if not over:
        return None
    highest = surface[near, 2].max() if near.any() else surface[:, 2].max()
    if p_WP[2] - r <= highest:
        return (f"the probe (centre at z = {p_WP[2]:.4g} m, radius {r} m) "
                f"starts in the surface (up to z = {highest:.4g} m under it)")
    return None


def AddDeformableScene(builder: DiagramBuilder, *, scene: DeformableSurface, time_step_s: float,
                       X_WI_start: RigidTransform) -> SceneParts:
    """Add the tool's plant and scene graph and the lattice to ``builder``.

    The tool starts at X_WI_start (X_IT the identity), at rest; the lattice at rest
    as built. A ValueError names a bad config field (a link stiffness symplectic
    Euler cannot step among them), or X_WI_start if the probe would start in or
    under the surface."""
    scene.validate()
    positive("time_step_s", time_step_s)
    lattice = build_scene_lattice(scene)
    check_explicit_stability(scene, lattice, time_step_s)
    X_IT = RigidTransform()
    X_WT = X_WI_start @ X_IT
    overlap = probe_start_overlap(scene, lattice, X_WT)
    if overlap is not None:
        raise ValueError(f"X_WI_start (p_WI = {np.round(X_WI_start.translation(), 6).tolist()} "
                         f"m): {overlap}; rest the instrument beside the lattice "
                         "(motion.start_xy_yaw) or move the lattice (center_m, size_m)")
    plant, scene_graph = AddMultibodyPlant(
        MultibodyPlantConfig(time_step=time_step_s, use_sampled_output_ports=False), builder)
    plant.set_name("scene_plant")
    scene_graph.set_name("scene_graph")
    tool = Parser(plant).AddModelsFromString(probe_tool_sdf(
        scene.tool_offset_m, scene.probe.radius_m, scene.tool_mass_kg, scene.min_inertia_kg_m2),
        "sdf")[0]
    plant.set_gravity_enabled(tool, False)
    plant.Finalize()
    tool_body = plant.GetBodyByName("body", tool)
    plant.SetDefaultFloatingBaseBodyPose(tool_body, X_WT)

    model = lattice_model(lattice.links, lattice.rest_lengths_m, lattice.fixed, lattice.surface,
                          node_mass_kg=scene.node_mass_kg,
                          link_stiffness_n_per_m=scene.link_stiffness_n_per_m,
                          link_damping_n_s_per_m=scene.link_damping_n_s_per_m,
                          gravity_m_s2=scene.gravity_m_s2)
    surface = builder.AddNamedSystem("deformable_surface", DeformableBody(
        dynamics=lattice_dynamics(model, probe=scene.probe, period_s=time_step_s,
                                  integrator=scene.integrator, substeps=scene.substeps,
                                  cg_tolerance=scene.cg_tolerance,
                                  cg_max_iterations=scene.cg_max_iterations),
        positions_m=lattice.positions_m, p_TP_m=scene.tool_offset_m, X_WT_start=X_WT,
        period_s=time_step_s, worker_thread=scene.worker_thread))
    total = builder.AddNamedSystem("scene_tool_wrench_sum", Adder(2, 6))
    gain = builder.AddNamedSystem("scene_tool_wrench", MatrixGain(
        wrench_to_generalized_force(tool_body.floating_velocities_start_in_v(),
                                    plant.num_velocities())))
    builder.Connect(total.get_output_port(), gain.get_input_port())
    builder.Connect(gain.get_output_port(), plant.get_applied_generalized_force_input_port())
    split = builder.AddNamedSystem("scene_tool_state", Demultiplexer([7, 6]))
    builder.Connect(plant.get_state_output_port(tool), split.get_input_port())
    builder.Connect(split.get_output_port(0), surface.GetInputPort("X_WT"))
    builder.Connect(split.get_output_port(1), surface.GetInputPort("V_WT"))
    builder.Connect(surface.GetOutputPort("wrench_on_tool_W"), total.get_input_port(1))
    return SceneParts(
        plant=plant, scene_graph=scene_graph, tool_body=tool_body, X_IT=X_IT, ball_body=None,
        wrench_on_tool_input=total.get_input_port(0), X_WT_output=split.get_output_port(0),
        V_WT_output=split.get_output_port(1),
        contact_wrench_output=surface.GetOutputPort("wrench_on_tool_W"),
        in_contact_output=surface.GetOutputPort("in_contact"), surface=surface, lattice=lattice)
