"""Real-time priority for the paced loop: granted where the OS allows and undone
after, reported either way (the runner's use of it: tests/test_runner.py)."""

import os
import threading

import pytest

from maglev_haptics.hardware.realtime_priority import (
    LOOP_PRIORITY, add_follower, fifo_permitted, is_realtime, realtime_priority,
    rt_throttle_share, set_thread_priority)


needs_fifo = pytest.mark.skipif(not fifo_permitted(),
                                reason="this process may not use SCHED_FIFO (not root, no "
                                "CAP_SYS_NICE, `ulimit -r` 0)")


@needs_fifo
def test_granted_while_entered_and_undone_after():
    assert not is_realtime()
    with realtime_priority() as priority:
        assert priority == f"SCHED_FIFO {LOOP_PRIORITY}"
        assert is_realtime()
        assert os.sched_getparam(0).sched_priority == LOOP_PRIORITY
    assert os.sched_getscheduler(0) == os.SCHED_OTHER
    with pytest.raises(RuntimeError), realtime_priority():
        raise RuntimeError("the loop failed")
    assert not is_realtime()  # undone on an error too


def test_refused_or_not_wanted_runs_at_normal_priority(monkeypatch):
    def refuse(*_):
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(os, "sched_setscheduler", refuse)
    with realtime_priority() as priority:
        assert priority.startswith("normal: SCHED_FIFO not permitted")
        assert "ulimit -r" in priority
        assert not is_realtime()
    with realtime_priority(wanted=False) as priority:
        assert priority == "normal: not asked for"


@needs_fifo
def test_followers_are_told_and_their_threads_take_it_up():
    """A follower (a helper the loop waits on) is told on entry and exit; one that is
    collected is dropped, not called."""
    class Helper:
        def __init__(self):
            self.told = []
            self.stopped = threading.Event()
            self.thread = threading.Thread(target=self.stopped.wait)

        def follow(self, realtime):
            self.told.append(realtime)
            set_thread_priority(self.thread.native_id, realtime)

    helper, gone = Helper(), Helper()
    helper.thread.start()  # made at normal priority
    add_follower(helper.follow)
    add_follower(gone.follow)
    del gone
    with realtime_priority():
        assert is_realtime(helper.thread.native_id)
    assert helper.told == [True, False]
    assert not is_realtime(helper.thread.native_id)
    helper.stopped.set()
    helper.thread.join()


@pytest.mark.parametrize("runtime_us, period_us, share", [
    ("950000", "1000000", 0.05), ("-1", "1000000", 0.0), ("1000000", "1000000", 0.0),
    ("garbled", "1000000", 0.0)])
def test_the_throttles_share_is_what_the_kernel_keeps(tmp_path, runtime_us, period_us, share):
    files = (tmp_path / "runtime", tmp_path / "period")
    files[0].write_text(runtime_us + "\n")
    files[1].write_text(period_us + "\n")
    assert rt_throttle_share(files) == pytest.approx(share)
    assert rt_throttle_share((tmp_path / "missing", files[1])) == 0.0


@needs_fifo
@pytest.mark.parametrize("compute_us, stays", [(300.0, True), (960.0, False)])
def test_a_loop_with_too_little_sleep_for_the_throttle_goes_back_to_normal(compute_us, stays):
    """Paced at real-time priority, a loop whose ticks leave it time to sleep keeps it;
    one that sleeps less than the throttle's due (on Linux's default, 50 ms a second)
    goes back to normal priority after RT_WINDOW_MIN_SLOTS, and says when,
    rather than be stopped for 50 ms each second."""
    from maglev_haptics.analysis.host_pacing import host_pacing
    from maglev_haptics.diagrams.runner import RT_WINDOW_MIN_SLOTS

    if rt_throttle_share() == 0.0:
        pytest.skip("the kernel's real-time throttle is off here")
    report = host_pacing(1.5 * RT_WINDOW_MIN_SLOTS * 1e-3, compute_us)
    if stays:
        assert report["priority"] == f"SCHED_FIFO {LOOP_PRIORITY}"
    else:
        assert report["priority"].startswith(
            f"SCHED_FIFO {LOOP_PRIORITY} (at normal priority from 0.50 s: its waits left it "
            "less sleep than the real-time throttle's due, 50 ms a second)"), report
    assert not is_realtime()


def test_the_budget_sends_a_loop_back_and_returns_it():
    """RealtimeBudget on a 1 ms slot and the default throttle (50 ms a second): waits
    that leave 0.35 ms of sleep keep real-time priority; a stretch of waits that leave
    none sends it back to normal once its last second slept under 50 ms; waits that
    would sleep 0.35 ms again return it once that second's sleep passes 100 ms."""
    from maglev_haptics.diagrams.runner import RT_SPIN_S, RealtimeBudget

    if rt_throttle_share() == 0.0:
        pytest.skip("the kernel's real-time throttle is off here")
    budget = RealtimeBudget(1e-3)
    waits = [0.35e-3 + RT_SPIN_S] * 1000 + [0.0] * 1000 + [0.35e-3 + RT_SPIN_S] * 1000
    allowed = [budget.add(wait, 1e-3 * k) for k, wait in enumerate(waits)]
    sent_back, returned = allowed.index(False), 2000 + allowed[2000:].index(True)
    # 858 slots of no sleep leave 142 of 0.35 ms (49.7 ms); 286 of 0.35 ms again 100.1.
    assert (sent_back, returned) == (1857, 2285)
    assert budget.stretches == [[pytest.approx(1.857), pytest.approx(2.285)]]
    assert budget.describe().startswith("at normal priority 1.86-2.2")
