"""Every study on every shipped scenario where it applies (quick settings), from the
CLI; a study that does not apply says why."""

import json

import numpy as np
import pytest

from maglev_haptics.analysis.loop_studies import ZWidthSettings, loop_parameters, zwidth_study
from maglev_haptics.analysis.studies import study_names
from maglev_haptics.cli import main
from maglev_haptics.diagrams.scenario import load_scenario, scenario_names, shipped_scenario_files

SCENARIOS = [(path.stem, name) for path in shipped_scenario_files()
             for name in scenario_names(path)]
LOOP_STUDIES = ("passivity", "zwidth", "stability-map")


@pytest.mark.parametrize("study", LOOP_STUDIES)
@pytest.mark.parametrize("file, name", SCENARIOS)
def test_coupling_study_runs_or_says_why(study, file, name, tmp_path, capsys):
    code = main(["analyze", study, file, "--name", name, "--quick", "--json",
                 "--out", str(tmp_path)])
    scenario = load_scenario(file, name)
    if scenario.haptics is None:
        assert code == 2
        assert "does not apply" in capsys.readouterr().err
        return
    assert code == 0
    results = json.loads((tmp_path / f"{study.replace('-', '_')}.json").read_text())
    assert results["scenario"] == f"{file}:{name}"
    for plot in results["plots"]:
        assert (tmp_path / plot).stat().st_size > 10_000


def test_peg_loop_numbers(tmp_path):
    """The peg scene's coupling needs 3.3 N s/m it does not have, and the hand gives 8."""
    scenario = load_scenario("peg_in_hole")
    p = loop_parameters(scenario)
    assert p.mass_kg == pytest.approx(0.125) and p.grip_stiffness == pytest.approx(2000.0)
    assert p.delay_s == pytest.approx(1.5e-3 + 0.5 / 860 + 1e-3 + 1 / (2 * np.pi * 1000))
    assert main(["analyze", "passivity", "peg_in_hole", "--quick", "--out", str(tmp_path)]) == 0
    results = json.loads((tmp_path / "passivity.json").read_text())
    assert results["margin_device_only_n_s_m"] < 0 < results["margin_with_hand_n_s_m"]
    assert results["ideal_wall_damping_needed_n_s_m"] == pytest.approx(
        results["closed_form_ideal_wall_n_s_m"], rel=0.01)


def test_zwidth_says_where_the_scenarios_coupling_lies(tmp_path, capsys):
    """The terminal shows the scenario's own point and its region, not only the
    parameters; the same point and region are in zwidth.json."""
    assert main(["analyze", "zwidth", "peg_in_hole", "--quick", "--out", str(tmp_path)]) == 0
    printed = capsys.readouterr().out
    shown = json.loads(printed[printed.index("{"):printed.rindex("}") + 1])
    point = json.loads((tmp_path / "zwidth.json").read_text())["scenario_point"]
    assert shown["scenario_point"] == point
    assert point["region"] == "passive with the hand's damping"  # 400 N/m, 5 N s/m


def test_zwidth_regions_are_nested():
    """Passive with the device implies passive with the hand implies stable: along
    each damping row, the region code never rises with stiffness."""
    scenario = load_scenario("peg_in_hole")
    results = zwidth_study(scenario, ZWidthSettings.quick())
    region = np.array(results["region"])
    assert np.all(np.diff(region, axis=1) <= 0)
    assert (region == 0).any() and (region == 2).any()


def test_study_names():
    assert set(LOOP_STUDIES) | {"linearize", "multirate", "workspace"} == set(study_names())


@pytest.mark.slow
def test_workspace_runs_on_every_scenario(tmp_path):
    """The workspace applies to every scenario: it depends on the scenario's device
    only, so each distinct device of the shipped scenarios gets one run (quick grids;
    tests/test_workspace.py checks the numbers)."""
    devices = []
    for file, name in SCENARIOS:
        device = load_scenario(file, name).device
        if device not in [d for d, _ in devices]:
            devices.append((device, (file, name)))
    assert len(devices) >= 2  # the 2- and the 4-magnet instrument's scenarios
    for device, (file, name) in devices:
        out = tmp_path / f"{file}-{name}"
        assert main(["analyze", "workspace", file, "--name", name, "--quick", "--json",
                     "--out", str(out)]) == 0
        results = json.loads((out / "workspace.json").read_text())
        _check_workspace(results, out)


def _check_workspace(results, tmp_path):
    assert set(results["instruments"]) == {"two_magnet", "four_magnet"}
    assert all((tmp_path / plot).stat().st_size > 10_000 for plot in results["plots"])


# The default suite linearizes one haptic loop with a scripted hand (B, C, D) and the
# refused deformable scenes; `-m slow` covers every scenario.
QUICK_LINEARIZATIONS = {("linearize", "peg_in_hole"), ("linearize", "deformable_surface"),
                        ("linearize", "palpate_inclusion")}


def first_of_each_file(study):
    seen = set()
    for file, name in SCENARIOS:
        quick = (study, file) in QUICK_LINEARIZATIONS and file not in seen
        seen.add(file)
        yield pytest.param(study, file, name, marks=() if quick else pytest.mark.slow)


@pytest.mark.parametrize("study, file, name", [
    *first_of_each_file("linearize"), *first_of_each_file("multirate")])
def test_loop_linearization_runs_or_says_why(study, file, name, tmp_path, capsys):
    """Every shipped scenario's loop is stable at its operating point, the deformable
    ones (the lattice, tissue) are refused with the reason."""
    code = main(["analyze", study, file, "--name", name, "--quick", "--json",
                 "--out", str(tmp_path)])
    if file == "deformable_surface":
        assert code == 2
        assert "tens of thousands of states" in capsys.readouterr().err
        return
    if file == "palpate_inclusion":
        assert code == 2
        assert "its tissue has thousands of states" in capsys.readouterr().err
        return
    assert code == 0
    results = json.loads((tmp_path / f"{study}.json").read_text())
    assert results["stable"] and 0.0 < results["spectral_radius"] < 1.0
    assert results["modes"][0]["states"]
    if study == "linearize" and load_scenario(file, name).hand is not None:
        n = len(results["states"])
        B, C, D = (np.array(results[key]) for key in ("B", "C", "D"))
        assert B.shape == (n, 3) and C.shape == (6, n) and D.shape == (6, 3)
        # The arm pulls the hand toward its target: a 1 m offset held over the period
        # gives the hand ~ k_arm T / m_hand of velocity along it, next to nothing across.
        z_velocity = results["states"].index("station/plant/hand_vz")
        assert 2.0 < B[z_velocity, 2] < 20.0
        assert abs(B[z_velocity, 0]) < 0.05 * B[z_velocity, 2]
        assert np.abs(D).max() == 0.0  # the rendered wrench is a held state


@pytest.mark.slow
def test_peg_multirate_against_single_rate(tmp_path):
    """The true 860 Hz / 1 kHz loop and the single-rate one agree on the slowest mode
    over the 50 ms hyperperiod (the hand on the arm, ~4 Hz)."""
    assert main(["analyze", "multirate", "peg_in_hole", "--json", "--out", str(tmp_path)]) == 0
    results = json.loads((tmp_path / "multirate.json").read_text())
    assert results["hyperperiod_s"] == pytest.approx(0.05)
    assert results["spectral_radius"] == pytest.approx(
        results["single_rate"]["spectral_radius_over_multirate_hyperperiod"], rel=0.02)


@pytest.mark.slow
def test_whole_loop_onset_linearized_matches_simulation():
    """At the three operating points (the scenario, an 860 Hz loop, doubled coupling
    damping), the linearized critical stiffness is within 10% of the simulated onset."""
    from maglev_haptics.analysis.onset import onset_study
    for point in onset_study(load_scenario("peg_in_hole")):
        assert point["relative_difference"] < 0.10, point
