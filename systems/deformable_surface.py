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

The discrete state is one vector [x; v]: every mass's position (m) then
velocity (m/s) in W, 3 numbers each, mass by mass. Each period the lattice
advances one tick with the configured integrator (``lattice_dynamics``), the
probe held at its pose from ``X_WT``, ``V_WT`` ([qw, qx, qy, qz, x, y, z];
[wx, wy, wz, vx, vy, vz] in W). ``wrench_on_tool_W`` [f; tau] (N, N*m, in W
about T's origin) is the contact's wrench on the tool at the current state and
tool pose: exactly the opposite of the forces the next tick applies to the
masses (with one substep; with more, of the first substep's). ``in_contact`` is
1.0 while any surface vertex is inside the probe. ``surface_positions_m``
(3 n_s) are the surface vertices' positions, column by column, for drawing.

Float only: a state of tens of thousands of numbers has no use for AutoDiffXd.
"""

from __future__ import annotations

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import LeafSystem, ValueProducer

from maglev_haptics.systems.lattice_dynamics import (
    LINEARLY_IMPLICIT, LatticeModel, ProbeContact, implicit_workspace, linearly_implicit_tick,
    probe_point, probe_wrench, symplectic_euler_tick)


class DeformableSurface(LeafSystem):
    """See the module docstring."""

    def __init__(self, *, model: LatticeModel, positions_m: np.ndarray, probe: ProbeContact,
                 p_TP_m, period_s: float, integrator: str, substeps: int = 1,
                 cg_tolerance: float = 1e-4, cg_max_iterations: int = 40):
        """``positions_m`` (n, 3): the masses at rest (m), where the state starts;
        ``p_TP_m`` (3,): the probe sphere's centre in the tool frame T (m)."""
        LeafSystem.__init__(self)
        self._model = model
        self._n = len(positions_m)
        self._probe = probe
        self._p_TP = np.asarray(p_TP_m, dtype=float).copy()
        self._period_s = float(period_s)
        self._implicit = integrator == LINEARLY_IMPLICIT
        self._substeps = int(substeps)
        self._cg_tolerance = float(cg_tolerance)
        self._cg_max_iterations = int(cg_max_iterations)
        self._external = np.zeros((self._n, 3))
        self._workspace = (implicit_workspace(self._n, len(model.links)) if self._implicit
                           else np.zeros((self._n, 3)))
        self._surface_rows = np.asarray(model.surface)
        self._X_WT = self.DeclareVectorInputPort("X_WT", 7)
        self._V_WT = self.DeclareVectorInputPort("V_WT", 6)
        initial = np.concatenate((np.asarray(positions_m, float).ravel(), np.zeros(3 * self._n)))
        self._state = self.DeclareDiscreteState(initial)
        self.DeclarePeriodicDiscreteUpdateEvent(period_s, 0.0, self._update)
        self._contact = self.DeclareCacheEntry(
            description="probe contact",
            value_producer=ValueProducer(allocate=AbstractValue.Make(()).Clone,
                                         calc=self._calc_contact),
            prerequisites_of_calc={self._X_WT.ticket(), self._V_WT.ticket(),
                                   self.xd_ticket()})
        self.DeclareVectorOutputPort("wrench_on_tool_W", 6, self._calc_wrench,
                                     prerequisites_of_calc={self._contact.ticket()})
        self.DeclareVectorOutputPort("in_contact", 1, self._calc_in_contact,
                                     prerequisites_of_calc={self._contact.ticket()})
        self.DeclareVectorOutputPort("surface_positions_m", 3 * len(self._surface_rows),
                                     self._calc_surface, prerequisites_of_calc={self.xd_ticket()})

    @property
    def num_masses(self) -> int:
        return self._n

    def _probe_arguments(self, context):
        X_WT = self._X_WT.Eval(context)
        p_WP, v_WP = probe_point(X_WT, self._V_WT.Eval(context), self._p_TP)
        probe = self._probe
        return (p_WP, v_WP, X_WT[4:7].copy(), probe.radius_m, probe.stiffness_n_per_m,
                probe.onset_depth_m, probe.dissipation_s_per_m, probe.friction, probe.slip_speed_m_s)

    def _positions_velocities(self, state_vector):
        both = state_vector.reshape(2, self._n, 3)
        return both[0], both[1]

    def _calc_contact(self, context, value):
        x, v = self._positions_velocities(context.get_discrete_state(self._state).get_value())
        value.set_value(probe_wrench(x, v, self._model.surface, *self._probe_arguments(context)))

    def _calc_wrench(self, context, output):
        output.SetFromVector(self._contact.Eval(context)[0])

    def _calc_in_contact(self, context, output):
        output.SetFromVector([1.0 if self._contact.Eval(context)[1] > 0 else 0.0])

    def _calc_surface(self, context, output):
        x, _ = self._positions_velocities(context.get_discrete_state(self._state).get_value())
        output.SetFromVector(x[self._surface_rows].ravel())

    def _update(self, context, discrete_state):
        # The update's state starts as a copy of the context's: step it in place.
        x, v = self._positions_velocities(
            discrete_state.get_mutable_vector(self._state).get_mutable_value())
        m = self._model
        common = (x, v, m.links, m.rest_lengths_m, m.stiffness_n_per_m, m.damping_n_s_per_m,
                  m.mass_kg, m.inv_mass_per_kg, m.gravity_m_s2, m.surface, self._external,
                  *self._probe_arguments(context), self._period_s)
        if self._implicit:
            linearly_implicit_tick(*common, self._cg_tolerance, self._cg_max_iterations,
                                   *self._workspace)
        else:
            symplectic_euler_tick(*common, self._substeps, self._workspace)
