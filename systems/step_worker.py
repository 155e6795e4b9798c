"""A core of its own for a deformable body: the next tick's step, computed while the
rest of the diagram runs (the paper ran its physics in a thread of its own too).

The ``DeformableBody`` update at tick k knows everything the update at k+1 will
need (the state it writes), so it hands that to the worker, which steps a private
copy of the body on the machine's other core, outside Python's GIL, while the
other systems compute. At k+1 the update takes the worker's result if it was
computed from exactly the state now in the context, and steps synchronously
otherwise (the first tick, a context changed from outside, a busy worker). The
result is bit for bit the synchronous step's: the same tick kernel on the same
numbers. Any model's tick ``tick(masses_in, masses_out, probe, *arguments)`` is
served (masses [x; v], 6 n; probe [p_WP, v_WP, p_WT], 9): ``tick_server`` declares
the loop that runs it, once per model, when the model's module is imported.

Protocol, on ``control`` (int64): [0] stop flag, [1] the sequence number of the
last request, [2] that of the last finished step, [3] 1 while the paced loop runs
at real-time priority (``hardware/realtime_priority.py``), which the worker then
shares, polling by sleeping RT_POLL_US rather than yielding (a SCHED_FIFO thread
that never sleeps is throttled by the kernel for 50 ms a second), [4] which of the
two mass buffers holds the request's input (the other gets the result), [5] how long
the worker's last step took (ns, CLOCK_MONOTONIC, timed around the tick alone). The main
thread writes the inputs only while the worker is idle ([1] == [2]) and then bumps
[1]; the worker polls [1], steps, and sets [2]. A tick that took the worker's result
asks for the next from that result: the buffers swap roles and no state is copied
in; the update checks the state against the input with one compiled compare. x86
keeps stores in order, and an opaque libc call before [2] is set keeps the
compiler from moving the result's stores after it. During a run a request comes
every tick and the worker polls by yielding its core (``sched_yield``: no timer
slack, and other processes go first); idle for FAST_POLLS looks it sleeps
IDLE_POLL_US between them, and after IDLE_EXIT_POLLS of those (~0.5 s) it ends (a
pydrake diagram keeps its Python systems alive, so a worker must not outlive its
use); the next request starts a new one.

Each result taken records its step's duration (``step_us``): the other core's tick as
the loop ran it, beside the rest of the diagram (on a 2-core machine 0.8-1.4 times the
kernel timed alone, as the machine's load came and went).
"""

import ctypes
import threading
import weakref

import numpy as np
from numba import types

from maglev_haptics.hardware.kernels import FLAG, INDEX_VECTOR, READONLY_VECTOR, VECTOR, kernel
from maglev_haptics.hardware.realtime_priority import (
    RT_POLL_US, add_follower, is_realtime, set_thread_priority)
from maglev_haptics.systems.lattice_dynamics import probe_point

FAST_POLLS = 20000  # looks by yielding (~5-10 ms idle) before the worker sleeps between them
IDLE_POLL_US = 1000  # (us)
IDLE_EXIT_POLLS = 500  # and after this many slow looks (~0.5 s) it ends
_STOP, _REQUESTED, _DONE, _POLL_BY_SLEEPING, _INPUT, _STEP_NS = 0, 1, 2, 3, 4, 5
_CONTROL_SIZE = 6
STEP_TIMES_KEPT = 1 << 17  # the last this many steps' durations (~131 s at 1 kHz)
_CLOCK_MONOTONIC = 1
_COMPARE_CHUNK = 512  # numbers compared between looks for a difference

_libc = ctypes.CDLL(None)
_usleep = _libc.usleep
_usleep.argtypes = [ctypes.c_uint]
_usleep.restype = ctypes.c_int
_sched_yield = _libc.sched_yield
_sched_yield.argtypes = []
_sched_yield.restype = ctypes.c_int
_clock_gettime = _libc.clock_gettime
_clock_gettime.argtypes = [ctypes.c_int, ctypes.c_void_p]
_clock_gettime.restype = ctypes.c_int


@kernel((INDEX_VECTOR,), cache=False, nogil=True)
def _monotonic_ns(timespec):
    """CLOCK_MONOTONIC (ns), through ``timespec`` (2,) int64 work space."""
    _clock_gettime(_CLOCK_MONOTONIC, timespec.ctypes)
    return timespec[0] * 1_000_000_000 + timespec[1]


def tick_server(tick, argument_types: tuple):
    """The worker loop ``serve(control, masses_a, masses_b, probe, arguments)`` for
    ``tick(masses_in, masses_out, probe, *arguments)``, ``arguments`` of the numba
    types ``argument_types``: it runs ``tick(masses_a, masses_b, probe, *arguments)``
    (a and b swapped where control[_INPUT] is 1) for every request until the stop
    flag is set. Declared with ``kernel``, so ``compile_kernels`` compiles it before
    the clock starts; call this once per tick, at import."""

    # Not cached (numba cannot cache code that calls a ctypes function), so kept small:
    # the tick it calls comes compiled from the cache. A tick lives with the kernels it
    # calls: numba's cache goes stale only when the function's own file changes.
    @kernel((INDEX_VECTOR, VECTOR, VECTOR, VECTOR, types.Tuple(tuple(argument_types))),
            cache=False, nogil=True)
    def serve(control, masses_a, masses_b, probe, arguments):
        done = control[_DONE]
        idle = 0
        timespec = np.zeros(2, dtype=np.int64)
        while control[_STOP] == 0:
            sequence = control[_REQUESTED]
            if sequence == done:
                idle += 1
                if idle > FAST_POLLS + IDLE_EXIT_POLLS:
                    return
                if idle > FAST_POLLS:
                    _usleep(IDLE_POLL_US)
                elif control[_POLL_BY_SLEEPING]:
                    _usleep(RT_POLL_US)
                else:
                    _sched_yield()
                continue
            idle = 0
            start_ns = _monotonic_ns(timespec)
            if control[_INPUT] == 0:
                tick(masses_a, masses_b, probe, *arguments)
            else:
                tick(masses_b, masses_a, probe, *arguments)
            control[_STEP_NS] = _monotonic_ns(timespec) - start_ns
            _usleep(0)  # a compiler barrier: the result is stored before it is announced
            control[_DONE] = sequence
            done = sequence
    return serve


@kernel((READONLY_VECTOR, VECTOR, VECTOR), (VECTOR, VECTOR, VECTOR))
def _is_state(state, masses, tool):
    """state == [masses; tool] exactly (as np.array_equal), the tool's first; a chunk
    at a time, so the compare vectorizes and stops soon after a difference."""
    split = masses.shape[0]
    for i in range(tool.shape[0]):
        if state[split + i] != tool[i]:
            return False
    for start in range(0, split, _COMPARE_CHUNK):
        differs = False
        for i in range(start, min(start + _COMPARE_CHUNK, split)):
            differs |= state[i] != masses[i]
        if differs:
            return False
    return True


@kernel((VECTOR, VECTOR, VECTOR, VECTOR, VECTOR, FLAG))
def _store_request(state, p_TP, masses, tool, probe, copy_masses):
    """[masses; tool] = state (the masses only where ``copy_masses``), and probe =
    [p_WP, v_WP, p_WT] at that tool state."""
    split = masses.shape[0]
    if copy_masses:
        masses[:] = state[:split]
    tool[:] = state[split:]
    p_WP, v_WP = probe_point(tool[0:7], tool[7:13], p_TP)
    probe[0:3] = p_WP
    probe[3:6] = v_WP
    probe[6:9] = tool[4:7]


def other_core_report(step_us: np.ndarray, ticks_there: int, ticks_here: int) -> dict:
    """summary.json's account of a body's ticks: how many the worker stepped
    (``ticks_there``) and how long it took over them (``step_us``, us, the last
    STEP_TIMES_KEPT: median, 99th percentile, longest), and how many the update
    stepped on the loop's thread (``ticks_here``)."""
    timed = step_us.size > 0
    return {
        "ticks_on_other_core": int(ticks_there),
        "ticks_stepped_here": int(ticks_here),
        "other_core_tick_us_p50": float(np.percentile(step_us, 50)) if timed else 0.0,
        "other_core_tick_us_p99": float(np.percentile(step_us, 99)) if timed else 0.0,
        "other_core_tick_us_max": float(step_us.max()) if timed else 0.0,
    }


def _stop(control: np.ndarray) -> None:
    control[_STOP] = 1


class StepWorker:
    """The worker thread and its private copy of a deformable body (see the module
    docstring)."""

    def __init__(self, server, num_nodes: int, tick_arguments: tuple):
        """``server``: the loop ``tick_server`` declared for the body's tick;
        ``num_nodes``: n; ``tick_arguments``: the tick's arguments after the probe, the
        worker's own (no work space shared with another caller of the tick)."""
        self._server = server
        self._control = np.zeros(_CONTROL_SIZE, dtype=np.int64)
        # Two buffers of [x; v] (6 n): a request's input in one ([_INPUT]), the step's
        # result in the other; the request's tool state (13) and probe point (9).
        self._masses = (np.zeros(6 * num_nodes), np.zeros(6 * num_nodes))
        self._tool_in = np.zeros(13)
        self._probe = np.zeros(9)
        self._pending = False  # a request not yet taken
        self._filled = None  # the array result_into last wrote the result into
        self._arguments = tuple(tick_arguments)
        self._step_ns = np.zeros(STEP_TIMES_KEPT, dtype=np.int64)  # a ring of the steps taken
        self._steps_taken = 0
        self._thread = None
        weakref.finalize(self, _stop, self._control)
        add_follower(self._follow_loop)

    def _follow_loop(self, realtime: bool) -> None:
        """The paced loop entered (True) or left real-time priority: so does the worker."""
        self._control[_POLL_BY_SLEEPING] = realtime
        if self._thread is not None and self._thread.is_alive():
            set_thread_priority(self._thread.native_id, realtime)

    def idle(self) -> bool:
        return self._control[_REQUESTED] == self._control[_DONE]

    def _ensure_running(self) -> None:
        if self._thread is not None and self._thread.is_alive():
            return
        # A worker that ended idle may have left a request unserved: drop it.
        self._control[_DONE] = self._control[_REQUESTED]
        # Started by a loop at real-time priority, it has that priority: it must sleep.
        self._control[_POLL_BY_SLEEPING] = is_realtime()
        self._thread = threading.Thread(
            target=self._server, args=(self._control, *self._masses, self._probe, self._arguments),
            daemon=True, name="step-worker")
        self._thread.start()

    def request(self, state: np.ndarray, p_TP: np.ndarray) -> bool:
        """Start a tick from ``state`` ([x; v; tool], 6 n + 13), the probe's centre at
        ``p_TP`` (m) in the tool's frame. False, and nothing started, while the worker
        is busy. Where ``state`` is the array ``result_into`` just wrote the result
        into (its masses unchanged since: only the tool's part may be), the worker
        steps on from its own copy of that result, and nothing of the masses is copied."""
        self._ensure_running()
        if not self.idle():
            return False
        continues = state is self._filled
        self._filled = None
        if continues:  # the last result is the next input: the buffers swap roles
            self._control[_INPUT] = 1 - self._control[_INPUT]
        _store_request(state, p_TP, self._masses[self._control[_INPUT]], self._tool_in,
                       self._probe, not continues)
        self._pending = True
        self._control[_REQUESTED] += 1
        return True

    def result_into(self, state: np.ndarray, out: np.ndarray) -> bool:
        """out[:6 n] = [x; v] one tick after exactly ``state``, waiting for the worker
        if it is on it; False, and ``out`` untouched, if it was not asked for that state."""
        self._filled = None
        source = self._control[_INPUT]
        if not (self._pending and _is_state(state, self._masses[source], self._tool_in)):
            return False
        self._pending = False
        while not self.idle():  # the worker is within a tick of done
            if not self._thread.is_alive():
                return False  # it ended before it saw the request
            _sched_yield()  # a process on the other core must not keep the worker waiting
        result = self._masses[1 - source]
        out[:len(result)] = result
        self._filled = out
        self._step_ns[self._steps_taken % STEP_TIMES_KEPT] = self._control[_STEP_NS]
        self._steps_taken += 1
        return True

    @property
    def steps_taken(self) -> int:
        """How many of the worker's results ``result_into`` gave."""
        return self._steps_taken

    def step_us(self) -> np.ndarray:
        """How long the worker took over each step whose result was taken (us), the
        last STEP_TIMES_KEPT of them, oldest first."""
        if self._steps_taken <= STEP_TIMES_KEPT:
            return 1e-3 * self._step_ns[:self._steps_taken]
        return 1e-3 * np.roll(self._step_ns, -(self._steps_taken % STEP_TIMES_KEPT))
