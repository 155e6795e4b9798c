"""Tissue in a model scene: the finite elements in the diagram, their substeps, the
worker, the drawing, the felt force over the lump, and the refusals."""

import numpy as np
import pytest
from pydrake.systems.analysis import Simulator

from maglev_haptics.analysis.run_results import run_scenario
from maglev_haptics.cli import main
from maglev_haptics.diagrams.application import BuildDiagram
from maglev_haptics.diagrams.haptics import interactive_variant
from maglev_haptics.diagrams.scenario import ScenarioError, load_scenario
from maglev_haptics.plant_models.tissue_meshes import TISSUE_RGBA, TissueMaterial, tissue_sdf
from maglev_haptics.systems.tissue_fem import stable_substeps

SLAB = '{add_model: {name: slab, file: "package://maglev_haptics/tissue/palpation_slab.sdf"}}'


def scene_text(tissue: str = "{}", tool: str = "{shape: sphere, size_m: [0.008], "
               "tool_offset_m: [0.0, 0.0, -0.025]}") -> str:
    return (f"{{haptics: {{scene: !ModelScene {{directives: [{SLAB}], tool: {tool}, "
            f"tissue: {tissue}}}}}}}")


def tissue_state(built, seconds: float) -> np.ndarray:
    """The slab system's state after ``seconds`` (s) of the diagram."""
    simulator = Simulator(built.diagram)
    simulator.AdvanceTo(seconds)
    system = built.haptics.scene.tissue[0].system
    context = system.GetMyContextFromRoot(simulator.get_context())
    return context.get_discrete_state(0).get_value().copy()


def test_the_slab_steps_with_the_substeps_its_mesh_and_material_need():
    built = BuildDiagram(load_scenario("palpate_inclusion"))
    (tissue,) = built.haptics.scene.tissue
    assert tissue.system.get_name() == "tissue_slab_palpation_slab"
    scene = load_scenario("palpate_inclusion").haptics.scene
    assert tissue.substeps == stable_substeps(
        tissue.model, 1e-3, probe_stiffness_n_per_m3=scene.tissue.probe.stiffness_n_per_m3)
    assert 1 <= tissue.substeps <= scene.tissue.max_substeps
    assert tissue.model.num_tetrahedra == len(tissue.body.tetrahedra) > 2000
    # The rigid scene plant holds the tool only: Drake never steps the tissue itself.
    assert built.haptics.scene.plant.deformable_model().num_bodies() == 0


def test_the_worker_and_the_update_step_the_tissue_alike():
    # Under gravity the slab settles from its rest shape: the states move every tick.
    on, off = (tissue_state(BuildDiagram(load_scenario(
        "palpate_inclusion", scenario_text=scene_text(f"{{worker_thread: {flag}}}"))), 0.05)
        for flag in ("true", "false"))
    rest = BuildDiagram(load_scenario("palpate_inclusion")).haptics.scene.tissue[0]
    n = rest.model.num_nodes
    assert np.abs(on[:3 * n] - rest.body.positions_m.ravel()).max() > 1e-7
    np.testing.assert_array_equal(on, off)


def test_meshcat_draws_the_tissue_in_its_colour(meshcat):
    built = BuildDiagram(interactive_variant(load_scenario("palpate_inclusion"), 10.0),
                         meshcat=meshcat)
    names = [system.get_name() for system in built.diagram.GetSystems()]
    assert "tissue_slab_palpation_slab_visualizer" in names
    built.diagram.ForcedPublish(built.diagram.CreateDefaultContext())
    for part in ("top", "wire", "contact_force"):
        assert meshcat.HasPath(f"/tissue/slab/{part}")


@pytest.mark.parametrize("text, message", [
    (scene_text("{max_substeps: 1}"),
     r"haptics.scene: tissue slab::palpation_slab .* substeps a 1 ms tick, more than "
     r"haptics.scene.tissue.max_substeps = 1"),
    # The contact is a pressure: a per-node stiffness (N/m) is refused either way.
    (scene_text("{probe: {stiffness_n_per_m3: 300.0}}"),
     r"haptics.scene.tissue.probe.stiffness_n_per_m3 = 300.0: must be from 1e5 to 1e10 \(N/m\^3"),
    (scene_text("{probe: {stiffness_n_per_m: 300.0}}"),
     r"haptics.scene.tissue.probe.stiffness_n_per_m: unknown field; TissueProbe has"),
    (scene_text(tool="{shape: peg, size_m: [0.01, 0.01, 0.03]}"),
     r"haptics.scene.tissue.probe_offset_m = None: must place the sphere"),
    # The tool waits where the hand grips: the first hover pose, here low over the slab.
    ("{motion: {waypoints: [{pose: [0.015, 0.0, 0.012, 0.0, 0.0, 0.0], move_s: 1.0, "
     "hold_s: 40.0}]}}", r"X_WI_start .*starts in tissue slab::palpation_slab"),
])
def test_bad_tissue_input_names_the_field(text, message):
    with pytest.raises((ValueError, ScenarioError), match=message):
        BuildDiagram(load_scenario("palpate_inclusion", scenario_text=text))


@pytest.mark.slow
def test_the_felt_force_rises_over_the_lump():
    scenario = load_scenario("palpate_inclusion")
    result = run_scenario(scenario, label="palpate_inclusion", progress=False)
    log = result.log
    x_mm = 1e3 * log["p_WI_true"][:, 0]
    pressing = log["t"] > 6.2  # 3 mm in: across the lump, back, and over it
    force_n = log["f_user"][:, 2]  # the tissue pushes the hand up
    over_lump = pressing & (np.abs(x_mm - 15.0) < 3.0)
    over_plain = pressing & (np.abs(x_mm + 5.0) < 3.0)
    assert over_lump.sum() > 100 and over_plain.sum() > 100
    # 3 mm in, the force rises ~20 % over the lump (measured 0.094 against 0.079 N); its
    # stiffness there, 1.5-1.9 times, is tissue_press's test.
    assert np.median(force_n[over_lump]) > 1.1 * np.median(force_n[over_plain])
    assert result.summary["max_coil_current_a"] <= scenario.device.amplifier.current_limit_a


def test_a_surface_mesh_declared_deformable_stops_the_run_in_one_line(tmp_path, capsys):
    (tmp_path / "tri.obj").write_text("v 0 0 0\nv 0.01 0 0\nv 0 0.01 0\nv 0 0 0.01\n"
                                      "f 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n")
    (tmp_path / "skin.sdf").write_text(tissue_sdf(
        "skin", "skin", "tri.obj", (0.015, 0.0, -0.035), TissueMaterial(),
        (0.015, 0.0, -0.034), TISSUE_RGBA))
    scenario = tmp_path / "skin.yaml"
    scenario.write_text(
        "skin:\n  hand: !ScriptedHand {events: [{at_s: 1.0, grip: true}]}\n"
        "  haptics:\n    scene: !ModelScene\n      directives:\n"
        "        - add_model: {name: skin, file: \"file://{here}/skin.sdf\"}\n")
    out = tmp_path / "out"
    assert main(["run", str(scenario), "--no-meshcat", "--out", str(out)]) == 2
    error = capsys.readouterr().err.strip()
    assert "\n" not in error and "must be a tetrahedral volume mesh" in error
    assert error.startswith("maglev run: error: haptics.scene.directives[0].add_model.file")
    assert not out.exists()
