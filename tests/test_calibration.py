"""The device's own truth and its calibration (issue 38): the new device fields, a
simulated device unlike the model, the fit's arithmetic on synthetic data, and the
command's refusals. The whole plan-fly-fit-check cycle is the slow test at the end."""

import dataclasses
import glob
import json
import time

import numpy as np
import pytest
from pydrake.math import RigidTransform, RollPitchYaw
from pydrake.multibody.plant import AddMultibodyPlantSceneGraph
from pydrake.systems.framework import DiagramBuilder

from maglev_haptics.analysis.calibration_fit import (
    CalibrationError, Flight, Hold, fit_thermal, fit_wrench_model, gravity_wrench, overlay_text)
from maglev_haptics.analysis.run_results import run_scenario
from maglev_haptics.cli import main
from maglev_haptics.diagrams.lcm_station import LcmStation
from maglev_haptics.diagrams.scenario import ScenarioError, load_scenario, scenario_yaml
from maglev_haptics.diagrams.station import MakeStation, add_station_models
from maglev_haptics.hardware.device import DeviceConfig
from maglev_haptics.hardware.link.lcm_link import publish
from maglev_haptics.hardware.magnetics import load_magnetics
from maglev_haptics.hardware.thermal import (
    coil_thermal, current_bounds_a, step_temperatures_c, thermal_budget, winding_numbers)
from maglev_haptics.systems.haptic_supervisor import HAPTIC
from maglev_haptics.systems.station_messages import status_message

TRACKER_OFF = ("X_WT: {translation: [0.0012, -0.0008, 0.0005], "
               "rotation: !Rpy {deg: [0.4, -0.3, 0.7]}}")


def _coil_scales(seed=7):
    return [round(float(v), 4) for v in 1 + np.random.default_rng(seed).uniform(-0.03, 0.03, 27)]


def _thermal(seed=9):
    """Each coil's R_th (K/W) and C (J/K), +-10 % about the nominal's."""
    rng = np.random.default_rng(seed)
    return ([round(float(v), 4) for v in 2.5 * (1 + rng.uniform(-0.1, 0.1, 27))],
            [round(float(v), 3) for v in 27.7 * (1 + rng.uniform(-0.1, 0.1, 27))])


def device_text(latency_s=0.0022):
    """A device within the issue's ranges, as a simulated station's overlay."""
    resistances, capacities = _thermal()
    return ("{station: !SimStation {device: {instrument_mass_kg: 0.133, "
            "instrument_com_offset_m: [0.00015, -0.00009, 0.00006], "
            f"coil_force_scales: {_coil_scales()}, magnet_strength_scales: [1.035, 0.965], "
            f"tracker: {{latency_s: {latency_s}, {TRACKER_OFF}}}, "
            f"thermal: {{thermal_resistances_k_per_w: {resistances}, "
            f"heat_capacities_j_per_k: {capacities}}}}}}}}}")


@pytest.mark.parametrize("text, fragment", [
    ("{device: {coil_force_scales: [1.0, 1.0]}}",
     "device.coil_force_scales = [1.0, 1.0]: must be 27 numbers (one per coil)"),
    ("{device: {magnet_strength_scales: [1.0, 2.0]}}", "in [0.5, 1.5], or null for 1.0 each"),
    ("{device: {instrument_com_offset_m: [0.05, 0, 0]}}",
     "device.instrument_com_offset_m = [0.05, 0.0, 0.0]: must be [x, y, z] in I (m), at most "
     "0.02 m"),
    ("{device: {tracker: {X_WT: {base_frame: world}}}}", "device.tracker.X_WT"),
    ("{station: !SimStation {device: {instrument: four_magnet}}}",
     "station.device.instrument: a simulated station's device may differ from the "
     "scenario's only in"),
    ("{calibration: {payload_kg: 0.1}}", "calibration.payload_kg = 0.1: must be between 0 and"),
    ("{device: {thermal: {thermal_resistances_k_per_w: [2.5, -1]}}}",
     "device.thermal.thermal_resistances_k_per_w = [2.5, -1.0]: must be 27 positive numbers"),
])
def test_bad_device_truth_is_one_line_naming_the_field(text, fragment):
    with pytest.raises(ScenarioError) as error:
        load_scenario("levitate", None, text)
    assert fragment in str(error.value)
    assert "\n" not in str(error.value)


def test_a_simulated_device_is_the_scenarios_with_its_layers():
    scenario = load_scenario("levitate", "four_magnet_tilt",
                             "{station: !SimStation {device: {tracker: {latency_s: 0.003}}}}",
                             "{station: !SimStation {device: {instrument_mass_kg: 0.08}}}")
    device = scenario.station.device
    assert device.instrument == "four_magnet"  # the scenario's, not the default's
    assert device.tracker.latency_s == 0.003 and device.instrument_mass_kg == 0.08
    assert scenario.device.tracker.latency_s == 0.0015  # the model the application flies
    assert scenario.device.instrument_mass_kg is None
    # A later layer that names the station alone keeps its device, as Drake layers do.
    again = load_scenario("levitate", None, "{station: !SimStation {device: {instrument_mass_kg: "
                          "0.13}}}", "{station: !SimStation {}}")
    assert again.station.device.instrument_mass_kg == 0.13


def test_scales_weigh_each_magnet_and_coil_of_the_wrench_matrix():
    nominal = DeviceConfig()
    scales = dataclasses.replace(nominal, magnet_strength_scales=[1.04, 0.97],
                                 coil_force_scales=_coil_scales())
    p_AI, R_AI = np.array([0.004, -0.003, 0.028]), RollPitchYaw(0.1, -0.05, 0.7).ToRotationMatrix().matrix()
    shares = load_magnetics(nominal).magnet_wrench_matrices(p_AI, R_AI)
    expected = np.einsum("m,mkj,j->kj", [1.04, 0.97], shares, _coil_scales())
    np.testing.assert_allclose(load_magnetics(scales).wrench_matrix_from(p_AI, R_AI), expected,
                               rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(shares.sum(axis=0),
                               load_magnetics(nominal).wrench_matrix_from(p_AI, R_AI),
                               rtol=1e-12, atol=1e-15)


def test_the_instrument_model_carries_the_devices_mass_and_centre_of_mass():
    scenario = load_scenario("levitate", None, "{device: {instrument_mass_kg: 0.14, "
                             "instrument_com_offset_m: [0.001, -0.002, 0.0005]}}")
    plant, scene_graph = AddMultibodyPlantSceneGraph(DiagramBuilder(), 0.001)
    instrument, _ = add_station_models(plant, scenario)
    plant.Finalize()
    body = plant.GetBodyByName("instrument", instrument)
    assert body.default_mass() == pytest.approx(0.14)
    np.testing.assert_allclose(body.default_com(), [0.001, -0.002, 0.0005])
    # the model's contact pads keep their drake: properties through the edit
    inspector = scene_graph.model_inspector()
    pads = plant.GetCollisionGeometriesForBody(body)
    assert pads and all(inspector.GetProximityProperties(pad).GetProperty(
        "material", "point_contact_stiffness") == 2000 for pad in pads)


def _fly(text, seconds=3.0):
    scenario = load_scenario("levitate", None, text)
    return run_scenario(scenario, label="t", duration_s=seconds, progress=False,
                        raise_priority=False).log


def test_a_tracker_bolted_off_moves_the_instrument_until_its_registration_is_applied():
    """The device's tracker reports in T, 1.5 mm and 0.8 deg off W: an application that
    believes T is W flies the instrument off by that much; one with the calibrated X_WT
    flies it where it commands."""
    t_hover = slice(2000, 3000)
    believed = _fly(f"{{station: !SimStation {{device: {{tracker: {{{TRACKER_OFF}}}}}}}}}")
    calibrated = _fly(f"{{device: {{tracker: {{{TRACKER_OFF}}}}}}}")
    X_WT = RigidTransform(RollPitchYaw(np.radians([0.4, -0.3, 0.7])), [0.0012, -0.0008, 0.0005])
    p_true, p_measured = believed["p_WI_true"][t_hover], believed["p_WI_measured"][t_hover]
    # measured (in T, taken for W) = X_TW p_true: off by the bolt's ~1.5 mm
    np.testing.assert_allclose(p_measured.mean(axis=0),
                               (X_WT.inverse() @ p_true.T).T.mean(axis=0), atol=1e-5)
    assert np.linalg.norm(p_true - p_measured, axis=1).min() > 1e-3
    error = calibrated["p_WI_true"][t_hover] - calibrated["p_WI_measured"][t_hover]
    assert np.linalg.norm(error.mean(axis=0)) < 1e-5


def _synthetic_holds(truth: DeviceConfig, rng, n=36, payload_every=6, unused=()):
    """Still holds of ``truth``: at each pose the currents a minimum-norm allocation
    gives for its weight (the ``unused`` coils left out), the pose and currents as a
    tracker and amplifier report them."""
    magnetics = load_magnetics(truth)
    holds = []
    for k in range(n):
        payload = 0.02 if k % payload_every == 0 else 0.0
        p_WI = np.array([*rng.uniform(-0.025, 0.025, 2), rng.uniform(0.012, 0.022)])
        R_WI = RollPitchYaw(*rng.uniform(-0.15, 0.15, 2), rng.uniform(0, 3)).ToRotationMatrix().matrix()
        A = magnetics.wrench_matrix_from(p_WI - truth.p_WA, R_WI)
        weight = gravity_wrench(truth.instrument_spec().mass_kg, truth.instrument_com_offset_m, R_WI,
                                payload, np.zeros(3))
        A[:, list(unused)] = 0.0
        currents = np.linalg.pinv(A) @ -weight
        holds.append(Hold("holds", p_WI + rng.normal(0, 2e-6, 3), R_WI,
                          currents + rng.normal(0, 2e-4, 27), payload, np.zeros(3)))
    return holds


def test_the_fit_recovers_a_device_from_its_holds():
    nominal = DeviceConfig()
    truth = dataclasses.replace(nominal, magnet_strength_scales=[1.035, 0.965],
                                coil_force_scales=_coil_scales(), instrument_mass_kg=0.133,
                                instrument_com_offset_m=[0.0002, -0.0001, 0.0001])
    fit = fit_wrench_model(_synthetic_holds(truth, np.random.default_rng(1)),
                           load_magnetics(nominal), nominal)
    assert fit.mass_kg == pytest.approx(0.133, rel=2e-3)
    np.testing.assert_allclose(fit.com_I_m, truth.instrument_com_offset_m, atol=5e-5)
    gauge = np.exp(np.mean(np.log(truth.coil_force_scales)))
    np.testing.assert_allclose(fit.coil_scales, np.array(truth.coil_force_scales) / gauge,
                               rtol=5e-3)
    np.testing.assert_allclose(fit.magnet_scales, np.array([1.035, 0.965]) * gauge, rtol=5e-3)
    assert np.linalg.norm(fit.residuals_after) < 0.01 * np.linalg.norm(fit.residuals_before)
    assert fit.not_identified == []


def test_a_coil_no_hold_uses_is_said_not_identified():
    nominal = DeviceConfig()
    holds = _synthetic_holds(nominal, np.random.default_rng(2), n=40, unused=[0])
    for hold in holds:
        hold.currents_a[0] = 0.0  # coil 0, in a corner, never carries current
    fit = fit_wrench_model(holds, load_magnetics(nominal), nominal)
    assert [line.split(" (")[0] for line in fit.not_identified] == ["coil_force_scales[0]"]
    assert "a hold above it, pose [-0.052, -0.045, 0.014" in fit.not_identified[0]
    assert fit.coil_scales[0] == 1.0
    np.testing.assert_allclose(fit.coil_scales, 1.0, atol=5e-3)


def test_too_few_holds_is_refused_naming_the_flights():
    nominal = DeviceConfig()
    with pytest.raises(CalibrationError, match="fly the plan's holds_\\* flights and its "
                                               "payload flight"):
        fit_wrench_model(_synthetic_holds(nominal, np.random.default_rng(3), n=8),
                         load_magnetics(nominal), nominal)


def test_the_overlay_is_a_device_layer_maglev_run_takes():
    device = dataclasses.replace(DeviceConfig(), magnet_strength_scales=[1.01, 0.99],
                                 coil_force_scales=[1.0] * 27, instrument_mass_kg=0.126)
    scenario = load_scenario("levitate", None, overlay_text(device))
    assert scenario.device.instrument_mass_kg == pytest.approx(0.126)
    assert scenario.device.magnet_strength_scales == pytest.approx([1.01, 0.99])
    with pytest.raises(ScenarioError, match="must be 4 numbers \\(one per magnet"):
        load_scenario("levitate", "four_magnet_tilt", overlay_text(device))


def _fake_run(folder, scenario, seconds=1.0):
    """A run folder of ``scenario`` with a log of its shape (for the refusals)."""
    folder.mkdir(parents=True)
    (folder / "scenario.yaml").write_text(scenario_yaml(scenario))
    t = np.arange(0, seconds, 0.001)
    np.savez(folder / "log.npz", t=t, coil_currents=np.zeros((len(t), 27)),
             markers_measured=np.full((len(t), 9), np.nan),
             markers_sample_time_s=t, tracking_ok=np.zeros(len(t)),
             fault_bits=np.zeros(len(t), dtype=np.int64) + (2 if "lost" in folder.name else 0))


@pytest.mark.parametrize("runs, fragment", [
    (["ordinary"], "not a calibration flight (its scenario has no calibration block)"),
    (["nothing"], "not a run folder (scenario.yaml missing)"),
    (["holds", "four"], "the flights are of different instruments"),
    (["holds"], "the registration needs 2"),
    (["holds", "check"], "the check flight is among the folders"),
    (["holds", "lost"], "lost: the flight latched a fault at 0.000 s"),
])
def test_calibrate_fit_refuses_in_one_line_and_writes_nothing(tmp_path, capsys, runs, fragment):
    _fake_run(tmp_path / "ordinary", load_scenario("levitate"))
    _fake_run(tmp_path / "holds", load_scenario("levitate", None, "{calibration: {flight: holds}}"))
    _fake_run(tmp_path / "four", load_scenario("levitate", "four_magnet_tilt",
                                               "{calibration: {flight: holds}}"))
    _fake_run(tmp_path / "check", load_scenario("levitate", None, "{calibration: {flight: check}}"))
    _fake_run(tmp_path / "lost", load_scenario("levitate", None, "{calibration: {flight: holds}}"))
    (tmp_path / "nothing").mkdir()
    out = tmp_path / "fit" / "lab_device.yaml"
    code = main(["calibrate", "fit", *[str(tmp_path / r) for r in runs], "--out", str(out)])
    error = capsys.readouterr().err
    assert code == 2
    assert fragment in error and error.count("\n") == 1
    assert not (tmp_path / "fit").exists()


def test_calibrate_check_refuses_an_overlay_for_another_instrument(tmp_path, capsys):
    _fake_run(tmp_path / "check", load_scenario("levitate", None, "{calibration: {flight: check}}"))
    overlay = tmp_path / "lab_device.yaml"
    overlay.write_text("device: {instrument: four_magnet, instrument_mass_kg: 0.08}\n")
    assert main(["calibrate", "check", str(tmp_path / "check"), "--device", str(overlay)]) == 2
    assert "an overlay for the four_magnet instrument" in capsys.readouterr().err


def test_calibrate_plan_writes_flights_every_station_can_fly(tmp_path, capsys):
    assert main(["calibrate", "plan", "--out", str(tmp_path / "plan")]) == 0
    printed = capsys.readouterr().out
    flights = ["holds_1", "holds_2", "holds_3", "holds_4", "steps", "payload", "check"]
    for name in flights:
        assert f"--name {name} " in printed
        assert (tmp_path / "plan" / f"mark_{name}.png").exists()
        scenario = load_scenario(str(tmp_path / "plan" / "calibration_flights.yaml"), name)
        assert scenario.calibration.flight == name.split("_")[0]
        assert scenario.motion.takeoff_at_s >= 1.0  # resting on its mark first
    total_s = float(printed.split(" s of flight")[0].split(", ")[-1])
    assert total_s <= 600  # at most 10 minutes of flight


@pytest.mark.slow
def test_the_whole_cycle_calibrates_a_device_unlike_the_model(tmp_path, capsys):
    """Plan, fly against a device within the issue's ranges (in-process simulated
    station), fit, check; then the twin flown with the fit predicts the device."""
    start = time.perf_counter()
    plan = tmp_path / "plan" / "calibration_flights.yaml"
    assert main(["calibrate", "plan", "--out", str(tmp_path / "plan")]) == 0
    for name in ("holds_1", "holds_2", "holds_3", "holds_4", "steps", "payload", "check"):
        assert main(["run", str(plan), "--name", name, "--no-meshcat", "--out",
                     str(tmp_path / "runs" / name), "--scenario-text", device_text()]) == 0
    runs = sorted(glob.glob(str(tmp_path / "runs" / "*")))
    fitted_runs = [r for r in runs if not r.endswith("check")]
    overlay = tmp_path / "fit" / "lab_device.yaml"
    assert main(["calibrate", "fit", *fitted_runs, "--out", str(overlay)]) == 0
    capsys.readouterr()
    assert main(["calibrate", "check", str(tmp_path / "runs" / "check"), "--device",
                 str(overlay), "--json"]) == 0
    check = json.loads(capsys.readouterr().out)
    minutes = (time.perf_counter() - start) / 60
    assert minutes < 15

    truth = load_scenario(str(plan), "holds_1", device_text()).station.device
    fitted = load_scenario(str(plan), "holds_1", overlay.read_text()).device
    # The wrench matrix at 50 poses the flights did not visit.
    rng = np.random.default_rng(50)
    models = [load_magnetics(d) for d in (truth, fitted, DeviceConfig())]
    errors = []
    for _ in range(50):
        p_AI = np.array([*rng.uniform(-0.025, 0.025, 2), rng.uniform(0.012, 0.022)]) - truth.p_WA
        R_AI = RollPitchYaw(*rng.uniform(-0.12, 0.12, 2), rng.uniform(0, 6.28)).ToRotationMatrix().matrix()
        A = [m.wrench_matrix_from(p_AI, R_AI) for m in models]
        errors.append([np.linalg.norm(a - A[0]) / np.linalg.norm(A[0]) for a in A[1:]])
    errors = np.array(errors)
    assert errors[:, 0].max() < 0.005  # fitted
    assert errors[:, 1].min() > 0.02  # nominal: several percent
    assert fitted.instrument_mass_kg == pytest.approx(0.133, rel=0.01)
    np.testing.assert_allclose(fitted.instrument_com_offset_m, truth.instrument_com_offset_m,
                               atol=3e-4)
    assert fitted.tracker.latency_s == pytest.approx(truth.tracker.latency_s, abs=2e-4)
    X_fit, X_true = fitted.tracker.pose_WT(), truth.tracker.pose_WT()
    assert np.linalg.norm(X_fit.translation() - X_true.translation()) < 2e-4
    angle = X_fit.rotation().InvertAndCompose(X_true.rotation()).ToAngleAxis().angle()
    assert np.degrees(angle) < 0.1
    assert check["fitted"]["colocation_error_mm"] < 0.2 < check["nominal"]["colocation_error_mm"]
    assert check["fitted"]["hover_current_error_percent"] < 1 < check["nominal"][
        "hover_current_error_percent"]
    report = json.loads((tmp_path / "fit" / "calibration_report.json").read_text())
    fitted_r = np.array(report["parameters"]["thermal.thermal_resistances_k_per_w"]["fitted"])
    weighed = np.isfinite(np.array(report["parameters"]["thermal.thermal_resistances_k_per_w"]
                                   ["interval_95"], dtype=float))
    assert weighed.sum() >= 10  # the coils the flights warm by a kelvin or more
    np.testing.assert_allclose(fitted_r[weighed], np.array(_thermal()[0])[weighed], rtol=0.05)

    # The twin (the fitted device simulated) against the device, flying peg_in_hole.
    device_hover, device_stiffness = _peg(device_text())
    twin_text = "station: !SimStation\n" + "".join(
        f"  {line}\n" for line in overlay.read_text().splitlines())
    twin_hover, twin_stiffness = _peg(twin_text)
    nominal_hover, nominal_stiffness = _peg("{}")
    assert twin_hover == pytest.approx(device_hover, rel=0.01)
    assert twin_stiffness == pytest.approx(device_stiffness, rel=0.01)
    # the nominal twin is several % off
    assert abs(nominal_hover / device_hover - 1) > 0.02
    assert abs(nominal_stiffness / device_stiffness - 1) > 0.02


def _peg(device_overlay):
    """(mean hover current norm before haptics (A), the stiffness the hand feels pressing
    the peg on the hole's floor (N/m)): the slope of the true hand wrench against the
    true depth (a slope: where the floor's contact begins is the registration's)."""
    scenario = load_scenario("peg_in_hole", None, device_overlay)
    log = run_scenario(scenario, label="peg", progress=False, raise_priority=False).log
    scene = scenario.haptics.scene
    hovering = (log["t"] > 1.0) & (log["t"] < scenario.haptics.enable_at_s)
    hover = np.linalg.norm(log["coil_currents"][hovering], axis=1).mean()
    bottom = log["p_WI_true"][:, 2] + scene.tool_offset_m[2] - scene.peg_size_m[2] / 2
    depth = scene.hole_center_m[2] - scene.hole_size_m[2] - bottom
    pressing = (log["tool_in_contact"] > 0.5) & (depth > 2e-4) & (log["haptic_mode"] == HAPTIC)
    felt = -log["hand_wrench_on_instrument_W"][pressing, 2]
    return hover, float(np.polyfit(depth[pressing], felt, 1)[0])


def test_per_coil_thermal_numbers_equal_to_the_scalar_give_the_same_model():
    nominal = DeviceConfig()
    same = dataclasses.replace(nominal, thermal=dataclasses.replace(
        nominal.thermal, thermal_resistances_k_per_w=[2.5] * 27,
        heat_capacities_j_per_k=[float(coil_thermal(nominal).heat_capacity_j_per_k)] * 27))
    temperatures = {}
    for name, device in (("scalar", nominal), ("per coil", same)):
        model = coil_thermal(device)
        t = np.full(27, 40.0)
        step_temperatures_c(t, np.linspace(-3, 3, 27), 0.01, *winding_numbers(model, 27))
        budget = thermal_budget(model, horizon_s=10.0, margin_c=5.0, current_limit_a=4.0)
        temperatures[name] = (t, current_bounds_a(budget, np.linspace(20, 95, 27)))
    for a, b in zip(*temperatures.values()):
        np.testing.assert_array_equal(a, b)


def test_the_thermal_fit_recovers_each_warmed_coils_resistance_and_capacity():
    """Reported temperatures of a device whose coils differ, under currents that warm
    some coils and leave the others cold."""
    nominal = DeviceConfig()
    resistances, capacities = _thermal()
    truth = coil_thermal(dataclasses.replace(nominal, thermal=dataclasses.replace(
        nominal.thermal, thermal_resistances_k_per_w=resistances,
        heat_capacities_j_per_k=capacities)))
    rng = np.random.default_rng(4)
    flights = []
    for k in range(3):
        steps = 2000  # 20 s at 10 ms
        currents = np.zeros((steps, 27))
        currents[:, :20] = np.repeat(rng.uniform(-2.5, 2.5, (20, 20)), 100, axis=0)
        temperature = np.full(27, 25.0 + k)
        reported = [temperature.copy()]
        for current in currents[:-1]:
            step_temperatures_c(temperature, np.ascontiguousarray(current), 0.01,
                                *winding_numbers(truth, 27))
            reported.append(temperature.copy())
        log = {"t": np.arange(steps) * 0.01, "coil_currents": currents,
               "coil_temperature_reported_c": np.array(reported)}
        flights.append(Flight("holds", None, None, log))
    fit = fit_thermal(flights, nominal)
    np.testing.assert_allclose(fit["resistances_k_per_w"][:20], resistances[:20], rtol=1e-3)
    np.testing.assert_allclose(fit["capacities_j_per_k"][:20], capacities[:20], rtol=1e-3)
    assert fit["resistances_k_per_w"][20] == 2.5  # cold: the nominal, and said
    assert fit["not_identified"][0].startswith("device.thermal of coils 20, 21, 22")


def test_over_lcm_a_calibration_flight_reads_the_coil_temperatures_the_device_reports():
    """The application's station on LCM turns the device's status into
    ``coil_temperature_reported_c`` on a calibration flight (the port the fit reads)."""
    scenario = dataclasses.replace(  # an in-memory bus (the schema allows UDP only)
        load_scenario("levitate", None, "{calibration: {flight: holds}}"),
        station=LcmStation(url="memq://", command_url="memq://", channel_prefix="CAL_"))
    station = MakeStation(scenario, magnetics=load_magnetics(scenario.device))
    receiver = station.receiver
    context = receiver.CreateDefaultContext()
    reported = receiver.GetOutputPort("coil_temperature_reported_c")
    assert np.all(np.isnan(reported.Eval(context)))  # nothing reported yet
    temperatures = np.linspace(25.0, 51.0, 27)
    publish(receiver._lcm, "CAL_DEVICE_STATUS", status_message(1, 0.0, False, 0, temperatures))
    context.SetTime(0.002)
    context.SetDiscreteState(receiver.EvalUniquePeriodicDiscreteUpdate(context))
    np.testing.assert_array_equal(reported.Eval(context), temperatures)
