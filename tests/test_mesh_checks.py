"""A collision mesh that contact cannot use is refused in one line before anything
runs: an open surface, an edge of more than two faces, a flipped face, a flat or
inside-out mesh; in a scene's models, in an SDFormat model's collision and in a
tool's body. A plant step too costly for the tick names the lever its geometry
has."""

import dataclasses
import textwrap

import numpy as np
import pytest

from maglev_haptics.cli import main
from maglev_haptics.diagrams.haptics import scene_warnings
from maglev_haptics.diagrams.scenario import ScenarioError, load_scenario
from maglev_haptics.diagrams.scenario_files import SCENARIO_DIR
from maglev_haptics.diagrams.scene_models import obj_surface_problem, surface_problem

# A 10 mm cube, corners 1-8 (OBJ counts from 1), each face two triangles wound
# counter-clockwise seen from outside; the bottom's and top's diagonals run from
# corner 1 to 3 and 5 to 7.
CUBE_VERTICES = [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0),
                 (0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1)]
CUBE_FACES = [(1, 4, 3), (1, 3, 2), (5, 6, 7), (5, 7, 8), (1, 2, 6), (1, 6, 5),
              (2, 3, 7), (2, 7, 6), (3, 4, 8), (3, 8, 7), (4, 1, 5), (4, 5, 8)]
SIDE_M = 0.01


def obj_text(faces, vertices=CUBE_VERTICES) -> str:
    return "".join(f"v {x * SIDE_M:g} {y * SIDE_M:g} {z * SIDE_M:g}\n" for x, y, z in vertices) \
        + "".join("f " + " ".join(map(str, face)) + "\n" for face in faces)


BAD_MESHES = {
    # The left face (x = 0) left out: its four edges have one face each.
    "open": (obj_text(CUBE_FACES[:10]),
             "its surface is open: 4 edges belong to one face only (a hole), e.g. between "
             "vertices (0, 0, 0) and (0, 0, 0.01)"),
    # A wall through the diagonals 1-3 and 5-7: four of its edges are also the cube's.
    "not manifold": (obj_text(CUBE_FACES + [(1, 3, 7), (1, 7, 5)]),
                     "its surface is not a manifold: 4 edges shared by more than two faces, "
                     "e.g. between vertices (0, 0, 0) and (0, 0, 0.01), shared by 3 faces"),
    "one face flipped": (obj_text([(1, 3, 4)] + CUBE_FACES[1:]),
                         "its faces are not consistently oriented: 3 edges traversed the same "
                         "way by both faces (a face flipped), e.g. between vertices (0, 0, 0) "
                         "and (0.01, 0.01, 0)"),
    "inside out": (obj_text([face[::-1] for face in CUBE_FACES]),
                   "it encloses -1e-06 m^3 (its faces are wound inwards)"),
    # Closed and consistently wound, but enclosing nothing.
    "flat": (obj_text([(1, 2, 3), (1, 3, 2)]), "it encloses 0 m^3 (a flat surface)"),
}
NEEDS = "; hydroelastic contact needs a closed, manifold mesh with outward normals"


def test_closed_meshes_pass(tmp_path):
    (tmp_path / "cube.obj").write_text(obj_text(CUBE_FACES))
    assert obj_surface_problem(str(tmp_path / "cube.obj")) == ""
    assert obj_surface_problem(str(SCENARIO_DIR / "models" / "gear.obj")) == ""
    # The bottom's corners repeated for its faces alone, as exporters write them:
    # the same points, so no gap.
    repeated = CUBE_VERTICES + [(0, 0, 0), (1, 1, 0), (1, 0, 0), (0, 1, 0)]
    (tmp_path / "repeated.obj").write_text(obj_text(
        [(9, 12, 10), (9, 10, 11)] + CUBE_FACES[2:], repeated))
    assert obj_surface_problem(str(tmp_path / "repeated.obj")) == ""


@pytest.mark.parametrize("kind", ["open", "not manifold", "one face flipped"])
def test_surface_problems_name_the_edges(tmp_path, kind):
    text, problem = BAD_MESHES[kind]
    (tmp_path / "part.obj").write_text(text)
    assert obj_surface_problem(str(tmp_path / "part.obj")) == problem


def test_a_face_of_zero_area_is_no_edge():
    vertices = np.array(CUBE_VERTICES, dtype=float)
    triangles = np.array(CUBE_FACES + [(1, 1, 2)]) - 1
    assert surface_problem(vertices, triangles) == ""


def write_scenario(tmp_path, scene_yaml: str):
    """A scenario file "s" in ``tmp_path`` with ``scene_yaml`` as its haptic scene."""
    path = tmp_path / "scene.yaml"
    path.write_text("Defaults: {}\ns:\n  hand: !ScriptedHand {}\n  haptics:\n    scene: "
                    + textwrap.indent(scene_yaml, "      ").lstrip())
    return path


def sdf_with_mesh(name: str, obj: str, *, static: bool = True, properties: str = "") -> str:
    """A one-link model whose collision is the mesh ``obj`` (beside it); a free link
    has the inertia of a 20 g tool."""
    inertial = ("" if static else "<inertial><mass>0.02</mass><inertia><ixx>6e-6</ixx>"
                "<iyy>6e-6</iyy><izz>6e-6</izz><ixy>0</ixy><ixz>0</ixz><iyz>0</iyz>"
                "</inertia></inertial>")
    return ('<?xml version="1.0"?><sdf version="1.9" xmlns:drake="http://drake.mit.edu">'
            f'<model name="{name}"><static>{str(static).lower()}</static><link name="{name}">'
            f'{inertial}<collision name="c"><geometry><mesh><uri>{obj}</uri></mesh></geometry>'
            f"{properties}</collision></link></model></sdf>")


GEAR = '- add_model: {name: gear, file: "file://{here}/gear.obj"}\n'
WELD_GEAR = "- add_weld: {parent: world, child: gear::gear}\n"


def copy_gear(tmp_path):
    (tmp_path / "gear.obj").write_bytes((SCENARIO_DIR / "models" / "gear.obj").read_bytes())


@pytest.mark.parametrize("kind", list(BAD_MESHES))
@pytest.mark.parametrize("used_as", ["obj model", "sdf collision", "tool body"])
def test_a_mesh_contact_cannot_use_is_refused_in_one_line(tmp_path, kind, used_as):
    text, problem = BAD_MESHES[kind]
    (tmp_path / "part.obj").write_text(text)
    obj_url = f"file://{tmp_path}/part.obj"
    copy_gear(tmp_path)
    if used_as == "obj model":
        scene = ('!ModelScene\ndirectives:\n- add_model: {name: part, file: '
                 '"file://{here}/part.obj"}\n- add_weld: {parent: world, child: part::part}\n')
        where = f"haptics.scene.directives[0]: model 'part' ({obj_url}): "
    elif used_as == "sdf collision":
        (tmp_path / "part.sdf").write_text(sdf_with_mesh("part", "part.obj"))
        scene = "!ModelScene\ndirectives:\n" + GEAR + WELD_GEAR + (
            '- add_model: {name: part, file: "file://{here}/part.sdf"}\n')
        where = (f"haptics.scene.directives[2]: model 'part', geometry 'part::c' "
                 f"({tmp_path}/part.obj): ")
    else:
        (tmp_path / "probe.sdf").write_text(sdf_with_mesh("probe", "part.obj", static=False))
        scene = "!ModelScene\ndirectives:\n" + GEAR + WELD_GEAR + (
            'tool: {file: "file://{here}/probe.sdf", body: probe}\n')
        where = (f"haptics.scene.tool.file = 'file://{tmp_path}/probe.sdf': model 'probe', "
                 f"geometry 'probe::c' ({tmp_path}/part.obj): ")
    with pytest.raises(ScenarioError) as error:
        load_scenario(str(write_scenario(tmp_path, scene)))
    assert str(error.value) == f"scene:s: {where}{problem}{NEEDS}"


def test_an_open_mesh_declared_compliant_is_its_closed_hull(tmp_path):
    """Contact meets a compliant OBJ's convex hull, closed whatever the file: it runs,
    with the hull's warning."""
    (tmp_path / "part.obj").write_text(BAD_MESHES["open"][0])
    (tmp_path / "part.sdf").write_text(sdf_with_mesh(
        "part", "part.obj", properties="<drake:proximity_properties><drake:compliant_hydroelastic/>"
        "<drake:hydroelastic_modulus>1e6</drake:hydroelastic_modulus>"
        "</drake:proximity_properties>"))
    scenario = load_scenario(str(write_scenario(
        tmp_path, '!ModelScene\ndirectives:\n- add_model: {name: part, file: '
        '"file://{here}/part.sdf"}\n')))
    lines = scene_warnings(scenario, "s")
    assert len(lines) == 1 and "an OBJ mesh declared compliant" in lines[0]


def test_cli_refuses_an_open_mesh_before_writing_anything(tmp_path, capsys):
    (tmp_path / "part.obj").write_text(BAD_MESHES["open"][0])
    path = write_scenario(tmp_path, '!ModelScene\ndirectives:\n- add_model: {name: part, '
                          'file: "file://{here}/part.obj"}\n')
    out = tmp_path / "out"
    assert main(["run", str(path), "--no-meshcat", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err == (f"maglev run: error: scene:s: haptics.scene.directives[0]: model 'part' "
                   f"(file://{tmp_path}/part.obj): {BAD_MESHES['open'][1]}{NEEDS}\n")
    assert not out.exists()


BOX = '<collision name="box"><geometry><box><size>0.1 0.1 0.02</size></box></geometry></collision>'


def cylinder(properties: str = "") -> str:
    return ('<collision name="cylinder"><pose>0 0 0.03 0 0 0</pose><geometry><cylinder>'
            f"<radius>0.01</radius><length>0.04</length></cylinder></geometry>{properties}"
            "</collision>")


def stack_sdf(*collisions: str) -> str:
    """A static model "stack" of one link with ``collisions``."""
    return ('<?xml version="1.0"?><sdf version="1.9" xmlns:drake="http://drake.mit.edu">'
            '<model name="stack"><static>true</static><link name="stack">'
            + "".join(collisions) + "</link></model></sdf>")


def costly_step_warning(tmp_path, sdf: str, contact: str = "") -> str:
    """The step-cost warning of a scene of ``sdf``'s model, at a 10 us tick (shorter
    than any plant step)."""
    (tmp_path / "stack.sdf").write_text(sdf)
    scenario = load_scenario(str(write_scenario(
        tmp_path, '!ModelScene\ndirectives:\n- add_model: {name: stack, file: '
        '"file://{here}/stack.sdf"}\n' + contact)))
    lines = scene_warnings(dataclasses.replace(scenario, control_rate_hz=1e5), "s")
    assert len(lines) == 1 and "a step of its plant costs" in lines[0]
    return lines[0]


def test_a_costly_step_of_primitives_names_the_resolution_hint(tmp_path):
    """The issue's scene: an SDF cylinder on an SDF box."""
    line = costly_step_warning(tmp_path, stack_sdf(BOX, cylinder()),
                               "contact: {resolution_hint_m: 0.004}\n")
    assert line.endswith(
        "make its contact cheaper: a coarser contact.resolution_hint_m (now 0.004 m; it "
        "sets how finely Drake meshes 'tool::sphere', 'stack::cylinder')")


def test_a_costly_step_of_boxes_names_fewer_geometries(tmp_path):
    line = costly_step_warning(tmp_path, stack_sdf(BOX), "tool: {shape: peg}\n")
    assert line.endswith("make its contact cheaper: fewer collision geometries (Drake meshes "
                         "boxes coarsely whatever the hint)")


def test_a_costly_step_names_a_models_own_hint_and_its_meshes(tmp_path):
    line = costly_step_warning(tmp_path, stack_sdf(BOX, cylinder(
        "<drake:proximity_properties><drake:compliant_hydroelastic/>"
        "<drake:hydroelastic_modulus>1e6</drake:hydroelastic_modulus>"
        "<drake:mesh_resolution_hint>0.003</drake:mesh_resolution_hint>"
        "</drake:proximity_properties>")))
    assert ("a coarser <drake:mesh_resolution_hint> in the model files ('stack::cylinder' "
            "at 0.003 m)") in line
    copy_gear(tmp_path)
    line = costly_step_warning(tmp_path, sdf_with_mesh("stack", "gear.obj"))
    assert line.endswith("or fewer, coarser collision meshes ('stack::c')")
