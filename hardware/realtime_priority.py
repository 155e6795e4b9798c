"""Real-time priority for a paced loop: SCHED_FIFO, where the OS grants it.

At normal priority every other runnable thread on the machine, the kernel's own
included, shares the loop's core by time slices: the loop loses single ticks of
1-4 ms at no fixed period (this VM's memory monitor, ``kdamond``, alone runs about
twelve times a second for about a millisecond). A SCHED_FIFO thread is preempted
by no normal-priority thread. Measured, peg_in_hole paced for 15 s on the 2-core
machine while two test runs loaded it: 1,021 and 10,804 of 15,000 ticks missed at
normal priority, 36 and 37 at SCHED_FIFO.

A SCHED_FIFO thread that never blocks owns its core, and Linux's throttle
(``/proc/sys/kernel/sched_rt_runtime_us``: 950 ms of each second) then stops it
for 50 ms: so at real-time priority the loop sleeps until RT_SPIN_S before each
slot. A loop whose ticks leave it too little of that sleep cannot stay at
real-time priority: measured on a 2-core machine, a loop spinning 880 us of each
1 ms slot slept not at all, met the throttle, stopped 53 ms each second and missed
63 % of its slots (2.9 % at normal priority). So a loop that slept less than the
throttle's due (``rt_throttle_share`` of its last second) goes back to normal
priority (``set_loop_realtime``) until its ticks would leave it twice that
(``runner.RealtimeBudget``). The helpers it waits on (the scene worker process, the
lattice's worker thread), told as followers, take up the same priority, and the
scene worker sleeps between requests and the lattice's worker polls by sleeping
RT_POLL_US. Work the
loop does not wait on (the log's writer thread) runs at BACKGROUND_PRIORITY, just
below: above every normal thread, preempted at once by the loop and its helpers.
Measured, deformable_surface paced for 30 s: with the writer at the loop's priority,
each half-second chunk it wrote held the other core for ~1 ms, the lattice's worker
waited for it and the loop for the lattice (92 of 30,000 ticks missed, one every
half second).

Granted to root, to a process with CAP_SYS_NICE, or up to ``ulimit -r``
(RLIMIT_RTPRIO, e.g. ``@realtime - rtprio 20`` in /etc/security/limits.conf).
"""

from __future__ import annotations

import os
import weakref
from pathlib import Path
from contextlib import contextmanager
from typing import Callable, Iterator

# SCHED_FIFO priority (1-99) of the loop: above every normal thread, below the
# interrupt threads of a PREEMPT_RT kernel (50), which the loop's I/O needs.
LOOP_PRIORITY = 10
# SCHED_FIFO priority of the loop's background work (the log's writer): a woken
# thread of the loop's priority takes the core from it at once, where one of equal
# priority would wait until it blocked.
BACKGROUND_PRIORITY = LOOP_PRIORITY - 1
# At real-time priority the wait for a slot sleeps until this long before it, then
# spins (s): a woken SCHED_FIFO thread runs within tens of microseconds.
RT_SPIN_S = 150e-6
# A helper thread at real-time priority polls for requests this often (us): no timer
# slack at SCHED_FIFO, a few microseconds a look.
RT_POLL_US = 20
# A loop sent back to normal priority returns once its waits would sleep this many
# times the throttle's due (-): less, and one slow second would send it back again.
RT_RETURN_MARGIN = 2.0
RT_THROTTLE_FILES = ("/proc/sys/kernel/sched_rt_runtime_us",
                     "/proc/sys/kernel/sched_rt_period_us")


# Told when the loop enters (True) and leaves (False) real-time priority: the helper
# threads it waits on, which take up its priority and stop polling by spinning.
_followers: list = []  # weakref.WeakMethod


def add_follower(method: Callable[[bool], None]) -> None:
    """``method(realtime)``, a bound method held weakly, is called as the loop enters
    (True) and leaves (False) real-time priority (``realtime_priority``)."""
    _followers.append(weakref.WeakMethod(method))


def _tell_followers(realtime: bool) -> None:
    _followers[:] = [ref for ref in _followers if ref() is not None]
    for ref in list(_followers):
        method = ref()
        if method is not None:
            method(realtime)


def set_thread_priority(thread_id: int, realtime: bool,
                        priority: int = LOOP_PRIORITY) -> None:
    """Thread ``thread_id`` (a native id) at SCHED_FIFO ``priority`` or back to normal;
    no change where that is refused or the thread has ended."""
    try:
        if realtime:
            os.sched_setscheduler(thread_id, os.SCHED_FIFO, os.sched_param(priority))
        else:
            os.sched_setscheduler(thread_id, os.SCHED_OTHER, os.sched_param(0))
    except (PermissionError, ProcessLookupError):
        pass


def rt_throttle_share(throttle_files=RT_THROTTLE_FILES) -> float:
    """The share of each period (-) the kernel's throttle keeps from real-time
    threads (1 - runtime / period, read from ``throttle_files``, us): 0.05 by
    default; 0 where the throttle is off (runtime -1) or cannot be read."""
    try:
        runtime_us, period_us = (int(Path(path).read_text()) for path in throttle_files)
    except (OSError, ValueError):
        return 0.0
    if runtime_us < 0 or period_us <= 0:
        return 0.0
    return max(0.0, 1.0 - runtime_us / period_us)


def set_loop_realtime(realtime: bool) -> None:
    """Inside ``realtime_priority``: the calling thread back at normal priority
    (False) or at SCHED_FIFO LOOP_PRIORITY again (True), and the followers told
    (``add_follower``); its exit restores what it found."""
    set_thread_priority(0, realtime)
    _tell_followers(realtime)


def is_realtime(pid: int = 0) -> bool:
    """Whether thread ``pid`` (0: the calling thread) runs at SCHED_FIFO."""
    return os.sched_getscheduler(pid) == os.SCHED_FIFO


@contextmanager
def realtime_priority(wanted: bool = True) -> Iterator[str]:
    """The calling thread at SCHED_FIFO LOOP_PRIORITY while entered, where the OS
    grants it, and the followers told (``add_follower``); yields what it runs at
    (``"SCHED_FIFO 10"``, or ``"normal: why"``). Threads and processes it starts
    meanwhile inherit the priority."""
    if not wanted:
        yield "normal: not asked for"
        return
    before = os.sched_getscheduler(0), os.sched_getparam(0)
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(LOOP_PRIORITY))
    except PermissionError:
        yield ("normal: SCHED_FIFO not permitted (run as root, give the interpreter "
               "CAP_SYS_NICE, or raise `ulimit -r`)")
        return
    try:
        _tell_followers(True)
        yield f"SCHED_FIFO {LOOP_PRIORITY}"
    finally:
        _tell_followers(False)
        os.sched_setscheduler(0, *before)


def fifo_permitted() -> bool:
    """Whether this process may run a thread at SCHED_FIFO (tried and undone)."""
    with realtime_priority() as priority:
        return priority.startswith("SCHED_FIFO")
