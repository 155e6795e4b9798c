"""Tissue in a model scene: each deformable body the scene's model files declare
(read by Drake, ``tissue_model.read_scene_tissue``) stepped at the haptic rate by
our linear corotated finite elements (``systems/tissue_fem.py``) in a
``DeformableBody`` system, the next tick on the other core, touched by the sphere
``ModelScene.tissue`` places on the tool.

``AddTissue`` takes the rigid scene's ``SceneParts`` (its plant holds the tool and
the scene's rigid models, never the tissue) and returns them with the tissue in:
each body's wrench on the tool added to the coupling's, and its contact wrench and
contact flag added to the rigid scene's, so the coupling, the supervisor, the log
and the plots treat tissue like any contact.

The substeps a tick come from the mesh and the material (``stable_substeps``: the
highest mode of the tissue with the probe's pressure stiffness times each boundary
node's share of the area on it); a
body that needs more than ``tissue.max_substeps`` is refused, naming its stiffest
material and the stable step.
"""

import dataclasses
from dataclasses import dataclass
from typing import List, Optional

import numpy as np
from pydrake.math import RigidTransform
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import Adder

from maglev_haptics.diagrams.scene import ModelScene, TissueContact
from maglev_haptics.diagrams.scene_builder import SceneParts
from maglev_haptics.diagrams.tissue_model import TissueBody
from maglev_haptics.systems.deformable_surface import DeformableBody, DeformableDynamics
from maglev_haptics.systems.step_worker import tick_server
from maglev_haptics.systems.surface_visualizer import surface_faces
from maglev_haptics.systems.tissue_fem import (
    TISSUE_TICK_ARGUMENTS, TissueModel, TissueProbe, contact_quadrature, highest_angular_frequency,
    stable_step_s, stable_substeps, state_contact, tick_arguments, tissue_model,
    tissue_tick_from)

TISSUE_SERVER = tick_server(tissue_tick_from, TISSUE_TICK_ARGUMENTS[3:])


@dataclass(eq=False)
class Tissue:
    """One tissue body in the diagram."""

    body: TissueBody
    model: TissueModel
    substeps: int  # symplectic Euler substeps a tick
    probe: TissueProbe  # the sphere's contact with it, its radius the sphere's
    system: DeformableBody
    faces: np.ndarray  # (3, T) int32: the boundary's triangles over surface_positions_m's rows


def kernel_model(body: TissueBody, contact: TissueContact) -> TissueModel:
    """The finite-element arrays of ``body`` at rest, under the scene's gravity."""
    return tissue_model(
        body.positions_m, body.tetrahedra, youngs_modulus_pa=body.youngs_modulus_pa,
        poissons_ratio=body.poissons_ratio, mass_density_kg_m3=body.mass_density_kg_m3,
        fixed=body.fixed, mass_damping_per_s=body.mass_damping_per_s,
        stiffness_damping_s=body.stiffness_damping_s, gravity_m_s2=contact.gravity_m_s2)


def tissue_substeps(body: TissueBody, model: TissueModel, contact: TissueContact,
                    period_s: float, path: str) -> int:
    """The stable substeps of a ``period_s`` (s) tick for ``model`` touched by the
    scene's probe; a ValueError if more than ``contact.max_substeps``."""
    probe_n_per_m3 = contact.probe.stiffness_n_per_m3
    substeps = stable_substeps(model, period_s, probe_stiffness_n_per_m3=probe_n_per_m3)
    if substeps > contact.max_substeps:
        step_s = stable_step_s(highest_angular_frequency(model, probe_n_per_m3),
                               model.mass_damping_per_s, model.stiffness_damping_s)
        raise ValueError(
            f"{path}: tissue {body.model}::{body.name} (E up to "
            f"{float(np.max(body.youngs_modulus_pa)):.4g} Pa, {model.num_tetrahedra} "
            f"tetrahedra) is stable in explicit steps of {1e6 * step_s:.0f} us at most: "
            f"{substeps} substeps a {1e3 * period_s:g} ms tick, more than "
            f"haptics.scene.tissue.max_substeps = {contact.max_substeps}; soften the material, "
            "coarsen the mesh (its smallest tetrahedra set the step), lower the probe's "
            "stiffness_n_per_m3 or the stiffness damping, or raise max_substeps (each substep "
            "is one more pass over the elements a tick)")
    return substeps


def tissue_dynamics(model: TissueModel, probe: TissueProbe, period_s: float,
                    substeps: int) -> DeformableDynamics:
    """What ``DeformableBody`` needs to step ``model`` a ``period_s`` (s) tick in
    ``substeps`` substeps, touched by ``probe``: the wrench on the tool the first
    substep's contact (``tissue_fem.state_contact``)."""
    constants, quadrature = probe.constants(), contact_quadrature()
    first_step_s = period_s / substeps

    def contact(state, p_TP):
        return state_contact(state, p_TP, model.triangles, model.triangle_rows, quadrature,
                             constants, first_step_s)
    return DeformableDynamics(
        node_mass_kg=model.mass_kg, surface_nodes=model.surface, tick=tissue_tick_from,
        tick_arguments=lambda: tick_arguments(model, probe, period_s, substeps),
        server=TISSUE_SERVER, state_contact=contact)


def probe_start_problem(body: TissueBody, p_WP, radius_m: float) -> Optional[str]:
    """A message if the probe sphere (centre p_WP in W, m) starts touching ``body``
    or inside its footprint below its top, else None."""
    p_WP = np.asarray(p_WP, float)
    nodes = body.positions_m
    near = np.linalg.norm(nodes - p_WP, axis=1) < radius_m
    lower, upper = nodes.min(axis=0), nodes.max(axis=0)
    inside = bool(np.all(p_WP[:2] > lower[:2]) and np.all(p_WP[:2] < upper[:2])
                  and lower[2] < p_WP[2] < upper[2])
    if near.any() or inside:
        return (f"the probe (centre {np.round(p_WP, 4).tolist()} m, radius {radius_m} m) "
                f"starts in tissue {body.model}::{body.name} (its nodes span z "
                f"{lower[2]:.4g} to {upper[2]:.4g} m)")
    return None


def _sum(builder: DiagramBuilder, name: str, ports) -> object:
    """The sum of ``ports`` (one vector size), or the port itself if it is alone."""
    if len(ports) == 1:
        return ports[0]
    adder = builder.AddNamedSystem(name, Adder(len(ports), ports[0].size()))
    for i, port in enumerate(ports):
        builder.Connect(port, adder.get_input_port(i))
    return adder.get_output_port()


def AddTissue(builder: DiagramBuilder, *, scene: ModelScene, bodies: List[TissueBody],
              parts: SceneParts, time_step_s: float, X_WT_start: RigidTransform,
              rigid_contact: bool = True, path: str = "haptics.scene") -> SceneParts:
    """Add a ``DeformableBody`` for each of ``bodies`` to ``builder``, wired to the
    tool of ``parts`` (the rigid scene's), and return ``parts`` with the tissue in
    (``tissue`` the list of ``Tissue``). ``rigid_contact``: whether the rigid scene
    has anything besides the tool to touch (else its contact ports are left out of
    the sums). A ValueError names the field: a probe the tool cannot place, a tool
    that starts in the tissue, a body that needs more than ``max_substeps``."""
    contact = scene.tissue
    p_TP, radius_m = contact.sphere(scene.tool, f"{path}.tissue")
    probe = dataclasses.replace(contact.probe, radius_m=radius_m)
    p_WP = X_WT_start @ np.asarray(p_TP, float)
    tissues = []
    for body in bodies:
        problem = probe_start_problem(body, p_WP, radius_m)
        if problem is not None:
            raise ValueError(
                f"X_WI_start (p_WI = {np.round(X_WT_start.translation(), 6).tolist()} m): "
                f"{problem}; start the instrument where the probe is clear of the tissue "
                "(motion.start_xy_yaw, the hand's first pose)")
        model = kernel_model(body, contact)
        substeps = tissue_substeps(body, model, contact, time_step_s, path)
        system = builder.AddNamedSystem(f"tissue_{body.model}_{body.name}", DeformableBody(
            dynamics=tissue_dynamics(model, probe, time_step_s, substeps),
            positions_m=body.positions_m, p_TP_m=p_TP, X_WT_start=X_WT_start,
            period_s=time_step_s, worker_thread=contact.worker_thread))
        builder.Connect(parts.X_WT_output, system.GetInputPort("X_WT"))
        builder.Connect(parts.V_WT_output, system.GetInputPort("V_WT"))
        tissues.append(Tissue(body=body, model=model, substeps=substeps, probe=probe,
                              system=system,
                              faces=surface_faces(model.surface, model.triangles)))
    wrenches = [tissue.system.GetOutputPort("wrench_on_tool_W") for tissue in tissues]
    flags = [tissue.system.GetOutputPort("in_contact") for tissue in tissues]
    coupling = builder.AddNamedSystem("tissue_tool_wrench_sum", Adder(len(tissues) + 1, 6))
    builder.Connect(coupling.get_output_port(), parts.wrench_on_tool_input)
    for i, port in enumerate(wrenches):
        builder.Connect(port, coupling.get_input_port(i + 1))
    rigid = ([parts.contact_wrench_output], [parts.in_contact_output]) if rigid_contact \
        else ([], [])
    return dataclasses.replace(
        parts, wrench_on_tool_input=coupling.get_input_port(0),
        contact_wrench_output=_sum(builder, "tool_contact_wrench_sum", rigid[0] + wrenches),
        in_contact_output=_sum(builder, "tool_in_contact_sum", rigid[1] + flags),
        tissue=tissues)
