"""Head tracking, prediction and co-location of the stereo display; the display in runs."""

import json

import numpy as np
import pytest
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import ConstantVectorSource, VectorLogSink

from maglev_haptics.analysis.run_results import run_scenario
from maglev_haptics.analysis.stereo_metrics import closest_point_of_rays, colocation_errors
from maglev_haptics.cli import main
from maglev_haptics.diagrams.scenario import ScenarioError, load_scenario
from maglev_haptics.hardware.device import DisplaySpec, GlassesSpec, HeadTrackerSpec
from maglev_haptics.systems.head_predictor import HeadPosePredictor, HeadPredictorConfig
from maglev_haptics.systems.head_sensor import HeadOcclusion, HeadSensor, glasses_pose
from maglev_haptics.systems.marker_sensor import extrapolate_pose
from maglev_haptics.systems.stereo import display_rectangle

SCREEN = display_rectangle(DisplaySpec())
HEAD = np.array([0.02, -0.3, 0.45, 0.0, 0.0, 0.0, 0.1, 0.05])


def run_sensor(tracker, occlusions=(), duration_s=1.0):
    builder = DiagramBuilder()
    head = builder.AddSystem(ConstantVectorSource(HEAD))
    sensor = builder.AddSystem(HeadSensor(tracker=tracker, glasses=GlassesSpec(),
                                          occlusions=occlusions, seed=3))
    builder.Connect(head.get_output_port(), sensor.get_input_port())
    log = builder.AddSystem(VectorLogSink(9, 1e-3))
    builder.Connect(sensor.get_output_port(), log.get_input_port())
    diagram = builder.Build()
    simulator = Simulator(diagram)
    simulator.AdvanceTo(duration_s)
    data = log.FindLog(simulator.get_context())
    return data.sample_times(), data.data().T


@pytest.mark.parametrize("latency_s", [0.0, 0.03, 0.25])
def test_head_sensor_publishes_each_capture_its_latency_later(latency_s):
    tracker = HeadTrackerSpec(latency_s=latency_s)
    times, samples = run_sensor(tracker)
    period_s = 1 / tracker.rate_hz
    for t, sample in zip(times, samples):
        # The newest capture (every 0.1 s) whose latency has passed by t, to the instant;
        # one made at t itself is queued after the log's publish at t.
        newest = np.floor((t - latency_s + 1e-9) / period_s) * period_s
        if newest > t - 1e-9:
            newest -= period_s
        if newest < 0:
            assert sample[8] == 0.0
        else:
            assert sample[0] == pytest.approx(newest, abs=1e-9), t
            assert sample[8] == 1.0


def test_head_sensor_noise_and_occlusion():
    tracker = HeadTrackerSpec(latency_s=0.0)
    _, samples = run_sensor(tracker, occlusions=[HeadOcclusion(0.5, 0.7)], duration_s=3.0)
    q_WG, p_WG = glasses_pose(HEAD)
    captured = {round(s[0], 3): s for s in samples if np.isfinite(s[0])}
    hidden = [s for t, s in captured.items() if 0.5 <= t < 0.7]
    assert len(hidden) == 2 and all(s[8] == 0.0 and np.isnan(s[1]) for s in hidden)
    seen = np.array([s for t, s in captured.items() if not 0.5 <= t < 0.7])
    errors = seen[:, 5:8] - p_WG
    # Four markers at 0.1 mm: the fitted origin, ~8 cm from the markers, errs by a
    # fraction of a millimetre, not more, and not zero.
    assert 2e-5 < np.sqrt(np.mean(errors**2)) < 5e-4
    assert np.abs(np.mean(errors, axis=0)).max() < 2e-4


def predictor_step(predictor, context, t, measurement):
    context.SetTime(t)
    predictor.get_input_port().FixValue(context, measurement)
    context.SetDiscreteState(predictor.EvalUniquePeriodicDiscreteUpdate(context))


def test_predictor_bridges_latency_on_constant_velocity_motion():
    """A head moving at constant 0.3 m/s and 0.5 rad/s: the prediction at the display
    time matches the truth; the hold mode shows the latest sample; a lost head freezes."""
    rate_hz, latency_s, view_s = 10.0, 0.03, 1 / 120
    V = np.array([0.0, 0.0, 0.5, 0.3, 0.1, 0.0])
    q0, p0 = glasses_pose(HEAD)
    x0 = np.concatenate([q0, p0])

    def truth(t):
        return extrapolate_pose(x0, V, t)

    outputs = {}
    for mode in ("kalman", "hold"):
        predictor = HeadPosePredictor(config=HeadPredictorConfig(mode=mode),
                                      tracker_rate_hz=rate_hz, period_s=view_s)
        context = predictor.CreateDefaultContext()
        errors = []
        for k in range(240):
            t = k * view_s
            capture = np.floor((t - latency_s) * rate_hz + 1e-9) / rate_hz
            lost = t > 1.6
            measurement = (np.concatenate([[capture], truth(capture), [1.0]]) if capture >= 0
                           and not lost else np.concatenate([[capture], np.full(7, np.nan),
                                                             [0.0]]))
            predictor_step(predictor, context, t, measurement)
            predicted = predictor.GetOutputPort("X_WG_predicted").Eval(context)
            if 1.0 < t < 1.6:  # after the filter has converged from rest
                errors.append(np.linalg.norm(predicted[4:7] - truth(t + view_s / 2)[4:7]))
        outputs[mode] = (np.array(errors), predictor, context)
    kalman_errors = outputs["kalman"][0]
    assert kalman_errors.max() < 1e-6  # constant velocity is predicted exactly
    hold_errors = outputs["hold"][0]
    # The latest sample is latency + up to a period + half a frame old: 0.3 m/s x that.
    assert 0.3 * (latency_s + view_s / 2) * 0.99 < hold_errors.min()
    assert hold_errors.max() < 0.32 * (latency_s + 1 / rate_hz + view_s)
    _, predictor, context = outputs["kalman"]
    assert predictor.GetOutputPort("head_tracking_ok").Eval(context)[0] == 0.0
    frozen = predictor.GetOutputPort("X_WG_predicted").Eval(context).copy()
    predictor_step(predictor, context, 2.5, np.concatenate([[2.4], np.full(7, np.nan), [0.0]]))
    np.testing.assert_array_equal(predictor.GetOutputPort("X_WG_predicted").Eval(context), frozen)


def test_colocation_error_geometry():
    eye = np.array([[[0.0, -0.3, 0.45], [0.063, -0.3, 0.45]]])
    point = np.array([0.01, 0.02, -0.04])
    zero = colocation_errors(SCREEN, eye, eye, point)
    assert zero["screen_mm"].max() < 1e-9 and zero["perceived_mm"].max() < 1e-9
    shift = 0.02  # drawn for eyes 20 mm to the left of the true ones
    moved = colocation_errors(SCREEN, eye, eye - [shift, 0.0, 0.0], point)
    # Similar triangles: a sideways eye error e moves the spot by e d / (h + d).
    np.testing.assert_allclose(moved["screen_mm"], 1e3 * shift * 0.04 / 0.49, rtol=1e-9)
    a, b = np.array([0.0, 0, 1]), np.array([1.0, 0, 1])
    np.testing.assert_allclose(closest_point_of_rays(a, np.array([0.5, 0, -1]), b, np.array([-0.5, 0, -1])),
                               [0.5, 0, 0])


def test_head_sweep_prediction_halves_the_colocation_error():
    """The acceptance run: head sweeps at 0.3 m/s on average."""
    scenario = load_scenario("stereo_display", "head_sweep",
                             "{stereo: {images: {rate_hz: 0}}}")
    result = run_scenario(scenario, label="head_sweep", progress=False)
    colocation = result.summary["stereo"]["colocation"]
    assert 0.25 < colocation["head_speed_m_s"]["mean_moving"] < 0.4
    predicted = colocation["predicted"]["screen_error_mm"]["mean"]
    held = colocation["held"]["screen_error_mm"]["mean"]
    assert held > 0.5  # the baseline does lag visibly
    assert predicted <= 0.5 * held
    assert result.log["view_ok"][-1] == 1.0


def test_the_rendered_world_shows_the_station_where_its_plant_has_it():
    # The display renders from a SceneGraph of its own (the plant's would update the
    # render engine at every step): each perceived geometry must be where the plant's
    # SceneGraph has it, mid-flight, bit for bit.
    from maglev_haptics.diagrams.application import BuildDiagram
    from pydrake.geometry import Role

    built = BuildDiagram(load_scenario("stereo_display", "head_sweep"))
    simulator = Simulator(built.diagram)
    simulator.AdvanceTo(1.5)  # hovering, the head moving
    station = built.diagram.GetSubsystemByName("station")
    context = station.GetMyContextFromRoot(simulator.get_context())

    def perceived_poses(port_name):
        query = station.GetOutputPort(port_name).Eval(context)
        inspector = query.inspector()
        return {inspector.GetName(g): query.GetPoseInWorld(g).GetAsMatrix34()
                for g in inspector.GetAllGeometryIds(Role.kPerception)}

    rendered, plant = perceived_poses("rendered_world"), perceived_poses("query_object")
    assert rendered and rendered.keys() == plant.keys()
    assert plant["two_magnet_instrument::base"][2, 3] > 0.015  # up, not at rest
    for name, pose in plant.items():
        np.testing.assert_array_equal(rendered[name], pose, err_msg=name)


def test_stereo_run_writes_frames(tmp_path):
    code = main(["run", "levitate", "--no-meshcat", "--stereo", "--duration", "0.5",
                 "--out", str(tmp_path), "--scenario-text",
                 "{stereo: {images: {rate_hz: 10, size_px: [84, 52], encoder: png}}}"])
    assert code == 0
    summary = json.loads((tmp_path / "summary.json").read_text())
    images = summary["stereo"]["images"]
    assert images["rendered_pairs"] == 5  # 10 Hz over 0.5 s, from the first view on
    assert (tmp_path / "stereo_first_anaglyph.png").is_file()
    assert len(list((tmp_path / "stereo_sbs").glob("*.png"))) == summary["stereo"]["video"]["frames"]
    assert (tmp_path / "stereo.png").is_file()


@pytest.mark.parametrize("text, message", [
    ("{device: {display: {size_m: [0.47, 0.0]}}}", r"device.display.size_m = \[0.47, 0.0\]"),
    ("{device: {glasses: {ipd_m: 0.09}}}", r"device.glasses.ipd_m = 0.09: must be within"),
    ("{stereo: {head: {start: {position_m: [0.0, -0.3, -0.1]}}}}",
     r"stereo.head.start.position_m = \[0.0, -0.3, -0.1\]: the left eye would be -1\d\d.\d mm"),
    ("{stereo: {head: {waypoints: [{position_m: [0.0, 0.0, 0.3], look_at_m: [0.0, 0.0, 0.3]}]}}}",
     r"stereo.head.waypoints\[0\]: head at .* the line of sight must have length"),
    ("{stereo: {head: {waypoints: [{look_at_m: [0.0, 1e300, 0.0]}]}}}",
     r"stereo.head.waypoints\[0\].look_at_m = \[0.0, 1e\+300, 0.0\]: must be within 5 m"),
    ("{stereo: {predictor: {bandwidth_hz: 6.0}}}", r"bandwidth_hz = 6.0: must be below"),
    ("{stereo: {images: {encoder: gif}}}", r"stereo.images.encoder = 'gif'"),
    ("{stereo: {view_rate: 60}}", r"stereo.view_rate: unknown field; StereoConfig has"),
])
def test_bad_stereo_input_is_named(text, message):
    with pytest.raises(ScenarioError, match=message):
        load_scenario("stereo_display", "head_sweep", text)
