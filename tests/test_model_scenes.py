"""Scenes from model files (``!ModelScene``): each shipped kind touches what it
should, the paper scenes build the same plant through directives as from their
text, and bad input is refused in one line before anything runs."""

import dataclasses
import pickle
import textwrap
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from pydrake.math import RigidTransform
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder, LeafSystem
from pydrake.trajectories import PiecewisePolynomial

from maglev_haptics.analysis.run_results import run_scenario
from maglev_haptics.cli import main
from maglev_haptics.diagrams.haptics import scene_warnings
from maglev_haptics.diagrams.scenario import (
    ScenarioError, load_scenario, scenario_from_yaml, scenario_yaml)
from maglev_haptics.diagrams.scene import HangingBall, PaddleBall, PegInHole
from maglev_haptics.diagrams.scene_builder import AddScene, SceneStepper
from maglev_haptics.diagrams import scene_models
from maglev_haptics.diagrams.scene_models import check_model_scene
from maglev_haptics.diagrams.scenario_files import SCENARIO_DIR
from maglev_haptics.systems.scene_worker import CONTACT, STEP

MODELS = SCENARIO_DIR / "models"
K_N_PER_M, B_N_S_PER_M = 400.0, 5.0  # the coupling's translational gains
B_ROT_N_M_S = 1e-4  # keeps the tool from spinning (N*m*s/rad)


class ToolPD(LeafSystem):
    """A wrench on the tool that pulls its origin to ``target(t)`` (m), as the
    coupling's spring and damper do with the hand's pose."""

    def __init__(self, target: PiecewisePolynomial):
        LeafSystem.__init__(self)
        self._target = target
        self._X_WT = self.DeclareVectorInputPort("X_WT", 7)
        self._V_WT = self.DeclareVectorInputPort("V_WT", 6)
        self.DeclareVectorOutputPort("wrench_on_tool_W", 6, self._calc_wrench_on_tool_W)

    def _calc_wrench_on_tool_W(self, context, output):
        p_WT = self._X_WT.Eval(context)[4:7]
        V_WT = self._V_WT.Eval(context)
        force = (K_N_PER_M * (self._target.value(context.get_time()).ravel() - p_WT)
                 - B_N_S_PER_M * V_WT[3:6])
        output.SetFromVector(np.concatenate([force, -B_ROT_N_M_S * V_WT[0:3]]))


def drive(scene, waypoints, times):
    """The scene, its tool's origin pulled through ``waypoints`` (m) at ``times`` (s)
    from rest at the first; returns (samples every 10 ms: t, p_WT, contact wrench on
    the tool, in contact; the plant; its context)."""
    builder = DiagramBuilder()
    X_WT = RigidTransform(np.asarray(waypoints[0], dtype=float))
    parts = AddScene(builder, scene=scene, time_step_s=1e-3, X_WI_start=X_WT,
                     use_sampled_output_ports=False, stepping="in_place")
    pd = builder.AddSystem(ToolPD(PiecewisePolynomial.FirstOrderHold(
        times, np.asarray(waypoints, dtype=float).T)))
    builder.Connect(parts.X_WT_output, pd.GetInputPort("X_WT"))
    builder.Connect(parts.V_WT_output, pd.GetInputPort("V_WT"))
    builder.Connect(pd.get_output_port(), parts.wrench_on_tool_input)
    diagram = builder.Build()
    simulator = Simulator(diagram)
    context = simulator.get_mutable_context()
    samples = []
    for t in np.arange(0.0, times[-1] + 1e-9, 0.01):
        simulator.AdvanceTo(t)
        samples.append((t, parts.X_WT_output.Eval(
            parts.X_WT_output.get_system().GetMyContextFromRoot(context))[4:7].copy(),
            *[port.Eval(port.get_system().GetMyContextFromRoot(context)).copy()
              for port in (parts.contact_wrench_output, parts.in_contact_output)]))
    t, p, wrench, touching = (np.array(column) for column in zip(*samples))
    return (t, p, wrench, touching[:, 0] > 0.5), parts.plant, \
        parts.plant.GetMyContextFromRoot(context)


def shipped_scene(name, **tool):
    """The shipped scenario's scene, its tool's shape centred on T (so the test's
    pull on T acts through the shape's centre)."""
    scene = load_scenario(name).haptics.scene
    return dataclasses.replace(scene, tool=dataclasses.replace(
        scene.tool, tool_offset_m=[0.0, 0.0, 0.0], **tool))


def test_gear_mesh_holds_the_tool_up_and_pushes_it_back():
    """The tool pressed 4 mm into the gear's top face (z = -12 mm, rigid mesh) stops
    on it; the force is upwards and only in contact; beside the gear the teeth
    push it outwards."""
    scene = shipped_scene("gear_trace")
    radius = scene.tool.size_m[0]
    top_z = -0.012
    (t, p, wrench, touching), _, _ = drive(scene, [
        [0.008, 0.0, 0.0], [0.008, 0.0, 0.0], [0.008, 0.0, top_z + radius - 0.004],
        [0.008, 0.0, top_z + radius - 0.004]], [0.0, 0.1, 0.5, 0.9])
    assert not touching[t < 0.2].any() and np.abs(wrench[~touching]).max() == 0.0
    assert touching[-1]
    pressed = t > 0.7
    assert wrench[pressed, 2].min() > 0.5 * K_N_PER_M * 0.004  # upwards, about k x 4 mm
    assert np.abs(wrench[pressed, :2]).max() < 0.1 * wrench[pressed, 2].min()
    # The compliant sphere sinks into the rigid face, but by far less than 4 mm.
    assert p[pressed, 2].min() > top_z + radius - 0.002

    (t, p, wrench, touching), _, _ = drive(scene, [
        [0.030, 0.0, -0.016], [0.030, 0.0, -0.016], [0.020, 0.0, -0.016],
        [0.020, 0.0, -0.016]], [0.0, 0.1, 0.5, 0.9])
    assert touching[-1] and wrench[-1, 0] > 0.3  # the teeth push it back out along +x
    assert p[-1, 0] > 0.021


def test_push_block_slides_the_block_the_way_it_is_pushed():
    scene = shipped_scene("push_block")
    (t, p, wrench, touching), plant, context = drive(scene, [
        [0.0, 0.0, -0.023], [0.0, 0.0, -0.023], [0.020, 0.0, -0.023],
        [0.020, 0.0, -0.023]], [0.0, 0.2, 1.2, 1.5])
    block = plant.GetBodyByName("block")
    p_WB = plant.EvalBodyPoseInWorld(context, block).translation()
    assert p_WB[0] > 0.025 + 0.005  # pushed along +x from 25 mm
    assert p_WB[2] == pytest.approx(-0.025, abs=1e-3)  # still on the table
    assert not touching[t < 0.3].any()
    pushing = touching & (t > 0.3) & (t < 1.2)
    assert pushing.any() and (wrench[pushing, 0] < 0).all()  # the block resists along -x


def test_door_swings_open_when_pushed():
    scene = shipped_scene("door")
    (t, p, wrench, touching), plant, context = drive(scene, [
        [0.0, 0.015, 0.0], [0.0, 0.015, 0.0], [0.022, 0.015, 0.0],
        [0.022, 0.015, 0.0]], [0.0, 0.2, 1.2, 1.5])
    hinge = plant.GetJointByName("hinge")
    assert hinge.get_angle(context) > 0.2  # rad, open towards +x
    assert touching.any() and (wrench[touching, 0] <= 0).all()
    assert not touching[t < 0.3].any()


def test_tool_from_a_model_file(tmp_path):
    """The tool can be a body of a model file; gravity is off for it."""
    (tmp_path / "probe.sdf").write_text(textwrap.dedent("""\
        <?xml version="1.0"?>
        <sdf version="1.9"><model name="probe"><link name="tip">
          <inertial><mass>0.02</mass><inertia><ixx>6e-6</ixx><iyy>6e-6</iyy><izz>6e-6</izz>
            <ixy>0</ixy><ixz>0</ixz><iyz>0</iyz></inertia></inertial>
          <collision name="tip"><geometry><sphere><radius>0.005</radius></sphere></geometry>
          </collision></link></model></sdf>"""))
    scene = dataclasses.replace(shipped_scene("gear_trace"), tool=dataclasses.replace(
        load_scenario("gear_trace").haptics.scene.tool, file=f"file://{tmp_path}/probe.sdf",
        body="tip"))
    (t, p, wrench, touching), _, _ = drive(scene, [
        [0.008, 0.0, 0.0], [0.008, 0.0, 0.0], [0.008, 0.0, -0.011], [0.008, 0.0, -0.011]],
        [0.0, 0.1, 0.5, 0.9])
    assert not touching[t < 0.2].any() and p[t < 0.1, 2].max() == pytest.approx(0.0, abs=1e-6)
    assert touching[-1] and wrench[-1, 2] > 0.5


def test_gear_trace_flies_and_the_user_feels_the_face():
    """The whole diagram: free before the press; the press is felt upwards and the
    instrument stops above where the hand pushes it."""
    scenario = load_scenario("gear_trace")
    log = run_scenario(scenario, label="gear_trace", duration_s=5.6, progress=False).log
    t, f = log["t"], log["f_user"]
    free = (t > 3.0) & (t < 3.8)
    assert np.abs(f[free]).max() < 0.05 and not log["tool_in_contact"][free].any()
    pressed = (t > 5.0) & (t < 5.6)  # the hand's target is I at z = 14 mm
    assert log["tool_in_contact"][pressed].all()
    assert f[pressed, 2].min() > 0.2 and np.abs(f[pressed, :2]).max() < 0.05
    assert log["p_WI_true"][pressed, 2].min() > 0.015


def _added_from_text(directives, parser):
    """What the paper scenes did before directives: each model added from its text."""
    infos = []
    for directive in directives.directives:
        text = Path(directive.add_model.file.removeprefix("file://")).read_text()
        infos.append(SimpleNamespace(model_name=directive.add_model.name,
                                     model_instance=parser.AddModelsFromString(text, "sdf")[0]))
    return infos


@pytest.mark.parametrize("scene", [PegInHole(), HangingBall(), PaddleBall()],
                         ids=lambda scene: type(scene).__name__)
def test_paper_scenes_through_directives_step_as_from_their_text(scene, monkeypatch):
    """The paper scenes' plants, built through directives, step as the same models
    added from their SDFormat text, bit for bit, pushed down into the scene."""
    X_WI = RigidTransform([0.0, 0.0, 0.03])
    runs = []
    for patched in (False, True):
        if patched:
            monkeypatch.setattr(scene_models, "ProcessModelDirectives", _added_from_text)
        stepper = SceneStepper(scene, 1e-3, X_WI)
        request = np.concatenate([stepper.x0, [0.0, 0.0, -2.0, 0.0, 0.0, 0.0]])
        result = np.zeros(stepper.n + 7)
        contact = []
        for _ in range(300):
            stepper(STEP | CONTACT, request, result)
            request[:stepper.n] = result[:stepper.n]
            contact.append(result[stepper.n:].copy())
        runs.append((result.copy(), np.array(contact)))
    (x, contact), (x_text, contact_text) = runs
    assert contact[:, 6].any()  # pushed into the scene, or the ball landed
    np.testing.assert_array_equal(x, x_text)
    np.testing.assert_array_equal(contact, contact_text)


def test_model_scene_crosses_processes_and_yaml():
    scenario = load_scenario("door")
    scene = scenario.haptics.scene
    unpickled = dataclasses.replace(scenario, haptics=dataclasses.replace(
        scenario.haptics, scene=pickle.loads(pickle.dumps(scene))))
    assert scenario_yaml(unpickled) == scenario_yaml(scenario)
    assert scenario_yaml(scenario_from_yaml(scenario_yaml(scenario))) == scenario_yaml(scenario)
    assert f"file://{MODELS}/door.urdf" in scenario_yaml(scenario)  # {here} resolved


def test_worker_steps_a_model_scene_as_in_place():
    """With joints, the tool's state is not first in q and v: the worker's outputs
    pick it out where the plant put it."""
    scene = load_scenario("door").haptics.scene
    results = []
    for stepping in ("in_place", "worker"):
        builder = DiagramBuilder()
        parts = AddScene(builder, scene=scene, time_step_s=1e-3,
                         X_WI_start=RigidTransform([0.0, 0.0, 0.025]),
                         use_sampled_output_ports=False, contact_sample_period_s=1e-3,
                         stepping=stepping)
        diagram = builder.Build()
        context = diagram.CreateDefaultContext()
        parts.wrench_on_tool_input.FixValue(
            parts.wrench_on_tool_input.get_system().GetMyMutableContextFromRoot(context),
            [0.2, 0.0, 0.0, 0.0, 0.0, 0.0])
        simulator = Simulator(diagram, context)
        simulator.AdvanceTo(0.05)
        results.append([port.Eval(port.get_system().GetMyContextFromRoot(context)).copy()
                        for port in (parts.X_WT_output, parts.V_WT_output)])
        del simulator, diagram
    assert results[1][0][4] > 0.0  # pushed along +x
    for in_place, worker in zip(*results):
        np.testing.assert_array_equal(in_place, worker)


def _scenario_file(tmp_path, scene_yaml: str):
    (tmp_path / "models").mkdir(exist_ok=True)
    for name in ("gear.obj", "block.sdf", "door.urdf", "table.sdf"):
        (tmp_path / "models" / name).write_text((MODELS / name).read_text())
    (tmp_path / "models" / "flat.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    (tmp_path / "models" / "ghost.sdf").write_text(
        '<?xml version="1.0"?><sdf version="1.9"><model name="ghost"><link name="ghost">'
        '<visual name="v"><geometry><box><size>0.01 0.01 0.01</size></box></geometry>'
        "</visual></link></model></sdf>")
    (tmp_path / "models" / "sheet.sdf").write_text(
        '<?xml version="1.0"?><sdf version="1.9"><model name="sheet"><static>true</static>'
        '<link name="sheet"><collision name="c"><geometry><mesh><uri>flat.obj</uri></mesh>'
        "</geometry></collision></link></model></sdf>")
    (tmp_path / "models" / "two.sdf").write_text(
        '<?xml version="1.0"?><sdf version="1.9"><model name="two">'
        + "".join(f'<link name="{name}"><collision name="c"><geometry><sphere><radius>0.005'
                  "</radius></sphere></geometry></collision></link>" for name in "ab")
        + "</model></sdf>")
    (tmp_path / "models" / "broken.sdf").write_text('<?xml version="1.0"?><sdf version="1.9">'
                                                     "<model name='x'><link")
    path = tmp_path / "scene.yaml"
    path.write_text("Defaults: {}\ns:\n  hand: !ScriptedHand {}\n  haptics:\n    scene: "
                    + textwrap.indent(scene_yaml, "      ").lstrip())
    return path


GEAR = '- add_model: {name: gear, file: "file://{here}/models/gear.obj"}\n'
WELD = "- add_weld: {parent: world, child: gear::gear}\n"


@pytest.mark.parametrize("scene_yaml, message", [
    ("!ModelScene\ndirectives:\n- add_model: {name: gear, file: \"file://{here}/models/no.obj\"}",
     "haptics.scene.directives[0]: model 'gear': URI 'file://"),
    ("!ModelScene\ndirectives:\n- add_model: {name: d, file: \"file://{here}/models/no.sdf\"}",
     "haptics.scene.directives: URI 'file://"),
    ("!ModelScene\ndirectives:\n" + GEAR + "- add_weld: {parent: world, child: gear::cog}",
     "haptics.scene.directives[1].add_weld.child = 'gear::cog': GetFrameByName(): There is "
     "no Frame named 'cog'"),
    ("!ModelScene\ndirectives:\n" + GEAR + "- {}",
     "haptics.scene.directives[1] = '{}': must hold exactly one of add_model,"),
    ("!ModelScene\ndirectives:\n- add_model: {file: \"file://{here}/models/gear.obj\"}",
     "haptics.scene.directives[0].add_model.name = '': must name it"),
    ("!ModelScene\ndirectives:\n- add_model: {name: gear, file: models/gear.obj}",
     "haptics.scene.directives[0].add_model.file = 'models/gear.obj': must be a file:// or "
     "package:// URL"),
    ("!ModelScene\ndirectives:\n- add_model: {name: b, file: \"file://{here}/models/block.sdf\","
     " default_free_body_pose: 7}",
     "haptics.scene.directives[0].add_model.default_free_body_pose = 7: must be a mapping"),
    ("!ModelScene\ndirectives:\n" + GEAR + WELD + "tool: {file: \"file://{here}/models/"
     "block.sdf\", body: tip}", "haptics.scene.tool.body = 'tip': no such body in file://"),
    ("!ModelScene\ndirectives:\n" + GEAR + WELD + "tool: {file: \"file://{here}/models/"
     "door.urdf\", body: panel}", "haptics.scene.tool.body = 'panel': has joints (hinge)"),
    ("!ModelScene\ndirectives:\n" + GEAR + WELD + "tool: {file: \"file://{here}/models/"
     "two.sdf\", body: a}", "haptics.scene.tool.file = 'file://"),
    ("!ModelScene\ndirectives:\n" + GEAR + WELD + "tool: {file: \"file://{here}/models/"
     "block.sdf\", body: block, min_inertia_kg_m2: 1e-5}",
     "haptics.scene.tool.body = 'block': its smallest principal moment of inertia"),
    ("!ModelScene\ndirectives:\n" + GEAR + WELD + "tool: {shape: cube}",
     "haptics.scene.tool.shape = 'cube': must be one of peg, paddle, sphere"),
    ("!ModelScene\ndirectives:\n" + GEAR + WELD + "tool: {shape: peg, size_m: [0.01]}",
     "haptics.scene.tool.size_m = [0.01]: must be a list of 3 finite numbers > 0 for a peg"),
    ("!ModelScene\ndirectives:\n- add_model: {name: ghost, file: \"file://{here}/models/"
     "ghost.sdf\"}\n- add_weld: {parent: world, child: ghost::ghost}",
     "haptics.scene.directives[0]: model 'ghost' has no collision geometry"),
    ("!ModelScene\ndirectives:\n- add_model: {name: flat, file: \"file://{here}/models/"
     "flat.obj\"}\n- add_weld: {parent: world, child: flat::flat}",
     "haptics.scene.directives[0]: model 'flat' (file://"),
    ("!ModelScene\ndirectives:\n- add_model: {name: sheet, file: \"file://{here}/models/"
     "sheet.sdf\"}", "model 'sheet', geometry 'sheet::c'"),
    ("!ModelScene\ndirectives:\n- add_model: {name: x, file: \"file://{here}/models/"
     "broken.sdf\"}", "haptics.scene.directives: "),
    ("!ModelScene\ndirectives:\n- add_modle: {name: gear}",
     "haptics.scene.directives[0].add_modle: unknown field; ModelDirective has add_model"),
    ("!ModelScene\ndirectives: {add_model: {name: gear}}",
     "haptics.scene.directives = {add_model: {name: gear}}: must be a list of mappings"),
    ("!ModelScene\ndirectives: []", "haptics.scene.directives = []: must add at least one"),
    ("!ModelScene\ndirectives:\n" + GEAR + WELD + "friction: 0.3",
     "haptics.scene.friction: unknown field; ModelScene has directives, tool, contact"),
    # A frame the built-in tool has ("body"): Drake names the tool, this names the frames.
    ("!ModelScene\ndirectives:\n" + GEAR + "- add_weld: {parent: world, child: gear::body}",
     "haptics.scene.directives[1].add_weld.child = 'gear::body': model 'gear' has no frame "
     "'body'; its frames: gear"),
], ids=["missing obj", "missing sdf", "unknown frame", "no kind", "no name", "not a url",
        "pose not a mapping", "unknown tool body", "tool with joints", "tool among others",
        "light tool", "unknown shape", "wrong size", "no collision", "flat obj", "flat mesh",
        "malformed sdf", "unknown directive", "not a list", "no models", "unknown field",
        "a frame another model has"])
def test_bad_model_scene_is_refused_in_one_line(tmp_path, scene_yaml, message):
    path = _scenario_file(tmp_path, scene_yaml)
    with pytest.raises(ScenarioError) as error:
        load_scenario(str(path))
    assert message in str(error.value) and "\n" not in str(error.value)
    assert str(error.value).startswith("scene:s: haptics.scene")


def test_cli_refuses_a_bad_model_before_writing_anything(tmp_path, capsys):
    path = _scenario_file(tmp_path, "!ModelScene\ndirectives:\n" + GEAR
                          + "- add_weld: {parent: world, child: gear::cog}")
    out = tmp_path / "out"
    assert main(["run", str(path), "--no-meshcat", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "There is no Frame named 'cog'" in err and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1
    assert not out.exists()


def test_warnings_at_load_name_a_compliant_obj_and_a_costly_step(tmp_path):
    (tmp_path / "models").mkdir()
    (tmp_path / "models" / "gear.obj").write_text((MODELS / "gear.obj").read_text())
    (tmp_path / "models" / "bowl.sdf").write_text(
        '<?xml version="1.0"?><sdf version="1.9" xmlns:drake="http://drake.mit.edu">'
        '<model name="bowl"><static>true</static><link name="bowl"><collision name="shell">'
        "<pose>0 0 -0.03 0 0 0</pose><geometry><mesh><uri>gear.obj</uri></mesh></geometry>"
        "<drake:proximity_properties><drake:compliant_hydroelastic/><drake:hydroelastic_modulus>"
        "1e6</drake:hydroelastic_modulus></drake:proximity_properties></collision></link>"
        "</model></sdf>")
    path = tmp_path / "bowl.yaml"
    path.write_text("Defaults: {}\ns:\n  hand: !ScriptedHand {}\n  haptics:\n    scene: "
                    '!ModelScene\n      directives:\n      - add_model: {name: bowl, file: '
                    '"file://{here}/models/bowl.sdf"}\n')
    scenario = load_scenario(str(path))
    lines = scene_warnings(scenario, "bowl:s")
    assert len(lines) == 1
    assert "model 'bowl', geometry 'bowl::shell': an OBJ mesh declared compliant" in lines[0]
    # A tick of 10 us is shorter than any plant step.
    lines = scene_warnings(dataclasses.replace(load_scenario("push_block"),
                                               control_rate_hz=1e5), "push_block")
    assert len(lines) == 1 and "a step of its plant costs" in lines[0]
    assert scene_warnings(load_scenario("gear_trace"), "gear_trace") == []  # ~20 us a step
    # A tool 50 mm below the grip turns under a push there: 1.8 g against the damper.
    far = load_scenario("door", scenario_text="{haptics: {scene: !ModelScene {tool: "
                        "{tool_offset_m: [0, 0, -0.05]}}}}")
    lines = scene_warnings(far, "door")
    assert len(lines) == 1 and "a force at the grip meets as little as 1.8 g" in lines[0]
    assert "b h / m = 2.7" in lines[0]  # 5 N s/m x 1 ms x (1 / 20 g + (50 mm)^2 / 5e-6)
    assert scene_warnings(load_scenario("peg_in_hole"), "peg_in_hole") == []


def test_here_must_be_resolved():
    scene = load_scenario("gear_trace").haptics.scene
    raw = pickle.loads(pickle.dumps(scene))
    raw.directives[0].add_model.file = "file://{here}/models/gear.obj"
    with pytest.raises(ValueError, match=r"holds \{here\}, the scenario file's folder"):
        check_model_scene(raw, "scene")


def test_the_readme_example_presses_on_the_model(tmp_path):
    """README's "Feel your own model" scenario, as written there, with the gear as
    my_part.obj: haptics engages and the hand's press reaches the model."""
    readme = (Path(__file__).parents[1] / "README.md").read_text()
    example = readme.split("```yaml\nmy_part:")[1].split("```")[0]
    (tmp_path / "my_scenarios.yaml").write_text("my_part:" + example)
    (tmp_path / "models").mkdir()
    (tmp_path / "models" / "my_part.obj").write_bytes(
        (SCENARIO_DIR / "models" / "gear.obj").read_bytes())
    scenario = load_scenario(str(tmp_path / "my_scenarios.yaml"), "my_part")
    result = run_scenario(scenario, label="my_part", progress=False)
    assert result.summary["haptics_engaged_s"] > 3.0
    assert result.log["tool_in_contact"][result.log["t"] > 5.0].any()
