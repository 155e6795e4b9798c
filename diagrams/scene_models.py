"""Every rigid scene as Drake models in the scene's plant, by one path: the tool's
model first (its body then leads the free bodies in the plant's state, after any
joints'), the scene's models by Drake
model directives (``ProcessModelDirectives``), then hydroelastic properties for
every collision geometry that declares none.

A ``ModelScene`` brings its directives and names its model files; the paper
scenes (``PegInHole``, ``HangingBall``, ``PaddleBall``) generate SDFormat text
(``plant_models/scene_sdf.py``) and the directives that add it, written for the
parse into a private folder that is removed after it. Their table and the
hanging ball's spring are added by ``scene_builder`` after this (a half-space
and a force element, which no model file holds).

URLs: ``{here}`` is the scenario file's folder (``resolve_here``, at load);
``package://maglev_haptics/`` is ``plant_models/``; Drake reads ``file://``
URLs as absolute paths.

Contact defaults (``ModelScene.contact``) for a geometry without hydroelastic
properties: an OBJ mesh rigid (Drake's compliant hydroelastic needs a primitive
or a tetrahedral ``.vtk``; an OBJ declared compliant is replaced by its convex
hull, which fills a bowl's hollow: ``scene_warnings`` names it), everything
else compliant, the tool's built-in shape included, so a compliant tool meets a
rigid mesh; friction and dissipation wherever the model gives none. A half-space
(SDFormat's ``<plane>``) gets a slab TABLE_SLAB_M deep.

A collision mesh must bound a solid, or the tool passes through it: one whose own
surface contact meets (a rigid OBJ) must have every edge shared by exactly two
faces that run it opposite ways (``surface_problem``) and enclose a positive
volume; one replaced by its convex hull (a compliant OBJ, a ``Convex``) a hull of
positive volume. Else a ValueError names the field that brought it.
"""

import dataclasses
import re
import tempfile
from pathlib import Path
from typing import Dict, List, NamedTuple, Optional

import numpy as np
from pydrake.common.yaml import yaml_dump_typed, yaml_load_typed
from pydrake.geometry import (
    AddCompliantHydroelasticProperties, AddCompliantHydroelasticPropertiesForHalfSpace,
    AddContactMaterial, AddRigidHydroelasticProperties, CalcVolume, Capsule, Convex, Cylinder,
    Ellipsoid, HalfSpace, Mesh, ProximityProperties, ReadObjToTriangleSurfaceMesh, Role,
    RoleAssign, SceneGraph, Sphere)
from pydrake.multibody.parsing import (
    AddModel, LoadModelDirectives, ModelDirective, ModelDirectives, Parser,
    ProcessModelDirectives)
from pydrake.multibody.plant import CoulombFriction, MultibodyPlant

from maglev_haptics.diagrams.scene import (
    HERE, HangingBall, ModelScene, PegInHole, SceneConfig, SceneTool)
from maglev_haptics.plant_models import PACKAGE_XML
from maglev_haptics.plant_models.scene_geometry import (
    box_inertia, hole_block_boxes, sphere_inertia)
from maglev_haptics.plant_models.scene_sdf import (
    ANCHOR_RGBA, BALL_RGBA, BLOCK_RGBA, PADDLE_RGBA, PEG_RGBA, TABLE_SLAB_M, Part, box_geometry,
    model_sdf, sphere_geometry)

DEFORMABLE_TAG = "drake:deformable_properties"  # what marks a model file as holding tissue
SMALLEST_VOLUME_M3 = 1e-12  # a collision mesh enclosing less has no inside to press (m^3)
TOOL_MODEL = "tool"  # a generated tool's model instance; its link is "body"


class SceneModels(NamedTuple):
    """A scene as model text and directives: the tool's SDFormat ``tool_sdf`` (or
    None: the tool is ``tool_body`` of the model at ``tool_url``), the directives,
    and generated files {name: SDFormat text} they add as ``file://{generated}/name``."""

    tool_sdf: Optional[str]
    tool_url: str
    tool_body: str
    directives: List[ModelDirective]
    generated: Dict[str, str]


GENERATED = "{generated}"  # in a generated directive's URL: the folder of its text


def _add_generated(name: str) -> ModelDirective:
    return ModelDirective(add_model=AddModel(name=name, file=f"file://{GENERATED}/{name}.sdf"))


def tool_sdf(scene: SceneConfig) -> str:
    """The generated tool's model "tool": its link's frame is T (at the grip, I's
    origin when relaxed); the tool's shape and centre of mass are at
    ``tool_offset_m`` in T. A paper scene's tool is rigid against its compliant
    objects; a model scene's is compliant against rigid meshes."""
    tool = scene.tool if isinstance(scene, ModelScene) else None
    p_TA = tuple(float(v) for v in (tool or scene).tool_offset_m)
    if isinstance(scene, PegInHole) or tool is not None and tool.shape == "peg":
        size, mass = (scene.peg_size_m, scene.peg_mass_kg) if tool is None else (
            tool.size(), tool.mass_kg)
        solid = box_inertia(mass, size)
        part = Part("peg", box_geometry(size), p_TA, PEG_RGBA)
    elif isinstance(scene, HangingBall) or tool is not None and tool.shape == "sphere":
        radius, mass = (scene.anchor_radius_m, scene.anchor_mass_kg) if tool is None else (
            tool.size()[0], tool.mass_kg)
        solid = sphere_inertia(mass, radius)
        part = Part("anchor" if tool is None else "sphere", sphere_geometry(radius), p_TA,
                    ANCHOR_RGBA)
    else:
        size, mass = (scene.paddle_size_m, scene.paddle_mass_kg) if tool is None else (
            tool.size(), tool.mass_kg)
        solid = box_inertia(mass, size)
        part = Part("paddle", box_geometry(size), p_TA, PADDLE_RGBA)
    inertia = np.maximum(solid, (tool or scene).min_inertia_kg_m2)
    return model_sdf(TOOL_MODEL, [part], scene.contact, compliant=tool is not None,
                     mass_kg=mass, inertia_kg_m2=inertia, p_LCm=p_TA)


def ball_sdf(radius_m: float, mass_kg: float, contact) -> str:
    part = Part("ball", sphere_geometry(radius_m), (0, 0, 0), BALL_RGBA)
    return model_sdf("ball", [part], contact, mass_kg=mass_kg,
                     inertia_kg_m2=sphere_inertia(mass_kg, radius_m))


def block_sdf(scene: PegInHole) -> str:
    """The static plate "block": its four walls on one body, placed in W."""
    parts = [Part(name, box_geometry(size), centre, BLOCK_RGBA)
             for name, centre, size in hole_block_boxes(scene.block_size_m, scene.hole_size_m,
                                                        scene.hole_center_m)]
    return model_sdf("block", parts, scene.contact)


def scene_models(scene: SceneConfig) -> SceneModels:
    """The scene's tool and models as SceneModels."""
    if isinstance(scene, ModelScene):
        tool = scene.tool
        if tool.file:
            return SceneModels(None, tool.file, tool.body, rigid_directives(scene.directives), {})
        return SceneModels(tool_sdf(scene), "", "body", rigid_directives(scene.directives), {})
    if isinstance(scene, PegInHole):
        generated = {"block": block_sdf(scene)}
    else:
        generated = {"ball": ball_sdf(scene.ball_radius_m, scene.ball_mass_kg, scene.contact)}
    return SceneModels(tool_sdf(scene), "", "body", [_add_generated(name) for name in generated],
                       generated)


def resolve_here(scene: ModelScene, folder: Path) -> ModelScene:
    """``scene`` with ``{here}`` in its URLs replaced by ``folder`` (absolute)."""
    here = str(Path(folder).resolve())

    def resolved(url: str) -> str:
        return url.replace(HERE, here)

    # A copy (through YAML: Drake's config types do not copy), its URLs then replaced.
    directives = yaml_load_typed(schema=ModelDirectives, data=yaml_dump_typed(
        ModelDirectives(directives=scene.directives))).directives
    for directive in directives:
        for item in (directive.add_model, directive.add_directives):
            if item is not None:
                item.file = resolved(item.file)
    return dataclasses.replace(scene, directives=directives, tool=dataclasses.replace(
        scene.tool, file=resolved(scene.tool.file)))


def drake_reason(error: Exception) -> str:
    """Drake's message as one line, without its "error: " prefix."""
    line = next((line for line in str(error).splitlines() if line.strip()), type(error).__name__)
    return line.strip().removeprefix("error: ").removeprefix("ERROR: ")


def scene_parser(plant: MultibodyPlant) -> Parser:
    """A parser into ``plant`` that knows ``package://maglev_haptics/``."""
    parser = Parser(plant)
    parser.package_map().AddPackageXml(str(PACKAGE_XML))
    return parser


def _declares_tissue(parser: Parser, url: str) -> bool:
    """Whether the model file at ``url`` declares a deformable body (its text names
    DEFORMABLE_TAG); a file that cannot be read does not (Drake's parse says why)."""
    try:
        return DEFORMABLE_TAG in Path(parser.package_map().ResolveUrl(url)).read_text()
    except (RuntimeError, OSError, UnicodeDecodeError):
        return False


def tissue_directive_indices(parser: Parser, directives: List[ModelDirective], path: str) -> list:
    """Indices of the add_model directives whose files declare deformable bodies; a
    ValueError for one inside an add_directives file (its add_model would be
    beyond the reach of the rigid scene's directives)."""
    found = []
    for i, directive in enumerate(directives):
        if directive.add_model is not None and _declares_tissue(parser,
                                                                directive.add_model.file):
            found.append(i)
        elif directive.add_directives is not None:
            nested = directive.add_directives.file
            try:
                inner = LoadModelDirectives(parser.package_map().ResolveUrl(nested)).directives
            except Exception:  # Drake's parse of the scene says why
                continue
            if tissue_directive_indices(parser, inner, f"{path}[{i}].add_directives"):
                raise ValueError(f"{path}[{i}].add_directives.file = {nested!r}: adds a model "
                                 "with a deformable body; add it by the scene's own add_model")
    return found


def holds_tissue(directives: List[ModelDirective]) -> bool:
    """Whether any model the directives add (add_directives files included) declares
    a deformable body; a look at the files' text, no parse."""
    try:
        return bool(tissue_directive_indices(scene_parser(MultibodyPlant(0.0)), list(directives),
                                       "directives"))
    except ValueError:  # a deformable body inside an add_directives file
        return True


def rigid_directives(directives: List[ModelDirective]) -> List[ModelDirective]:
    """``directives`` less the add_model of each model file that declares a deformable
    body (``diagrams/tissue_model.py`` reads those): what the rigid scene plant gets,
    so that it never steps Drake's own finite elements."""
    try:
        tissue = tissue_directive_indices(scene_parser(MultibodyPlant(0.0)), list(directives),
                                          "directives")
    except ValueError:  # a deformable body inside an add_directives file: Drake's parse refuses
        return list(directives)
    return [directive for i, directive in enumerate(directives) if i not in tissue]


def _frame_field(directives: List[ModelDirective], reason: str) -> str:
    """The field (``[i].add_weld.child = 'name'``) that names the frame Drake did not
    find in ``reason``, or "" if none does."""
    match = re.search(r"no Frame named '([^']*)'", reason)
    if match is None:
        return ""
    for i, directive in enumerate(directives):
        weld = directive.add_weld
        fields = [] if weld is None else [("add_weld.parent", weld.parent),
                                          ("add_weld.child", weld.child)]
        if directive.add_frame is not None:
            fields.append(("add_frame.X_PF.base_frame", directive.add_frame.X_PF.base_frame))
        for field, value in fields:
            if value is not None and (value == match[1] or value.endswith(f"::{match[1]}")):
                return f"[{i}].{field} = {value!r}"
    return ""


def _frames_of_model(plant: MultibodyPlant, reason: str) -> str:
    """Drake's ``reason`` for a frame missing from a model that exists, with the frames
    that model has; Drake's own names the other models that have one (the built-in
    tool's among them), not the valid names."""
    match = re.search(r"no Frame named '([^']*)' in the model instance named '([^']*)'", reason)
    if match is None or not plant.HasModelInstanceNamed(match[2]):
        return reason
    frames = [plant.get_frame(index).name()
              for index in plant.GetFrameIndices(plant.GetModelInstanceByName(match[2]))]
    return (f"model {match[2]!r} has no frame {match[1]!r}; its frames: "
            + ", ".join(sorted(set(frames))))


class AddedModels(NamedTuple):
    """What ``add_scene_models`` added: the tool's body, the directives' models
    [(index of the add_model that added it or None, model name, model instance)], and
    the ids of the collision geometries whose hydroelastic properties are the
    scene's ``contact`` (the generated models', and those a model leaves undeclared)."""

    tool_body: object
    models: list
    contact_geometries: list


def add_scene_models(plant: MultibodyPlant, scene_graph: SceneGraph, scene: SceneConfig,
                     path: str = "scene") -> AddedModels:
    """The scene's tool and models in ``plant`` (not finalized), registered with
    ``scene_graph``, every collision geometry with hydroelastic properties. A
    ValueError names ``path``'s field, the model and geometry, and why Drake cannot
    use it."""
    models = scene_models(scene)
    parser = scene_parser(plant)
    with tempfile.TemporaryDirectory(prefix="maglev_scene_") as folder:
        for name, text in models.generated.items():
            (Path(folder) / f"{name}.sdf").write_text(text)
        tool = _add_tool(plant, parser, models, scene, path)
        for i, directive in enumerate(models.directives):
            if directive.add_model is not None and GENERATED in directive.add_model.file:
                directive.add_model.file = directive.add_model.file.replace(GENERATED, folder)
            if directive.add_model is not None and directive.add_model.file.endswith(".obj"):
                _check_obj_model(parser, directive.add_model, f"{path}.directives[{i}]")
        try:
            infos = ProcessModelDirectives(ModelDirectives(directives=models.directives), parser)
        except Exception as error:  # Drake's parser: RuntimeError, its YAML's ValueError
            reason = drake_reason(error)
            raise ValueError(f"{path}.directives{_frame_field(models.directives, reason)}: "
                             f"{_frames_of_model(plant, reason)}") from None
    # Each model named by the add_model that added it (nested directive files: theirs).
    add_model_index = {d.add_model.name: i for i, d in enumerate(models.directives)
                       if d.add_model}
    added = [(add_model_index.get(info.model_name), info.model_name, info.model_instance)
             for info in infos]
    # The field that brought each model instance, for errors about its geometry.
    fields = {instance: f"{path}.directives" + ("" if i is None else f"[{i}]")
              for i, _, instance in added}
    fields[tool.model_instance()] = (f"{path}.tool" if models.tool_sdf is not None
                                     else f"{path}.tool.file = {models.tool_url!r}")
    for i, name, instance in added:
        if not _collision_geometries(plant, instance):
            raise ValueError(f"{fields[instance]}: model {name!r} has no collision "
                             "geometry: the tool would pass through it (give its links "
                             "<collision> elements)")
    if not plant.GetCollisionGeometriesForBody(tool):
        raise ValueError(f"{path}.tool: body {tool.scoped_name()} has no collision geometry: "
                         "it would touch nothing")
    generated = [instance for _, name, instance in added if name in models.generated]
    if models.tool_sdf is not None:
        generated.append(tool.model_instance())
    contact_geometries = _default_contact(plant, scene_graph, scene.contact, fields) + [
        geometry for instance in generated
        for geometry in _collision_geometries(plant, instance)]
    return AddedModels(tool, added, contact_geometries)


def _collision_geometries(plant: MultibodyPlant, instance) -> list:
    return [geometry for index in plant.GetBodyIndices(instance)
            for geometry in plant.GetCollisionGeometriesForBody(plant.get_body(index))]


def _add_tool(plant: MultibodyPlant, parser: Parser, models: SceneModels, scene, path: str):
    """The tool's model, gravity off; its body."""
    if models.tool_sdf is not None:
        instance = parser.AddModelsFromString(models.tool_sdf, "sdf")[0]
    else:
        try:
            instance = parser.AddModelsFromUrl(models.tool_url)[0]
        except Exception as error:
            raise ValueError(f"{path}.tool.file = {models.tool_url!r}: "
                             f"{drake_reason(error)}") from None
    plant.set_gravity_enabled(instance, False)
    bodies = [plant.get_body(index).name() for index in plant.GetBodyIndices(instance)]
    if models.tool_body not in bodies:
        raise ValueError(f"{path}.tool.body = {models.tool_body!r}: no such body in "
                         f"{models.tool_url}; it has {', '.join(bodies)}")
    body = plant.GetBodyByName(models.tool_body, instance)
    if isinstance(scene, ModelScene) and scene.tool.file:
        _check_tool_body(plant, body, scene.tool, path)
    return body


def _check_tool_body(plant: MultibodyPlant, body, tool: SceneTool, path: str) -> None:
    """A file's tool body must be free (the coupling moves it) and its inertia high
    enough for the explicit coupling (see scene_builder's docstring)."""
    joints = [joint.name() for joint in map(plant.get_joint, plant.GetJointIndices(
        body.model_instance())) if body in (joint.child_body(), joint.parent_body())]
    if joints:
        raise ValueError(f"{path}.tool.body = {tool.body!r}: has joints ({', '.join(joints)}); "
                         "the tool must be a free body, moved only by the coupling")
    others = [plant.get_body(index).name() for index in plant.GetBodyIndices(
        body.model_instance()) if index != body.index()]
    if others:
        raise ValueError(f"{path}.tool.file = {tool.file!r}: holds other bodies besides "
                         f"{tool.body!r} ({', '.join(others)}); a tool's model is its one body")
    M_BBo = body.default_spatial_inertia()
    moments = np.linalg.eigvalsh(  # principal moments about the centre of mass (kg*m^2)
        M_BBo.Shift(M_BBo.get_com()).CalcRotationalInertia().CopyToFullMatrix3())
    if moments.min() < tool.min_inertia_kg_m2:
        raise ValueError(
            f"{path}.tool.body = {tool.body!r}: its smallest principal moment of inertia, "
            f"{moments.min():.3g} kg*m^2, is below min_inertia_kg_m2 = "
            f"{tool.min_inertia_kg_m2:g}, which the explicit coupling needs at 1 kHz: "
            "raise the body's <inertia> in its file")


def _check_obj_model(parser: Parser, model: AddModel, path: str) -> None:
    """An OBJ added as a model is one rigid body whose inertia Drake computes from its
    volume: a ValueError naming the model if its file is missing or its surface
    bounds no solid."""
    try:
        filename = parser.package_map().ResolveUrl(model.file)
    except Exception as error:  # a missing file, an unknown package
        raise ValueError(f"{path}: model {model.name!r}: {drake_reason(error)}") from None
    problem = _mesh_problem(Mesh(filename), touched=True)
    if problem:
        raise ValueError(f"{path}: model {model.name!r} ({model.file}): {problem}")


CLOSED_MESH_NEEDED = "hydroelastic contact needs a closed, manifold mesh with outward normals"


def _mesh_problem(shape, touched: bool) -> str:
    """Why hydroelastic contact cannot use a Mesh or Convex ``shape``, ending in what
    it needs; "" if it can. ``touched``: contact meets the shape's own surface (a
    rigid OBJ), which then must bound a solid; a compliant OBJ's and a Convex's is
    their convex hull, closed whatever the file."""
    try:
        problem = obj_surface_problem(shape.source().path()) if touched else ""
        volume = CalcVolume(shape)  # (m^3)
    except Exception as error:  # Drake's reader: a missing or unreadable file
        return drake_reason(error)
    if not problem and not volume > SMALLEST_VOLUME_M3:
        problem = (f"it encloses {volume:.3g} m^3 ("
                   + ("its faces are wound inwards" if volume < 0 else "a flat surface") + ")")
    return f"{problem}; {CLOSED_MESH_NEEDED}" if problem else ""


def obj_surface_problem(filename: str) -> str:
    """surface_problem of the triangles Drake reads from the OBJ ``filename`` (its
    polygons split as Drake splits them), in the file's coordinates."""
    # Drake's reader rather than a mesh library's (trimesh): the check sees the very
    # triangles contact uses, where another reader welds, drops or splits its own way.
    mesh = ReadObjToTriangleSurfaceMesh(filename)
    triangles = np.array([[t.vertex(0), t.vertex(1), t.vertex(2)] for t in mesh.triangles()],
                         dtype=int).reshape(-1, 3)
    return surface_problem(np.array(mesh.vertices()).reshape(-1, 3), triangles)


def surface_problem(vertices: np.ndarray, triangles: np.ndarray) -> str:
    """Why the triangles (m, 3) of indices into ``vertices`` (n, 3) bound no solid: an
    edge of one face only (a hole), an edge of more than two faces (not a manifold),
    or an edge both its faces traverse the same way (a face flipped); with how many
    edges and one of them. "" if every edge is shared by exactly two faces that
    traverse it in opposite directions."""
    # Vertices at the same point are one: exporters repeat a vertex per face and
    # Drake keeps the copies, which leave no gap between the faces.
    points, merged = np.unique(vertices, axis=0, return_inverse=True)
    faces = merged.reshape(-1)[triangles]
    faces = faces[(faces != np.roll(faces, 1, axis=1)).all(axis=1)]  # none of zero area
    directed = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)  # each face's edges as it winds
    edges, faces_per_edge = np.unique(np.sort(directed, axis=1), axis=0, return_counts=True)
    runs, times_run = np.unique(directed, axis=0, return_counts=True)

    def between(edge) -> str:
        # + 0.0 turns -0.0 into 0.0, which reads as the file writes it.
        a, b = ("(" + ", ".join(f"{x + 0.0:.6g}" for x in points[i]) + ")" for i in edge)
        return f"between vertices {a} and {b}"

    open_edges = edges[faces_per_edge == 1]
    if len(open_edges):
        verb = "belongs" if len(open_edges) == 1 else "belong"
        return (f"its surface is open: {_count(len(open_edges), 'edge')} {verb} to one face "
                f"only (a hole), e.g. {between(open_edges[0])}")
    shared = np.flatnonzero(faces_per_edge > 2)
    if len(shared):
        return (f"its surface is not a manifold: {_count(len(shared), 'edge')} shared by more "
                f"than two faces, e.g. {between(edges[shared[0]])}, shared by "
                f"{faces_per_edge[shared[0]]} faces")
    # Every edge has two faces now: outward normals need them to run it opposite ways.
    same_way = runs[times_run > 1]
    if len(same_way):
        return (f"its faces are not consistently oriented: {_count(len(same_way), 'edge')} "
                f"traversed the same way by both faces (a face flipped), e.g. "
                f"{between(same_way[0])}")
    return ""


def _count(n: int, noun: str) -> str:
    return f"{n} {noun}" if n == 1 else f"{n} {noun}s"


def _is_obj(shape) -> bool:
    return isinstance(shape, (Mesh, Convex)) and shape.extension() == ".obj"


def _declared_compliant(properties) -> bool:
    """Whether ``properties`` make a geometry compliant: those carry a modulus (the
    compliance type's value is not bound in Python)."""
    return properties.HasProperty("hydroelastic", "hydroelastic_modulus")


# The shapes Drake meshes at their resolution hint, compliant or rigid; a box's mesh is
# the same whatever the hint, a half-space has none, a mesh is its file's.
HINTED_SHAPES = (Sphere, Cylinder, Capsule, Ellipsoid)


def _default_contact(plant: MultibodyPlant, scene_graph: SceneGraph, contact,
                     fields: Dict[object, str]) -> List[object]:
    """Hydroelastic properties from ``contact`` on every collision geometry of the
    plant that declares none (and friction, dissipation where missing); a
    ValueError, naming the field in ``fields`` of the geometry's model instance, for
    a mesh hydroelastic contact cannot use. The ids of the geometries it gave
    ``contact``'s hydroelastic properties."""
    inspector = scene_graph.model_inspector()
    source = plant.get_source_id()
    defaulted = []
    for geometry in inspector.GetAllGeometryIds(Role.kProximity):
        shape = inspector.GetShape(geometry)
        properties = ProximityProperties(inspector.GetProximityProperties(geometry))
        if not properties.HasProperty("hydroelastic", "compliance_type"):
            defaulted.append(geometry)
            if _is_obj(shape):
                AddRigidHydroelasticProperties(contact.resolution_hint_m, properties)
            elif isinstance(shape, HalfSpace):
                AddCompliantHydroelasticPropertiesForHalfSpace(
                    TABLE_SLAB_M, contact.hydroelastic_modulus_pa, properties)
            else:
                AddCompliantHydroelasticProperties(
                    contact.resolution_hint_m, contact.hydroelastic_modulus_pa, properties)
        if isinstance(shape, (Mesh, Convex)):
            # Checked before Drake builds its contact mesh, which aborts the process
            # on a flat convex hull.
            rigid_obj = (isinstance(shape, Mesh) and shape.extension() == ".obj"
                         and not _declared_compliant(properties))
            problem = _mesh_problem(shape, touched=rigid_obj)
            if problem:
                body = plant.GetBodyFromFrameId(inspector.GetFrameId(geometry))
                raise ValueError(
                    f"{fields[body.model_instance()]}: model "
                    f"{_model_name(plant, inspector, geometry)!r}, geometry "
                    f"{inspector.GetName(geometry)!r} ({shape.source().description()}): "
                    f"{problem}")
        if not properties.HasProperty("material", "hunt_crossley_dissipation"):
            AddContactMaterial(dissipation=contact.hunt_crossley_dissipation_s_per_m,
                               properties=properties)
        if not properties.HasProperty("material", "coulomb_friction"):
            AddContactMaterial(friction=CoulombFriction(contact.friction, contact.friction),
                               properties=properties)
        scene_graph.AssignRole(source, geometry, properties, RoleAssign.kReplace)
    return defaulted


def _model_name(plant: MultibodyPlant, inspector, geometry) -> str:
    body = plant.GetBodyFromFrameId(inspector.GetFrameId(geometry))
    return plant.GetModelInstanceName(body.model_instance())


def model_scene_warnings(scene: ModelScene) -> List[str]:
    """A line for each OBJ mesh declared compliant: Drake replaces it by its convex
    hull, which fills any hollow (a bowl, a hole)."""
    plant, scene_graph, _ = _scratch_plant(scene, "scene")
    inspector = scene_graph.model_inspector()
    lines = []
    for geometry in inspector.GetAllGeometryIds(Role.kProximity):
        shape = inspector.GetShape(geometry)
        properties = inspector.GetProximityProperties(geometry)
        if _is_obj(shape) and _declared_compliant(properties):
            lines.append(
                f"model {_model_name(plant, inspector, geometry)!r}, geometry "
                f"{inspector.GetName(geometry)!r}: an OBJ mesh declared compliant; Drake "
                f"uses its convex hull ({shape.source().description()}), which fills any "
                "hollow: declare it <drake:rigid_hydroelastic/> or give a tetrahedral .vtk")
    return lines


def check_model_scene(scene: ModelScene, path: str) -> None:
    """A ValueError, before anything runs, if Drake cannot build ``scene``'s models
    (add_scene_models's checks) or a URL still holds ``{here}`` (a scene built in
    Python: ``resolve_here`` it first)."""
    urls = [scene.tool.file] + [item.file for directive in scene.directives
                                for item in (directive.add_model, directive.add_directives)
                                if item is not None]
    for url in urls:
        if HERE in url:
            raise ValueError(f"{path}: {url!r} holds {HERE}, the scenario file's folder: load "
                             "the scene from a scenario file or resolve_here(scene, folder)")
    _scratch_plant(scene, path)


def _scratch_plant(scene: ModelScene, path: str):
    """(plant, scene graph, AddedModels) of ``scene``'s models, finalized, outside any
    diagram."""
    plant = MultibodyPlant(1e-3)
    scene_graph = SceneGraph()
    plant.RegisterAsSourceForSceneGraph(scene_graph)
    added = add_scene_models(plant, scene_graph, scene, path)
    try:
        plant.Finalize()
    except Exception as error:
        raise ValueError(f"{path}: {drake_reason(error)}") from None
    return plant, scene_graph, added


def step_cost_levers(scene: ModelScene) -> str:
    """What would make a step of the scene's plant cheaper, as its collision geometry
    allows: a coarser resolution hint for the shapes Drake meshes at one (the
    scene's ``contact.resolution_hint_m`` or their model's own), fewer and coarser
    meshes; fewer geometries if it has neither."""
    plant, scene_graph, added = _scratch_plant(scene, "scene")
    inspector = scene_graph.model_inspector()
    from_contact, own_hint, meshes = [], [], []
    for geometry in inspector.GetAllGeometryIds(Role.kProximity):
        shape = inspector.GetShape(geometry)
        name = repr(inspector.GetName(geometry))
        if isinstance(shape, (Mesh, Convex)):
            meshes.append(name)
        elif isinstance(shape, HINTED_SHAPES) and geometry in added.contact_geometries:
            from_contact.append(name)
        elif isinstance(shape, HINTED_SHAPES):
            hint_m = inspector.GetProximityProperties(geometry).GetProperty(
                "hydroelastic", "resolution_hint")
            own_hint.append(f"{name} at {hint_m:g} m")
    levers = []
    if from_contact:
        levers.append(f"a coarser contact.resolution_hint_m (now "
                      f"{scene.contact.resolution_hint_m:g} m; it sets how finely Drake "
                      f"meshes {_some(from_contact)})")
    if own_hint:
        levers.append(f"a coarser <drake:mesh_resolution_hint> in the model files "
                      f"({_some(own_hint)})")
    if meshes:
        levers.append(f"fewer, coarser collision meshes ({_some(meshes)})")
    return " or ".join(levers) or ("fewer collision geometries (Drake meshes boxes "
                                   "coarsely whatever the hint)")


def _some(names: List[str], shown: int = 3) -> str:
    """Up to ``shown`` of ``names``, and how many more."""
    more = f" and {len(names) - shown} more" if len(names) > shown else ""
    return ", ".join(names[:shown]) + more


def grip_inverse_mass_per_kg(M_BBo) -> float:
    """The largest inverse mass (1/kg) a free body presents to a force at its origin
    Bo, whatever the force's direction: 1/m + the largest eigenvalue of
    S I_Bcm^-1 S^T, S the cross-product matrix of p_BoBcm, since a force off the
    centre of mass also turns the body. ``M_BBo`` is its SpatialInertia about Bo."""
    p = M_BBo.get_com()
    S = np.array([[0.0, -p[2], p[1]], [p[2], 0.0, -p[0]], [-p[1], p[0], 0.0]])
    I_Bcm = M_BBo.Shift(p).CalcRotationalInertia().CopyToFullMatrix3()
    return 1.0 / M_BBo.get_mass() + float(np.linalg.eigvalsh(S @ np.linalg.solve(I_Bcm, S.T))[-1])


def tool_grip_inverse_mass_per_kg(scene: ModelScene) -> float:
    """grip_inverse_mass_per_kg of the scene's tool, at its frame T (1/kg)."""
    _, _, added = _scratch_plant(scene, "scene")
    return grip_inverse_mass_per_kg(added.tool_body.default_spatial_inertia())
