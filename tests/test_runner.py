"""The real-time loop: paced ticks, their timing, deadline misses, the work between ticks
(frames, the log, the progress bar run only where they fit), and a paced run's summary."""

import json
import os
import time

import numpy as np
import pytest

from maglev_haptics.analysis.run_metrics import first_touchdown, log_arrays
from maglev_haptics.diagrams import runner
from maglev_haptics.diagrams.application import BuildDiagram
from maglev_haptics.cli import main
from maglev_haptics.diagrams.motion import longest_landing_s
from maglev_haptics.diagrams.runner import (
    BETWEEN_TICKS_MARGIN_S, MEASURED_RUNS, PROGRESS_CHUNK_S, RETRY_AFTER_SKIPS, BetweenTicks,
    BetweenTicksJob, LandBeforeStopping, PacedTicks, StopOnSignal, TickTimes, advance_paced,
    realtime_report, simulate)
from maglev_haptics.diagrams.scenario import load_scenario
from maglev_haptics.hardware.realtime_priority import (
    LOOP_PRIORITY, RT_SPIN_S, fifo_permitted, is_realtime)

TICK_S = 1e-3


class FakeSimulator:
    """AdvanceTo takes ``cost_s(tick)`` wall seconds; time is the tick's end."""

    def __init__(self, cost_s):
        self._cost_s = cost_s
        self._time = 0.0

    def get_context(self):
        return self

    def get_time(self):
        return self._time

    def AdvanceTo(self, t):
        tick = int(round(t / TICK_S)) - 1
        end = time.perf_counter() + self._cost_s(tick)
        while time.perf_counter() < end:
            pass
        self._time = t


class Bar:
    n = 0.0
    total = float("inf")

    def update(self, step):
        self.n += step

    def set_postfix_str(self, *_, **__):
        pass


def busy(seconds: float):
    def run():
        end = time.perf_counter() + seconds
        while time.perf_counter() < end:
            pass
    return run


def test_report_counts_misses_and_percentiles():
    compute = np.full(1000, 300e-6)
    compute[10] = 2.5e-3
    lateness = compute - 1e-3
    lateness[11] = 0.4e-3  # the tick after a long one starts late and ends late
    report = realtime_report(TickTimes(slot_s=1e-3, compute_s=compute, lateness_s=lateness))
    assert report["ticks"] == 1000
    assert report["deadline_misses"] == 2
    assert report["miss_fraction"] == pytest.approx(0.002)
    assert report["tick_compute_us_p50"] == pytest.approx(300.0)
    assert report["tick_compute_us_max"] == pytest.approx(2500.0)
    assert report["longest_stall_ms"] == pytest.approx(1.5)
    assert report["slot_us"] == pytest.approx(1000.0)


class VirtualClock:
    """The runner's ``time`` module on a clock of its own: each read advances it by
    READ_S (a spin), a sleep by its length, a tick by its cost. What the loop does
    with its clock, not what a loaded host does to it."""
    READ_S = 1e-6

    def __init__(self):
        self.now = 100.0

    def perf_counter(self):
        self.now += self.READ_S
        return self.now

    def sleep(self, seconds):
        self.now += max(seconds, 0.0)


class VirtualSimulator(FakeSimulator):
    def __init__(self, cost_s, clock):
        super().__init__(cost_s)
        self._clock = clock

    def AdvanceTo(self, t):
        self._clock.now += self._cost_s(int(round(t / TICK_S)) - 1)
        self._time = t


def test_paced_loop_holds_the_clock_and_catches_up_after_a_stall(monkeypatch):
    clock = VirtualClock()
    monkeypatch.setattr(runner, "time", clock)
    stall_tick = 20
    simulator = VirtualSimulator(lambda k: 3e-3 if k == stall_tick else 50e-6, clock)
    ticks = PacedTicks(60, slot_s=TICK_S)
    start = clock.now
    advance_paced(simulator, 60 * TICK_S, TICK_S, ticks, Bar())
    times = ticks.times()
    # Paced: 60 ticks of 1 ms cannot end before the 60th slot opens, 58 slots after the
    # first tick (off the clock) ended.
    assert clock.now - start >= 58 * TICK_S + 50e-6
    assert times.compute_s.size == 60
    assert ticks.missed == np.count_nonzero(times.lateness_s > 0)
    assert times.compute_s[stall_tick] == pytest.approx(3e-3, abs=1e-5)
    assert times.lateness_s[stall_tick] == pytest.approx(2e-3, abs=1e-4)
    # The two ticks whose slots passed during the stall run back to back behind it and
    # end late; the next one ends within its slot: the loop is on its clock again.
    assert np.all(times.lateness_s[stall_tick + 1:stall_tick + 3] > 0)
    assert np.all(times.lateness_s[stall_tick + 3:] < 0)
    assert times.lateness_s[0] == 0.0  # the clock starts as the first tick ends
    assert np.all(times.lateness_s[1:stall_tick] < 0)
    assert ticks.missed == 3
    assert simulator.get_time() == pytest.approx(60 * TICK_S)


def test_the_first_tick_runs_before_the_clock_starts(monkeypatch):
    """Its first calls cost it milliseconds; counted on the clock, the dozen ticks after
    it would miss as they caught up."""
    clock = VirtualClock()
    monkeypatch.setattr(runner, "time", clock)
    simulator = VirtualSimulator(lambda k: 3e-3 if k == 0 else 400e-6, clock)
    ticks = PacedTicks(60, slot_s=TICK_S)
    advance_paced(simulator, 60 * TICK_S, TICK_S, ticks, Bar())
    report = realtime_report(ticks.times())
    assert report["deadline_misses"] == 0 and report["ticks"] == 60
    assert report["first_tick_compute_us"] == pytest.approx(3000.0, abs=2.0)  # clock reads
    assert np.all(ticks.times().lateness_s[1:] == pytest.approx(-600e-6, abs=5e-6))


def test_paced_loop_on_the_wall_clock_ends_no_sooner_than_its_slots():
    """The real clock: a lower bound only, which no load on the host can break."""
    simulator = FakeSimulator(lambda k: 50e-6)
    ticks = PacedTicks(60, slot_s=TICK_S)
    start = time.perf_counter()
    advance_paced(simulator, 60 * TICK_S, TICK_S, ticks, Bar())
    assert time.perf_counter() - start >= 58 * TICK_S
    assert ticks.done == 60


def test_cli_paced_run_reports_its_deadlines(tmp_path):
    out = tmp_path / "paced"
    assert main(["run", "levitate", "--duration", "0.5", "--no-meshcat", "--realtime", "1.0",
                 "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    realtime = summary["realtime"]
    assert realtime["ticks"] == 500
    assert realtime["rate"] == 1.0
    for key in ("deadline_misses", "tick_compute_us_p50", "tick_compute_us_p99",
                "tick_compute_us_max", "longest_stall_ms"):
        assert key in realtime
    assert 0 < realtime["tick_compute_us_p50"] <= realtime["tick_compute_us_p99"] \
        <= realtime["tick_compute_us_max"]
    # Paced to the wall clock: the last of 500 ticks is released 499 ms after the first.
    assert summary["wall_time_s"] >= 0.499
    assert (out / "realtime.png").stat().st_size > 10_000


def test_unpaced_run_has_no_realtime_block(tmp_path):
    out = tmp_path / "free"
    assert main(["run", "levitate", "--duration", "0.2", "--no-meshcat", "--out", str(out)]) == 0
    assert "realtime" not in json.loads((out / "summary.json").read_text())
    assert not (out / "realtime.png").exists()


def test_a_job_runs_when_due_and_only_where_its_cost_fits():
    job = BetweenTicksJob("frame", lambda: None, period_s=0.01)
    job.costs_s.extend([200e-6] * 3)  # as if measured
    gaps = BetweenTicks([job])
    gaps.fill_gap(0.0, time.perf_counter() + 0.1)  # due at 0, room to spare
    assert job.runs == 1 and job.due_s == pytest.approx(0.01)
    gaps.fill_gap(0.005, time.perf_counter() + 0.1)  # not yet due
    assert job.runs == 1
    gaps.fill_gap(0.02, time.perf_counter() + 200e-6 + BETWEEN_TICKS_MARGIN_S)
    assert job.runs == 1  # due, but with its safety factor it would run into the next slot
    gaps.fill_gap(0.05, time.perf_counter() + 0.1)
    assert job.runs == 2
    assert job.late_s == pytest.approx(0.04)
    assert job.due_s == pytest.approx(0.06)  # the frames it missed are skipped, not queued


def test_paced_loop_publishes_frames_between_ticks_and_not_one_that_cannot_fit():
    class Publisher:
        def __init__(self, name, cost_s):
            self.name, self.run, self.times = name, busy(cost_s), []

        def get_name(self):
            return self.name

        def GetMyContextFromRoot(self, context):
            return context

        def ForcedPublish(self, context):
            self.times.append(context.get_time())
            self.run()

    cheap, too_slow = Publisher("cheap", 100e-6), Publisher("too slow", 2e-3)
    ticks = PacedTicks(300, slot_s=TICK_S)
    simulator = FakeSimulator(lambda tick: 100e-6)
    gaps = advance_paced(simulator, 0.3, TICK_S, ticks, Bar(), frame_publishers=[cheap, too_slow],
                         frame_period_s=0.03)
    before = 1 + MEASURED_RUNS  # a warm-up and the measured runs, before the clock
    # Each 30 ms in the loop where due (a loaded host may delay some), and the last
    # frame after it.
    assert 5 <= len(cheap.times) - before - 1 <= 11
    assert cheap.times[:before] == [0.0] * before and cheap.times[-1] == pytest.approx(0.3)
    # 2 ms never fits a 1 ms slot: drawn before and after the loop only (a loop that is
    # on its clock never draws a frame that would make a tick late).
    if ticks.missed == 0:
        assert too_slow.times == [0.0] * before + [pytest.approx(0.3)]
    assert {job.name for job in gaps.jobs} == {"progress", "cheap", "too slow"}


def test_on_progress_is_called_often_and_last_after_the_clock():
    calls = []
    ticks = PacedTicks(300, slot_s=TICK_S)
    simulator = FakeSimulator(lambda tick: 100e-6)
    advance_paced(simulator, 0.3, TICK_S, ticks, Bar(),
                  on_progress=lambda context: calls.append(context.get_time()))
    # Measured before the clock, every 50 ms in it where due, and once at the end.
    assert 4 <= len(calls) - (1 + MEASURED_RUNS) - 1 <= 6
    assert calls[-1] == pytest.approx(0.3)


def test_a_job_whose_first_run_was_slow_is_not_barred_by_it():
    calls = []

    def slow_first():
        calls.append(None)
        if len(calls) == 1:
            busy(5e-3)()  # a cold first call: caches, allocations

    job = BetweenTicksJob("frame", slow_first, period_s=0.01)
    gaps = BetweenTicks([job])
    gaps.measure()
    assert job.cost_s() < 1e-3  # the warm-up is not what it costs
    gaps.fill_gap(0.0, time.perf_counter() + 0.1)
    assert job.runs == MEASURED_RUNS + 1


def test_a_job_that_never_fitted_is_retried_at_its_cheapest():
    job = BetweenTicksJob("frame", lambda: None, period_s=0.01)
    job.costs_s.extend([150e-6, 2e-3, 2e-3])  # as if preempted twice: the median bars it
    gaps = BetweenTicks([job])
    for _ in range(RETRY_AFTER_SKIPS):
        gaps.fill_gap(0.0, time.perf_counter() + 500e-6)
    assert job.runs == 0 and job.skipped == RETRY_AFTER_SKIPS
    gaps.fill_gap(0.0, time.perf_counter() + 500e-6)
    assert job.runs == 1 and job.skipped == 0


def test_a_loop_behind_its_clock_still_draws_a_frame_that_is_long_overdue():
    frame = BetweenTicksJob("frame", lambda: None, period_s=1 / 30, max_late_s=1.0)
    frame.costs_s.append(1.0)  # never fits
    gaps = BetweenTicks([frame])
    gaps.fill_gap(2.0, time.perf_counter() + 1e-3)  # overdue, but the loop is on its clock
    assert frame.runs == 0
    gaps.fill_gap(2.0, time.perf_counter() - 1e-3)  # behind: its ticks are late already
    assert frame.runs == 1


def test_a_job_that_must_not_wait_for_ever_runs_once_it_is_that_late():
    job = BetweenTicksJob("log to disk", lambda: None, period_s=0.25, max_late_s=2.0,
                          must_run=True)
    job.costs_s.append(1.0)  # as if measured: never fits a gap
    gaps = BetweenTicks([job])
    gaps.fill_gap(1.5, time.perf_counter() + 1e-3)
    assert job.runs == 0
    gaps.fill_gap(2.5, time.perf_counter() + 1e-3)
    assert job.runs == 1 and job.due_s == pytest.approx(2.75)


@pytest.mark.skipif(not fifo_permitted(), reason="this process may not use SCHED_FIFO")
def test_paced_loop_runs_at_real_time_priority_and_sleeps_its_waits(monkeypatch):
    """At SCHED_FIFO the wait for a slot spins at most RT_SPIN_S (a spinning FIFO thread
    is throttled 50 ms a second); at normal priority it spins all of it."""
    waits = []
    policies = []
    simulator = FakeSimulator(lambda k: policies.append(os.sched_getscheduler(0)) or 50e-6)
    monkeypatch.setattr(runner, "wait_until",
                        lambda wall_s, spin_s: waits.append(spin_s) or 0.5e-3)
    for priority in (True, False):
        waits.clear()
        policies.clear()
        ticks = PacedTicks(20, slot_s=TICK_S)
        advance_paced(simulator, simulator.get_time() + 20 * TICK_S, TICK_S, ticks, Bar(),
                      raise_priority=priority)
        assert ticks.priority == (f"SCHED_FIFO {LOOP_PRIORITY}" if priority
                                  else "normal: not asked for")
        expected = os.SCHED_FIFO if priority else os.SCHED_OTHER
        assert policies and set(policies) == {expected}
        assert np.all(np.array(waits) <= RT_SPIN_S) == priority
    assert not is_realtime()


def test_a_run_lands_the_instrument_from_its_land_from_time_before_it_stops():
    """What a run over LCM does when its time ends with the instrument flying (a
    device's instrument is never let fall): from ``land_from_s`` on the run lands it,
    softly and level, and stops once the force is ramped down, well before the longest
    landing's horizon; ``landing_end_s`` says it landed."""
    scenario = load_scenario("levitate")  # hovering at z = 18 mm from 2.2 s to 5.2 s
    built = BuildDiagram(scenario)
    stop = LandBeforeStopping(built.diagram.GetSubsystemByName("device_supervisor"),
                              StopOnSignal(), land_from_s=3.0)
    horizon_s = 3.0 + longest_landing_s(scenario.motion) + PROGRESS_CHUNK_S
    simulator, _, _ = simulate(built, horizon_s, progress=False, stop=stop)
    end_s = simulator.get_context().get_time()
    log = log_arrays(built.logger, built.log_layout, simulator.get_context(), scenario.device)
    assert log["p_WI_true"][log["t"] <= 3.0][-1, 2] > 0.015  # flying when its time came
    touchdown = first_touchdown(log, scenario.device.instrument_spec().rest_height_m)
    assert touchdown is not None and 3.0 < touchdown["time_s"] < end_s
    assert touchdown["speed_m_s"] < 0.05 and touchdown["tilt_deg"] < 1.0
    assert stop.landing_end_s is not None and end_s < horizon_s - 0.1
    assert np.all(np.abs(log["coil_currents"][-10:]) < 1e-9)


@pytest.mark.parametrize("ran_s, shown", [(8.95, "8.95/8.95 sim s [00:00, landing +3.95 s]"),
                                          (4.0, "4.00/5.00 sim s [00:00]")])
def test_the_progress_bar_ends_where_the_run_ended(ran_s, shown):
    """A run over LCM of 5 s whose landing took it to 8.95 s ends its bar at 100% with
    the landing's extra time, not at 81% of a horizon it never meant to reach; one cut
    short keeps its true fraction."""
    import io

    from tqdm import tqdm
    from maglev_haptics.diagrams.runner import BAR_FORMAT, advance_bar, finish_bar
    text = io.StringIO()
    with tqdm(total=5.0, file=text, bar_format=BAR_FORMAT) as bar:
        for t_s in np.arange(0.25, ran_s, 0.25).tolist() + [ran_s]:
            advance_bar(bar, t_s)
        finish_bar(bar, 5.0)
    assert shown in text.getvalue().rstrip().split("\r")[-1]
