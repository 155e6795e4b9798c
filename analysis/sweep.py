"""``maglev sweep SPEC.yaml``: a scenario run over a grid of its own fields.

The spec names a scenario, the fields to vary (their YAML paths in the scenario,
dotted) with a list of values or a range, and the metrics to keep from each run's
``summary.json`` (dotted paths too)::

    scenario: levitate                 # a shipped scenario or a YAML file
    name: takeoff_hover_land           # optional: the file's first
    scenario_text: "{duration_s: 4.0}" # optional: layered on it first
    vary:
      estimator.bandwidth_hz: [20, 50, 100]
      device.tracker.latency_s: {start: 0.001, stop: 0.004, num: 4}   # evenly spaced
    metrics: [hover_position_error_rms_mm, max_coil_temperature_c, touchdown.speed_m_s]

Every combination of the varied values is a job: the scenario's text, the point's
values as one more YAML layer, and the scenario's own random seed, so a point gives
the same numbers wherever it runs (``analysis/parallel.py``). Written: ``sweep.csv``
(a row a point: the varied fields, the metrics, then the point's error: what its run
raised, or the line ``maglev run`` ends with when the instrument was lost),
``sweep.json`` (the spec, the rows, what ran them) and ``sweep.png`` (each metric
against each varied field, a failed point marked with a red cross). A metric that no
point's summary has is named after the runs (a ScenarioError).
"""

import csv
import itertools
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, List, Optional

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import yaml  # noqa: E402

from maglev_haptics.analysis.parallel import map_jobs  # noqa: E402
from maglev_haptics.analysis.run_plots import save_figure  # noqa: E402
from maglev_haptics.diagrams.scenario import ScenarioError, load_scenario  # noqa: E402

MAX_POINTS = 10_000  # a grid larger than this is surely a mistake in the spec


@dataclass
class SweepSpec:
    scenario: str
    vary: Dict[str, List[Any]]  # dotted field path -> its values
    metrics: List[str]
    name: Optional[str] = None
    scenario_text: str = "{}"
    source: str = "sweep spec"  # where it came from, for error messages

    def points(self) -> List[Dict[str, Any]]:
        """Every combination of the varied values, the first field slowest."""
        fields = list(self.vary)
        return [dict(zip(fields, values))
                for values in itertools.product(*(self.vary[f] for f in fields))]


def _values(source: str, path: str, spec) -> List[Any]:
    """A list as it is, or {start, stop, num} as num evenly spaced floats."""
    if isinstance(spec, list) and spec:
        return spec
    if isinstance(spec, dict) and set(spec) == {"start", "stop", "num"}:
        start, stop, num = spec["start"], spec["stop"], spec["num"]
        if (all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
                for v in (start, stop)) and isinstance(num, int) and num >= 1):
            return [float(v) for v in np.linspace(start, stop, num)]
    raise ScenarioError(f"{source}: vary.{path} = {spec!r}: must be a non-empty list of "
                        "values or {start: NUMBER, stop: NUMBER, num: WHOLE NUMBER >= 1}")


def parse_spec(text: str, source: str = "sweep spec") -> SweepSpec:
    """The spec in ``text``; a ScenarioError names the field, its value and what is
    allowed. The scenario and each point's overrides are loaded once here, so a bad
    field fails before any run."""
    try:
        top = yaml.compose(text)
    except yaml.YAMLError as error:
        raise ScenarioError(f"{source}: not YAML: {str(error).splitlines()[0]}") from None
    keys = ([key.value for key, _ in top.value] if isinstance(top, yaml.MappingNode) else [])
    if keys and not {"scenario", "vary"} & set(keys):
        # A scenario file, most likely: its tags would otherwise be the complaint.
        raise ScenarioError(f"{source}: not a sweep spec: it has " + ", ".join(keys[:5])
                            + ("..." if len(keys) > 5 else "") + "; a sweep spec has "
                            "scenario, vary and metrics (see maglev sweep --help)")
    try:
        raw = yaml.safe_load(text)
    except yaml.YAMLError as error:
        raise ScenarioError(f"{source}: not YAML: {str(error).splitlines()[0]}") from None
    if not isinstance(raw, dict):
        raise ScenarioError(f"{source}: must be a mapping with scenario, vary and metrics")
    allowed = {"scenario", "name", "scenario_text", "vary", "metrics"}
    unknown = sorted(set(raw) - allowed)
    if unknown:
        raise ScenarioError(f"{source}: {unknown[0]}: unknown field; a sweep spec has "
                            + ", ".join(sorted(allowed)))
    for key in ("scenario", "vary", "metrics"):
        if key not in raw:
            raise ScenarioError(f"{source}: {key}: missing")
    if not isinstance(raw["scenario"], str):
        raise ScenarioError(f"{source}: scenario = {raw['scenario']!r}: must be a scenario "
                            "name or a YAML file")
    vary = raw["vary"]
    if not isinstance(vary, dict) or not vary:
        raise ScenarioError(f"{source}: vary = {vary!r}: must map field paths to values")
    metrics = raw["metrics"]
    if (not isinstance(metrics, list) or not metrics
            or not all(isinstance(m, str) and m for m in metrics)):
        raise ScenarioError(f"{source}: metrics = {metrics!r}: must be a non-empty list of "
                            "summary.json paths (dotted)")
    scenario_text = raw.get("scenario_text", "{}")
    if not isinstance(scenario_text, str):
        raise ScenarioError(f"{source}: scenario_text = {scenario_text!r}: must be a string "
                            "of YAML (quote it)")
    spec = SweepSpec(scenario=raw["scenario"], name=raw.get("name"),
                     scenario_text=scenario_text,
                     vary={path: _values(source, path, values) for path, values in vary.items()},
                     metrics=metrics, source=source)
    count = math.prod(len(values) for values in spec.vary.values())
    if count > MAX_POINTS:
        raise ScenarioError(f"{source}: vary: {count} points: at most {MAX_POINTS}")
    for point in spec.points():
        try:
            load_scenario(spec.scenario, spec.name, spec.scenario_text, point_text(point))
        except ScenarioError as error:
            raise ScenarioError(f"{source}: the point {point_text(point)}: {error}") from None
    return spec


def point_text(point: Dict[str, Any]) -> str:
    """The point's values as a YAML layer: {a: {b: value}} for the path a.b."""
    nested: Dict[str, Any] = {}
    for path, value in point.items():
        here = nested
        *parents, leaf = path.split(".")
        for key in parents:
            here = here.setdefault(key, {})
        here[leaf] = value
    return yaml.safe_dump(nested, default_flow_style=True, width=10_000).strip()


@dataclass
class SweepJob:
    """One point of a sweep, all a worker needs to run it."""
    scenario: str
    name: Optional[str]
    scenario_text: str
    point: Dict[str, Any]
    metrics: tuple


def metric(summary: Dict, path: str):
    """The value at a dotted path of a run's summary; None where it has none (a run
    that never touched down has no touchdown.speed_m_s)."""
    value: Any = summary
    for key in path.split("."):
        if not isinstance(value, dict) or key not in value:
            return None
        value = value[key]
    return value


@dataclass
class PointResult:
    row: Dict[str, Any]  # the varied values, the metrics kept and the error (None: none)
    summary_keys: List[str]  # the top-level keys of its summary.json (none: it raised)


def run_point(job: SweepJob) -> PointResult:
    """One point: its scenario run, the metrics kept. Its error: what the run raised,
    or the line ``maglev run`` ends with when the instrument was lost or a fault
    latched in a run that injected none (``analysis/run_outcome.py``)."""
    from maglev_haptics.analysis.run_outcome import instrument_outcome
    from maglev_haptics.analysis.run_results import run_scenario
    row: Dict[str, Any] = dict(job.point)
    try:
        scenario = load_scenario(job.scenario, job.name, job.scenario_text,
                                 point_text(job.point))
        result = run_scenario(scenario, label="sweep point", progress=False)
        row |= {name: metric(result.summary, name) for name in job.metrics}
        row["error"] = instrument_outcome(scenario, result.summary, result.log, "its run")
        return PointResult(row, sorted(result.summary))
    except Exception as error:  # recorded in its row: the rest of the sweep goes on
        row |= {name: None for name in job.metrics}
        row["error"] = f"{type(error).__name__}: {error}"
        return PointResult(row, [])


def unknown_metrics(metrics: List[str], results: List[PointResult]) -> List[str]:
    """The metrics whose first key no point's summary.json has (a misspelling: a metric
    that only some runs have, such as touchdown.speed_m_s, is known)."""
    keys = {key for result in results for key in result.summary_keys}
    if not keys:  # no run got as far as a summary: their errors say why
        return []
    return [name for name in metrics if name.split(".")[0] not in keys]


def run_sweep(spec: SweepSpec, out_dir: Path, *, workers: int = 1,
              scheduler: Optional[str] = None, progress: bool = True) -> Dict:
    """Run every point; write sweep.csv, sweep.json and sweep.png into ``out_dir``."""
    jobs = [SweepJob(spec.scenario, spec.name, spec.scenario_text, point, tuple(spec.metrics))
            for point in spec.points()]
    ran = map_jobs(run_point, jobs, workers=workers, scheduler=scheduler,
                   description="sweep", progress=progress)
    rows = [result.row for result in ran.results]
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    columns = [*spec.vary, *spec.metrics, "error"]
    with open(out_dir / "sweep.csv", "w", newline="") as file:
        writer = csv.DictWriter(file, fieldnames=columns)
        writer.writeheader()
        writer.writerows(rows)
    jobs_ran = {"where": ran.where, "workers": ran.workers, "reran": ran.reran}
    (out_dir / "sweep.json").write_text(json.dumps(
        {"spec": {"scenario": spec.scenario, "name": spec.name,
                  "scenario_text": spec.scenario_text, "vary": spec.vary,
                  "metrics": spec.metrics},
         "rows": rows, "jobs": jobs_ran}, indent=1))
    plot = plot_sweep(spec, rows, out_dir / "sweep.png")
    unknown = unknown_metrics(spec.metrics, ran.results)
    if unknown:  # said after the files are written: the runs are not lost
        keys = sorted({key for result in ran.results for key in result.summary_keys})
        raise ScenarioError(f"{spec.source}: metrics: {unknown[0]}: no point's summary.json "
                            f"has it (wrote {out_dir}); a summary has " + ", ".join(keys))
    return {"rows": rows, "jobs": jobs_ran, "files": [out_dir / "sweep.csv",
                                                      out_dir / "sweep.json", plot]}


def _cell(value) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value)


def format_table(spec: SweepSpec, rows: List[Dict]) -> str:
    """The sweep as the terminal shows it: a row a point, the varied fields then the
    metrics (4 significant digits; "-": no value), a failed point's error last."""
    columns = [*spec.vary, *spec.metrics]
    cells = [[_cell(row[column]) for column in columns]
             + ([f"error: {row['error']}"] if row.get("error") else []) for row in rows]
    widths = [max([len(column)] + [len(line[i]) for line in cells])
              for i, column in enumerate(columns)]
    lines = ["  ".join(column.rjust(width) for column, width in zip(columns, widths))]
    lines += ["  ".join(cell.rjust(width) for cell, width in zip(line, widths))
              + ("  " + line[-1] if len(line) > len(columns) else "") for line in cells]
    return "\n".join(lines)


# A metric whose positive values span more than this ratio is plotted on a log axis (one
# diverged point would flatten the others on a linear one).
LOG_AXIS_RATIO = 20.0


def plot_sweep(spec: SweepSpec, rows: List[Dict], path: Path) -> Path:
    """A panel for each (metric, varied field): the metric at every point against the
    field's value, the points that share the other fields' values joined; a log axis
    where a metric's values span more than LOG_AXIS_RATIO."""
    fields, metrics = list(spec.vary), spec.metrics
    figure, panels = plt.subplots(len(metrics), len(fields), squeeze=False,
                                  figsize=(4.0 * len(fields), 2.8 * len(metrics)))
    for j, varied in enumerate(fields):
        others = [f for f in fields if f != varied]
        groups: Dict[tuple, List[Dict]] = {}
        for row in rows:
            groups.setdefault(tuple(repr(row[f]) for f in others), []).append(row)
        for i, name in enumerate(metrics):
            panel = panels[i][j]
            if not any(isinstance(row[name], (int, float)) for row in rows):
                panel.text(0.5, 0.5, "no value at any point", ha="center", va="center",
                           transform=panel.transAxes, color="0.4")
            for key, group in groups.items():
                # A failed point stands alone, crossed out: joined, it reads as a trend.
                points = [(row[varied], row[name]) for row in group
                          if not row.get("error") and isinstance(row[name], (int, float))]
                if points:
                    x, y = zip(*points)
                    label = ", ".join(f"{f}={v}" for f, v in zip(others, key)) or None
                    panel.plot(x, y, "o-", ms=4, label=label)
            failed = [(row[varied], row[name]) for row in rows
                      if row.get("error") and isinstance(row[name], (int, float))]
            if failed:  # its run raised or lost the instrument: the table says how
                panel.plot(*zip(*failed), "x", color="red", ms=9, mew=2,
                           label="failed (see its error)" if i == 0 else None)
            values = [row[name] for row in rows if isinstance(row[name], (int, float))
                      and math.isfinite(row[name])]
            log_axis = bool(values) and min(values) > 0 and max(values) > LOG_AXIS_RATIO * min(
                values)
            if log_axis:
                panel.set_yscale("log")
            panel.set_xlabel(varied)
            panel.set_ylabel(name + (" (log)" if log_axis else ""))
            if i == 0 and (len(groups) <= 8 or failed) and panel.get_legend_handles_labels()[1]:
                panel.legend(fontsize=6)
    figure.suptitle(f"sweep of {spec.scenario}" + (f":{spec.name}" if spec.name else ""))
    return save_figure(figure, path)
