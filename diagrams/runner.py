"""Advance a built diagram: a simulator, optionally paced to the wall clock, with progress.

Paced (``realtime_rate > 0``), the runner is the real-time loop: each control
tick of ``tick_s`` simulated seconds is released at its wall-clock slot
(``tick_s / realtime_rate`` wall seconds long), computed with one ``AdvanceTo``,
and timed. The first tick runs before the clock starts, which starts as it ends: it
makes every first call (the workers' threads started, caches filled), 1.3-3.3 ms
against a steady tick's 0.2-0.4 ms, and would otherwise make the first dozen ticks
miss as they caught up. A tick whose compute ends after its slot has missed its
deadline; the next tick then starts at once, so a late loop catches up rather than skipping
ticks (a haptic loop may not drop its samples). What is not the loop's (Meshcat's
frames, moving the log to disk, the progress bar) runs between ticks, where its
measured cost fits before the next slot, or once it is long overdue and the loop
is behind its clock anyway (``BetweenTicks``): a frame may be late, a tick may not.
"""

from __future__ import annotations

import gc
import math
import signal
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Callable, Dict, List, Optional

import numpy as np
from pydrake.systems.analysis import Simulator
from tqdm import tqdm

from maglev_haptics.diagrams.application import MESHCAT_PERIOD_S
from maglev_haptics.diagrams.motion import IDLE_AFTER_S
from maglev_haptics.hardware.constants import SAME_INSTANT_S
from maglev_haptics.hardware.realtime_priority import (
    RT_RETURN_MARGIN, RT_SPIN_S, is_realtime, realtime_priority,
    rt_throttle_share, set_loop_realtime)
from maglev_haptics.hardware.kernels import compile_kernels

PROGRESS_CHUNK_S = 0.25  # simulated seconds between progress-bar updates
BAR_FORMAT = "{l_bar}{bar}| {n:.2f}/{total:.2f} sim s [{elapsed}{postfix}]"
# A paced loop calls ``on_progress`` (moving the log to disk) this often (simulated s),
# and one so far behind that no gap fits it at least this often, so the logger never
# grows without bound.
ON_PROGRESS_PERIOD_S = 0.05
PROGRESS_MAX_LATE_S = 2.0
# A loop that is behind its clock (its ticks late already) still draws each visualizer
# this often (simulated s), so an overloaded run's view is not frozen.
FRAME_MAX_LATE_S = 1.0
MISS_WARNING_FRACTION = 0.001  # more missed deadlines than this and the terminal says so


@dataclass
class TickTimes:
    """Wall-clock timing of a paced run, one entry a tick (s)."""
    slot_s: float  # wall seconds a tick may take: tick_s / realtime_rate
    compute_s: np.ndarray  # wall time each tick's AdvanceTo took
    lateness_s: np.ndarray  # when each tick's compute ended, past its slot's end (< 0: early)
    priority: str = ""  # what the loop ran at (``realtime_priority``)


def realtime_report(times: TickTimes) -> Dict:
    """The ``realtime`` block of summary.json: deadline misses and compute-time
    percentiles of the ticks run (us, ms), and the scheduling the loop ran at."""
    compute_us = 1e6 * times.compute_s
    missed = times.lateness_s > 0.0
    ticks = int(compute_us.size)
    return {
        "ticks": ticks,
        "slot_us": 1e6 * times.slot_s,
        "deadline_misses": int(missed.sum()),
        "miss_fraction": float(missed.mean()) if ticks else 0.0,
        "tick_compute_us_p50": float(np.percentile(compute_us, 50)) if ticks else 0.0,
        "tick_compute_us_p99": float(np.percentile(compute_us, 99)) if ticks else 0.0,
        "tick_compute_us_max": float(compute_us.max()) if ticks else 0.0,
        # Off the clock (module docstring), and counted in the percentiles above.
        "first_tick_compute_us": float(compute_us[0]) if ticks else 0.0,
        # The longest the loop ran behind its clock: one long tick, or a run of late ones.
        "longest_stall_ms": float(1e3 * max(0.0, times.lateness_s.max())) if ticks else 0.0,
        "priority": times.priority,
    }


def wait_until(wall_s: float, spin_s: float) -> float:
    """Return at ``wall_s`` (time.perf_counter's clock, s), spinning its last ``spin_s``;
    returns how long it waited (s, 0 if called late)."""
    # The last ``spin_s`` before the slot is spun, not slept: a core that idles wakes
    # cold. On the 2-core test machine levitate missed 1.7-1.8% of its slots sleeping
    # and 0.08-0.1% spinning the whole wait (15 s runs alternated; another day, 59-71%
    # sleeping until 0.3 ms before the slot against 22-37% spinning throughout).
    waited_s = wall_s - time.perf_counter()
    if waited_s - spin_s > 0:
        time.sleep(waited_s - spin_s)
    while time.perf_counter() < wall_s:
        pass
    return max(0.0, waited_s)


# A real-time loop's sleep is judged over at least this many slots (and at most a
# second's): long enough for one long tick not to count, short of the throttle's 0.95 s.
RT_WINDOW_MIN_SLOTS = 500


class RealtimeBudget:
    """Whether a paced loop of ``slot_s`` (s) slots may run at real-time priority:
    over its last second's slots (at least RT_WINDOW_MIN_SLOTS), a loop at it sleeps
    each wait but its last RT_SPIN_S, and must sleep the kernel's throttle's due
    (``rt_throttle_share``) or be stopped by it; back at normal priority, it returns
    once its waits would sleep RT_RETURN_MARGIN times that. ``stretches``: [start,
    end] (s) of each stretch at normal priority."""

    def __init__(self, slot_s: float):
        self._sleeps_s = np.zeros(max(1, int(round(1.0 / slot_s))))
        self._sum_s = 0.0
        self._count = 0
        self._due_s = rt_throttle_share() * self._sleeps_s.size * slot_s  # a second's (s)
        self._realtime = True
        self.stretches: List[List[float]] = []

    def add(self, waited_s: float, t_s: float) -> bool:
        """Count a wait of ``waited_s`` (s) at simulated time ``t_s`` (s); returns
        whether the loop may run at real-time priority from now."""
        slot = self._count % self._sleeps_s.size
        sleep_s = max(0.0, waited_s - RT_SPIN_S)
        self._sum_s += sleep_s - self._sleeps_s[slot]
        self._sleeps_s[slot] = sleep_s
        self._count += 1
        window = min(self._count, self._sleeps_s.size)
        due_s = self._due_s * window / self._sleeps_s.size
        if window < RT_WINDOW_MIN_SLOTS or due_s == 0.0:
            return self._realtime
        if self._realtime and self._sum_s < due_s:
            self._realtime = False
            self.stretches.append([t_s, math.inf])
        elif not self._realtime and self._sum_s > RT_RETURN_MARGIN * due_s:
            self._realtime = True
            self.stretches[-1][1] = t_s
        return self._realtime

    def describe(self) -> str:
        """The stretches at normal priority, in words."""
        spans = ", ".join(f"{start:.2f}-{end:.2f} s" if math.isfinite(end) else
                          f"from {start:.2f} s" for start, end in self.stretches)
        return (f"at normal priority {spans}: its waits left it less sleep than the "
                f"real-time throttle's due, {1e3 * self._due_s:.0f} ms a second")


# A paced process that shares the machine with another (the device's, on LCM) sleeps
# until this much before each slot, so the other one gets a core (s).
SHARED_SPIN_S = 0.0003


class StopOnSignal:
    """While entered: SIGINT (Ctrl-C) and SIGTERM ask the run to stop instead of killing
    it. Passed as ``simulate``'s ``stop``, the run ends at its next check, between
    ticks (the handler only sets a flag: nothing is raised inside a kernel), so its
    results are written. ``received``: the signal's name, or None."""

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self):
        self.received = None
        self.count = 0  # signals received
        self._previous = {}

    def __enter__(self) -> "StopOnSignal":
        if threading.current_thread() is threading.main_thread():  # where Python allows it
            for number in self.SIGNALS:
                self._previous[number] = signal.signal(number, self._handle)
        return self

    def __exit__(self, *exception) -> None:
        for number, handler in self._previous.items():
            signal.signal(number, handler)

    def _handle(self, number, frame) -> None:
        self.received = signal.Signals(number).name
        self.count += 1

    def __call__(self, context) -> bool:
        return self.received is not None


class LandBeforeStopping:
    """``simulate``'s ``stop`` that lands first: once ``requested`` (a StopOnSignal)
    has a signal, or from ``land_from_s`` (s; None: never) on, a flying instrument
    lands (the device supervisor's landing, as on a fault; ``haptics``, a
    HapticParts or None, ends haptics first, as a fault does, so the coils' force is
    the landing's) and the run stops once that is done; a second signal stops at
    once. ``landing_end_s``: when the landing it waited for ends (s; None: none)."""

    def __init__(self, supervisor, requested: StopOnSignal,
                 land_from_s: Optional[float] = None, haptics=None):
        self._supervisor = supervisor
        self._requested = requested
        self._land_from_s = math.inf if land_from_s is None else land_from_s
        self._haptics = haptics
        self.landing_end_s = None

    def __call__(self, context) -> bool:
        t_s = context.get_time()
        if not (self._requested(context) or t_s >= self._land_from_s - SAME_INSTANT_S):
            return False
        if self._requested.count > 1:
            return True
        if self.landing_end_s is None:
            supervisor_context = self._supervisor.GetMyMutableContextFromRoot(context)
            motion = self._supervisor.active_motion(supervisor_context)
            if motion.at(t_s)[1] == 0.0:
                return True  # the coils carry nothing: nothing to land
            if self._haptics is not None:
                self._haptics.end_request()
            if not motion.landing:
                motion = self._supervisor.land(supervisor_context)
            self.landing_end_s = motion.end_s
        # As a script ends: a while after the force has ramped to zero.
        return t_s >= self.landing_end_s + IDLE_AFTER_S


# A job runs between ticks only where COST_SAFETY times the median of its last
# COST_MEMORY costs, and this margin, fit before the next tick's release (s). The
# median, not the most, and after RETRY_AFTER_SKIPS gaps that it did not fit, its
# cheapest run: one run that the host preempted must not bar a job for good.
BETWEEN_TICKS_MARGIN_S = 50e-6
COST_MEMORY = 15
COST_SAFETY = 1.5
RETRY_AFTER_SKIPS = 250
MEASURED_RUNS = 3  # timed before the clock starts, after one run that warms it up


@dataclass
class BetweenTicksJob:
    """Work due every ``period_s`` of simulated time, first at ``due_s`` (s). Once it is
    ``max_late_s`` (simulated s) late it runs in the next gap, fitting or not, while the
    loop is behind its clock anyway (its ticks are late already), or always if it
    ``must_run`` (moving the log to disk: the logger must not grow without bound)."""
    name: str
    run: Callable[[], None]
    period_s: float
    due_s: float = 0.0
    max_late_s: float = math.inf
    must_run: bool = False
    costs_s: deque = field(default_factory=lambda: deque(maxlen=COST_MEMORY))
    runs: int = 0
    late_s: float = 0.0  # the longest a run came after it was due (simulated s)
    skipped: int = 0  # gaps in a row it was due but did not fit

    def timed_run(self) -> None:
        begin = time.perf_counter()
        self.run()
        self.costs_s.append(time.perf_counter() - begin)
        self.runs += 1

    def cost_s(self) -> float:
        """What a gap must hold for it (s), as measured."""
        if not self.costs_s:
            return 0.0
        if self.skipped >= RETRY_AFTER_SKIPS:
            return min(self.costs_s)
        return COST_SAFETY * float(np.median(self.costs_s))


class BetweenTicks:
    """The paced loop's gaps: each due job runs, most overdue first, where its cost
    (as measured) fits before ``release`` (time.perf_counter's clock, s), so it makes
    no tick late; a job that never fits runs only once it is ``max_late_s`` late."""

    def __init__(self, jobs: List[BetweenTicksJob]):
        self.jobs = jobs

    def measure(self) -> None:
        """Run every job, off the clock, for a first measure of its cost."""
        for job in self.jobs:
            job.run()  # a first call pays for caches and allocations
            for _ in range(MEASURED_RUNS):
                job.timed_run()

    def fill_gap(self, t_s: float, release: float) -> None:
        """Run the jobs due at simulated time ``t_s`` that fit before ``release``."""
        for job in sorted((job for job in self.jobs if job.due_s <= t_s),
                          key=lambda job: job.due_s):
            now = time.perf_counter()
            fits = release - now >= job.cost_s() + BETWEEN_TICKS_MARGIN_S
            forced = t_s - job.due_s > job.max_late_s and (job.must_run or release < now)
            if not (fits or forced):
                job.skipped += 1
                continue
            job.skipped = 0
            job.late_s = max(job.late_s, t_s - job.due_s)
            job.timed_run()
            job.due_s += job.period_s
            if job.due_s <= t_s:  # a period or more behind: the missed runs are skipped
                job.due_s = t_s + job.period_s


def frame_jobs(publishers, context, period_s: float) -> List[BetweenTicksJob]:
    """One job a visualizer: its ForcedPublish at the context's time; a loop that is
    behind its clock still draws a frame every FRAME_MAX_LATE_S."""
    return [BetweenTicksJob(
        name=publisher.get_name(), period_s=period_s, max_late_s=FRAME_MAX_LATE_S,
        run=lambda publisher=publisher: publisher.ForcedPublish(
            publisher.GetMyContextFromRoot(context))) for publisher in publishers]


class PacedTicks:
    """The timing of a paced run as it goes: kept when Ctrl-C ends the run early."""

    def __init__(self, n_ticks: int, slot_s: float):
        self.slot_s = slot_s
        self.compute_s = np.zeros(n_ticks)
        self.lateness_s = np.zeros(n_ticks)
        self.done = 0
        self.missed = 0  # counted as the run goes: the progress bar shows it
        self.priority = ""

    def times(self) -> TickTimes:
        return TickTimes(slot_s=self.slot_s, compute_s=self.compute_s[:self.done],
                         lateness_s=self.lateness_s[:self.done], priority=self.priority)


def advance_paced(simulator, duration_s: float, tick_s: float, ticks: PacedTicks, bar,
                  stop=None, spin_s: float = math.inf, on_progress=None,
                  frame_publishers=(), frame_period_s: float = MESHCAT_PERIOD_S,
                  show_rate=None, raise_priority: bool = True) -> BetweenTicks:
    """Tick by tick to ``duration_s``, each released at its wall-clock slot; ``stop(context)``,
    asked every PROGRESS_CHUNK_S, ends the run early when it returns True. Between
    ticks, where they fit (``BetweenTicks``): the progress bar every PROGRESS_CHUNK_S,
    ``on_progress(context)`` every ON_PROGRESS_PERIOD_S, each of ``frame_publishers`` every
    ``frame_period_s`` (s), and ``show_rate(rate)`` told the real-time rate over each
    progress interval (Meshcat's panel, which stayed empty in Chromium with only the
    visualizers, published from here, to fill it). With ``raise_priority`` the loop runs
    at real-time priority where granted (``realtime_priority``: then it spins at most
    RT_SPIN_S, and goes back to normal priority where its ticks leave it too little
    sleep for the kernel's throttle, ``RealtimeBudget``; ``ticks.priority`` says
    when). The wait for a slot spins for its last ``spin_s`` (s) and sleeps
    before that. Returns the gaps' jobs, with what they cost and how late they ran."""
    context = simulator.get_context()
    start_s = context.get_time()
    ticks_per_update = max(1, int(round(PROGRESS_CHUNK_S / tick_s)))
    last = [time.perf_counter(), start_s]  # wall (s), simulated (s) at the last report

    def report_progress():
        advance_bar(bar, context.get_time())
        bar.set_postfix_str(f"missed {ticks.missed}/{ticks.done}", refresh=False)
        now, t_s = time.perf_counter(), context.get_time()
        if show_rate is not None and t_s > last[1]:
            show_rate((t_s - last[1]) / (now - last[0]))
        last[:] = now, t_s

    # ``on_progress`` (the log's move to disk) often, so each run is short and costs
    # about the same: a gap holds it where its cost was measured to fit.
    jobs = [BetweenTicksJob("progress", report_progress, PROGRESS_CHUNK_S)]
    if on_progress is not None:
        jobs.append(BetweenTicksJob("on_progress", lambda: on_progress(context),
                                    ON_PROGRESS_PERIOD_S, max_late_s=PROGRESS_MAX_LATE_S,
                                    must_run=True))
    between = BetweenTicks(jobs + frame_jobs(frame_publishers, context, frame_period_s))
    between.measure()
    try:
        with realtime_priority(raise_priority) as ticks.priority:
            fifo, normal_spin_s = is_realtime(), spin_s
            throttle = RealtimeBudget(ticks.slot_s)
            realtime = fifo
            if realtime:
                spin_s = min(spin_s, RT_SPIN_S)
            for k in range(ticks.compute_s.size):
                if k > 0:  # the first tick runs before the clock starts (module docstring)
                    release = clock_zero + (k - 1) * ticks.slot_s
                    between.fill_gap(context.get_time(), release)
                    waited = wait_until(release, spin_s)
                    if fifo and throttle.add(waited, context.get_time() - start_s) != realtime:
                        realtime = not realtime
                        spin_s = min(normal_spin_s, RT_SPIN_S) if realtime else normal_spin_s
                        set_loop_realtime(realtime)
                begin = time.perf_counter()
                simulator.AdvanceTo(start_s + (k + 1) * tick_s)
                end = time.perf_counter()
                if k == 0:
                    clock_zero = end  # the first slot ends as the first tick does
                ticks.compute_s[k] = end - begin
                ticks.lateness_s[k] = end - (clock_zero + k * ticks.slot_s)
                ticks.missed += ticks.lateness_s[k] > 0.0
                ticks.done = k + 1
                if ticks.done % ticks_per_update == 0 and stop is not None and stop(context):
                    break
            if fifo and throttle.stretches:
                ticks.priority += f" ({throttle.describe()})"
    finally:
        advance_bar(bar, context.get_time())
    # The last frame and the log's tail, off the clock (not after an error: what
    # raised it is what the caller must see).
    for job in between.jobs:
        job.run()
    return between


def advance_bar(bar, t_s: float) -> None:
    """Move the progress bar to simulated time ``t_s`` (s); a landing past the bar's
    total stretches it (tqdm cannot draw a count past its total)."""
    if t_s > bar.total:
        bar.total = t_s
    bar.update(t_s - bar.n)


def finish_bar(bar, total_s: float) -> None:
    """End the progress bar where the run ended: a run past its ``total_s`` (a landing
    after the run's time) shows the extra time; one cut short keeps its fraction."""
    if bar.n > total_s:
        bar.total = bar.n
        bar.set_postfix_str(f"{bar.postfix + ', ' if bar.postfix else ''}landing "
                            f"+{bar.n - total_s:.2f} s", refresh=False)
    bar.refresh()


def simulate(built, duration_s: float, *, realtime_rate: float = 0.0,
             progress: bool = True, label: str = "", stop=None,
             shares_cores: bool = False, on_progress=None, raise_priority: bool = True,
             progress_total_s: Optional[float] = None):
    """Advance the diagram to ``duration_s``; returns (simulator, wall seconds,
    TickTimes of the paced ticks or None when not paced). The progress bar counts to
    ``progress_total_s`` (s; default ``duration_s``): a run's time, where ``duration_s``
    leaves room for a landing after it.
    ``stop(context)``, asked every PROGRESS_CHUNK_S of simulated time, ends the run
    early when True (``StopOnSignal`` for Ctrl-C and SIGTERM). ``shares_cores``:
    another paced process runs on this machine, so the wait between ticks sleeps
    (``SHARED_SPIN_S``).
    ``on_progress(context)`` is called every PROGRESS_CHUNK_S of simulated time
    (paced: every ON_PROGRESS_PERIOD_S). ``raise_priority``: the paced loop runs at
    real-time priority where the OS grants it (``hardware/realtime_priority.py``)."""
    # Nothing compiles inside the loop: every kernel is ready before the clock starts.
    compile_kernels(progress=progress)
    simulator = Simulator(built.diagram)
    # The collector took a tenth of a run's time and paused the loop for milliseconds;
    # the loop makes no reference cycles, so it is off until the run ends. It collects
    # before Initialize, which reads the station's inputs: a collection after it (60 ms
    # or more) left the station's messages waiting for the first tick.
    gc.collect()
    gc.disable()
    try:
        simulator.Initialize()
        paced = None
        if realtime_rate > 0:
            n_ticks = int(round(duration_s / built.tick_s))
            paced = PacedTicks(n_ticks, built.tick_s / realtime_rate)
        start = time.perf_counter()
        total_s = float(duration_s if progress_total_s is None else progress_total_s)
        with tqdm(total=total_s, unit="sim s", disable=not progress, desc=label,
                  bar_format=BAR_FORMAT
                  ) as bar:
            if paced is not None:
                advance_paced(simulator, duration_s, built.tick_s, paced, bar, stop,
                              SHARED_SPIN_S if shares_cores else math.inf, on_progress,
                              built.frame_publishers, MESHCAT_PERIOD_S,
                              built.meshcat.SetRealtimeRate if built.meshcat is not None
                              else None, raise_priority)
            else:
                chunks = np.append(np.arange(PROGRESS_CHUNK_S, duration_s, PROGRESS_CHUNK_S),
                                   duration_s)
                for t in chunks:
                    simulator.AdvanceTo(float(t))
                    advance_bar(bar, float(t))
                    if on_progress is not None:
                        on_progress(simulator.get_context())
                    if stop is not None and stop(simulator.get_context()):
                        break
            finish_bar(bar, total_s)
    finally:
        gc.enable()
    wall_s = time.perf_counter() - start
    return simulator, wall_s, paced.times() if paced is not None else None
