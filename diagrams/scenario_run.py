"""A scenario flown to its end: the path every ``maglev run`` takes, up to its log.

``fly_scenario`` builds the diagram for the run (paced or not), records it in
Meshcat, lets Ctrl-C and SIGTERM land a flying instrument before the run stops (a
second one stops it at once), lands what flies before a device's run ends, stops at
once where the station says so (a device gone silent), and advances the simulator
(``diagrams/runner.py``). What it leaves, ``FlownScenario``, is read into results
(``summary.json``, the plots) by ``analysis/run_results.py``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional

from pydrake.geometry import Meshcat
from pydrake.systems.analysis import Simulator

from maglev_haptics.diagrams.application import BuildDiagram, BuiltDiagram, RunMode
from maglev_haptics.diagrams.motion import longest_landing_s
from maglev_haptics.diagrams.runner import (
    PROGRESS_CHUNK_S, LandBeforeStopping, StopOnSignal, TickTimes, simulate)
from maglev_haptics.diagrams.scenario import Scenario
from maglev_haptics.diagrams.station import station_kind
from maglev_haptics.systems.device_visualizer import aim_camera_at_device
from maglev_haptics.systems.meshcat_hand import wait_for_browser


@dataclass
class FlownScenario:
    """What a flown scenario leaves: its diagram and simulator at the run's end, the
    wall time it took (s), the paced ticks' timing (None unpaced), the rate it ran
    at, the signals it received and the landing it waited for."""
    built: BuiltDiagram
    simulator: Simulator
    wall_s: float
    tick_times: Optional[TickTimes]
    realtime_rate: float
    stop_signal: StopOnSignal
    landing: LandBeforeStopping


def run_rate(scenario: Scenario, realtime_rate: float) -> float:
    """The real-time rate a run of ``scenario`` takes: as told, or 1.0 where its station
    keeps the wall clock's time (a device: the application must keep it too)."""
    if station_kind(scenario).keeps_wall_clock and realtime_rate <= 0:
        return 1.0
    return realtime_rate


def fly_scenario(scenario: Scenario, *, label: str, duration_s: Optional[float] = None,
                 viewer: Optional[Meshcat] = None, realtime_rate: float = 0.0,
                 progress: bool = True, raise_priority: bool = True, frame_sink=None,
                 on_built: Callable[[BuiltDiagram], Optional[Callable]] = lambda built: None
                 ) -> FlownScenario:
    """Fly ``scenario`` for ``duration_s`` (s; default its own, else its script's end)
    at ``run_rate``; ``viewer``, a Meshcat to draw in (the run's recording is published
    there). ``on_built(built)``, once the diagram is built, returns what the run calls
    with the root context as it goes (the log's move to disk), or None.
    ``raise_priority``: a paced loop runs at real-time priority where granted."""
    realtime_rate = run_rate(scenario, realtime_rate)
    built = BuildDiagram(scenario, meshcat=viewer, label=label, frame_sink=frame_sink,
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
    on_progress = on_built(built)
    try:
        if built.meshcat_hand is not None:
            wait_for_browser(viewer)
        with StopOnSignal() as stop_signal:
            landing = LandBeforeStopping(built.app.supervisor, stop_signal,
                                         land_from_s=duration_s if lands_at_end else None,
                                         haptics=built.haptics)
            # What the station stops a run for (a device gone silent) stops it at once:
            # no landing without one.
            simulator, wall_s, tick_times = simulate(
                built, horizon_s, realtime_rate=realtime_rate, progress=progress, label=label,
                stop=built.station.watch(landing), shares_cores=built.station.shares_cores,
                on_progress=on_progress, raise_priority=raise_priority,
                progress_total_s=duration_s)
    finally:
        if built.meshcat_hand is not None:
            built.meshcat_hand.Delete()
    if record:
        viewer.StopRecording()
        viewer.PublishRecording()
        aim_camera_at_device(viewer, close=scenario.haptics is not None)
    return FlownScenario(built=built, simulator=simulator, wall_s=wall_s,
                         tick_times=tick_times, realtime_rate=realtime_rate,
                         stop_signal=stop_signal, landing=landing)
