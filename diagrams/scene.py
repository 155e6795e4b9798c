"""The rigid virtual scenes' configuration: a tool coupled to the instrument and
the rigid objects it touches, picked by the config's type, with their range
checks. ``diagrams/scene_builder.py`` adds them to a diagram.

- ``PegInHole``: a square peg (the tool) and a static plate lying on a table,
  with a rectangular hole through it, so the hole's floor is the table;
- ``HangingBall``: a small anchor sphere (the tool) with a ball hung from it by a
  ``LinearSpringDamper``, over a table;
- ``PaddleBall``: a paddle (the tool) and a ball dropped onto it, over a table;
- ``ModelScene``: the user's own models (SDFormat, URDF, MJCF, OBJ) placed by
  Drake model directives, and a tool that is a built-in shape or a body of a
  model file (``diagrams/scene_models.py`` turns every kind into Drake models).
  Its deformable bodies (Drake's ``drake:deformable_properties``) are tissue,
  stepped by our finite elements and touched by a sphere on the tool
  (``TissueContact``; ``diagrams/tissue_scene.py``).
"""

from dataclasses import dataclass, field
from typing import List, Optional, Union

from pydrake.common.yaml import yaml_dump_typed, yaml_load_typed
from pydrake.multibody.parsing import ModelDirective, ModelDirectives

from maglev_haptics.hardware.config_checks import finite, nonnegative, positive, require, vector
from maglev_haptics.hardware.constants import GRAVITY_M_S2
from maglev_haptics.systems.tissue_fem import TissueProbe


@dataclass
class ContactProperties:
    """Hydroelastic contact properties shared by every collision geometry of a scene."""

    hydroelastic_modulus_pa: float = 1.0e6  # pressure at the deepest point of a compliant body (Pa)
    hunt_crossley_dissipation_s_per_m: float = 5.0  # (s/m); impacts barely bounce
    friction: float = 0.15  # Coulomb coefficient, static = dynamic (-)
    # Edge length of a sphere's mesh (m): 5 mm gives a 10 mm ball 128 tetrahedra
    # (faces ~0.6 mm inside the sphere); 10 mm, 32 (~2 mm inside, ~40 us a step less).
    resolution_hint_m: float = 0.005

    def validate(self, path: str = "contact") -> None:
        positive(f"{path}.hydroelastic_modulus_pa", self.hydroelastic_modulus_pa)
        nonnegative(f"{path}.hunt_crossley_dissipation_s_per_m",
                    self.hunt_crossley_dissipation_s_per_m)
        nonnegative(f"{path}.friction", self.friction)
        positive(f"{path}.resolution_hint_m", self.resolution_hint_m)


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

    def validate(self, path: str = "scene") -> None:
        """Range checks; a ValueError names ``path.field``, its value and what is allowed."""
        _validate_tool(self, path)
        vector(f"{path}.peg_size_m", self.peg_size_m, positive=True)
        positive(f"{path}.peg_mass_kg", self.peg_mass_kg)
        vector(f"{path}.hole_size_m", self.hole_size_m, positive=True)
        vector(f"{path}.hole_center_m", self.hole_center_m)
        vector(f"{path}.block_size_m", self.block_size_m, positive=True, length=2,
               meaning=": the plate's outer x, y (its thickness is the hole's depth, "
               "hole_size_m[2])")
        for i, axis in enumerate("xy"):
            require(self.peg_size_m[i] < self.hole_size_m[i], f"{path}.peg_size_m[{i}]",
                    self.peg_size_m[i], f"the peg must be narrower than the hole in {axis} "
                    f"(hole_size_m[{i}] = {self.hole_size_m[i]})")
            require(self.hole_size_m[i] < self.block_size_m[i], f"{path}.hole_size_m[{i}]",
                    self.hole_size_m[i], f"the hole must be narrower than the plate in {axis} "
                    f"(block_size_m[{i}] = {self.block_size_m[i]})")


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

    def validate(self, path: str = "scene") -> None:
        """Range checks; a ValueError names ``path.field``, its value and what is allowed."""
        _validate_tool(self, path)
        positive(f"{path}.anchor_radius_m", self.anchor_radius_m)
        positive(f"{path}.anchor_mass_kg", self.anchor_mass_kg)
        positive(f"{path}.ball_radius_m", self.ball_radius_m)
        positive(f"{path}.ball_mass_kg", self.ball_mass_kg)
        positive(f"{path}.spring_stiffness_n_per_m", self.spring_stiffness_n_per_m)
        nonnegative(f"{path}.spring_damping_n_s_per_m", self.spring_damping_n_s_per_m)
        positive(f"{path}.spring_rest_length_m", self.spring_rest_length_m)
        gap = self.anchor_radius_m + self.ball_radius_m
        require(hanging_drop_m(self) > gap, f"{path}.spring_rest_length_m",
                self.spring_rest_length_m, f"the ball must hang clear of the anchor: rest "
                f"length + m g / k = {hanging_drop_m(self):.4g} m must exceed "
                f"anchor_radius_m + ball_radius_m = {gap:.4g} m")


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

    def validate(self, path: str = "scene") -> None:
        """Range checks; a ValueError names ``path.field``, its value and what is allowed."""
        _validate_tool(self, path)
        vector(f"{path}.paddle_size_m", self.paddle_size_m, positive=True)
        positive(f"{path}.paddle_mass_kg", self.paddle_mass_kg)
        positive(f"{path}.ball_radius_m", self.ball_radius_m)
        positive(f"{path}.ball_mass_kg", self.ball_mass_kg)
        vector(f"{path}.ball_start_m", self.ball_start_m)


# A built-in tool shape's default size_m: the paper scenes' peg and paddle (box x, y,
# z) and the hanging ball's anchor (sphere radius) (m).
TOOL_SHAPES = {"peg": [0.025, 0.025, 0.040], "paddle": [0.08, 0.05, 0.006], "sphere": [0.008]}
HERE = "{here}"  # in a model URL: the folder of the scenario file that names it
URL_SCHEMES = ("file://", "package://")  # what Drake's model directives read
LARGEST_TOOL_M = 1.0  # a built-in tool's size at most (m)


@dataclass
class SceneTool:
    """A model scene's tool: a built-in shape, or (with ``file``) a body of a model
    file. Its frame T is at the grip (I's origin when relaxed). A built-in shape is
    centred at ``tool_offset_m`` in T, its principal moments raised to
    ``min_inertia_kg_m2``; a file's body frame is T itself, its shape and inertia
    as the file says (a body whose moments fall short is refused)."""

    shape: str = "sphere"  # peg or paddle (boxes), sphere; unused with file
    # peg, paddle: x, y, z; sphere: [radius] (m); null: the shape's TOOL_SHAPES size
    size_m: Optional[List[float]] = None
    mass_kg: float = 0.020  # a built-in shape's (kg); >= 10 g for the explicit coupling
    min_inertia_kg_m2: float = 5e-6  # floor of the tool's principal moments (kg*m^2)
    tool_offset_m: List[float] = field(default_factory=lambda: [0.0, 0.0, -0.025])  # (m)
    file: str = ""  # a model URL (file://, package://; {here} as in directives); "": shape
    body: str = ""  # the tool's body in that file's model

    def validate(self, path: str) -> None:
        nonnegative(f"{path}.min_inertia_kg_m2", self.min_inertia_kg_m2)
        vector(f"{path}.tool_offset_m", self.tool_offset_m)
        if self.file:
            require(bool(self.body), f"{path}.body", self.body,
                    f"must name the tool's body in {self.file}")
            return
        require(not self.body, f"{path}.body", self.body,
                "needs file: the model file that holds the body (or leave body out for a "
                "built-in shape)")
        require(self.shape in TOOL_SHAPES, f"{path}.shape", self.shape,
                f"must be one of {', '.join(TOOL_SHAPES)}")
        size = self.size()
        vector(f"{path}.size_m", size, len(TOOL_SHAPES[self.shape]), positive=True,
               meaning=f" for a {self.shape}")
        require(max(size) <= LARGEST_TOOL_M, f"{path}.size_m", size,
                f"a tool is at most {LARGEST_TOOL_M:g} m across")
        positive(f"{path}.mass_kg", self.mass_kg)

    def size(self) -> List[float]:
        """size_m, or the shape's default (m)."""
        return TOOL_SHAPES.get(self.shape, []) if self.size_m is None else self.size_m


@dataclass
class TissueContact:
    """How the tool touches the scene's deformable bodies (tissue): a sphere on the
    tool pressing the tissue's boundary triangles, a penalty pressure of
    ``probe.stiffness_n_per_m3`` (N/m^3: Pa a metre of depth) integrated over them
    (``TissueProbe``). The sphere is the built-in sphere tool's own (its radius and
    ``tool_offset_m``) unless ``probe_offset_m`` places one in T; then
    ``probe.radius_m`` is its radius. The tissue steps on the other core
    (``worker_thread``) with the stable substeps its mesh and material need: a
    material that needs more than ``max_substeps`` a tick is refused."""

    probe: TissueProbe = field(default_factory=TissueProbe)  # the shipped scenes' law
    probe_offset_m: Optional[List[float]] = None  # the sphere's centre in T (m); null: the tool's
    max_substeps: int = 8  # explicit substeps a tick at most (each a pass over the elements)
    worker_thread: bool = True  # false: step the tissue in the update itself (same results)
    gravity_m_s2: List[float] = field(default_factory=lambda: [0.0, 0.0, -GRAVITY_M_S2])

    def validate(self, path: str) -> None:
        """Range checks; a ValueError names ``path.field``, its value and what is allowed."""
        self.probe.validate(f"{path}.probe")
        if self.probe_offset_m is not None:
            vector(f"{path}.probe_offset_m", self.probe_offset_m, length=3)
        require(isinstance(self.max_substeps, int) and 1 <= self.max_substeps <= 64,
                f"{path}.max_substeps", self.max_substeps, "an integer from 1 to 64")
        vector(f"{path}.gravity_m_s2", self.gravity_m_s2, length=3)

    def sphere(self, tool: "SceneTool", path: str):
        """(centre in T (3,) m, radius m) of the sphere that touches the tissue; a
        ValueError if the tool is no built-in sphere and ``probe_offset_m`` is null."""
        if self.probe_offset_m is not None:
            return list(self.probe_offset_m), float(self.probe.radius_m)
        require(not tool.file and tool.shape == "sphere", f"{path}.probe_offset_m", None,
                "must place the sphere that touches the tissue, in the tool's frame (m), "
                f"unless the tool is the built-in sphere (it is {tool.file or tool.shape})")
        return list(tool.tool_offset_m), float(tool.size()[0])


@dataclass
class ModelScene:
    """The user's own models as the scene: Drake model directives (``add_model`` with
    a ``file://`` or ``package://`` URL, ``add_weld``, ``add_frame``; Drake's
    ModelDirective type, processed by ProcessModelDirectives). ``{here}`` in a URL
    is the scenario file's folder; ``package://maglev_haptics/`` is
    ``plant_models/``. Welded models are static; free bodies move, with gravity;
    the tool has none. An OBJ added directly is one body named after its model
    (``part::part``).

    Collision geometries that declare no hydroelastic properties get ``contact``'s:
    compliant, except OBJ meshes (rigid: Drake's compliant meshes are tetrahedral
    ``.vtk`` files; an OBJ declared compliant becomes its convex hull).

    A model whose link declares ``drake:deformable_properties`` (a tetrahedral
    ``.vtk`` and a ``drake:wall_boundary_condition``) is tissue: Drake's parser reads
    it, our finite elements step it at the haptic rate, and ``tissue`` says how the
    tool touches it (``diagrams/tissue_model.py``, ``diagrams/tissue_scene.py``)."""

    directives: List[ModelDirective] = field(default_factory=list)
    tool: SceneTool = field(default_factory=SceneTool)
    contact: ContactProperties = field(default_factory=ContactProperties)
    tissue: TissueContact = field(default_factory=TissueContact)  # its deformable bodies

    def validate(self, path: str = "scene") -> None:
        """Range checks; a ValueError names ``path.field``, its value and what is allowed.
        The models themselves are checked by ``scene_models.check_model_scene``."""
        require(len(self.directives) > 0, f"{path}.directives", [],
                "must add at least one model (add_model: {name: ..., file: ...})")
        for i, directive in enumerate(self.directives):
            _validate_directive(directive, f"{path}.directives[{i}]")
        self.tool.validate(f"{path}.tool")
        self.contact.validate(f"{path}.contact")
        self.tissue.validate(f"{path}.tissue")

    # Drake's config types do not pickle; a scene worker gets its directives as YAML.
    def __getstate__(self):
        state = dict(self.__dict__)
        state["directives"] = yaml_dump_typed(ModelDirectives(directives=self.directives))
        return state

    def __setstate__(self, state):
        state = dict(state)
        state["directives"] = yaml_load_typed(schema=ModelDirectives,
                                              data=state["directives"]).directives
        self.__dict__.update(state)


SceneConfig = Union[PegInHole, HangingBall, PaddleBall, ModelScene]


def table_top_z(scene: SceneConfig) -> Optional[float]:
    """z of the table's top in W (m), None without a table. Under the peg's plate it
    is the hole's floor. A model scene's table, if any, is one of its models."""
    if isinstance(scene, ModelScene):
        return None
    if isinstance(scene, PegInHole):
        return scene.hole_center_m[2] - scene.hole_size_m[2]
    return scene.table_z_m


def hanging_drop_m(scene: HangingBall) -> float:
    """Static distance (m) of the ball's centre below the anchor's: rest length + m g / k."""
    return (scene.spring_rest_length_m
            + scene.ball_mass_kg * GRAVITY_M_S2 / scene.spring_stiffness_n_per_m)


def _validate_directive(directive: ModelDirective, path: str) -> None:
    """What Drake's directives need before they are processed: one kind each, and
    its names and URLs given (Drake reads a directive of no kind as garbage)."""
    kinds = [f.name for f in ModelDirective.__fields__ if getattr(directive, f.name) is not None]
    require(len(kinds) == 1, path, "{" + ", ".join(kinds) + "}", "must hold exactly one of "
            + ", ".join(f.name for f in ModelDirective.__fields__))
    kind = kinds[0]
    item = getattr(directive, kind)
    names = {"add_model": ("name",), "add_model_instance": ("name",), "add_frame": ("name",),
             "add_weld": ("parent", "child"), "add_collision_filter_group": ("name",)}
    for name in names.get(kind, ()):
        require(bool(getattr(item, name)), f"{path}.{kind}.{name}", getattr(item, name),
                "must name it (a model, or a frame as model::frame)")
    if kind in ("add_model", "add_directives"):
        require(item.file.startswith(URL_SCHEMES), f"{path}.{kind}.file", item.file,
                "must be a file:// or package:// URL (file://{here}/... is beside the "
                "scenario file)")


def _validate_tool(scene: SceneConfig, path: str) -> None:
    """The checks every rigid scene shares: its tool, its table and its contact."""
    nonnegative(f"{path}.min_inertia_kg_m2", scene.min_inertia_kg_m2)
    vector(f"{path}.tool_offset_m", scene.tool_offset_m)
    if not isinstance(scene, PegInHole) and scene.table_z_m is not None:
        require(finite(scene.table_z_m), f"{path}.table_z_m", scene.table_z_m,
                "must be a finite number or null")
    scene.contact.validate(f"{path}.contact")
