"""Scenario files: every shipped one loads; bad input names the field, value and what is allowed."""

import pytest

from maglev_haptics.cli import main
from maglev_haptics.diagrams.scenario import (
    Scenario, ScenarioError, load_scenario, scenario_names, shipped_scenario_files)


def write(tmp_path, text):
    path = tmp_path / "s.yaml"
    path.write_text(text)
    return str(path)


def test_every_shipped_scenario_loads():
    files = shipped_scenario_files()
    assert files
    for path in files:
        for name in scenario_names(path):
            assert isinstance(load_scenario(str(path), name), Scenario)


def test_levitate_names_the_required_scenarios():
    names = scenario_names(shipped_scenario_files()[[p.stem for p in shipped_scenario_files()]
                                                    .index("levitate")])
    for required in ("takeoff_hover_land", "four_magnet_tilt", "yaw_turn", "square",
                     "vertical_sweep"):
        assert required in names
    assert load_scenario("levitate", "four_magnet_tilt").device.instrument == "four_magnet"


@pytest.mark.parametrize("text, fragment", [
    ("a: {device: {coil: {tunrs: 3}}}", "a: device.coil.tunrs: unknown field; CoilSpec has"),
    ("a: {motion: {waypoints: [{pose: [0, 0, 0.02, 0, 0, 0], hold: 1}]}}",
     "motion.waypoints[0].hold: unknown field"),
    ("a: {device: {tracker: {rate_hz: fast}}}",
     "device.tracker.rate_hz = fast: must be a number (Hz)"),
    ("a: {device: {instrument_mass_kg: -0.1}}", "device.instrument_mass_kg = -0.1: must be a finite number > 0"),
    ("a: {device: {instrument: three_magnet}}", "device.instrument = 'three_magnet': must be one of"),
    ("a: {motion: {waypoints: [{pose: [0, 0, 0.02]}]}}", "motion.waypoints[0].pose = [0.0, 0.0, 0.02]: must be a list of 6"),
    ("a: {device: {amplifier: {current_limit_a: 0}}}", "device.amplifier.current_limit_a = 0"),
    ("a: {controller: {damping_ratio: [0.7, 0.7, 0.7, 0.7, 0.7, .nan]}}", "controller.damping_ratio"),
    ("a: {occlusions: [{marker: 5, start_s: 1, end_s: 2}]}", "occlusions[0].marker = 5"),
    ("a: {marker_dropout_probability: 1.5}", "marker_dropout_probability = 1.5: must be in [0, 1]"),
    ("a: {hardware: real}", "hardware: unknown field"),
    ("a: {station: {url: x}}", "station: needs a tag to choose its kind, one of !SimStation {...}, "
     "!LcmStation {...}"),
    ("a: {station: !LcmStation {url: 'tcp://10.0.0.1'}}", "station.url = 'tcp://10.0.0.1': must be an LCM UDP multicast URL"),
    ("a: {station: !LcmStation {stale_margin_s: -1}}", "station.stale_margin_s = -1"),
    # The rate itself, not a check that divides by it.
    ("a: {control_rate_hz: -5}", "a: control_rate_hz = -5.0: must be a finite number > 0"),
    ("a: 5", "a: must be a YAML mapping of the scenario's fields, not int (5)"),
    # YAML keeps the last of two; the first would be ignored without a word.
    ("a:\n  duration_s: 0.2\n  duration_s: 0.3\n",
     "a.duration_s: given twice (lines 2 and 3); say each key once"),
    ("a: {motion: {waypoints: [{pose: [0, 0, 0.02, 0, 0, 0], hold_s: 1, hold_s: 2}]}}",
     "a.motion.waypoints[0].hold_s: given twice (line 1)"),
])
def test_bad_values_name_the_field(tmp_path, text, fragment):
    with pytest.raises(ScenarioError) as error:
        load_scenario(write(tmp_path, text), "a")
    assert fragment in str(error.value)


def test_si_values_in_exponent_notation_load(tmp_path):
    """YAML 1.1 reads 1e-5 (no dot) as text; Drake's loader, and so the scenario, as a number."""
    scenario = load_scenario(write(tmp_path, "a: {device: {tracker: {noise_m: 2e-5}}}"), "a",
                             scenario_text="{device: {instrument_mass_kg: 1e-1}}")
    assert scenario.device.tracker.noise_m == 2e-5
    assert scenario.device.instrument_mass_kg == 0.1
    heavy = load_scenario("levitate", scenario_text="{device: {instrument_mass_kg: 1e9}}")
    assert heavy.device.instrument_mass_kg == 1e9


def test_unknown_scenario_name_lists_the_known_ones(tmp_path):
    with pytest.raises(ScenarioError, match="no scenario named 'b'; it has a"):
        load_scenario(write(tmp_path, "a: {}"), "b")


def test_cli_reports_bad_input_without_a_traceback(tmp_path, capsys):
    path = write(tmp_path, "a: {device: {coil: {turns: -3}}}")
    assert main(["run", path, "--no-meshcat"]) == 2
    assert "device.coil.turns = -3: must be a positive integer" in capsys.readouterr().err


@pytest.mark.parametrize("pose, fragment", [
    ([0, 0, 0.002, 0, 0, 0], "inside the display glass"),
    ([0, 0, 0.06, 0, 0, 0], r"takes [0-9.]+ A in the busiest coil .* falls [0-9.]+ N short"),
    ([0, 0, 0.15, 0, 0, 0], "out of the coils' reach"),
    ([0.3, 0, 0.018, 0, 0, 0], "out of the coils' reach"),
    ([0, 0, 0.03, 1.4, 0, 0], "tilt 80.2 deg is beyond the 45 deg"),
])
def test_unreachable_waypoints_are_refused(tmp_path, pose, fragment):
    from maglev_haptics.diagrams.application import BuildDiagram

    scenario = load_scenario(write(tmp_path, f"a: {{motion: {{waypoints: [{{pose: {pose}}}]}}}}"), "a")
    with pytest.raises(ScenarioError, match=r"motion.waypoints\[0\].pose = .*" + fragment):
        BuildDiagram(scenario, label="a")


@pytest.mark.parametrize("argv, fragment", [
    (["--duration", "-1"], "argument --duration: '-1': must be > 0"),
    (["--scenario-text", "{device: {instrument: four_magnet"], "--scenario-text: not valid YAML"),
    (["--scenario-text", "[1, 2]"], "--scenario-text: must be a YAML mapping"),
])
def test_cli_bad_arguments_are_one_line_errors(capsys, argv, fragment):
    try:
        code = main(["run", "levitate", "--no-meshcat", *argv])
    except SystemExit as exit:  # argparse's own checks exit, as for any bad option
        code = exit.code
    assert code == 2
    assert fragment in capsys.readouterr().err


def test_cli_out_that_is_a_file_is_a_one_line_error(tmp_path, capsys):
    existing = tmp_path / "file"
    existing.write_text("x")
    assert main(["run", "levitate", "--no-meshcat", "--duration", "0.05",
                 "--out", str(existing)]) == 2
    assert "error:" in capsys.readouterr().err


# Every refusal of the loader, whole: each message is built from the schema (the field's
# path, its value, what its type takes), never from Drake's error text, so a Drake
# upgrade that words its errors differently changes none of them.
@pytest.mark.parametrize("text, message", [
    ("{duration_s: three}", "duration_s = three: must be a number (s), or null"),
    ("{duration_s: [1, 2]}", "duration_s = [1, 2]: must be a number (s), or null"),
    ("{control_rate_hz: true}", "control_rate_hz = true: must be a number (Hz)"),
    ("{random_seed: 1.5}", "random_seed = 1.5: must be a whole number"),
    ("{random_seed: abc}", "random_seed = abc: must be a whole number"),
    ("{motion: 3}", "motion = 3: must be a mapping of MotionScript's fields (start_xy_yaw, "
     "takeoff_at_s, force_ramp_s, waypoints, landing_s, settle_s)"),
    ("{motion: {waypoints: 3}}", "motion.waypoints = 3: must be a list of Waypoint mappings"),
    ("{motion: {waypoints: [{pose: abc}]}}",
     "motion.waypoints[0].pose = abc: must be a list of numbers"),
    ("{motion: {waypoints: [{pose: [0, 0, x, 0, 0, 0]}]}}",
     "motion.waypoints[0].pose[2] = x: must be a number"),
    ("{motion: {start_xy_yaw: -1}}", "motion.start_xy_yaw = -1: must be a list of numbers"),
    ("{occlusions: [{marker: x}]}", "occlusions[0].marker = x: must be a whole number, or null"),
    ("{motion: {nope: 1}}", "motion.nope: unknown field; MotionScript has start_xy_yaw, "
     "takeoff_at_s, force_ramp_s, waypoints, landing_s, settle_s"),
    ("{station: !Foo {}}", "station: !Foo is not one of !SimStation {...}, !LcmStation {...}"),
    ("{hand: !Foo {}}", "hand: !Foo is not one of !ScriptedHand {...}, !MeshcatHand {...}, "
     "or null"),
    ("{hand: 3}", "hand = 3: must be one of !ScriptedHand {...}, !MeshcatHand {...}, or null"),
    ("{plant_config: {time_step: abc}}", "plant_config.time_step = abc: must be a number"),
    ("{plant_config: {nope: 1}}", "plant_config.nope: unknown field; MultibodyPlantConfig has "
     "time_step, use_sampled_output_ports, penetration_allowance, stiction_tolerance, "
     "contact_model, discrete_contact_approximation, sap_near_rigid_threshold, "
     "contact_surface_representation, adjacent_bodies_collision_filters"),
    ("{faults: [{at_s: 1}]}", "faults[0]: needs a tag to choose its kind, one of "
     "!LatencySpike {...}, !CorruptSample {...}, !StuckAmplifier {...}, !Shove {...}"),
])
def test_each_loader_refusal_is_one_line_built_from_the_schema(text, message):
    with pytest.raises(ScenarioError) as error:
        load_scenario("levitate", scenario_text=text)
    assert str(error.value) == f"levitate:takeoff_hover_land (--scenario-text): {message}"


@pytest.mark.parametrize("text, message", [
    ("{motion: {waypoints: [{hold_s: 1.0e308}]}}", "motion.waypoints[0].hold_s = 1e+308: "
     "takes its script to 1e+308 s; a script lasts at most 3600 s"),
    ("{motion: {waypoints: [{move_s: 1.0e300}]}}", "motion.waypoints[0].move_s = 1e+300: "
     "takes its script to 1e+300 s; a script lasts at most 3600 s"),
    ("{motion: {takeoff_at_s: 1.0e308}}", "motion.takeoff_at_s = 1e+308: "
     "takes its script to 1e+308 s; a script lasts at most 3600 s"),
    ("{motion: {waypoints: [{hold_s: 3599}]}}", "motion.waypoints[0].hold_s = 3599.0: "
     "takes its script to 3600.4 s; a script lasts at most 3600 s"),
    ("{duration_s: 1.0e308}", "duration_s = 1e+308: a run lasts at most 3600 s"),
    ("{control_rate_hz: 1.0e308}", "control_rate_hz = 1e+308: must be at most 100000 Hz"),
    ("{log_rate_hz: 1.0e300}", "log_rate_hz = 1e+300: must be at most 100000 Hz"),
    ("{device: {tracker: {rate_hz: 1.0e300}}}",
     "device.tracker.rate_hz = 1e+300: must be at most 100000 Hz"),
    ("{device: {head_tracker: {rate_hz: 1.0e300}}}",
     "device.head_tracker.rate_hz = 1e+300: must be at most 100000 Hz"),
    ("{device: {tracker: {rate_hz: 2000}}}", "device.tracker.rate_hz = 2000.0: must be at "
     "most one sample a tick: 1 / control_rate_hz (1000 Hz)"),
    ("{control_rate_hz: 2000, device: {tracker: {rate_hz: 2000}}}",
     "device.tracker.rate_hz = 2000.0: must be at most one sample a tick: 1 / "
     "plant_config.time_step (1000 Hz)"),
    ("{estimator: {processing_delay_s: 0.0005}}", "estimator.processing_delay_s = 0.0005: "
     "must be at most 0.000162791 s: the tracker's period less the loop's tick, so each "
     "sample is processed before the next is published"),
    ("{plant_config: {time_step: 1.0e300}}", "plant_config.time_step = 1e+300: must be at "
     "most 0.1 s"),
    ("{controller: {natural_frequency_hz: [1.0e300, 10, 10, 10, 10, 10]}}",
     "controller.natural_frequency_hz[0] = 1e+300: must be below half the control rate "
     "(500 Hz)"),
    ("{controller: {damping_ratio: [0.7, 0.7, 1.0e300, 0.7, 0.7, 0.7]}}",
     "controller.damping_ratio[2] = 1e+300: must be at most 100"),
])
def test_a_huge_finite_time_or_rate_is_refused_naming_its_field(text, message):
    """A hold of 1e308 s once ended in Drake's 'Times must be in increasing order.'"""
    with pytest.raises(ScenarioError) as error:
        load_scenario("levitate", scenario_text=text)
    assert str(error.value) == f"levitate:takeoff_hover_land (--scenario-text): {message}"


@pytest.mark.parametrize("file, text, field", [
    ("peg_in_hole", "{hand: !ScriptedHand {waypoints: [{hold_s: 1.0e308}]}}",
     "hand.waypoints[0].hold_s = 1e+308"),
    ("peg_in_hole", "{hand: !ScriptedHand {events: [{at_s: 1.0e308}]}}",
     "hand.events[0].at_s = 1e+308"),
    ("stereo_display", "{stereo: {head: {waypoints: [{move_s: 1.0e308}]}}}",
     "stereo.head.waypoints[0].move_s = 1e+308"),
])
def test_the_hands_and_the_heads_scripts_are_bounded_too(file, text, field):
    with pytest.raises(ScenarioError, match=r"a script lasts at most 3600 s$") as error:
        load_scenario(file, scenario_text=text)
    assert field in str(error.value)


def test_a_long_hold_within_the_bound_loads():
    scenario = load_scenario("levitate", scenario_text="{motion: {waypoints: [{hold_s: 600}]}}")
    assert scenario.motion.waypoints[0].hold_s == 600


def test_an_error_the_overlay_makes_is_said_to_be_the_overlays(tmp_path):
    """A range error that --scenario-text brings in names it, as its type errors do;
    one already in the file is the file's, the overlay or not."""
    with pytest.raises(ScenarioError, match=r"^levitate:takeoff_hover_land \(--scenario-text\): "
                                            r"duration_s = -1.0: must be a finite number > 0"):
        load_scenario("levitate", scenario_text="{duration_s: -1}")
    with pytest.raises(ScenarioError, match=r"^--scenario-text: duration_s: given twice"):
        load_scenario("levitate", scenario_text="{duration_s: 1, duration_s: 2}")
    path = write(tmp_path, "a: {log_rate_hz: 0}")
    with pytest.raises(ScenarioError, match=r"^[^(]*a: log_rate_hz = 0"):
        load_scenario(path, "a", scenario_text="{duration_s: 1}")
