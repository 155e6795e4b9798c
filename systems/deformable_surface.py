"""A deformable body stepped at the haptic rate by its model's compiled tick, touched
by the probe on the scene's tool: the paper's lattice (``lattice_dynamics``) or any
other model whose tick keeps the same state layout and contact.

.. pydrake_system::

    name: DeformableBody
    input_ports:
    - X_WT
    - V_WT
    output_ports:
    - wrench_on_tool_W
    - in_contact
    - surface_positions_m

The discrete state is one vector [x; v; X_WT; V_WT]: every node's position (m)
then velocity (m/s) in W, 3 numbers each, node by node, then the tool's pose
[qw, qx, qy, qz, x, y, z] and spatial velocity [wx, wy, wz, vx, vy, vz] in W as
the last update read them from the inputs. Each period the body advances one
tick with its model's tick kernel, the probe held at that stored pose, and the
inputs are stored for the next tick. So the body and the tool see each other one
tick (1 ms) late, as the paper's unsynchronized physics thread did, and in
exchange the next step is known one tick ahead and runs on the other core
(``step_worker``) while the rest of the diagram computes.

``wrench_on_tool_W`` [f; tau] (N, N*m, in W about T's origin) is the contact's
wrench on the tool from the state alone: exactly the opposite of the forces the
next tick applies to the nodes (over the model's first contact step: with
substeps, the first substep's; ``DeformableDynamics.state_contact``). ``in_contact``
is 1.0 while the probe presses anything (the lattice: a surface node; tissue: a
point of its boundary triangles). ``surface_positions_m`` (3 n_s) are the surface nodes'
positions, column by column, for drawing.

Float only: a state of tens of thousands of numbers has no use for AutoDiffXd.
"""

from typing import Callable, NamedTuple

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform
from pydrake.systems.framework import LeafSystem, ValueProducer

from maglev_haptics.systems.lattice_dynamics import probe_arguments
from maglev_haptics.systems.step_worker import StepWorker, other_core_report


class DeformableDynamics(NamedTuple):
    """What ``DeformableBody`` needs of a deformable model: its tick and where the
    probe touches it. The tick is a ``kernel`` (``hardware/kernels.py``),
    ``tick(masses_in, masses_out, probe, *tick_arguments())``: ``masses_out`` ([x; v],
    6 n) one tick from ``masses_in`` (the same array for a step in place), the probe
    [p_WP, v_WP, p_WT] (9) held; ``state_contact`` the contact's wrench on the tool
    that tick applies from a state."""

    node_mass_kg: np.ndarray  # (n,) every node's mass (kg): caps the contact's damping
    surface_nodes: np.ndarray  # (n_s,) int64 indices of the nodes the probe touches
    tick: Callable  # the model's tick kernel
    # A new tuple of the tick's arguments after the probe, its own work space each call
    # (the model's read-only arrays may be shared): the worker and the update each get one.
    tick_arguments: Callable[[], tuple]
    server: Callable  # the worker loop ``step_worker.tick_server`` declared for ``tick``
    # (wrench on the tool [f; tau] in W about T's origin, count in contact) =
    # state_contact(state [x; v; X_WT; V_WT], p_TP): the opposite of the contact forces
    # the tick's first contact step (a tick or a substep) applies from that state.
    state_contact: Callable


class DeformableBody(LeafSystem):
    """See the module docstring."""

    def __init__(self, *, dynamics: DeformableDynamics, positions_m: np.ndarray, p_TP_m,
                 X_WT_start: RigidTransform, period_s: float, worker_thread: bool = True):
        """``positions_m`` (n, 3): the nodes at rest (m), where the state starts;
        ``p_TP_m`` (3,): the probe sphere's centre in the tool frame T (m);
        ``X_WT_start``: the tool's pose at the start, at rest; ``period_s``: the tick (s);
        ``worker_thread``: precompute each next tick on another core (the results are
        the same)."""
        LeafSystem.__init__(self)
        self._dynamics = dynamics
        self._n = len(positions_m)
        if len(dynamics.node_mass_kg) != self._n:
            raise ValueError(f"dynamics.node_mass_kg has {len(dynamics.node_mass_kg)} masses: "
                             f"must have one a node of positions_m ({self._n})")
        self._p_TP = np.asarray(p_TP_m, dtype=float).copy()
        self._tick_arguments = dynamics.tick_arguments()
        self._use_worker = worker_thread
        self._worker = None  # started by the first update
        self._ticks_here = 0  # updates that stepped the body on this thread
        self._surface_rows = np.asarray(dynamics.surface_nodes)
        self._X_WT = self.DeclareVectorInputPort("X_WT", 7)
        self._V_WT = self.DeclareVectorInputPort("V_WT", 6)
        q = X_WT_start.rotation().ToQuaternion()
        tool = np.concatenate(([q.w(), q.x(), q.y(), q.z()], X_WT_start.translation(),
                               np.zeros(6)))
        initial = np.concatenate((np.asarray(positions_m, float).ravel(), np.zeros(3 * self._n),
                                  tool))
        self._state = self.DeclareDiscreteState(initial)
        self.DeclarePeriodicDiscreteUpdateEvent(period_s, 0.0, self._update)
        self._contact = self.DeclareCacheEntry(
            description="probe contact",
            value_producer=ValueProducer(allocate=AbstractValue.Make(()).Clone,
                                         calc=self._calc_contact),
            prerequisites_of_calc={self.xd_ticket()})
        self.DeclareVectorOutputPort("wrench_on_tool_W", 6, self._calc_wrench,
                                     prerequisites_of_calc={self._contact.ticket()})
        self.DeclareVectorOutputPort("in_contact", 1, self._calc_in_contact,
                                     prerequisites_of_calc={self._contact.ticket()})
        self.DeclareVectorOutputPort("surface_positions_m", 3 * len(self._surface_rows),
                                     self._calc_surface, prerequisites_of_calc={self.xd_ticket()})

    @property
    def num_nodes(self) -> int:
        return self._n

    def step_report(self) -> dict:
        """Where this body's ticks were stepped (``step_worker.other_core_report``):
        by the worker, with how long it took over them (us, timed around its tick),
        and on the loop's thread (the first tick, a context changed from outside, a
        worker not yet done with an earlier request, or none)."""
        if self._worker is None:
            return other_core_report(np.zeros(0), 0, self._ticks_here)
        return other_core_report(self._worker.step_us(), self._worker.steps_taken,
                                 self._ticks_here)

    def _calc_contact(self, context, value):
        value.set_value(self._dynamics.state_contact(
            context.get_discrete_state(self._state).get_value(), self._p_TP))

    def _calc_wrench(self, context, output):
        output.SetFromVector(self._contact.Eval(context)[0])

    def _calc_in_contact(self, context, output):
        output.SetFromVector([1.0 if self._contact.Eval(context)[1] > 0 else 0.0])

    def _calc_surface(self, context, output):
        x = context.get_discrete_state(self._state).get_value()[:3 * self._n].reshape(-1, 3)
        output.SetFromVector(x[self._surface_rows].ravel())

    def _update(self, context, discrete_state):
        current = context.get_discrete_state(self._state).get_value()
        # The update's state starts as a copy of the context's: step it in place.
        new = discrete_state.get_mutable_vector(self._state).get_mutable_value()
        masses, tool = new[:6 * self._n], new[6 * self._n:]
        if self._use_worker and self._worker is None:
            self._worker = StepWorker(self._dynamics.server, self._n,
                                      self._dynamics.tick_arguments())
        if self._worker is None or not self._worker.result_into(current, new):
            self._ticks_here += 1
            self._dynamics.tick(masses, masses, probe_arguments(tool, self._p_TP),
                                *self._tick_arguments)
        tool[0:7] = self._X_WT.Eval(context)
        tool[7:13] = self._V_WT.Eval(context)
        if self._worker is not None:
            self._worker.request(new, self._p_TP)
