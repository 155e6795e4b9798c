"""A core of its own for the rigid scene's plant: a worker process that steps a
private copy of it while the rest of the tick runs.

A Drake plant advanced in a Python thread overlaps nothing (the Simulator holds
the GIL), so the copy lives in another process, started with the scene's config
and building the same plant with the same code (``diagrams/scene_process.py``).
The two share one block of memory (an anonymous ``memfd`` passed to the child)
and hand requests over by sequence numbers, as ``systems/lattice_worker.py``
does with its thread.

Protocol, on ``control`` (int64): [0] stop flag, [1] the sequence number of the
last request, [2] that of the last finished one, [3] the request's kind (a sum
of STEP and CONTACT), [4] 1 once the worker has built its plant (2 once it has
ended idle), [5] 1 if the
last request failed (its message, UTF-8, in ``message``), [6] the sequence
number of the request the worker last took up. The parent writes a request
([x; u] and the kind) only while the worker is idle ([1] == [2]) and then bumps
[1]; the worker sees [1], sets [6], serves it, writes the result, and then sets
[2]. Both are Python, whose statements keep their order, and x86 keeps
stores in order, so a result is whole once [2] says so.

Between requests the worker spins on [1], yielding its core (other processes
go first), for SPIN_S, longer than a tick: during a run it never sleeps. Then
it sets [7] and sleeps on an ``eventfd``, which the parent signals with a
request only while [7] is set. (Signalled every tick, the woken worker was
placed on its parent's core and preempted it: 250-400 us a tick lost on a
loaded two-core machine, measured.) A wake-up lost to the race between the two
(each stores a flag and then loads the other's) costs at most SLEEP_S, during
which ``RemoteScene`` steps the plant itself. The parent, whose wait is short,
spins on [2], yielding its core. The worker takes up the loop's real-time
priority with it (``hardware/realtime_priority.py``: the handle is told as the
loop enters and leaves it; at normal priority under load, a worker preempted
inside a step held the loop for 45-124 ms). At real-time priority the worker
sleeps between requests at once (a SCHED_FIFO process that spins is stopped by
the kernel's throttle for 50 ms a second), and the parent signals each.

The worker ends on the stop flag, when its parent is gone (it checks its
parent's id after every SLEEP_S asleep), or after IDLE_EXIT_S without a request:
a pydrake diagram of this project is not reliably collected (its systems keep it
alive), so a worker must not outlive its use; the next request starts a new one
and waits for it (Simulator.Initialize makes the first, before the clock
starts). The parent sets the flag when the handle is collected or at exit, and
kills a worker that has not ended within STOP_WAIT_S.
"""

import mmap
import os
import pickle
import select
import subprocess
import sys
import time
import weakref

import numpy as np

from maglev_haptics.hardware.realtime_priority import (
    add_follower, is_realtime, set_thread_priority)

STEP, CONTACT = 1, 2  # request kinds: x_{k+1} from (x_k, u_k); the contact sample at (x_k, u_k)
CONTACT_SIZE = 7  # [the contact wrench on the tool (6), in contact (1)]
WRENCH_SIZE = 6
MESSAGE_BYTES = 4096
_STOP, _REQUESTED, _DONE, _KIND, _READY, _FAILED, _TAKEN, _ASLEEP = range(8)
_CONTROL_SIZE = 8
_SERVING, _ENDED = 1, 2  # [4]: 0 while the worker starts

SPIN_S = 0.003  # (s)
SLEEP_S = 0.05  # the longest sleep between looks at [1] and at the parent (s)
IDLE_EXIT_S = 1.0  # (s)
START_TIMEOUT_S = 120.0  # to import Drake and build the plant, on a loaded machine
RESULT_TIMEOUT_S = 1.0  # a step takes under a millisecond: a worker this late is hung
HUNG_S = 10.0  # on one request this long (while its parent steps without it), it is hung
STOP_WAIT_S = 1.0
_CHECK_EVERY = 256  # spins between looks at the clock and the process


class SharedBlock:
    """The shared memory's views: control (int64), request [x; u], result
    [x_next; contact], message (bytes). ``n``: the plant's state size."""

    def __init__(self, buffer, n: int):
        sizes = [_CONTROL_SIZE * 8, 8 * (n + WRENCH_SIZE), 8 * (n + CONTACT_SIZE)]
        starts = np.cumsum([0] + sizes)
        self.control = np.frombuffer(buffer, np.int64, _CONTROL_SIZE, starts[0])
        self.request = np.frombuffer(buffer, np.float64, n + WRENCH_SIZE, starts[1])
        self.result = np.frombuffer(buffer, np.float64, n + CONTACT_SIZE, starts[2])
        self.message = memoryview(buffer)[starts[3]:starts[3] + MESSAGE_BYTES]

    @staticmethod
    def size(n: int) -> int:
        return 8 * (_CONTROL_SIZE + 2 * n + WRENCH_SIZE + CONTACT_SIZE) + MESSAGE_BYTES


def _stop(control: np.ndarray, wake: int, memory_fd: int, processes: list) -> None:
    """Ask the worker to end; kill it if it does not within STOP_WAIT_S."""
    control[_STOP] = 1
    os.eventfd_write(wake, 1)
    for process in processes:
        try:
            process.wait(STOP_WAIT_S)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
    os.close(wake)
    os.close(memory_fd)


class SceneWorker:
    """The parent's handle on a worker process (see the module docstring).

    ``module`` is run in the child with the memory's and the eventfd's file
    descriptors as its arguments and ``payload`` pickled on its standard input;
    ``n`` is the state size of the plant it steps. One request at a time, from one
    thread. The worker starts here; one that ended idle starts again at the next
    request, which waits for it."""

    def __init__(self, module: str, payload, n: int, *, name: str = "scene worker"):
        self._module = module
        self._payload = pickle.dumps(payload)
        self._n = n
        self._name = name
        self._memory_fd = os.memfd_create("maglev-scene-worker")
        os.ftruncate(self._memory_fd, SharedBlock.size(n))
        self._memory = mmap.mmap(self._memory_fd, SharedBlock.size(n))
        self._block = SharedBlock(self._memory, n)
        self._wake = os.eventfd(0)
        self._requested_at = 0.0  # perf_counter of the last request (s)
        self._asked = (b"", 0)  # the last request's [x; u] as bytes, and its kind
        self._processes = []  # the one running last
        weakref.finalize(self, _stop, self._block.control, self._wake, self._memory_fd,
                         self._processes)
        self._start()
        add_follower(self._follow_loop)

    def _follow_loop(self, realtime: bool) -> None:
        """The paced loop entered (True) or left real-time priority: so does the worker
        (one started meanwhile inherits it from the loop's thread)."""
        if self._processes and self._process.poll() is None:  # else its pid may be reused
            set_thread_priority(self._process.pid, realtime)

    def _start(self) -> None:
        self._processes.clear()
        self._block.control[:] = 0
        self._asked = (b"", 0)
        # A process group of its own: the terminal's Ctrl-C goes to the parent alone,
        # which stops the run between ticks and still needs its worker for that.
        process = subprocess.Popen(
            [sys.executable, "-m", self._module, str(self._memory_fd), str(self._wake)],
            stdin=subprocess.PIPE, pass_fds=(self._memory_fd, self._wake), process_group=0,
            env={**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, sys.path))})
        self._processes.append(process)
        process.stdin.write(self._payload)
        process.stdin.close()

    @property
    def _process(self) -> subprocess.Popen:
        return self._processes[0]

    @property
    def pid(self) -> int:
        return self._process.pid

    def _check_alive(self, waiting_for: str) -> None:
        code = self._process.poll()
        if code is not None:
            how = f"killed by signal {-code}" if code < 0 else f"exit status {code}"
            raise RuntimeError(f"the {self._name} (pid {self._process.pid}) died ({how}) while "
                               f"{waiting_for}; its output above says why if it could")

    def _spin(self, done, timeout_s: float, waiting_for: str) -> None:
        """Until ``done()``; a RuntimeError if the worker dies or takes ``timeout_s``."""
        deadline = None
        polls = 0
        while not done():
            polls += 1
            if polls % _CHECK_EVERY == 0:
                now = time.perf_counter()
                deadline = now + timeout_s if deadline is None else deadline
                self._check_alive(waiting_for)
                if now > deadline:
                    raise RuntimeError(
                        f"the {self._name} (pid {self._process.pid}) has not answered in "
                        f"{timeout_s:g} s while {waiting_for}: it is hung or starved")
            os.sched_yield()

    def wait_ready(self) -> None:
        """Until the worker has built its plant, started again if it ended idle (a
        RuntimeError if it dies first)."""
        control = self._block.control
        if control[_READY] == _SERVING:
            return
        if control[_READY] == _ENDED:
            self._process.wait()  # on its way out
            self._start()
        self._spin(lambda: control[_READY] == _SERVING, START_TIMEOUT_S, "starting")

    def idle(self) -> bool:
        return self._block.control[_DONE] == self._block.control[_REQUESTED]

    def check(self) -> None:
        """A RuntimeError if the worker has died, or has been on one request for
        HUNG_S."""
        self._check_alive("stepping the scene")
        if not self.idle() and time.perf_counter() - self._requested_at > HUNG_S:
            raise RuntimeError(
                f"the {self._name} (pid {self._process.pid}) has been on one step for over "
                f"{HUNG_S:g} s: it is hung")

    def request(self, x: np.ndarray, u: np.ndarray, kind: int) -> None:
        """Start serving ``kind`` at state ``x`` (n) and tool wrench ``u`` (6); only
        while the worker is idle."""
        control = self._block.control
        self._block.request[:self._n] = x
        self._block.request[self._n:] = u
        self._asked = (self._block.request.tobytes(), kind)
        control[_KIND] = kind
        self._requested_at = time.perf_counter()
        control[_REQUESTED] += 1
        if control[_ASLEEP]:
            os.eventfd_write(self._wake, 1)

    def answers(self, x: np.ndarray, u: np.ndarray, kind: int) -> bool:
        """Whether the last request asked for ``kind`` at exactly ``x`` and ``u`` (bit
        for bit: -0.0 is not 0.0 here)."""
        asked, asked_kind = self._asked
        return bool(asked_kind & kind) and asked == x.tobytes() + u.tobytes()

    def started(self) -> bool:
        """Whether the worker has taken up the last request (it may be done)."""
        return self._block.control[_TAKEN] == self._block.control[_REQUESTED]

    def wait(self) -> np.ndarray:
        """The last request's result [x_next; contact] (n + 7), once the worker has it
        (a view, valid until the next request)."""
        control = self._block.control
        if control[_DONE] != control[_REQUESTED]:
            self._spin(self.idle, RESULT_TIMEOUT_S, "stepping the scene")
        if control[_FAILED]:
            text = bytes(self._block.message).rstrip(b"\0").decode(errors="replace")
            raise RuntimeError(f"the {self._name} failed: {text}")
        return self._block.result


def serve(block: SharedBlock, wake: int, handle) -> None:
    """The worker's loop: ``handle(kind, request, result)`` for every request until
    the stop flag is set or the parent is gone; ``wake`` the eventfd the parent
    signals."""
    control = block.control
    parent = os.getppid()
    control[_READY] = _SERVING
    done = int(control[_DONE])
    last = time.perf_counter()  # when the last request was served
    spin_s = SPIN_S
    while control[_STOP] == 0:
        sequence = int(control[_REQUESTED])
        if sequence == done:
            idle_s = time.perf_counter() - last
            if idle_s < spin_s:
                os.sched_yield()
                continue
            if idle_s > IDLE_EXIT_S or os.getppid() != parent:
                control[_READY] = _ENDED
                return
            control[_ASLEEP] = 1
            if control[_REQUESTED] == done and select.select([wake], [], [], SLEEP_S)[0]:
                os.eventfd_read(wake)
            control[_ASLEEP] = 0
            continue
        control[_TAKEN] = sequence
        try:
            handle(int(control[_KIND]), block.request, block.result)
            control[_FAILED] = 0
        except Exception as error:  # reported to the parent, which raises it
            text = f"{type(error).__name__}: {error}".encode()[:MESSAGE_BYTES]
            block.message[:] = text + b"\0" * (MESSAGE_BYTES - len(text))
            control[_FAILED] = 1
        control[_DONE] = sequence
        done = sequence
        last = time.perf_counter()
        spin_s = 0.0 if is_realtime() else SPIN_S
