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


def test_paced_loop_holds_the_clock_and_catches_up_after_a_stall():
    stall_tick = 20
    simulator = FakeSimulator(lambda k: 3e-3 if k == stall_tick else 50e-6)
    ticks = PacedTicks(60, slot_s=TICK_S)
    start = time.perf_counter()
    advance_paced(simulator, 60 * TICK_S, TICK_S, ticks, Bar())
    wall_s = time.perf_counter() - start
    times = ticks.times()
    # Paced: 60 ticks of 1 ms cannot end before the 60th slot opens.
    assert wall_s >= 59 * TICK_S
    assert times.compute_s.size == 60
    assert ticks.missed == np.count_nonzero(times.lateness_s > 0)
    assert times.lateness_s[stall_tick] > 1.5e-3
    assert times.compute_s[stall_tick] >= 3e-3
    # The ticks after the stall run back to back until the loop is on its clock again
    # (any one of them may still be late when the host takes the core for a moment).
    assert np.any(times.lateness_s[stall_tick + 1:] < 0)
    assert simulator.get_time() == pytest.approx(60 * TICK_S)


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
