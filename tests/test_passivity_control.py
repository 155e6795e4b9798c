"""The passivity controller on the haptic coupling: a coupling stiffened past the
loop's onset of instability rings up to the force clamp without it and stays at the
level the tracker's noise sets with it, and what it withheld is in the log; and the
warning before a run whose coupling the loop analysis predicts unstable."""

import dataclasses

from maglev_haptics.analysis.loop_studies import stability_warnings
from maglev_haptics.analysis.onset import OnsetPoint, grows, held_still
from maglev_haptics.cli import main
from maglev_haptics.diagrams.scenario import load_scenario, scenario_names, shipped_scenario_files

# The peg scene's onset, the hand holding still, is ~4,500 N/m (docs/analysis.md).
OVERSTIFF_N_PER_M = 5500.0


def with_passivity_controller(scenario, on: bool):
    coupling = dataclasses.replace(scenario.haptics.coupling, passivity_controller=on)
    return dataclasses.replace(scenario, haptics=dataclasses.replace(
        scenario.haptics, coupling=coupling))


def test_an_overstiff_coupling_rings_without_the_passivity_controller_and_not_with_it():
    peg = load_scenario("peg_in_hole")
    as_shipped, engaged_s = held_still(peg, OnsetPoint("as shipped"),
                                       peg.haptics.coupling.translational_stiffness[0])
    reference = grows(as_shipped, engaged_s)
    assert not reference["unstable"]
    overstiff, _ = held_still(peg, OnsetPoint("overstiff"), OVERSTIFF_N_PER_M)
    without = grows(with_passivity_controller(overstiff, False), engaged_s,
                    reference["last_rms_m_s"])
    assert without["unstable"]
    controlled = with_passivity_controller(overstiff, True)
    with_it = grows(controlled, engaged_s, reference["last_rms_m_s"])
    assert not with_it["unstable"]
    # The 14x stiffer coupling turns the tracker's noise into ~10x the shipped one's
    # motion; without the controller the instrument rings at the force clamp, ~15x that.
    assert with_it["last_rms_m_s"] < 15 * reference["last_rms_m_s"]
    assert without["last_rms_m_s"] > 8 * with_it["last_rms_m_s"]
    assert with_it["passivity_dissipated_j"] > 0.0
    assert without["passivity_dissipated_j"] is None


def test_maglev_run_warns_of_coupling_gains_the_loop_analysis_predicts_unstable(
        capsys, tmp_path):
    for path in shipped_scenario_files():
        for name in scenario_names(path):
            assert stability_warnings(load_scenario(path, name), name) == []
    code = main(["run", "peg_in_hole", "--no-meshcat", "--duration", "0.01", "--out",
                 str(tmp_path), "--scenario-text",
                 "{haptics: {coupling: {translational_stiffness: [400, 6000, 400]}}}"])
    assert code == 0
    lines = capsys.readouterr().out.splitlines()
    warnings = [line for line in lines if line.startswith("warning:")]
    assert len(warnings) == 1
    assert warnings[0].startswith(
        "warning: peg_in_hole:peg_in_hole: the loop analysis predicts the haptic coupling "
        "unstable along y: haptics.coupling.translational_stiffness[1] = 6000 N/m is past the ")
    assert warnings[0].endswith("or set haptics.coupling.passivity_controller: true")
