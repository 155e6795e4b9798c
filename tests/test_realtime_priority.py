"""Real-time priority for the paced loop: granted where the OS allows and undone
after, reported either way (the runner's use of it: tests/test_runner.py)."""

import os
import threading

import pytest

from maglev_haptics.hardware.realtime_priority import (
    LOOP_PRIORITY, follow_scheduling, fifo_permitted, is_realtime, realtime_priority)


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
def test_a_thread_follows_the_scheduling_of_another():
    main_thread = threading.get_native_id()
    policies = []
    ready, go = threading.Event(), threading.Event()

    def follower():
        ready.set()
        go.wait()
        follow_scheduling(main_thread)
        policies.append(os.sched_getscheduler(0))
        follow_scheduling(main_thread)  # the main thread is back to normal by now
        policies.append(os.sched_getscheduler(0))

    thread = threading.Thread(target=follower)
    thread.start()  # made at normal priority
    ready.wait()
    with realtime_priority():
        go.set()
        while not policies:
            pass
    thread.join()
    # The second look may still have seen the main thread at SCHED_FIFO: then it kept it.
    assert policies[0] == os.SCHED_FIFO
    assert policies[1] in (os.SCHED_OTHER, os.SCHED_FIFO)
