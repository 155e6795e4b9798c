"""The rigid scene's plant, stepped in a worker process (``systems/scene_worker.py``)
on the machine's other core, as a system of the diagram.

The discrete update of tick k computes x_{k+1} = f(x_k, u_k) from the plant's
state x_k = [q; v] and the coupling's wrench on the tool u_k. Both are known
once tick k-1's update has been applied, so a periodic publish at tick k's time
(which the Simulator handles at the end of the step that reaches it, before
that time's updates) hands (x_k, u_k) to the worker; tick k's update then takes
x_{k+1} from it. The worker steps while this process sleeps to its slot (a
paced run) or updates every other system of the tick. The contact sample (the
wrench on the tool and the contact flag at (x_k, u_k), which a ZeroOrderHold
takes in place every ``contact_period_s``) comes with the step when the two
fall at one time.

Every result is computed from exactly the state and input of the context it is
written to, by the same plant and code, so it is bit for bit what the plant
stepped in place gives. Where the worker was not asked about the context's
(x, u) (a context changed from outside, an update called directly, a contact
sample between ticks), or has not yet taken the request up (no free core: the
process it would wait for is not running), the update steps ``local``, a copy
of the plant in this process, instead of waiting. After MISSES_TO_PAUSE such
misses in a row (a machine with no core to spare) it is not asked for a pause
(wall-clock) that starts at PAUSE_S and doubles, up to MAX_PAUSE_S, each time
it misses again after one, until it keeps up: fed while it cannot keep up, it
took CPU time from its parent and did work thrown away (a loaded two-core
machine ran 20-50% slower than in place, measured). A worker that has died, or
has been on one request for its HUNG_S, raises a RuntimeError.
"""

import time

import numpy as np
from pydrake.systems.framework import LeafSystem

from maglev_haptics.systems.scene_worker import CONTACT, CONTACT_SIZE, STEP, SceneWorker

MISSES_TO_PAUSE = 3
PAUSE_S = 0.1  # (s)
MAX_PAUSE_S = 0.8  # (s): shorter than the worker's IDLE_EXIT_S, so it stays started


def falls_on(t: float, period_s: float) -> bool:
    """Whether a periodic event of ``period_s`` (offset 0) falls at ``t`` (s): the
    Simulator times those at m * period_s exactly."""
    return round(t / period_s) * period_s == t


class RemoteScene(LeafSystem):
    """The scene plant's state, stepped by ``worker`` (or ``local``).

    .. pydrake_system::

        name: RemoteScene
        input_ports:
        - wrench_on_tool_W
        output_ports:
        - x
        - contact_wrench_on_tool_W
        - in_contact

    ``wrench_on_tool_W`` [fx, fy, fz, tx, ty, tz] in W (N, N*m) is the plant's
    applied wrench on the tool (the in-place plant's MatrixGain input). ``x`` is
    the plant's state [q; v] (``x0`` at the start); ``contact_wrench_on_tool_W``
    and ``in_contact`` are the tool contact sensor's outputs (N, N*m; 1.0 or 0.0)
    sampled every ``contact_period_s`` (s), as the in-place holds do.
    ``local(kind, [x; u], result)`` computes what the worker does, in this process.
    """

    def __init__(self, worker: SceneWorker, local, *, x0: np.ndarray, period_s: float,
                 contact_period_s: float):
        LeafSystem.__init__(self)
        self._worker = worker
        self._local = local
        self._n = n = len(x0)
        self._local_request = np.zeros(n + 6)
        self._local_result = np.zeros(n + CONTACT_SIZE)
        self._contact_period_s = contact_period_s
        self._misses = 0  # requests in a row that the worker had not taken up in time
        self._paused_until = 0.0  # (perf_counter, s)
        self._pause_s = PAUSE_S  # the next pause
        self._u = self.DeclareVectorInputPort("wrench_on_tool_W", 6)
        self._x = self.DeclareDiscreteState(np.asarray(x0, dtype=float))
        self._wrench = self.DeclareDiscreteState(6)
        self._in_contact = self.DeclareDiscreteState(1)
        self.DeclarePeriodicPublishEvent(period_s, 0.0, self._request)
        self.DeclarePeriodicDiscreteUpdateEvent(period_s, 0.0, self._step)
        self.DeclarePeriodicDiscreteUpdateEvent(contact_period_s, 0.0, self._sample_contact)
        self.DeclareStateOutputPort("x", self._x)
        self.DeclareStateOutputPort("contact_wrench_on_tool_W", self._wrench)
        self.DeclareStateOutputPort("in_contact", self._in_contact)

    @property
    def worker(self) -> SceneWorker:
        return self._worker

    def _request(self, context):
        worker = self._worker
        worker.wait_ready()  # Simulator.Initialize publishes: before the clock starts
        # Still on an earlier request, or not asked for now: this tick steps here. A
        # dead or hung worker is an error, not a run stepped here for ever.
        if not worker.idle() or time.perf_counter() < self._paused_until:
            worker.check()
            return
        kind = STEP | (CONTACT if falls_on(context.get_time(), self._contact_period_s) else 0)
        worker.request(context.get_discrete_state(self._x).value(),
                       self._u.EvalBasicVector(context).value(), kind)

    def _result(self, context, kind: int) -> np.ndarray:
        """[x_next; contact] at the context's (x, u): the worker's if it is on it, else
        computed here."""
        x = context.get_discrete_state(self._x).value()
        u = self._u.EvalBasicVector(context).value()  # a view: copied below, or compared
        worker = self._worker
        if worker.answers(x, u, kind):
            if worker.started():
                self._misses = 0
                self._pause_s = PAUSE_S
                return worker.wait()
            self._misses += 1
            if self._misses == MISSES_TO_PAUSE:
                self._misses = 0
                self._paused_until = time.perf_counter() + self._pause_s
                self._pause_s = min(2 * self._pause_s, MAX_PAUSE_S)
        request = self._local_request
        request[:self._n] = x
        request[self._n:] = u
        self._local(kind, request, self._local_result)
        return self._local_result

    def _step(self, context, discrete_state):
        discrete_state.get_mutable_vector(self._x).SetFromVector(
            self._result(context, STEP)[:self._n])

    def _sample_contact(self, context, discrete_state):
        result = self._result(context, CONTACT)
        discrete_state.get_mutable_vector(self._wrench).SetFromVector(
            result[self._n:self._n + 6])
        discrete_state.get_mutable_vector(self._in_contact).SetAtIndex(0, result[self._n + 6])
