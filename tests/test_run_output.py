"""What ``maglev run`` tells a person at the end: the files it wrote as paths to paste,
numbers rounded for people, hover errors only where a hover happened, and a last
Meshcat line that is true with a terminal and without one."""

import io
import json
from pathlib import Path

import pytest

from maglev_haptics.analysis.run_metrics import for_people
from maglev_haptics.analysis.run_outcome import device_cuts_sentence
from maglev_haptics.cli import _meshcat_last_line, main


def test_for_people_rounds_floats_to_six_significant_digits():
    assert for_people({"a": 6.6000000000000005, "b": [28.999999999999996, 0.000137123456],
                       "c": 3, "d": None, "e": "x", "f": float("inf")}) == {
        "a": 6.6, "b": [29.0, 0.000137123], "c": 3, "d": None, "e": "x", "f": float("inf")}


def test_the_devices_coil_cuts_are_said_in_one_clause():
    cuts = {"times": 2, "first_at_s": 0.01, "longest_ms": 12.0, "command_timeout_s": 0.01}
    assert device_cuts_sentence({"station": {"device_cut_coils": cuts}}) == (
        "the device cut the coils 2 times from 0.010 s, the longest 12 ms (no command "
        "within its 10 ms timeout)")
    assert device_cuts_sentence({"station": {"device_cut_coils": cuts | {"times": 1}}}) \
        .startswith("the device cut the coils once from 0.010 s")
    assert device_cuts_sentence({"station": {"device_cut_coils": cuts | {"times": 0}}}) is None
    assert device_cuts_sentence({}) is None  # a simulated station has none


def test_the_run_prints_each_file_as_a_path_and_rounded_numbers(tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["run", "levitate", "--no-meshcat", "--duration", "0.6", "--out", str(out),
                 "--realtime", "1.0"]) == 0
    printed = capsys.readouterr().out
    wrote = [line for line in printed.splitlines() if line.startswith("wrote ")]
    assert len(wrote) == 1
    paths = [Path(word) for word in wrote[0].removeprefix("wrote ").split()]
    assert [path.name for path in paths] == ["log.npz", "summary.json", "levitation.png",
                                             "realtime.png"]
    assert all(path.is_file() for path in paths), paths
    summary = json.loads(printed[printed.index("{"):printed.rindex("}") + 1])
    assert summary["realtime"]["slot_us"] == 1000.0
    for value in (summary["duration_s"], summary["max_coil_current_a"]):
        assert value == float(f"{value:.6g}")


def test_a_run_whose_instrument_never_flew_reports_no_hover_error(tmp_path):
    """The tracker sees nothing from the start: the instrument stays on the glass
    through the planned hold, so no hover error is reported (it was once 17 mm: the
    rest height against the hold's setpoint)."""
    out = tmp_path / "grounded"
    main(["run", "levitate", "--no-meshcat", "--duration", "2.2", "--out", str(out),
          "--scenario-text", "{occlusions: [{marker: null, start_s: 0.0, end_s: 10.0}]}"])
    summary = json.loads((out / "summary.json").read_text())
    assert summary["holds"] == []
    assert summary["hover_position_error_rms_mm"] is None
    assert summary["hover_angle_error_rms_deg"] is None
    assert summary["hover_busiest_coil_steady_temperature_at_hold_currents_c"] is None


def test_a_flown_hold_still_reports_its_hover_error(tmp_path):
    out = tmp_path / "flown"
    assert main(["run", "levitate", "--no-meshcat", "--duration", "2.2", "--out",
                 str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert len(summary["holds"]) == 1
    assert 0 < summary["hover_position_error_rms_mm"] < 0.1
    # The run ended 0.8 s into the 3 s hold: the hold says where it was last flown.
    hold = summary["holds"][0]
    assert hold["start_s"] == 1.4 and hold["end_s"] == pytest.approx(2.2, abs=0.002)
    assert hold["cut_short"] and summary["faults_latched"] == []


def test_a_run_with_injected_faults_says_which_latched_and_where_it_came_down(tmp_path,
                                                                             capsys):
    """The README's own example: a stuck amplifier latches coil over-current and the
    device lands the instrument; the run says so in one line (exit 0: the fault was
    asked for), the summary lists it, and the hold ends where the landing began."""
    out = tmp_path / "stuck"
    text = ("{faults: [!StuckAmplifier {coil: 13, at_s: 2.0, stuck_at: positive_limit}]}")
    assert main(["run", "levitate", "--no-meshcat", "--out", str(out),
                 "--scenario-text", text]) == 0
    summary = json.loads((out / "summary.json").read_text())
    [latched] = summary["faults_latched"]
    assert latched["fault"] == "coil over-current" and 2.0 < latched["at_s"] < 2.03
    hold = summary["holds"][0]
    # The landing's minimum-jerk start leaves the hold's pose by 1 um within 30 ms.
    assert hold["cut_short"] and latched["at_s"] < hold["end_s"] < latched["at_s"] + 0.05
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert last == (f"levitate:takeoff_hover_land: the injected faults latched coil "
                    f"over-current at {latched['at_s']:.3f} s; touchdown at "
                    f"{summary['touchdown']['time_s']:.3f} s, "
                    f"{summary['touchdown']['speed_m_s']:.3f} m/s")


@pytest.mark.parametrize("waits, replay, line", [
    (True, True, "Meshcat: http://localhost:7000 (the run's recording is replayable there)"),
    (True, False, "Meshcat: http://localhost:7000"),
    (False, True, "Meshcat (http://localhost:7000) closed with the run: no terminal to wait "
     "on (run it from a terminal to replay the recording there)"),
    (False, False, "Meshcat (http://localhost:7000) closed with the run: no terminal to wait "
     "on"),
])
def test_the_last_meshcat_line_says_what_is_true(waits, replay, line):
    assert _meshcat_last_line("http://localhost:7000", waits=waits, replay=replay) == line


class _Terminal(io.StringIO):
    def isatty(self):
        return True


@pytest.mark.parametrize("terminal", [False, True])
def test_the_demos_last_meshcat_line_with_and_without_a_terminal(terminal, tmp_path, capsys,
                                                                 monkeypatch):
    prompts = []
    if terminal:
        monkeypatch.setattr("sys.stdin", _Terminal())
        monkeypatch.setattr("builtins.input", prompts.append)
    assert main(["run", "levitate", "--duration", "0.3", "--out", str(tmp_path / "demo")]) == 0
    last = capsys.readouterr().out.strip().splitlines()[-1]
    if terminal:
        assert last.startswith("Meshcat: http://") and last.endswith("replayable there)")
        assert prompts == ["press Enter to close Meshcat and exit "]
    else:
        assert last.startswith("Meshcat (http://") and "closed with the run" in last


def _synthetic_log(n: int = 2000, temperature_rise_c: float = 0.008):
    """A 2 s flight: rest at 7 mm, hover at 18 mm with 0.02 mm noise, a 0.6 mm error at
    takeoff (the panel once clipped it at +-0.04 mm), coils warming by a few mK."""
    import numpy as np
    t = np.arange(n) * 1e-3
    desired = np.zeros((n, 3))
    desired[:, 2] = np.where((t > 0.5) & (t < 1.5), 0.018, 0.007)
    true = desired + 2e-5 * np.random.default_rng(0).standard_normal((n, 3))
    true[500:520, 2] -= 6e-4
    quaternions = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    return {"t": t, "tracking_ok": np.ones(n), "p_WI_true": true, "q_WI_true": quaternions,
            "V_WI_true": np.zeros((n, 6)), "rpy_WI_true": np.zeros((n, 3)),
            "p_WI_measured": true, "q_WI_measured": quaternions,
            "V_WI_measured": np.zeros((n, 6)), "rpy_WI_measured": np.zeros((n, 3)),
            "p_WI_desired": desired, "rpy_WI_desired": np.zeros((n, 3)),
            "coil_currents": np.full((n, 27), 0.5), "coil_power_w": np.full(n, 40.0),
            "coil_temperature_c": 25.0 + np.linspace(0, temperature_rise_c, n)[:, None]
            * np.ones((1, 27))}


def test_levitation_png_shows_every_error_a_legible_legend_and_plain_temperatures(
        tmp_path, monkeypatch):
    import numpy as np

    from maglev_haptics.analysis import run_plots
    figures = []
    monkeypatch.setattr(run_plots, "save_figure", lambda figure, path, **_: figures.append(
        figure) or path)
    log = _synthetic_log()
    run_plots.plot_run(log, tmp_path, title="synthetic", current_limit_a=4.0)
    position, _, error, _, power = figures[0].axes[:5]
    low, high = error.get_ylim()
    worst_mm = 1e3 * np.max(np.abs(log["p_WI_true"] - log["p_WI_desired"]))
    assert low <= -worst_mm and high >= worst_mm  # the takeoff's 0.6 mm error on the panel
    assert all(line.get_linewidth() >= 2 and (line.get_alpha() or 1) == 1
               for line in position.get_legend().get_lines())  # "measured" legible
    temperature = figures[0].axes[-1]  # the power panel's twin
    figures[0].canvas.draw()
    assert temperature.yaxis.get_offset_text().get_text() == ""  # no "+2.5e1"
    assert temperature.get_ylim()[1] - temperature.get_ylim()[0] >= 1.0
    assert all(24 <= float(label.get_text().replace("\u2212", "-")) <= 26
               for label in temperature.get_yticklabels() if label.get_text())


def test_levitation_png_draws_the_tracking_error_only_while_flying(tmp_path, monkeypatch):
    """Resting on the glass 0.6 mm above the commanded touchdown height is not a
    tracking error: the error panel draws nothing there."""
    import numpy as np

    from maglev_haptics.analysis import run_plots
    figures = []
    monkeypatch.setattr(run_plots, "save_figure", lambda figure, path, **_: figures.append(
        figure) or path)
    log = _synthetic_log()
    resting = log["p_WI_desired"][:, 2] < 0.01
    log["p_WI_true"][resting, 2] = log["p_WI_desired"][resting, 2] + 6e-4
    run_plots.plot_run(log, tmp_path, title="synthetic", current_limit_a=4.0)
    error = figures[0].axes[2]
    for line in error.get_lines():
        drawn = np.isfinite(line.get_ydata())
        assert not np.any(drawn & resting) and np.any(drawn & ~resting)


def test_haptics_png_does_not_stretch_a_quiet_axis_into_a_signal(tmp_path, monkeypatch):
    """A force of a few mN, or a position still to um, fills no panel: each keeps a
    floor on its scale (a force or torque with zero in view)."""
    import numpy as np

    from maglev_haptics.analysis import run_plots
    figures = []
    monkeypatch.setattr(run_plots, "save_figure", lambda figure, path, **_: figures.append(
        figure) or path)
    log = _synthetic_log()
    n = len(log["t"])
    noise = np.random.default_rng(1).standard_normal((n, 3))
    log.update({"haptic_mode": np.full(n, run_plots.HAPTIC), "tool_in_contact": np.zeros(n),
                "f_user": 0.003 * noise, "tau_user": 1e-5 * noise,
                "p_WI_measured": 0.018 + 2e-6 * noise})
    run_plots.plot_haptics(log, tmp_path, title="synthetic")
    axes = figures[0].axes
    spans = [high - low for low, high in (ax.get_ylim() for ax in axes[:7])]
    assert min(spans[:3]) >= run_plots.MIN_POSITION_SPAN_MM
    assert min(spans[3:6]) >= run_plots.MIN_FORCE_SPAN_N
    assert spans[6] >= run_plots.MIN_TORQUE_SPAN_NMM
    assert all(ax.get_ylim()[0] < 0.0 < ax.get_ylim()[1] for ax in axes[3:7])


def test_realtime_png_draws_each_miss_above_the_slot_line(tmp_path, monkeypatch):
    """A tick that computed briefly but started behind a late one misses its slot: it
    is drawn where it ended, above the slot line, not at its short compute."""
    import numpy as np

    from maglev_haptics.analysis import run_plots
    from maglev_haptics.diagrams.runner import TickTimes
    figures = []
    monkeypatch.setattr(run_plots, "save_figure", lambda figure, path, **_: figures.append(
        figure) or path)
    compute_s = np.array([3e-4, 2.5e-3, 3e-4, 3e-4, 3e-4])
    lateness_s = np.array([-7e-4, 1.5e-3, 8e-4, -7e-4, -7e-4])  # tick 2 started late
    run_plots.plot_tick_times(TickTimes(slot_s=1e-3, compute_s=compute_s,
                                        lateness_s=lateness_s), tmp_path, title="t")
    trace = figures[0].axes[0]
    marks = [line for line in trace.get_lines() if line.get_marker() == "o"][0]
    assert list(marks.get_xdata()) == [1, 2]
    assert np.all(np.asarray(marks.get_ydata()) > 1000.0)
