"""SDFormat text of generated scene models, and the table, so every size and
contact property comes from the scenario; nothing is read from files.

``contact`` arguments carry ``hydroelastic_modulus_pa`` (Pa),
``hunt_crossley_dissipation_s_per_m`` (s/m), ``friction`` (-) and
``resolution_hint_m`` (m), as the scenario's ContactProperties do.
"""

from typing import NamedTuple, Optional, Sequence

import numpy as np
from pydrake.geometry import (
    AddCompliantHydroelasticPropertiesForHalfSpace, AddContactMaterial,
    AddRigidHydroelasticProperties, Box, HalfSpace, ProximityProperties)
from pydrake.math import RigidTransform
from pydrake.multibody.plant import CoulombFriction, MultibodyPlant

from maglev_haptics.plant_models.scene_geometry import sphere_inertia

# The table's visual box, x, y, z (m), centred on W's z axis under the table's top;
# for contact the table is a half-space.
TABLE_SIZE_M = (0.24, 0.18, 0.010)
# Depth of the compliant half-space's slab (m): the pressure rises from 0 at the
# table's top to the modulus this deep, as in a 20 mm thick compliant box. At 1e6 Pa
# the peg's 25 x 25 mm face then meets 1e6 * 6.25e-4 / 0.010 = 62.5 N/mm.
TABLE_SLAB_M = 0.010
PROBE_SHAFT_RADIUS_M = 0.0015  # the deformable scene's probe shaft, drawn only (m)

# Visual colours, RGBA.
PROBE_RGBA = (0.75, 0.75, 0.78, 1.0)
PEG_RGBA = (0.20, 0.45, 0.85, 1.0)
PADDLE_RGBA = (0.90, 0.50, 0.10, 1.0)
ANCHOR_RGBA = (0.30, 0.30, 0.35, 1.0)
BALL_RGBA = (0.85, 0.15, 0.15, 1.0)
BLOCK_RGBA = (0.80, 0.65, 0.40, 1.0)
TABLE_RGBA = (0.35, 0.55, 0.40, 1.0)



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


def proximity_properties_sdf(contact, compliant: bool = True) -> str:
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


def model_sdf(name: str, parts: Sequence[Part], contact, *,
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


def register_table(plant: MultibodyPlant, top_z_m: float, contact, *,
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


def probe_tool_sdf(p_TP_m, radius_m: float, mass_kg: float, min_inertia_kg_m2: float) -> str:
    """The tool "tool": link frame T at the grip (I's origin when relaxed), a shaft
    from T down to the probe sphere (``radius_m``) centred at ``p_TP_m`` in T (m);
    visuals only. Its mass ``mass_kg`` sits at the sphere, its principal moments
    raised to ``min_inertia_kg_m2`` (kg*m^2)."""
    p_TP = np.asarray(p_TP_m, dtype=float)
    radius = radius_m
    shaft_length = max(float(np.linalg.norm(p_TP)) - radius, 1e-4)
    axis = p_TP / np.linalg.norm(p_TP) if np.linalg.norm(p_TP) > 0 else np.array([0, 0, -1.0])
    # The shaft's cylinder runs along its own z: Rz(yaw) Ry(pitch) turns z onto T -> P.
    pitch = float(np.arccos(np.clip(axis[2], -1.0, 1.0)))
    yaw = float(np.arctan2(axis[1], axis[0]))
    centre = axis * shaft_length / 2
    inertia = np.maximum(sphere_inertia(mass_kg, radius), min_inertia_kg_m2)
    material = "<material><diffuse>{:.3g} {:.3g} {:.3g} {:.3g}</diffuse></material>".format(
        *PROBE_RGBA)
    return (
        '<?xml version="1.0"?><sdf version="1.9"><model name="tool"><link name="body">'
        "<inertial><pose>{:.9g} {:.9g} {:.9g} 0 0 0</pose>".format(*p_TP) +
        f"<mass>{mass_kg:.9g}</mass><inertia><ixx>{inertia[0]:.9g}</ixx>"
        f"<iyy>{inertia[1]:.9g}</iyy><izz>{inertia[2]:.9g}</izz><ixy>0</ixy><ixz>0</ixz>"
        "<iyz>0</iyz></inertia></inertial>"
        '<visual name="tip"><pose>{:.9g} {:.9g} {:.9g} 0 0 0</pose>'.format(*p_TP) +
        f"<geometry><sphere><radius>{radius:.9g}</radius></sphere></geometry>{material}</visual>"
        '<visual name="shaft"><pose>{:.9g} {:.9g} {:.9g} 0 {:.9g} {:.9g}</pose>'.format(
            *centre, pitch, yaw) +
        f"<geometry><cylinder><radius>{PROBE_SHAFT_RADIUS_M:.9g}</radius>"
        f"<length>{shaft_length:.9g}</length></cylinder></geometry>{material}</visual>"
        "</link></model></sdf>")
