"""Magnetic actuation (station): true coil currents at the true pose give the true wrench."""

from __future__ import annotations

import numba
import numpy as np
from pydrake.systems.framework import LeafSystem

from maglev_haptics.hardware.kernels import (
    FLOAT32_TENSOR4, FLOAT32_VECTOR, MATRIX, VECTOR, kernel)
from maglev_haptics.hardware.wrench_kernel import POSE_OK, wrench_matrix_kernel
from maglev_haptics.systems.rotations import rotation_from_quaternion


def wrench_matrix_at(magnetics, p_WA, q_WI):
    """(6, n_coils) wrench matrix for the pose vector q_WI = [qw qx qy qz x y z] in W.

    The model works in the coil-array frame A, whose axes are W's and whose
    origin is p_WA [m] in W.
    """
    # The compiled helper, not Drake's RotationMatrix: this runs every 1 kHz tick.
    return magnetics.wrench_matrix_from(q_WI[4:7] - p_WA, rotation_from_quaternion(q_WI[0:4]))


def raise_pose_error(magnetics, p_WA, q_WI) -> None:
    """Raise the model's own error for a pose the wrench kernel refused (its status not
    ``POSE_OK``): a ValueError naming the pose."""
    wrench_matrix_at(magnetics, p_WA, np.array(q_WI))
    raise RuntimeError(f"q_WI = {list(q_WI)}: the wrench kernel refused it; the model did not")


@numba.njit(cache=True)
def wrench_matrix_at_pose(q_WI, p_WA, values, axes, p_ACj, p_IM, magnet_scales, coil_scales,
                          scratch):
    """(status, (6, n_coils) wrench matrix) for the pose vector q_WI (C-ordered, 7) in
    W: ``wrench_matrix_at`` inside a kernel; the model arguments are
    ``MagneticsModel.kernel_arguments()``."""
    return wrench_matrix_kernel(values, axes, p_ACj, p_IM, magnet_scales, coil_scales,
                                q_WI[4:7] - p_WA, rotation_from_quaternion(q_WI[0:4].copy()),
                                scratch)


@kernel((VECTOR, VECTOR, VECTOR, FLOAT32_TENSOR4, MATRIX, MATRIX, MATRIX, VECTOR, VECTOR,
         FLOAT32_VECTOR, VECTOR))
def instrument_generalized_force(instrument_state, coil_currents, p_WA, values, axes, p_ACj,
                                 p_IM, magnet_scales, coil_scales, scratch, out):
    """[tau; f] in W (N*m about I's origin, N) on the instrument's free body, into ``out``;
    returns the wrench matrix's pose status (``POSE_OK``: written).

    ``instrument_state`` is the plant's free-body state [q_WI (wxyz), p_WI, ...];
    the ordering [tau; f] is that of a quaternion floating joint's generalized
    forces, so the result feeds the plant's ``applied_generalized_force`` port. The
    model arguments are ``MagneticsModel.kernel_arguments()``.
    """
    status, A = wrench_matrix_at_pose(instrument_state[0:7].copy(), p_WA, values, axes, p_ACj,
                                      p_IM, magnet_scales, coil_scales, scratch)
    if status != POSE_OK:
        return status
    wrench = A @ coil_currents
    out[0:3] = wrench[3:6]
    out[3:6] = wrench[0:3]
    return POSE_OK


class MagneticActuation(LeafSystem):
    """The coils' wrench on the instrument's magnets, from the electromagnetic model:
    one compiled call a tick (``instrument_generalized_force``).

    .. pydrake_system::

        name: MagneticActuation
        input_ports:
        - coil_currents
        - instrument_state
        output_ports:
        - generalized_force
    """

    def __init__(self, *, magnetics, p_WA: np.ndarray):
        super().__init__()
        self._magnetics = magnetics
        self._p_WA = np.asarray(p_WA, dtype=float)
        self._currents = self.DeclareVectorInputPort("coil_currents", magnetics.n_coils)
        self._state = self.DeclareVectorInputPort("instrument_state", 13)
        self.DeclareVectorOutputPort("generalized_force", 6, self._calc_generalized_force)

    def _calc_generalized_force(self, context, output):
        state = self._state.EvalBasicVector(context).value()
        status = instrument_generalized_force(
            state, self._currents.EvalBasicVector(context).value(), self._p_WA,
            *self._magnetics.kernel_arguments(), output.get_mutable_value())
        if status != POSE_OK:
            raise_pose_error(self._magnetics, self._p_WA, state[0:7])
