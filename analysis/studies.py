"""``maglev analyze``: each study on a scenario, writing ``<study>.json`` and its plots.

Every study is also a Python function in its module; this one only dispatches,
shows progress and writes the files.
"""

import json
import math
from pathlib import Path
from typing import Callable, Dict, List, Optional

from tqdm import tqdm

from maglev_haptics.analysis import loop_linearization, loop_studies, onset, workspace
from maglev_haptics.analysis.loop_studies import StudyNotApplicable


def _passivity(scenario, label, out_dir, quick, progress, where):
    results = loop_studies.passivity_study(scenario)
    return results, [loop_studies.plot_passivity(results, out_dir, label)]


def _zwidth(scenario, label, out_dir, quick, progress, where):
    settings = (loop_studies.ZWidthSettings.quick() if quick
                else loop_studies.ZWidthSettings.full())
    results = loop_studies.zwidth_study(scenario, settings, progress)
    return results, [loop_studies.plot_zwidth(results, out_dir, label)]


def _stability_map(scenario, label, out_dir, quick, progress, where):
    settings = (loop_studies.StabilityMapSettings.quick() if quick
                else loop_studies.StabilityMapSettings.full())
    results = loop_studies.stability_map_study(scenario, settings, progress, **where)
    if not quick:
        # The whole loop's onset, linearized and simulated (minutes: each step of the
        # searches is a full linearization or a run; each is reported as it ends).
        results["onset"] = onset.onset_study(scenario, **where)
    return results, [loop_studies.plot_stability_map(results, out_dir, label)]


def _linearize(scenario, label, out_dir, quick, progress, where):
    results = loop_linearization.linearize_study(scenario, progress)
    return results, [loop_linearization.plot_multipliers(results, out_dir, label, "linearize")]


def _multirate(scenario, label, out_dir, quick, progress, where):
    results = loop_linearization.multirate_study(scenario, progress)
    return results, [loop_linearization.plot_multipliers(results, out_dir, label, "multirate")]


def _workspace(scenario, label, out_dir, quick, progress, where):
    settings = workspace.WorkspaceSettings.quick() if quick else workspace.WorkspaceSettings()
    results = workspace.workspace_study(settings, device=scenario.device, progress=progress,
                                        **where)
    return results, workspace.plot_workspace(results, out_dir)


STUDIES: Dict[str, Callable] = {
    "workspace": _workspace,
    "linearize": _linearize,
    "multirate": _multirate,
    "passivity": _passivity,
    "zwidth": _zwidth,
    "stability-map": _stability_map,
}


def _json_ready(value):
    """NaN and infinities as null (JSON has neither)."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {key: _json_ready(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_ready(item) for item in value]
    return value


def run_study(study: str, scenario, *, label: str, out_dir: Path, quick: bool = False,
              show_progress: bool = True, workers: int = 1,
              scheduler: Optional[str] = None) -> Dict:
    """Run ``study`` on ``scenario``; write ``<study>.json`` and its plots into
    ``out_dir``. The long ones (stability-map, workspace) run their jobs on ``workers``
    local processes or a Dask ``scheduler``'s workers (``analysis/parallel.py``).
    Raises StudyNotApplicable (a ValueError) saying why it does not apply."""
    if study not in STUDIES:
        raise ValueError(f"study {study!r}: unknown; the studies are {', '.join(STUDIES)}")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    with tqdm(total=1, desc=f"{study} {label}", disable=not show_progress,
              bar_format="{l_bar}{bar}| {n}/{total} [{elapsed}]") as bar:
        def progress(done: int, total: int) -> None:
            bar.total = total
            bar.n = done
            bar.refresh()
        try:
            results, plots = STUDIES[study](scenario, label, out_dir, quick, progress,
                                            {"workers": workers, "scheduler": scheduler})
        except StudyNotApplicable as reason:
            raise StudyNotApplicable(f"{study} does not apply to {label}: {reason}") from None
        bar.n = bar.total  # a study that reports no steps is one step, now done
        bar.refresh()
    results = {"study": study, "scenario": label, "quick": quick, **results,
               "plots": [str(path.name) for path in plots]}
    results = _json_ready(results)
    (out_dir / f"{study.replace('-', '_')}.json").write_text(json.dumps(results, indent=2))
    return results


def format_modes(rows: List[Dict]) -> str:
    """The modes of a linearization as a table: multiplier, frequency, damping, time
    constant, and the states that take part most."""
    lines = [f"{'|multiplier|':>12} {'Hz':>8} {'damping':>8} {'tau (s)':>9}  states"]
    for row in rows:
        tau = row["time_constant_s"]
        tau_text = "inf" if tau is None or tau > 1e6 else f"{tau:.4f}"
        lines.append(f"{row['multiplier_abs']:>12.6f} {row['frequency_hz']:>8.2f} "
                     f"{row['damping_ratio']:>8.3f} {tau_text:>9}  {', '.join(row['states'])}")
    return "\n".join(lines)


def study_names() -> List[str]:
    return list(STUDIES)
