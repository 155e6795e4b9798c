"""Run a scenario and write its results: ``log.npz``, ``summary.json`` and plots."""

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
from maglev_haptics.diagrams.application import BuildDiagram, RunMode
from maglev_haptics.diagrams.meshcat_lifetime import start_meshcat
from maglev_haptics.diagrams.motion import longest_landing_s
from maglev_haptics.diagrams.runner import (
    PROGRESS_CHUNK_S, LandBeforeStopping, StopOnSignal, realtime_report, simulate)
from maglev_haptics.diagrams.scenario import Scenario
from maglev_haptics.diagrams.station import station_kind
from maglev_haptics.hardware.thermal import coil_thermal
from maglev_haptics.systems.device_visualizer import aim_camera_at_device
from maglev_haptics.systems.meshcat_hand import wait_for_browser


@dataclass
class RunResult:
    summary: Dict  # what summary.json holds
    log: Dict[str, np.ndarray]  # what log.npz holds
    meshcat: Optional[object]  # the Meshcat, open for the viewer: close_meshcat it when done


def run_scenario(scenario: Scenario, *, label: str, out_dir: Optional[Path] = None,
                 meshcat: bool = False, realtime_rate: float = 0.0,
                 duration_s: Optional[float] = None, progress: bool = True,
                 raise_priority: bool = True) -> RunResult:
    """Simulate ``scenario``; write ``log.npz``, ``summary.json`` and plots to ``out_dir``.

    With a station on LCM the run is paced (at 1.0 unless told): the device keeps
    the wall clock's time, so the application must too. ``raise_priority``: a paced
    loop runs at real-time priority where the OS grants it."""
    if station_kind(scenario).keeps_wall_clock and realtime_rate <= 0:
        realtime_rate = 1.0
    viewer = start_meshcat() if meshcat else None
    video = None
    if scenario.stereo is not None and out_dir is not None and scenario.stereo.images.rate_hz > 0:
        video = StereoVideoWriter(Path(out_dir), frame_rate_hz=scenario.stereo.images.rate_hz,
                                  encoder=scenario.stereo.images.encoder)
    built = BuildDiagram(scenario, meshcat=viewer, label=label,
                         frame_sink=video.add if video is not None else None,
                         mode=RunMode.PACED if realtime_rate > 0 else RunMode.SIMULATE)
    if duration_s is None:
        duration_s = scenario.duration_s if scenario.duration_s is not None else built.plan.end_s
    # A real instrument is not let fall where the run's time ends: it lands first (the
    # simulated one's run may end anywhere). The stop is asked every PROGRESS_CHUNK_S.
    lands_at_end = built.station.lands_before_run_end
    horizon_s = duration_s + (longest_landing_s(scenario.motion) + PROGRESS_CHUNK_S
                              if lands_at_end else 0.0)
    # An interactive run is watched live; a recording would only grow.
    record = viewer is not None and built.meshcat_hand is None
    if record:
        viewer.StartRecording()
    thermal = coil_thermal(scenario.device)
    if out_dir is not None:  # an earlier run's, which a run that fails would leave as its own
        (Path(out_dir) / "summary.json").unlink(missing_ok=True)
    # The log goes to disk as the run goes: a run that is killed leaves it readable.
    log_writer = (RunLogWriter(Path(out_dir), built.logger, built.log_layout, thermal)
                  if out_dir is not None else None)
    try:
        if built.meshcat_hand is not None:
            wait_for_browser(viewer)
        # Ctrl-C or SIGTERM lands a flying instrument, ends the run between ticks,
        # and what it ran is written (a second one ends it at once).
        with StopOnSignal() as stop_signal:
            stop = LandBeforeStopping(built.app.supervisor, stop_signal,
                                      land_from_s=duration_s if lands_at_end else None,
                                      haptics=built.haptics)
            # What the station stops a run for (a device gone silent) stops it at once:
            # no landing without one.
            simulator, wall_s, tick_times = simulate(
                built, horizon_s, realtime_rate=realtime_rate, progress=progress, label=label,
                stop=built.station.watch(stop), shares_cores=built.station.shares_cores,
                on_progress=log_writer.drain if log_writer is not None else None,
                raise_priority=raise_priority, progress_total_s=duration_s)
    except BaseException:
        if log_writer is not None:
            log_writer.abandon()
        raise
    finally:
        if built.meshcat_hand is not None:
            built.meshcat_hand.Delete()
        video_summary = video.close() if video is not None else None
    if record:
        viewer.StopRecording()
        viewer.PublishRecording()
        aim_camera_at_device(viewer, close=scenario.haptics is not None)
    duration_s = simulator.get_context().get_time()
    log = (log_writer.finish(simulator.get_context()) if log_writer is not None else
           log_arrays(built.logger, built.log_layout, simulator.get_context(), scenario.device))
    spec = scenario.device.instrument_spec()
    summary = {
        "scenario": label,
        "instrument": spec.kind,
        "duration_s": float(duration_s),
        "wall_time_s": wall_s,
        "realtime_factor": float(duration_s / wall_s),
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
    if stop_signal.received is not None or stop.landing_end_s is not None:
        # What the log shows, not what was asked: a second signal ends a landing midway.
        summary["landed_before_stopping"] = (stop.landing_end_s is not None
                                             and summary["final_state"]["rests"])
    if tick_times is not None:
        summary["realtime"] = {"rate": realtime_rate, **realtime_report(tick_times)}
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
        plot_run(log, out_dir, title=label,
                 current_limit_a=scenario.device.amplifier.current_limit_a)
        if scenario.haptics is not None:
            plot_haptics(log, out_dir, title=label)
        if tick_times is not None:
            plot_tick_times(tick_times, out_dir, title=label)
        if "head_pose" in log:  # the true head: a simulated station's
            plot_colocation(log, scenario, out_dir, title=label)
    return RunResult(summary=summary, log=log, meshcat=viewer)
