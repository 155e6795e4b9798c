"""A scenario's run read into its results: ``log.npz``, ``summary.json`` and plots.

``run_scenario`` flies it (``diagrams/scenario_run.py``), moves its log to disk as it
goes, and reads the log into the summary and the plots; the sweeps, the fault
campaign and ``maglev run`` call it."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, Optional

import numpy as np

from maglev_haptics.analysis.haptic_metrics import haptic_summary
from maglev_haptics.analysis.run_log import RunLogWriter
from maglev_haptics.analysis.run_metrics import for_people, log_arrays, summarize
from maglev_haptics.analysis.run_outcome import latched_faults
from maglev_haptics.analysis.run_plots import plot_haptics, plot_run, plot_tick_times
from maglev_haptics.analysis.stereo_metrics import plot_colocation, stereo_summary
from maglev_haptics.analysis.stereo_video import StereoVideoWriter
from maglev_haptics.analysis.timing import deformable_step_reports
from maglev_haptics.diagrams.meshcat_lifetime import start_meshcat
from maglev_haptics.diagrams.runner import realtime_report
from maglev_haptics.diagrams.scenario import Scenario, scenario_yaml
from maglev_haptics.diagrams.scenario_run import fly_scenario
from maglev_haptics.hardware.thermal import coil_thermal

SCENARIO_FILE = "scenario.yaml"  # the scenario as it ran, every field (a run folder's)


@dataclass
class RunResult:
    summary: Dict  # what summary.json holds
    log: Dict[str, np.ndarray]  # what log.npz holds
    meshcat: Optional[object]  # the Meshcat, open for the viewer: close_meshcat it when done


def run_scenario(scenario: Scenario, *, label: str, out_dir: Optional[Path] = None,
                 meshcat: bool = False, realtime_rate: float = 0.0,
                 duration_s: Optional[float] = None, progress: bool = True,
                 raise_priority: bool = True) -> RunResult:
    """Fly ``scenario`` (``diagrams/scenario_run.py``: paced at ``realtime_rate``, or at
    1.0 against a device, which keeps the wall clock); write ``log.npz`` as it goes,
    then ``summary.json`` and plots, to ``out_dir``. ``raise_priority``: a paced loop
    runs at real-time priority where the OS grants it."""
    viewer = start_meshcat() if meshcat else None
    video = None
    if scenario.stereo is not None and out_dir is not None and scenario.stereo.images.rate_hz > 0:
        video = StereoVideoWriter(Path(out_dir), frame_rate_hz=scenario.stereo.images.rate_hz,
                                  encoder=scenario.stereo.images.encoder)
    thermal = coil_thermal(scenario.device)
    if out_dir is not None:  # an earlier run's, which a run that fails would leave as its own
        (Path(out_dir) / "summary.json").unlink(missing_ok=True)
        (Path(out_dir) / SCENARIO_FILE).unlink(missing_ok=True)
    log_writer = None

    def start_log(built):
        """The log goes to disk as the run goes: a run that is killed leaves it readable."""
        nonlocal log_writer
        if out_dir is None:
            return None
        log_writer = RunLogWriter(Path(out_dir), built.logger, built.log_layout, thermal)
        return log_writer.drain

    try:
        flown = fly_scenario(scenario, label=label, duration_s=duration_s, viewer=viewer,
                             realtime_rate=realtime_rate, progress=progress,
                             raise_priority=raise_priority,
                             frame_sink=video.add if video is not None else None,
                             on_built=start_log)
    except BaseException:
        if log_writer is not None:
            log_writer.abandon()
        raise
    finally:
        video_summary = video.close() if video is not None else None
    built, simulator = flown.built, flown.simulator
    stop_signal, landing = flown.stop_signal, flown.landing
    duration_s = simulator.get_context().get_time()
    log = (log_writer.finish(simulator.get_context()) if log_writer is not None else
           log_arrays(built.logger, built.log_layout, simulator.get_context(), scenario.device))
    spec = scenario.device.instrument_spec()
    summary = {
        "scenario": label,
        "instrument": spec.kind,
        "duration_s": float(duration_s),
        "wall_time_s": flown.wall_s,
        "realtime_factor": float(duration_s / flown.wall_s),
        "control_rate_hz": scenario.control_rate_hz,
        **summarize(log, built.plan, rest_height_m=spec.rest_height_m,
                    thermal=thermal,
                    holds_before_s=(scenario.haptics.enable_at_s
                                    if scenario.haptics is not None else None)),
        **haptic_summary(log, scenario, rest_height_m=spec.rest_height_m),
        "faults_latched": [{"fault": name, "at_s": at_s} for at_s, name in latched_faults(log)],
    }
    if stop_signal.received is not None:
        summary["stopped_by"] = stop_signal.received
        summary["signals_received"] = stop_signal.count
    if stop_signal.received is not None or landing.landing_end_s is not None:
        # What the log shows, not what was asked: a second signal ends a landing midway.
        summary["landed_before_stopping"] = (landing.landing_end_s is not None
                                             and summary["final_state"]["rests"])
    if flown.tick_times is not None:
        summary["realtime"] = {"rate": flown.realtime_rate,
                               **realtime_report(flown.tick_times)}
    deformable = deformable_step_reports(built.diagram)
    if deformable:
        summary["deformable_steps"] = deformable
    station_summary = built.station.summary(simulator.get_context())
    if station_summary is not None:
        summary["station"] = station_summary
    if scenario.stereo is not None:
        summary["stereo"] = stereo_summary(log, scenario, built.stereo, video_summary)
    if built.haptics is not None:
        config = built.haptics.coupling_config
        summary["coupling_limits"] = {"max_force_n": config.max_force_n,
                                      "max_torque_nm": config.max_torque_nm,
                                      "device_limit": config.device_limit}
    summary = for_people(summary)  # 6.6 s, not 6.6000000000000005
    if out_dir is not None:
        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        (out_dir / "summary.json").write_text(json.dumps(summary, indent=2))
        (out_dir / SCENARIO_FILE).write_text(scenario_yaml(scenario))
        plot_run(log, out_dir, title=label,
                 current_limit_a=scenario.device.amplifier.current_limit_a)
        if scenario.haptics is not None:
            plot_haptics(log, out_dir, title=label)
        if flown.tick_times is not None:
            plot_tick_times(flown.tick_times, out_dir, title=label)
        if "head_pose" in log:  # the true head: a simulated station's
            plot_colocation(log, scenario, out_dir, title=label)
    return RunResult(summary=summary, log=log, meshcat=viewer)
