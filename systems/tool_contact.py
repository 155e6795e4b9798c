"""Contact sensing on the scene's tool: the total contact wrench and a contact flag.

Each contact on the tool contributes a force f (N) applied at a point C and a
couple tau (N*m) about C, in W: for hydroelastic contact the spatial force at
the contact surface's centroid (``HydroelasticContactInfo.F_Ac_W`` is on the
body of geometry M, so its negative is on the body of geometry N); for point
contact the force at the contact point (``contact_force`` is on body B, its
negative on body A) with no couple. The sensor moves each to the tool body's
origin To and sums: tau_To = tau + (p_WC - p_WTo) x f.

Cost: in contact mostly the pybind calls that read the contact results; the sum
is compiled by numba.
"""

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.multibody.plant import ContactResults
from pydrake.systems.framework import LeafSystem, ValueProducer

from maglev_haptics.hardware.kernels import MATRIX, VECTOR, kernel


@kernel((MATRIX, MATRIX, MATRIX, VECTOR))
def wrench_about_point(forces_W, torques_W, p_WC, p_WO):
    """[f; tau] (6,) in W (N, N*m): the sum of forces (n, 3) applied at points p_WC
    (n, 3) (m) with couples torques_W (n, 3) about those points, moved to p_WO (3,) (m).
    Compiled: numpy's cross product alone costs ~20 us a call."""
    fx = fy = fz = tx = ty = tz = 0.0
    for i in range(forces_W.shape[0]):
        f0, f1, f2 = forces_W[i, 0], forces_W[i, 1], forces_W[i, 2]
        ax, ay, az = p_WC[i, 0] - p_WO[0], p_WC[i, 1] - p_WO[1], p_WC[i, 2] - p_WO[2]
        fx += f0
        fy += f1
        fz += f2
        tx += torques_W[i, 0] + ay * f2 - az * f1
        ty += torques_W[i, 1] + az * f0 - ax * f2
        tz += torques_W[i, 2] + ax * f1 - ay * f0
    return np.array([fx, fy, fz, tx, ty, tz])


def _rows(vectors):
    """(n, 3) array of n 3-vectors."""
    return np.array(vectors).reshape(-1, 3) if vectors else np.zeros((0, 3))


class ToolContactSensor(LeafSystem):
    """The scene plant's contact wrench on the tool body.

    .. pydrake_system::

        name: ToolContactSensor
        input_ports:
        - contact_results
        - X_WT
        output_ports:
        - wrench_on_tool_W
        - in_contact

    ``contact_results`` is the scene plant's ContactResults; ``X_WT`` the tool
    body's pose [qw, qx, qy, qz, x, y, z] (m), of which only the origin p_WTo is
    used. ``wrench_on_tool_W`` is [fx, fy, fz, tx, ty, tz] in W (N, N*m): the
    total contact force on the tool and its moment about the tool body's
    origin. ``in_contact`` is 1.0 while any contact (hydroelastic or point)
    touches the tool, else 0.0.
    """

    def __init__(self, plant, tool_body):
        LeafSystem.__init__(self)
        self._tool_index = tool_body.index()
        self._tool_geometries = frozenset(plant.GetCollisionGeometriesForBody(tool_body))
        self._contact_results = self.DeclareAbstractInputPort(
            "contact_results", AbstractValue.Make(ContactResults()))
        self._X_WT = self.DeclareVectorInputPort("X_WT", 7)
        # Both outputs come from one pass over the contact results.
        self._cache = self.DeclareCacheEntry(
            description="contact wrench and flag",
            value_producer=ValueProducer(allocate=AbstractValue.Make(()).Clone,
                                         calc=self._calc_cache),
            prerequisites_of_calc={self.all_input_ports_ticket()})
        self.DeclareVectorOutputPort("wrench_on_tool_W", 6, self._calc_wrench_on_tool_W)
        self.DeclareVectorOutputPort("in_contact", 1, self._calc_in_contact)

    def _contacts(self, context):
        """Lists of the forces, couples and their points (each (3,), in W) on the tool."""
        results = self._contact_results.Eval(context)
        forces, torques, points = [], [], []
        for i in range(results.num_hydroelastic_contacts()):
            info = results.hydroelastic_contact_info(i)
            surface = info.contact_surface()
            if surface.id_M() in self._tool_geometries:
                sign = 1.0
            elif surface.id_N() in self._tool_geometries:
                sign = -1.0
            else:
                continue
            F = info.F_Ac_W()
            forces.append(sign * F.translational())
            torques.append(sign * F.rotational())
            points.append(surface.centroid())
        for i in range(results.num_point_pair_contacts()):
            info = results.point_pair_contact_info(i)
            if info.bodyB_index() == self._tool_index:
                sign = 1.0
            elif info.bodyA_index() == self._tool_index:
                sign = -1.0
            else:
                continue
            forces.append(sign * info.contact_force())
            torques.append(np.zeros(3))
            points.append(info.contact_point())
        return forces, torques, points

    def _calc_cache(self, context, value):
        """(wrench [f; tau] about the tool's origin in W, 1.0 if in contact else 0.0)."""
        forces, torques, points = self._contacts(context)
        wrench = wrench_about_point(_rows(forces), _rows(torques), _rows(points),
                                    self._X_WT.Eval(context)[4:7])
        value.set_value((wrench, 1.0 if forces else 0.0))

    def _calc_wrench_on_tool_W(self, context, output):
        output.SetFromVector(self._cache.Eval(context)[0])

    def _calc_in_contact(self, context, output):
        output.SetFromVector([self._cache.Eval(context)[1]])
