"""The real-time loop: paced ticks, their timing, deadline misses, and a paced run's summary."""

import json
import time

import numpy as np
import pytest

from maglev_haptics.diagrams.cli import main
from maglev_haptics.diagrams.runner import TickTimes, advance_paced, PacedTicks, realtime_report

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

    def update(self, step):
        self.n += step

    def set_postfix_str(self, *_, **__):
        pass


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
    from maglev_haptics.diagrams import runner
    clock = VirtualClock()
    monkeypatch.setattr(runner, "time", clock)
    stall_tick = 20
    simulator = VirtualSimulator(lambda k: 3e-3 if k == stall_tick else 50e-6, clock)
    ticks = PacedTicks(60, slot_s=TICK_S)
    start = clock.now
    advance_paced(simulator, 60 * TICK_S, TICK_S, ticks, Bar())
    times = ticks.times()
    # Paced: 60 ticks of 1 ms cannot end before the 60th slot opens.
    assert clock.now - start >= 59 * TICK_S
    assert times.compute_s.size == 60
    assert ticks.missed == np.count_nonzero(times.lateness_s > 0)
    assert times.compute_s[stall_tick] == pytest.approx(3e-3, abs=1e-5)
    assert times.lateness_s[stall_tick] == pytest.approx(2e-3, abs=1e-4)
    # The two ticks whose slots passed during the stall run back to back behind it and
    # end late; the next one ends within its slot: the loop is on its clock again.
    assert np.all(times.lateness_s[stall_tick + 1:stall_tick + 3] > 0)
    assert np.all(times.lateness_s[stall_tick + 3:] < 0)
    assert np.all(times.lateness_s[:stall_tick] < 0)
    assert ticks.missed == 3
    assert simulator.get_time() == pytest.approx(60 * TICK_S)


def test_paced_loop_on_the_wall_clock_ends_no_sooner_than_its_slots():
    """The real clock: a lower bound only, which no load on the host can break."""
    simulator = FakeSimulator(lambda k: 50e-6)
    ticks = PacedTicks(60, slot_s=TICK_S)
    start = time.perf_counter()
    advance_paced(simulator, 60 * TICK_S, TICK_S, ticks, Bar())
    assert time.perf_counter() - start >= 59 * TICK_S
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
