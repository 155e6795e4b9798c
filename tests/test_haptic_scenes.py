"""The paper's three rigid demos, run with the whole diagram, against the paper's numbers."""

import numpy as np
import pytest
from pydrake.systems.analysis import Simulator

from maglev_haptics.analysis.run_results import run_scenario
from maglev_haptics.diagrams.application import BuildDiagram
from maglev_haptics.diagrams.haptics import interactive_variant
from maglev_haptics.diagrams.scenario import ScenarioError, load_scenario
from maglev_haptics.diagrams.scene import PegInHole
from maglev_haptics.systems.haptic_supervisor import HAPTIC, LANDING
from maglev_haptics.systems.meshcat_hand import GRIP_BUTTON

FREE_FORCE_LIMIT_N = 0.05
FREE_TORQUE_LIMIT_NM = 1e-3


def run(name, path=None, **kwargs):
    scenario = load_scenario(path or name, name)
    return scenario, run_scenario(scenario, label=name, progress=False, **kwargs)


@pytest.fixture(scope="module")
def peg():
    return run("peg_in_hole")


def test_peg_free_motion_is_transparent(peg):
    _, result = peg
    free = result.summary["free_motion"]
    assert free["duration_s"] > 5.0 and free["max_speed_mm_s"] > 20.0
    assert free["max_force_n"] < FREE_FORCE_LIMIT_N
    assert free["max_torque_nmm"] < 1e3 * FREE_TORQUE_LIMIT_NM


def test_peg_contact_stiffness_friction_and_travel(peg):
    scenario, result = peg
    metrics = result.summary["peg_in_hole"]
    expected = 1e-3 * scenario.haptics.coupling.translational_stiffness[2]  # N/mm
    assert metrics["effective_stiffness_n_per_mm"] == pytest.approx(expected, rel=0.25)
    assert metrics["stiffness_fit_r2"] > 0.95
    assert metrics["max_depth_mm"] > 1.0
    assert metrics["sliding_duration_s"] > 1.0
    assert metrics["sliding_friction_ratio"] == pytest.approx(
        scenario.haptics.scene.contact.friction, rel=0.2)
    assert metrics["x_range_in_hole_mm"] == pytest.approx(metrics["x_clearance_mm"], rel=0.25)
    # Pushed against the walls: forces along x and y, and torques from the lever arm.
    log = result.log
    engaged = log["haptic_mode"] == HAPTIC
    assert np.max(np.abs(log["f_user"][engaged, 0])) > 0.2
    assert np.max(np.abs(log["f_user"][engaged, 1])) > 0.05
    assert np.max(np.abs(log["tau_user"][engaged, 1])) > 5e-3


def test_peg_let_go_in_the_hole_is_held_still(peg):
    _, result = peg
    (release,) = result.summary["releases"]
    assert release["outcome"] == "held by the scene"
    assert release["watched_s"] == pytest.approx(5.0, abs=0.01)
    assert release["max_deviation_mm"] < 2.0
    # Nothing rings: the instrument's motion in the last 2 s is tracker-noise small.
    assert release["final_speed_rms_mm_s"] < 3.0
    log = result.log
    after = log["t"] > release["time_s"] + 3.0
    assert np.ptp(log["p_WI_true"][after], axis=0).max() < 0.1e-3


# The peg rested on the hole's floor and let go 6.5 s in, seen by a tracker 3 ms later than
# the default's 1.5 ms: about what the LCM link's two held hops and two clocks add.
LET_GO_OVER_A_SLOW_LINK = """{duration_s: 11.5, device: {tracker: {latency_s: 0.0045}},
 hand: !ScriptedHand {start_s: 3.0, events: [{at_s: 1.8, grip: true}, {at_s: 6.5, grip: false}],
   waypoints: [{pose: [0.0, 0.0, 0.0175, 0.0, 0.0, 0.0], move_s: 1.5, hold_s: 0.5},
               {pose: [-0.010, 0.0, 0.0125, 0.0, 0.0, 0.0], move_s: 1.0, hold_s: 5.0}]}}"""


def test_peg_let_go_stays_still_with_the_links_delay_in_the_loop():
    # The full PD's damping as the brake rang the instrument's roll up (21 Hz) until the
    # coils hit their limit 0.9 s after the let-go.
    scenario = load_scenario("peg_in_hole", "peg_in_hole", LET_GO_OVER_A_SLOW_LINK)
    result = run_scenario(scenario, label="peg_let_go_slow_link", progress=False)
    (release,) = result.summary["releases"]
    assert release["outcome"] == "held by the scene"
    assert release["max_deviation_mm"] < 2.0
    assert release["final_speed_rms_mm_s"] < 3.0
    assert not np.any(result.log["fault_bits"])
    last = result.log["t"] > result.log["t"][-1] - 1.0
    assert np.degrees(np.ptp(result.log["rpy_WI_true"][last], axis=0)).max() < 0.5


def test_the_scripts_landing_ends_haptics_and_lands_the_instrument_let_go_in_the_hole():
    # The script's last hold ends at 9.4 s, with the peg let go in its hole at 6.5 s:
    # haptics ends there, and the device lands the instrument where it is, straight
    # down (the script's pose is 10 mm across and 12 mm up: following it would pull
    # the peg out). Left engaged, the scene would hold an instrument the device no
    # longer carries once the script's force ramps down.
    text = """{duration_s: 14.0, motion: {waypoints: [{pose: [0.0, 0.0, 0.025, 0.0, 0.0, 0.0],
                                           move_s: 1.0, hold_s: 8.0}]},
     hand: !ScriptedHand {start_s: 3.0, events: [{at_s: 1.8, grip: true}, {at_s: 6.5, grip: false}],
       waypoints: [{pose: [0.0, 0.0, 0.0175, 0.0, 0.0, 0.0], move_s: 1.5, hold_s: 0.5},
                   {pose: [-0.010, 0.0, 0.0125, 0.0, 0.0, 0.0], move_s: 1.0, hold_s: 9.0}]}}"""
    scenario = load_scenario("peg_in_hole", "peg_in_hole", text)
    result = run_scenario(scenario, label="peg_script_lands", progress=False)
    log = result.log
    landing_starts_s = 9.4
    assert np.all(log["haptic_mode"][(log["t"] > 6.6) & (log["t"] < landing_starts_s)] == HAPTIC)
    after = log["t"] > landing_starts_s + 0.01
    assert np.all(log["haptic_mode"][after] == LANDING)
    p_WI = log["p_WI_true"]
    let_go = p_WI[np.searchsorted(log["t"], landing_starts_s)]
    assert np.abs(p_WI[after, 0:2] - let_go[0:2]).max() < 1e-3
    assert p_WI[after, 2].max() < let_go[2] + 3e-4
    touchdown = result.summary["touchdown"]
    assert touchdown is not None
    assert touchdown["speed_m_s"] < 0.05 and touchdown["tilt_deg"] < 2.0
    assert not np.any(log["fault_bits"])
    assert result.summary["max_coil_current_a"] <= scenario.device.amplifier.current_limit_a


def test_peg_let_go_outside_lands_within_the_limits():
    scenario, result = run("peg_release_outside", "peg_in_hole")
    (release,) = result.summary["releases"]
    assert release["outcome"] == "landed"
    assert release["final_height_above_rest_mm"] < 0.5
    touchdown = result.summary["touchdown"]
    assert touchdown["speed_m_s"] < 0.05 and touchdown["tilt_deg"] < 2.0
    assert result.summary["max_coil_current_a"] <= scenario.device.amplifier.current_limit_a


def test_hanging_ball_gives_inertial_forces_and_no_torque():
    scenario, result = run("hanging_ball", duration_s=7.5)
    ball = result.summary["hanging_ball"]
    weight_n = scenario.haptics.scene.ball_mass_kg * 9.81
    # The ball's weight hangs on the user, and swinging it adds its inertia.
    assert ball["mean_user_force_n"][2] == pytest.approx(-weight_n, rel=0.1)
    assert min(ball["user_force_range_n"]) > 0.05
    assert result.summary["max_user_torque_nmm"] < 1e3 * FREE_TORQUE_LIMIT_NM


@pytest.mark.parametrize("name, side", [("paddle_ball", -1.0), ("paddle_ball_mirrored", 1.0)])
def test_paddle_bounces_and_off_centre_hits_twist_the_user_their_way(name, side):
    _, result = run(name, "paddle_ball", duration_s=4.5)
    hits = result.summary["paddle_hits"]
    assert len(hits) >= 3  # resting, then struck and caught again
    off_centre = [h for h in hits if abs(h["x_hit_mm"]) > 5.0]
    assert off_centre
    for hit in off_centre:
        assert np.sign(hit["x_hit_mm"]) == side
        assert np.sign(hit["peak_user_torque_about_y_nmm"]) == side
        assert abs(hit["peak_user_torque_about_y_nmm"]) > 1.0


def test_interactive_hand_follows_meshcat_controls(meshcat, click_button):
    scenario = interactive_variant(load_scenario("peg_in_hole"), 30.0)
    built = BuildDiagram(scenario, meshcat=meshcat)
    simulator = Simulator(built.diagram)
    simulator.Initialize()
    context = simulator.get_mutable_context()
    station = built.diagram.GetSubsystemByName("station")
    supervisor = built.haptics.supervisor
    simulator.AdvanceTo(2.2)
    assert station.GetOutputPort("handle_gripped").Eval(
        station.GetMyContextFromRoot(context))[0] == 0.0
    click_button(meshcat, GRIP_BUTTON)
    simulator.AdvanceTo(3.0)
    assert station.GetOutputPort("handle_gripped").Eval(
        station.GetMyContextFromRoot(context))[0] == 1.0
    assert supervisor.GetOutputPort("mode").Eval(
        supervisor.GetMyContextFromRoot(context))[0] == HAPTIC
    # Raise the hand 4 mm and move it 6 mm along x with the sliders: the instrument follows.
    start = station.GetOutputPort("instrument_state").Eval(
        station.GetMyContextFromRoot(context))[4:7].copy()
    meshcat.SetSliderValue("Hand x (mm)", 1e3 * start[0] + 6.0)
    meshcat.SetSliderValue("Hand z (mm)", 1e3 * start[2] + 4.0)
    simulator.AdvanceTo(4.5)
    moved = station.GetOutputPort("instrument_state").Eval(
        station.GetMyContextFromRoot(context))[4:7] - start
    np.testing.assert_allclose(1e3 * moved, [6.0, 0.0, 4.0], atol=0.5)
    # Let go: free of the scene, the device lands the instrument.
    click_button(meshcat, GRIP_BUTTON)
    simulator.AdvanceTo(5.0)
    assert supervisor.GetOutputPort("mode").Eval(
        supervisor.GetMyContextFromRoot(context))[0] != HAPTIC
    built.meshcat_hand.Delete()


def test_interactive_needs_a_scene():
    with pytest.raises(ValueError, match="needs a scenario with haptics"):
        interactive_variant(load_scenario("levitate"), 10.0)


def test_scene_kind_is_chosen_by_its_tag():
    scenario = load_scenario("peg_in_hole",
                             scenario_text="{haptics: {scene: !PegInHole {peg_mass_kg: 0.03}}}")
    assert isinstance(scenario.haptics.scene, PegInHole)
    assert scenario.haptics.scene.peg_mass_kg == 0.03
    # Untagged, Drake would read any scene as the Union's first kind, a fresh PegInHole.
    with pytest.raises(ScenarioError, match=r"haptics.scene: needs a tag.*!PegInHole"):
        load_scenario("hanging_ball", scenario_text="{haptics: {scene: {contact: {friction: 0.3}}}}")
    with pytest.raises(ScenarioError, match=r"hand: needs a tag"):
        load_scenario("peg_in_hole", scenario_text="{hand: {start_s: 1.0}}")
    with pytest.raises(ScenarioError, match=r"haptics.scene.pegg: unknown field; HangingBall has"):
        load_scenario("hanging_ball", scenario_text="{haptics: {scene: !HangingBall {pegg: 1}}}")
    with pytest.raises(ScenarioError, match=r"haptics.scene: !Teapot is not one of !PegInHole "
                                            r"\{...\}, !HangingBall \{...\}, !PaddleBall \{...\}, "
                                            r"!ModelScene \{...\}, !DeformableSurface \{...\}$"):
        load_scenario("peg_in_hole", scenario_text="{haptics: {scene: !Teapot {}}}")


def test_haptics_needs_a_hand():
    with pytest.raises(ScenarioError, match=r"hand = null: a haptic scenario needs the user's hand"):
        load_scenario("peg_in_hole", scenario_text="{hand: null}")


@pytest.mark.parametrize("text, message", [
    ("{haptics: {coupling: {translational_stiffness: [400.0, -1.0, 400.0]}}}",
     r"haptics.coupling.translational_stiffness\[1\] = -1.0: must be a finite number > 0"),
    ("{haptics: {coupling: {device_limit: nominal}}}",
     r"haptics.coupling.device_limit = 'nominal': must be one of peak, thermal"),
    ("{haptics: {disable_at_s: 1.0}}", r"haptics.disable_at_s = 1.0: must be after enable_at_s"),
    ("{haptics: {scene: !PegInHole {peg_mass_kg: -0.02}}}", r"haptics.scene.peg_mass_kg = -0.02"),
])
def test_bad_haptics_input_names_the_field(text, message):
    with pytest.raises(ScenarioError, match=message):
        load_scenario("peg_in_hole", scenario_text=text)
