"""The deformable surface: a mass-spring-damper lattice stepped at the haptic rate,
touched by the probe on the scene's tool.

.. pydrake_system::

    name: DeformableSurface
    input_ports:
    - X_WT
    - V_WT
    output_ports:
    - wrench_on_tool_W
    - in_contact
    - surface_positions_m

The discrete state is one vector [x; v; X_WT; V_WT]: every mass's position (m)
then velocity (m/s) in W, 3 numbers each, mass by mass, then the tool's pose
[qw, qx, qy, qz, x, y, z] and spatial velocity [wx, wy, wz, vx, vy, vz] in W as
the last update read them from the inputs. Each period the lattice advances one
tick with the configured integrator (``lattice_dynamics``), the probe held at that
stored pose, and the inputs are stored for the next tick. So the lattice and the
tool see each other one tick (1 ms) late, as the paper's unsynchronized physics
thread did, and in exchange the next step is known one tick ahead and runs on
the other core (``lattice_worker``) while the rest of the diagram computes.

``wrench_on_tool_W`` [f; tau] (N, N*m, in W about T's origin) is the contact's
wrench on the tool from the state alone: exactly the opposite of the forces the
next tick applies to the masses (with one substep; with more, the first
substep's). ``in_contact`` is 1.0 while any surface vertex is inside the probe.
``surface_positions_m`` (3 n_s) are the surface vertices' positions, column by
column, for drawing.

Float only: a state of tens of thousands of numbers has no use for AutoDiffXd.
"""

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform
from pydrake.systems.framework import LeafSystem, ValueProducer

from maglev_haptics.systems.lattice_dynamics import (
    LINEARLY_IMPLICIT, LatticeModel, ProbeContact, implicit_workspace, linearly_implicit_tick,
    probe_arguments, state_contact, symplectic_euler_tick)
from maglev_haptics.systems.lattice_worker import LatticeWorker


class DeformableSurface(LeafSystem):
    """See the module docstring."""

    def __init__(self, *, model: LatticeModel, positions_m: np.ndarray, probe: ProbeContact,
                 p_TP_m, X_WT_start: RigidTransform, period_s: float, integrator: str,
                 substeps: int = 1, cg_tolerance: float = 1e-4, cg_max_iterations: int = 40,
                 worker_thread: bool = True):
        """``positions_m`` (n, 3): the masses at rest (m), where the state starts;
        ``p_TP_m`` (3,): the probe sphere's centre in the tool frame T (m);
        ``X_WT_start``: the tool's pose at the start, at rest; ``worker_thread``:
        precompute each next tick on another core (the results are the same)."""
        LeafSystem.__init__(self)
        self._model = model
        self._n = len(positions_m)
        self._probe = probe
        self._p_TP = np.asarray(p_TP_m, dtype=float).copy()
        self._period_s = float(period_s)
        self._implicit = integrator == LINEARLY_IMPLICIT
        self._substeps = int(substeps)
        # The step the contact is applied over first: the tick, or its first substep (s).
        self._first_step_s = (self._period_s if self._implicit
                              else self._period_s / self._substeps)
        self._cg_tolerance = float(cg_tolerance)
        self._cg_max_iterations = int(cg_max_iterations)
        self._external = np.zeros((self._n, 3))
        self._workspace = (implicit_workspace(self._n, len(model.links)) if self._implicit
                           else (np.zeros((self._n, 3)),))
        self._use_worker = worker_thread
        self._worker = None  # started by the first update
        self._surface_rows = np.asarray(model.surface)
        self._constants = np.array([probe.radius_m, probe.stiffness_n_per_m, probe.onset_depth_m,
                                    probe.dissipation_s_per_m, probe.friction,
                                    probe.slip_speed_m_s])
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
    def num_masses(self) -> int:
        return self._n

    def _split(self, state_vector):
        """Views (x (n, 3), v (n, 3), tool (13,)) into a state vector."""
        masses = state_vector[:6 * self._n].reshape(2, self._n, 3)
        return masses[0], masses[1], state_vector[6 * self._n:]

    def _calc_contact(self, context, value):
        value.set_value(state_contact(context.get_discrete_state(self._state).get_value(),
                                      self._model.surface, self._p_TP, self._constants,
                                      self._model.mass_kg, self._first_step_s))

    def _calc_wrench(self, context, output):
        output.SetFromVector(self._contact.Eval(context)[0])

    def _calc_in_contact(self, context, output):
        output.SetFromVector([1.0 if self._contact.Eval(context)[1] > 0 else 0.0])

    def _calc_surface(self, context, output):
        x, _, _ = self._split(context.get_discrete_state(self._state).get_value())
        output.SetFromVector(x[self._surface_rows].ravel())

    def _step(self, x, v, tool):
        """One tick of (x, v) in place, synchronously."""
        m = self._model
        probe = probe_arguments(tool, self._p_TP)
        common = (x, v, *m.topology, m.rest_lengths_m, m.stiffness_n_per_m, m.damping_n_s_per_m,
                  m.mass_kg, m.inv_mass_per_kg, m.gravity_m_s2, m.surface, self._external,
                  probe[0:3], probe[3:6], probe[6:9], *self._constants, self._period_s)
        if self._implicit:
            linearly_implicit_tick(*common, self._cg_tolerance, self._cg_max_iterations,
                                   *self._workspace)
        else:
            symplectic_euler_tick(*common, self._substeps, *self._workspace)

    def _start_worker(self):
        self._worker = LatticeWorker(
            self._model, self._n, (*self._constants, self._period_s, self._cg_tolerance),
            implicit=self._implicit, substeps=self._substeps,
            cg_max_iterations=self._cg_max_iterations)

    def _update(self, context, discrete_state):
        current = context.get_discrete_state(self._state).get_value()
        # The update's state starts as a copy of the context's: step it in place.
        new = discrete_state.get_mutable_vector(self._state).get_mutable_value()
        x, v, tool = self._split(new)
        if self._use_worker and self._worker is None:
            self._start_worker()
        if self._worker is None or not self._worker.result_into(current, new):
            self._step(x, v, tool)
        tool[0:7] = self._X_WT.Eval(context)
        tool[7:13] = self._V_WT.Eval(context)
        if self._worker is not None:
            self._worker.request(new, self._p_TP)
