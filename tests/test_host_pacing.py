"""The machine's own pacing floor: a loop that only burns its compute, paced as a
diagram is."""

import pytest

from maglev_haptics.analysis.host_pacing import BusyTicks, host_pacing


def test_each_tick_burns_the_compute_asked_and_moves_the_clock():
    report = host_pacing(0.3, 200.0)
    assert report["ticks"] == 300 and report["compute_us"] == 200.0
    # The spin ends once its time is up: never sooner, and within a preemption of it.
    assert 200.0 <= report["tick_compute_us_p50"] < 400.0
    ticks = BusyTicks(200e-6)
    ticks.AdvanceTo(0.25)
    assert ticks.get_context() is ticks and ticks.get_time() == 0.25


def test_a_compute_longer_than_the_slot_misses_every_slot_after_the_first():
    report = host_pacing(0.05, 1500.0)
    # The first tick runs before the clock starts (as a diagram's does) and ends its slot.
    assert report["deadline_misses"] == report["ticks"] - 1
    assert report["longest_stall_ms"] >= 0.5 * (report["ticks"] - 1) * 0.99


@pytest.mark.parametrize("duration_s, compute_us, field", [
    (1.0, -5.0, "compute_us = -5.0"), (1e-4, 100.0, "duration_s = 0.0001")])
def test_bad_arguments_are_named(duration_s, compute_us, field):
    with pytest.raises(ValueError, match=field):
        host_pacing(duration_s, compute_us)
