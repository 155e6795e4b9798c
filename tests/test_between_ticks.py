"""Work between the paced loop's ticks: frames, the log, the progress bar run only where they fit."""

import time

import pytest

from maglev_haptics.diagrams.runner import (
    BETWEEN_TICKS_MARGIN_S, MEASURED_RUNS, RETRY_AFTER_SKIPS, BetweenTicks, BetweenTicksJob,
    PacedTicks, advance_paced)

TICK_S = 1e-3


def busy(seconds: float):
    def run():
        end = time.perf_counter() + seconds
        while time.perf_counter() < end:
            pass
    return run


class FakeSimulator:
    """AdvanceTo takes TICK_COST_S of wall time; time is the tick's end."""
    TICK_COST_S = 100e-6

    def __init__(self):
        self._time = 0.0

    def get_context(self):
        return self

    def get_time(self):
        return self._time

    def AdvanceTo(self, t):
        busy(self.TICK_COST_S)()
        self._time = t


class Bar:
    n = 0.0

    def update(self, step):
        self.n += step

    def set_postfix_str(self, *_, **__):
        pass


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
    simulator = FakeSimulator()
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
    simulator = FakeSimulator()
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
