"""maglev sweep: a spec's grid of points, each a run of the scenario with its values,
the metrics kept as a table, a JSON and plots; a bad spec named before any run."""

import csv
import json
from pathlib import Path

import pytest

from maglev_haptics.analysis.sweep import parse_spec, point_text
from maglev_haptics.cli import main
from maglev_haptics.diagrams.scenario import ScenarioError, load_scenario

SPEC = """
scenario: levitate
name: takeoff_hover_land
scenario_text: "{duration_s: 2.5}"
vary:
  estimator.bandwidth_hz: [50, 100]
  device.tracker.latency_s: {start: 0.001, stop: 0.003, num: 2}
metrics: [max_coil_current_a, hover_position_error_rms_mm, touchdown.speed_m_s]
"""


def test_the_grid_is_every_combination_and_each_point_a_layer_of_the_scenario():
    spec = parse_spec(SPEC)
    points = spec.points()
    assert points == [{"estimator.bandwidth_hz": b, "device.tracker.latency_s": d}
                      for b in (50, 100) for d in (0.001, 0.003)]
    scenario = load_scenario("levitate", None, spec.scenario_text, point_text(points[3]))
    assert scenario.estimator.bandwidth_hz == 100 and scenario.device.tracker.latency_s == 0.003
    assert scenario.duration_s == 2.5


def test_a_sweep_writes_its_table_json_and_plot(tmp_path, capsys):
    spec_file = tmp_path / "spec.yaml"
    spec_file.write_text(SPEC)
    out = tmp_path / "out"
    assert main(["sweep", str(spec_file), "--workers", "1", "--out", str(out)]) == 0
    with open(out / "sweep.csv") as file:
        rows = list(csv.DictReader(file))
    assert len(rows) == 4
    assert list(rows[0]) == ["estimator.bandwidth_hz", "device.tracker.latency_s",
                             "max_coil_current_a", "hover_position_error_rms_mm",
                             "touchdown.speed_m_s", "error"]
    saved = json.loads((out / "sweep.json").read_text())
    assert [row["error"] for row in saved["rows"]] == [None] * 4
    hover = [row["hover_position_error_rms_mm"] for row in saved["rows"]]
    assert all(0.0 < value < 1.0 for value in hover)
    # The estimator's bandwidth and the tracker's latency change the hover: real runs.
    assert len(set(hover)) == 4
    assert all(row["touchdown.speed_m_s"] is None for row in saved["rows"])  # still flying
    assert saved["jobs"]["where"] == "this process"
    assert (out / "sweep.png").stat().st_size > 20_000
    assert "4 points on this process" in capsys.readouterr().out


@pytest.mark.parametrize("text, message", [
    ("scenario: levitate\nvary: {estimator.bandwith_hz: [1]}\nmetrics: [a]",
     "estimator.bandwith_hz: unknown field; PoseEstimatorConfig has bandwidth_hz"),
    ("scenario: levitate\nvary: {estimator.bandwidth_hz: {start: 1}}\nmetrics: [a]",
     "vary.estimator.bandwidth_hz = {'start': 1}: must be a non-empty list of values or"),
    ("scenario: levitate\nvary: {estimator.bandwidth_hz: [1000]}\nmetrics: [a]",
     "estimator.bandwidth_hz = 1000.0: must be in (0, 430.0) Hz"),
    ("scenario: levitate\nvary: {duration_s: [1]}\nmetrics: []", "metrics = []: must be"),
    ("scenario: levitate\nvary: {duration_s: [1]}\nmetric: [a]", "metric: unknown field"),
])
def test_a_bad_spec_names_its_field_before_any_run(text, message):
    with pytest.raises(ScenarioError, match="^spec.yaml: .*" + message.replace(
            "(", r"\(").replace(")", r"\)").replace("[", r"\[").replace("{", r"\{")):
        parse_spec(text, "spec.yaml")


def _spec():
    return parse_spec("scenario: levitate\nvary: {estimator.bandwidth_hz: [20, 50, 100]}\n"
                      "metrics: [hover_position_error_rms_mm, touchdown.speed_m_s]")


ROWS = [{"estimator.bandwidth_hz": 20, "hover_position_error_rms_mm": 17.123456,
         "touchdown.speed_m_s": None, "error": None},
        {"estimator.bandwidth_hz": 50, "hover_position_error_rms_mm": 0.0123456,
         "touchdown.speed_m_s": 0.0051, "error": None},
        {"estimator.bandwidth_hz": 100, "hover_position_error_rms_mm": None,
         "touchdown.speed_m_s": None, "error": "RuntimeError: boom"}]


def test_the_terminal_gets_the_sweep_as_a_table():
    from maglev_haptics.analysis.sweep import format_table
    assert format_table(_spec(), ROWS).splitlines() == [
        "estimator.bandwidth_hz  hover_position_error_rms_mm  touchdown.speed_m_s",
        "                    20                        17.12                    -",
        "                    50                      0.01235               0.0051",
        "                   100                            -                    -"
        "  error: RuntimeError: boom"]


def test_a_diverged_point_puts_its_metric_on_a_log_axis(tmp_path, monkeypatch):
    from maglev_haptics.analysis import sweep
    figures = []
    monkeypatch.setattr(sweep, "save_figure", lambda figure, path: figures.append(figure) or path)
    sweep.plot_sweep(_spec(), ROWS, tmp_path / "sweep.png")
    hover, touchdown = (figures[0].axes[0], figures[0].axes[1])
    assert hover.get_yscale() == "log" and hover.get_ylabel().endswith("(log)")
    assert touchdown.get_yscale() == "linear"


def test_a_failed_point_with_values_is_marked_in_the_plot(tmp_path, monkeypatch):
    from maglev_haptics.analysis import sweep
    figures = []
    monkeypatch.setattr(sweep, "save_figure", lambda figure, path: figures.append(figure) or path)
    rows = [dict(row) for row in ROWS]
    rows[0]["error"] = "its run: the instrument was lost at 1.391 s (sensor out of range)"
    sweep.plot_sweep(_spec(), rows, tmp_path / "sweep.png")
    crosses = [line for line in figures[0].axes[0].get_lines() if line.get_marker() == "x"]
    assert len(crosses) == 1 and list(crosses[0].get_xdata()) == [20]
    assert list(crosses[0].get_ydata()) == [17.123456]
    curves = [line for line in figures[0].axes[0].get_lines() if line.get_marker() == "o"]
    assert curves and all(20 not in list(line.get_xdata()) for line in curves)  # not joined


def _sweep(tmp_path, duration_s: float, vary: str, metrics: str):
    """(exit code, spec file, out folder) of ``maglev sweep`` over levitate."""
    spec_file = tmp_path / "spec.yaml"
    spec_file.write_text(f"scenario: levitate\nscenario_text: \"{{duration_s: {duration_s}}}\"\n"
                         f"vary: {vary}\nmetrics: {metrics}\n")
    out = tmp_path / "out"
    return main(["sweep", str(spec_file), "--workers", "1", "--out", str(out)]), spec_file, out


def test_a_point_that_loses_the_instrument_is_a_failed_point(tmp_path, capsys):
    # The estimator's 25 Hz behind a 3 ms tracker: the loop has no phase margin left.
    code, _, out = _sweep(tmp_path, 2.0, "{estimator.bandwidth_hz: [25], "
                          "device.tracker.latency_s: [0.003]}", "[max_coil_current_a]")
    assert code == 1
    row = json.loads((out / "sweep.json").read_text())["rows"][0]
    assert row["error"].startswith("its run: the instrument was lost at ")
    assert row["max_coil_current_a"] > 0.0  # what the run measured is kept
    assert "error: its run: the instrument was lost" in capsys.readouterr().out


def test_a_metric_no_summary_has_is_named_after_the_runs(tmp_path, capsys):
    code, spec_file, out = _sweep(tmp_path, 0.3, "{estimator.bandwidth_hz: [50]}",
                                  "[max_coil_current_a, hover_pos_err]")
    assert code == 2
    error = capsys.readouterr().err
    assert (f"{spec_file}: metrics: hover_pos_err: no point's summary.json has it (wrote {out}); "
            "a summary has ") in error
    assert "hover_position_error_rms_mm" in error
    assert (out / "sweep.json").exists()


@pytest.mark.slow  # nine 4 s flights
def test_the_shipped_example_sweep_holds_at_every_point(tmp_path, capsys):
    """The README's example runs as shown: exit 0, every point's hover held."""
    example = Path(__file__).resolve().parent.parent / "docs" / "sweep_example.yaml"
    assert main(["sweep", str(example), "--workers", "2", "--out", str(tmp_path)]) == 0
    rows = json.loads((tmp_path / "sweep.json").read_text())["rows"]
    assert len(rows) == 9 and not any(row["error"] for row in rows)
    assert all(row["hover_position_error_rms_mm"] < 0.05 for row in rows)
