"""Tissue: the deformable bodies of a ``ModelScene``'s model files, read by Drake.

A model file declares a deformable body the Drake way: an SDFormat ``<link>`` with
``<drake:deformable_properties>`` (Young's modulus, Poisson's ratio, mass density,
Rayleigh mass and stiffness damping, material model), one ``<collision>`` whose
``<mesh>`` is a tetrahedral ``.vtk``, a ``<drake:wall_boundary_condition>`` fixing
the nodes beyond a plane (written in W), and its colour from an ``<empty/>``
``<visual>``'s ``<diffuse>``. A stiffer inclusion is the ``.vtk``'s cell data
``youngs_modulus`` (Pa, one value a tetrahedron; see
``plant_models/tissue_meshes.py`` for why).

``read_scene_tissue`` hands the models that hold deformable bodies (found by
``holds_tissue``'s look at their files) to Drake's parser in a scratch plant,
takes each body's reference positions, tetrahedra, material and colour from what
Drake parsed, and its fixed nodes by Drake's own rule: one 1 ms step from rest
under gravity leaves exactly the wall's nodes where they were (Drake 1.58 does not
report the wall condition to Python). Only the cell data is read besides (meshio,
from the file the body's collision mesh names). The rest of the directives are for
the rigid scene plant, which then never steps Drake's FEM.

A ValueError, one line naming the directive, model and body, the value and what is
allowed, for: a surface mesh (triangles, an OBJ) declared deformable; a tetrahedron
of volume <= 0 (Drake's check, its volume added); no fixed node (the body would fall
forever) or no free one; a material model other than ``linear_corotated`` (the
haptic kernel's element); a material out of range (Drake's checks, and a Poisson's
ratio < 0 or anything not finite); cell data of the wrong length or not > 0; a
model that holds a deformable body and rigid links too; one added inside an
add_directives file; a tissue welded or named by another directive (a deformable body
has no frame), a pose in another frame than W, or one for a body the model does not
have.

A tissue is placed where its file puts it (its link's ``<pose>``), or where its
add_model's ``default_free_body_pose`` puts its link (in W, as Drake places a free
rigid body): the whole body moved rigidly from the file's placement, the wall's nodes
with it. Drake 1.58 itself pins the wall's nodes at the file's placement and tears a
posed body, so the body is read at the file's placement (the pose left out) and moved
after, its fixed nodes found there.
"""

import re
from dataclasses import dataclass
from typing import List, NamedTuple

import meshio
import numpy as np
from pydrake.math import RigidTransform
from pydrake.multibody.parsing import (
    AddModel, ModelDirective, ModelDirectives, ProcessModelDirectives)
from pydrake.multibody.plant import AddMultibodyPlant, MultibodyPlantConfig
from pydrake.multibody.fem import MaterialModel
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder

from maglev_haptics.diagrams.scene_models import (
    drake_reason, scene_parser, tissue_directive_indices)
from maglev_haptics.hardware.config_checks import require
from maglev_haptics.plant_models.tissue_meshes import (
    TISSUE_RGBA, YOUNGS_MODULUS_CELL_DATA, read_cell_youngs_modulus, tetrahedron_volumes)

SUPPORTED_MATERIAL = "linear_corotated"
STEP_S = 1e-3  # the scratch plant's step, which finds the fixed nodes (s)
MATERIAL_NAMES = {MaterialModel.kLinear: "linear", MaterialModel.kLinearCorotated:
                  "linear_corotated", MaterialModel.kCorotated: "corotated",
                  MaterialModel.kNeoHookean: "neohookean"}  # as drake:material_model spells them
# Physical ranges of the body's material (SI); the haptic kernel's stable step is the
# finite-element system's check.
POISSONS_RATIO_RANGE = (0.0, 0.5)  # [min, max) (-); 0.5 is incompressible


@dataclass(eq=False)
class TissueBody:
    """One deformable body as Drake parsed it. Nodes at their reference positions."""

    name: str  # the link's name
    model: str  # its model instance's name
    mesh_file: str  # the tetrahedral .vtk its collision names
    positions_m: np.ndarray  # (n, 3) nodes in W (m)
    tetrahedra: np.ndarray  # (m, 4) int64 node indices, positively oriented
    youngs_modulus_pa: np.ndarray  # (m,) per tetrahedron (Pa)
    poissons_ratio: float  # (-)
    mass_density_kg_m3: float
    mass_damping_per_s: float  # Rayleigh alpha: D = alpha M + beta K (1/s)
    stiffness_damping_s: float  # Rayleigh beta (s)
    material_model: str  # "linear_corotated"
    fixed: np.ndarray  # (n,) bool: nodes the wall condition holds
    rgba: np.ndarray  # (4,) diffuse colour


class SceneTissue(NamedTuple):
    """A scene's deformable bodies and the directives for its rigid plant (the
    scene's own, less the add_model of each model holding a deformable body)."""

    bodies: List[TissueBody]
    rigid_directives: List[ModelDirective]


def read_scene_tissue(directives: List[ModelDirective],
                      path: str = "scene.directives") -> SceneTissue:
    """The deformable bodies the directives' models declare, as Drake reads them,
    and the directives for the rigid plant. A ValueError (one line) names
    ``path[i]``, the model and body, the value and what is allowed."""
    directives = list(directives)
    builder = DiagramBuilder()
    plant, scene_graph = AddMultibodyPlant(MultibodyPlantConfig(
        time_step=STEP_S, discrete_contact_approximation="sap"), builder)
    parser = scene_parser(plant)
    tissue = tissue_directive_indices(parser, directives, path)
    if not tissue:
        return SceneTissue([], directives)
    names = {directives[i].add_model.name: i for i in tissue}
    for i, directive in enumerate(directives):
        _check_not_welded(directive, names, f"{path}[{i}]")
    fields = {name: f"{path}[{i}].add_model.file = {directives[i].add_model.file!r}"
              for name, i in names.items()}
    poses = {name: _directive_poses(directives[i].add_model, f"{path}[{i}].add_model")
             for name, i in names.items()}
    for name, i in names.items():  # one at a time, so that an error names its directive
        unposed = ModelDirective(add_model=AddModel(file=directives[i].add_model.file,
                                                    name=name))
        try:
            ProcessModelDirectives(ModelDirectives(directives=[unposed]), parser)
        except Exception as error:  # Drake's parser: RuntimeError, its YAML's ValueError
            raise ValueError(f"{fields[name]}: model {name!r}: "
                             f"{_deformable_reason(drake_reason(error))}") from None
    plant.Finalize()
    deformable = plant.deformable_model()
    bodies = [deformable.GetBody(body_id) for name in names
              for body_id in deformable.GetBodyIds(plant.GetModelInstanceByName(name))]
    holding = {plant.GetModelInstanceName(body.model_instance()) for body in bodies}
    for name in holding:
        rigid = [plant.get_body(index).name()
                 for index in plant.GetBodyIndices(plant.GetModelInstanceByName(name))]
        if rigid:
            raise ValueError(f"{fields[name]}: model {name!r} holds a deformable body and rigid "
                             f"links ({', '.join(rigid)}); put them in two model files")
    for name, posed in poses.items():
        known = [body.name() for body in bodies
                 if plant.GetModelInstanceName(body.model_instance()) == name]
        for body_name in posed:
            require(body_name in known,
                    f"{path}[{names[name]}].add_model.default_free_body_pose", body_name,
                    f"must name a deformable body of model {name!r}: {', '.join(known)}")
    inspector = scene_graph.model_inspector()
    read = []
    for body, (before, after) in zip(bodies, _one_step(builder.Build(), plant, bodies)):
        model = plant.GetModelInstanceName(body.model_instance())
        tissue_body = _tissue_body(inspector, body, model, before, after, fields[model])
        X_WB = poses[model].get(body.name())
        if X_WB is not None:  # moved from where the file puts it, its wall's nodes along
            X_BW_file = inspector.GetPoseInFrame(body.geometry_id()).inverse()
            tissue_body.positions_m = (X_WB @ X_BW_file).multiply(
                tissue_body.positions_m.T).T
        read.append(tissue_body)
    rigid_directives = [directive for i, directive in enumerate(directives)
                        if i not in tissue or directive.add_model.name not in holding]
    return SceneTissue(read, rigid_directives)


def _directive_poses(model: AddModel, path: str) -> dict:
    """{body name: X_WB} of a tissue's add_model ``model``'s default_free_body_pose
    (Drake's loader allows only fixed ones); a ValueError names ``path``'s field for a
    pose in another frame than W, or joint positions."""
    require(not model.default_joint_positions, f"{path}.default_joint_positions",
            dict(model.default_joint_positions), "must be empty: a deformable body has no joint")
    poses = {}
    for body, pose in model.default_free_body_pose.items():
        field = f"{path}.default_free_body_pose.{body}"
        require(pose.base_frame in (None, "", "world"), f"{field}.base_frame", pose.base_frame,
                "must be world (or left out): a tissue is placed in W")
        poses[body] = RigidTransform(pose.GetDeterministicValue())
    return poses


def _check_not_welded(directive: ModelDirective, tissue_models: dict, path: str) -> None:
    """A ValueError if ``directive`` welds or attaches to a tissue model's frame."""
    named = []
    if directive.add_weld is not None:
        named += [("add_weld.parent", directive.add_weld.parent),
                  ("add_weld.child", directive.add_weld.child)]
    if directive.add_frame is not None:
        named.append(("add_frame.X_PF.base_frame", directive.add_frame.X_PF.base_frame))
    for field, frame in named:
        if frame and frame.split("::")[0] in tissue_models:
            raise ValueError(f"{path}.{field} = {frame!r}: model {frame.split('::')[0]!r} "
                             "declares a deformable body, which has no frame to weld or "
                             "attach to; place it by its link's <pose> or its add_model's "
                             "default_free_body_pose")


def _deformable_reason(reason: str) -> str:
    """Drake's parse error, with what it means where a deformable body's mesh is a
    surface or holds an inverted tetrahedron (then with its volume, m^3)."""
    if "wrong extension type" in reason or "should only contain tetrahedra" in reason:
        return ("a deformable body's <collision> <mesh> must be a tetrahedral volume mesh "
                f"(a .vtk of tetra cells), not a surface; Drake: {reason}")
    inverted = re.search(r"MakeVolumeMeshFromVtk\('([^']*)'\).*The (\d+)-th tetrahedron", reason)
    if inverted is None:
        return reason
    mesh = meshio.read(inverted[1])
    index = int(inverted[2])
    volume = tetrahedron_volumes(mesh.points, mesh.cells_dict["tetra"][index:index + 1])[0]
    return (f"{inverted[1]}: tetrahedron {index} has volume {volume:.3g} m^3: each must be "
            "> 0, its 4th node on the side its first three's right-hand normal points to "
            "(an inverted or flat tetrahedron)")


def _one_step(diagram, plant, bodies) -> list:
    """Per body, its nodes' positions (n, 3) in W (m) at rest in the default state
    and after one step under gravity."""
    simulator = Simulator(diagram)
    context = plant.GetMyContextFromRoot(simulator.get_mutable_context())
    before = [np.array(body.GetPositions(context)).T for body in bodies]
    simulator.AdvanceTo(STEP_S)
    return [(q0, np.array(body.GetPositions(context)).T) for body, q0 in zip(bodies, before)]


def _tissue_body(inspector, body, model: str, before: np.ndarray, after: np.ndarray,
                 field: str) -> TissueBody:
    """TissueBody of Drake's deformable ``body``; ``before`` and ``after`` one step
    (nodes (n, 3), m); a ValueError names ``field``, the model and the body."""
    where = f"{field}: model {model!r}, body {body.name()!r}"
    reference = np.asarray(body.reference_positions()).reshape(-1, 3)  # (m)
    config = body.config()
    material = MATERIAL_NAMES.get(config.material_model(), str(config.material_model()))
    if material != SUPPORTED_MATERIAL:
        raise ValueError(f"{where}: drake:material_model = {material!r}: only "
                         f"{SUPPORTED_MATERIAL!r} is supported (the haptic kernel's element)")
    _check_material(where, config)
    mesh = inspector.GetReferenceMesh(body.geometry_id())
    tetrahedra = np.array([[t.vertex(i) for i in range(4)] for t in mesh.tetrahedra()],
                          dtype=np.int64).reshape(-1, 4)
    mesh_file = inspector.GetShape(body.geometry_id()).source().path()
    fixed = (after == before).all(axis=1)
    if not fixed.any():
        raise ValueError(f"{where}: no node is fixed: it would fall forever; add a "
                         "<drake:wall_boundary_condition> whose plane has nodes beyond it")
    if fixed.all():
        raise ValueError(f"{where}: the wall condition fixes all {len(fixed)} nodes: nothing "
                         "would move; put its plane through the body's underside")
    return TissueBody(
        name=body.name(), model=model, mesh_file=mesh_file,
        positions_m=reference, tetrahedra=tetrahedra,
        youngs_modulus_pa=_cell_youngs_modulus(where, mesh_file, tetrahedra,
                                               config.youngs_modulus()),
        poissons_ratio=config.poissons_ratio(), mass_density_kg_m3=config.mass_density(),
        mass_damping_per_s=config.mass_damping_coefficient(),
        stiffness_damping_s=config.stiffness_damping_coefficient(),
        material_model=material, fixed=fixed, rgba=_diffuse(inspector, body.geometry_id()))


def _check_material(where: str, config) -> None:
    """A ValueError naming the field of ``config`` (DeformableBodyConfig) that is not
    finite, or a Poisson's ratio below 0 (Drake's parser checks signs and that
    Poisson's ratio is in (-1, 0.5))."""
    values = {"youngs_modulus": config.youngs_modulus(),
              "poissons_ratio": config.poissons_ratio(),
              "mass_density": config.mass_density(),
              "mass_damping": config.mass_damping_coefficient(),
              "stiffness_damping": config.stiffness_damping_coefficient()}
    for field, value in values.items():
        require(bool(np.isfinite(value)), f"{where}: drake:{field}", value,
                "must be a finite number")
    low, high = POISSONS_RATIO_RANGE
    require(low <= values["poissons_ratio"] < high, f"{where}: drake:poissons_ratio",
            values["poissons_ratio"], f"must be in [{low:g}, {high:g}) for tissue")


def _cell_youngs_modulus(where: str, mesh_file: str, tetrahedra: np.ndarray,
                         body_modulus_pa: float) -> np.ndarray:
    """(m,) Young's modulus per tetrahedron (Pa): the file's cell data
    YOUNGS_MODULUS_CELL_DATA where it has one, else the body's."""
    file_tetrahedra, modulus = read_cell_youngs_modulus(mesh_file)
    if modulus is None:
        return np.full(len(tetrahedra), float(body_modulus_pa))
    if len(modulus) != len(tetrahedra) or not np.array_equal(file_tetrahedra, tetrahedra):
        raise ValueError(f"{where}: {mesh_file}'s cell data {YOUNGS_MODULUS_CELL_DATA!r} has "
                         f"{len(modulus)} values for {len(file_tetrahedra)} cells; Drake read "
                         f"{len(tetrahedra)} tetrahedra: it needs one value a tetrahedron")
    bad = np.flatnonzero(~(np.isfinite(modulus) & (modulus > 0)))
    if len(bad):
        raise ValueError(f"{where}: {mesh_file} cell data {YOUNGS_MODULUS_CELL_DATA}[{bad[0]}] "
                         f"= {float(modulus[bad[0]])!r}: must be a finite number > 0 (Pa)")
    return modulus


def _diffuse(inspector, geometry_id) -> np.ndarray:
    """(4,) RGBA of the body's <visual> <diffuse>, TISSUE_RGBA if it gives none."""
    properties = inspector.GetIllustrationProperties(geometry_id)
    if properties is not None and properties.HasProperty("phong", "diffuse"):
        return np.array(properties.GetProperty("phong", "diffuse").rgba)
    return np.array(TISSUE_RGBA)
