"""The deformable surface demo with the whole diagram: palpation, texture,
the integrator choice, and bad input."""

import numpy as np
import pytest
from pydrake.systems.analysis import Simulator

from maglev_haptics.analysis.run_results import run_scenario
from maglev_haptics.diagrams.application import BuildDiagram
from maglev_haptics.diagrams.deformable_scene import build_scene_lattice
from maglev_haptics.diagrams.haptics import interactive_variant
from maglev_haptics.diagrams.scenario import ScenarioError, load_scenario
from maglev_haptics.systems.surface_visualizer import SURFACE_PATH, WIRE_PATH

FLAT = "{haptics: {scene: !DeformableSurface {heightmap: !SineHeightmap {amplitude_m: [0.0, 0.0]}}}}"


def palpate(text="{}"):
    scenario = load_scenario("deformable_surface", scenario_text=text)
    return scenario, run_scenario(scenario, label="deformable_surface", progress=False)


@pytest.fixture(scope="module")
def palpation():
    return palpate()


@pytest.fixture(scope="module")
def palpation_flat():
    return palpate(FLAT)


def test_the_default_lattice_is_the_papers_size():
    scenario = load_scenario("deformable_surface")
    lattice = build_scene_lattice(scenario.haptics.scene)
    assert lattice.num_masses >= 5000
    assert lattice.num_links > 10 * lattice.num_masses  # the 26-neighbour links


@pytest.mark.slow  # the whole palpation script, twice below
def test_strikes_give_force_peaks(palpation):
    scenario, result = palpation
    strikes = result.summary["palpation"]["strikes"]
    assert len(strikes) == 3  # the script's three taps, each one touch
    for strike in strikes:
        assert strike["peak_force_z_n"] > 0.1  # the surface pushes the probe up (N)
    assert result.summary["max_coil_current_a"] <= scenario.device.amplifier.current_limit_a


@pytest.mark.slow
def test_sliding_over_texture_varies_the_z_force(palpation, palpation_flat):
    _, textured = palpation
    _, flat = palpation_flat
    slide, slide_flat = textured.summary["palpation"], flat.summary["palpation"]
    assert slide["sliding_s"] > 3.0 and slide_flat["sliding_s"] > 3.0
    assert slide["sliding_mean_force_z_n"] > 0.03  # pressed into the surface while sliding
    # The texture, not the tracker noise or the hand, makes the z force vary.
    assert slide["sliding_force_z_variation_n"] > 3.0 * slide_flat["sliding_force_z_variation_n"]


def test_linearly_implicit_lattice_runs_in_the_diagram():
    text = ("{haptics: {scene: !DeformableSurface {column_spacing_m: 0.005, "
            "integrator: linearly_implicit, link_stiffness_n_per_m: 2000.0}}}")
    scenario = load_scenario("deformable_surface", scenario_text=text)
    built = BuildDiagram(scenario)
    simulator = Simulator(built.diagram)
    simulator.Initialize()
    simulator.AdvanceTo(0.3)
    surface = built.haptics.scene.surface
    state = surface.GetMyContextFromRoot(simulator.get_context()).get_discrete_state(0)
    assert np.all(np.isfinite(state.get_value()))
    lattice = built.haptics.scene.lattice
    positions = state.get_value()[:3 * lattice.num_masses].reshape(-1, 3)
    # Sagged under its weight at 2000 N/m links (5x the explicit limit), not blown up.
    assert np.abs(positions - lattice.positions_m).max() < 1e-3


def test_interactive_variant_runs_with_the_lattice_in_meshcat(meshcat):
    scenario = interactive_variant(load_scenario("deformable_surface"), 10.0)
    built = BuildDiagram(scenario, meshcat=meshcat)
    simulator = Simulator(built.diagram)
    simulator.Initialize()
    simulator.AdvanceTo(0.1)
    built.meshcat_hand.Delete()
    # The lattice's surface is drawn, and the tool sits where the hand slider starts it.
    assert meshcat.HasPath(SURFACE_PATH) and meshcat.HasPath(WIRE_PATH)
    surface = built.haptics.scene.surface
    state = surface.GetMyContextFromRoot(simulator.get_context()).get_discrete_state(0)
    assert np.all(np.isfinite(state.get_value()))


@pytest.mark.parametrize("text, message", [
    ("{haptics: {scene: !DeformableSurface {node_mass_kg: -0.001}}}",
     r"haptics.scene.node_mass_kg = -0.001: must be"),
    ("{haptics: {scene: !DeformableSurface {integrator: runge_kutta}}}",
     r"haptics.scene.integrator = 'runge_kutta': one of symplectic_euler, linearly_implicit"),
    ("{haptics: {scene: !DeformableSurface {surface_z_m: -0.04}}}",
     r"haptics.scene.surface_z_m = -0.04: a finite height above base_z_m"),
    ("{haptics: {scene: !DeformableSurface {heightmap: !RandomHeightmap {amplitude_m: -1.0}}}}",
     r"haptics.scene.heightmap.amplitude_m = -1.0"),
    ("{haptics: {scene: !DeformableSurface {probe: {radius_m: 0.0}}}}",
     r"haptics.scene.probe.radius_m = 0.0"),
    ("{haptics: {scene: !DeformableSurface {node_mas_kg: 0.001}}}", r"node_mas_kg"),
])
def test_bad_lattice_input_names_the_field(text, message):
    with pytest.raises(ScenarioError, match=message):
        load_scenario("deformable_surface", scenario_text=text)


def test_probe_starting_in_the_surface_is_refused():
    # Resting over the lattice puts the probe, 30 mm under the instrument, in the jelly.
    scenario = load_scenario("deformable_surface",
                             scenario_text="{motion: {start_xy_yaw: [0.0, 0.0, 0.0]}}")
    with pytest.raises(ValueError, match=r"X_WI_start .*the probe .* starts in the surface"):
        BuildDiagram(scenario)


@pytest.mark.parametrize("name", ["deformable_surface", "peg_in_hole"])
def test_runs_shorter_than_the_guard_windows_still_summarize(name):
    # 0.1 s: fewer log samples than the 50 ms contact guard's window and the filters'.
    result = run_scenario(load_scenario(name), label=name, progress=False, duration_s=0.1)
    assert result.summary["duration_s"] == pytest.approx(0.1)


def test_the_summary_says_where_the_lattice_was_stepped_and_how_long_the_other_core_took():
    result = run_scenario(load_scenario("deformable_surface"), label="deformable_surface",
                          progress=False, duration_s=0.2)
    steps = result.summary["deformable_steps"]["deformable_surface"]
    assert steps["ticks_on_other_core"] + steps["ticks_stepped_here"] == 200
    assert steps["ticks_on_other_core"] >= 150
    assert 0.0 < steps["other_core_tick_us_p50"] <= steps["other_core_tick_us_p99"] \
        <= steps["other_core_tick_us_max"]
    rigid = run_scenario(load_scenario("peg_in_hole"), label="peg_in_hole", progress=False,
                         duration_s=0.05)
    assert "deformable_steps" not in rigid.summary


@pytest.mark.parametrize("text, message", [
    ("{haptics: {scene: !DeformableSurface {link_stiffness_n_per_m: 400.0}}}",
     r"haptics.scene.link_stiffness_n_per_m = 400.0: must be below 3\d\d(\.\d)? N/m for "
     r"symplectic Euler with 1 substep\(s\)"),
    ("{haptics: {scene: !DeformableSurface {link_damping_n_s_per_m: 1.0}}}",
     r"cannot be stable: link_damping_n_s_per_m = 1.0 alone is too much"),
])
def test_a_lattice_symplectic_euler_would_blow_up_is_refused(text, message):
    with pytest.raises(ValueError, match=message):
        BuildDiagram(load_scenario("deformable_surface", scenario_text=text))


def test_substeps_make_a_stiffer_lattice_steppable():
    text = "{haptics: {scene: !DeformableSurface {link_stiffness_n_per_m: 400.0, substeps: 2}}}"
    built = BuildDiagram(load_scenario("deformable_surface", scenario_text=text))
    simulator = Simulator(built.diagram)
    simulator.Initialize()
    simulator.AdvanceTo(0.2)
    lattice = built.haptics.scene.lattice
    state = built.haptics.scene.surface.GetMyContextFromRoot(
        simulator.get_context()).get_discrete_state(0).get_value()
    positions = state[:3 * lattice.num_masses].reshape(-1, 3)
    # Two substeps keep 400 N/m links (refused with one) stable: a small sag, no blow-up.
    assert np.all(np.isfinite(positions)) and np.abs(positions - lattice.positions_m).max() < 1e-3


@pytest.mark.parametrize("field, value", [("radius_m", -1.0), ("friction", -0.1),
                                          ("slip_speed_m_s", 0.0)])
def test_bad_probe_names_its_field(field, value):
    text = f"{{haptics: {{scene: !DeformableSurface {{probe: {{{field}: {value}}}}}}}}}"
    with pytest.raises(ValueError, match=rf"haptics\.scene\.probe\.{field} = {value}"):
        load_scenario("deformable_surface", None, text)
