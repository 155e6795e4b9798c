"""Run-time kernel: the (6, n_coils) wrench matrix from the wrench table (numba).

For every (magnet, coil) pair it finds the magnet's table coordinates relative to
the coil (rho, z, tilt vector w_r, w_t), interpolates the six local components
with 4-node (cubic) Lagrange stencils in rho and z and 3-node (quadratic) ones,
centred on the nearest node, in w_r and w_t (all one-sided at the axes' ends),
rotates them from the local (e_r, e_t, e_z) basis to the array frame A and sums
them into coil j's column about the instrument origin:
tau_I = tau_M + (p_AM - p_AI) x F. All coil axes are A's +z.

The quadratic tilt stencils on a finer tilt grid (2.5 deg, ``WrenchGrid``) read
144 nodes a pair instead of 256 and half the cache lines; they trade accuracy
the acceptance limit does not need (measured worst torque error 0.17 % of the
floored magnitude against 0.5 % allowed; 0.03 % with cubic ones on a 4 deg
grid). The interpolant jumps by up to that error where the nearest tilt node
changes.

Pairs with rho > rho_max or z > z_max (the table's far edges) contribute nothing;
lower magnets are read at z_min and tilt components beyond +/-tilt_max at the limit.

``values`` is the float32 table with its last two axes (w_t, component) merged,
so that the 3 w_t nodes x 6 components of a stencil are 18 contiguous numbers,
summed in float32 SIMD (2e-7 relative, 15 % faster than float64 sums); ``axes``
stacks the rho, z, w_r and w_t axis descriptors (``WrenchTable.axes``).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from maglev_haptics.hardware.interpolation import (
    axis_position, beyond_end, clamped_position, lagrange3_weights, lagrange4_weights,
    nearest_stencil_start, stencil_start)
from maglev_haptics.hardware.kernels import FLOAT32_TENSOR4, FLOAT32_VECTOR, MATRIX, VECTOR, kernel

# Let LLVM reassociate and fuse the table sums into SIMD multiply-adds (about 2x);
# unlike full fastmath it keeps IEEE NaN/inf semantics.
VECTORIZING_MATH = {"contract", "reassoc", "arcp", "nsz"}

POSE_OK = 0
POSE_NOT_FINITE = 1
POSE_NOT_ROTATION = 2


@numba.njit(cache=True, inline="always")
def local_wrench(values, axes, rho, z, w_r, w_t, out, scratch):
    """Interpolate the six local components into out (6,).

    rho, z [m] locate the magnet centre; (w_r, w_t) [rad] is its tilt vector in
    the local basis; scratch is (18,) float32 work space from the Python caller.
    Returns False, leaving out untouched, beyond the table's rho or z range.
    """
    t_rho = axis_position(axes[0], rho)
    t_z = axis_position(axes[1], max(z, 1e-9))
    if beyond_end(axes[0], t_rho) or beyond_end(axes[1], t_z):
        return False
    t_z = max(t_z, 0.0)
    t_wr = clamped_position(axes[2], w_r)
    t_wt = clamped_position(axes[3], w_t)
    i_rho = stencil_start(t_rho, axes[0])
    i_z = stencil_start(t_z, axes[1])
    i_wr = nearest_stencil_start(t_wr, axes[2])
    i_wt = nearest_stencil_start(t_wt, axes[3])
    w_z = lagrange4_weights(t_z - i_z)
    w_wr = lagrange3_weights(t_wr - i_wr)
    # Sum the contiguous (3 w_t nodes x 6 components) blocks over the other three
    # axes first, then over w_t; the 4 z x 3 w_r rows of a rho node go in one
    # pass. Unsigned column indices spare numba's negative-index wraparound,
    # which otherwise turns the loads into SIMD gathers (1.4x slower); scratch's
    # length (18) is a run-time number to LLVM, so it vectorizes this loop
    # instead of unrolling it into scalar code.
    first = np.uint64(6 * i_wt)
    block_len = np.uint64(scratch.shape[0])
    j0, j1, j2, j3 = i_z, i_z + 1, i_z + 2, i_z + 3
    c0, c1, c2 = i_wr, i_wr + 1, i_wr + 2
    scratch[:] = 0.0
    for a, w_a in enumerate(lagrange4_weights(t_rho - i_rho)):
        i = i_rho + a
        w0 = _row_weights(w_a * w_z[0], w_wr)
        w1 = _row_weights(w_a * w_z[1], w_wr)
        w2 = _row_weights(w_a * w_z[2], w_wr)
        w3 = _row_weights(w_a * w_z[3], w_wr)
        for n in range(block_len):
            k = first + n
            scratch[n] += (w0[0] * values[i, j0, c0, k] + w0[1] * values[i, j0, c1, k]
                           + w0[2] * values[i, j0, c2, k] + w1[0] * values[i, j1, c0, k]
                           + w1[1] * values[i, j1, c1, k] + w1[2] * values[i, j1, c2, k]
                           + w2[0] * values[i, j2, c0, k] + w2[1] * values[i, j2, c1, k]
                           + w2[2] * values[i, j2, c2, k] + w3[0] * values[i, j3, c0, k]
                           + w3[1] * values[i, j3, c1, k] + w3[2] * values[i, j3, c2, k])
    for k in range(6):
        out[k] = 0.0
    for d, w_d in enumerate(lagrange3_weights(t_wt - i_wt)):
        for k in range(6):
            out[k] += w_d * scratch[6 * d + k]
    return True


@numba.njit(cache=True, inline="always")
def _row_weights(w_node, w_wr):
    """float32 weights of the three w_r rows under a (rho, z) node of weight w_node."""
    return np.float32(w_node * w_wr[0]), np.float32(w_node * w_wr[1]), np.float32(w_node * w_wr[2])


@numba.njit(cache=True, inline="always")
def tilt_vector(u):
    """(w_x, w_y) = theta * (u_x, u_y) / sin(theta) [rad] of the unit axis u (3,),
    theta its tilt from +z: the table's tilt coordinates in the same axes."""
    sin_theta = math.sqrt(u[0] * u[0] + u[1] * u[1])
    theta = math.atan2(sin_theta, u[2])
    scale = theta / sin_theta if sin_theta > 1e-12 else 1.0
    return u[0] * scale, u[1] * scale


@numba.njit(cache=True, inline="always")
def pair_wrench_C(values, axes, p_CM, w_x, w_y, out, scratch):
    """Wrench per ampere of one coil on one magnet, C axes, about the magnet centre.

    p_CM [m]; (w_x, w_y) [rad] the magnet's tilt vector (``tilt_vector``) in C
    axes; out (6,) gets force [N/A] then torque [N m/A]; scratch is (18,) float32
    work space. Returns False (out zeroed) when the magnet is beyond the table's
    rho or z range.
    """
    x, y = p_CM[0], p_CM[1]
    rho = math.sqrt(x * x + y * y)
    if rho > 0.0:
        cos_az, sin_az = x / rho, y / rho
    else:
        cos_az, sin_az = 1.0, 0.0
    w_r = w_x * cos_az + w_y * sin_az
    w_t = -w_x * sin_az + w_y * cos_az
    if not local_wrench(values, axes, rho, p_CM[2], w_r, w_t, out, scratch):
        for k in range(6):
            out[k] = 0.0
        return False
    # Local (e_r, e_t, e_z) components to C axes, force then torque.
    for k in (0, 3):
        radial, tangential = out[k], out[k + 1]
        out[k] = radial * cos_az - tangential * sin_az
        out[k + 1] = radial * sin_az + tangential * cos_az
    return True


@kernel((FLOAT32_TENSOR4, MATRIX, MATRIX, MATRIX, VECTOR, VECTOR, VECTOR, MATRIX, FLOAT32_VECTOR),
        fastmath=VECTORIZING_MATH)
def wrench_matrix_kernel(values, axes, p_ACj, p_IM, magnet_scales, coil_scales, p_AI, R_AI,
                         scratch):
    """(status, (6, n_coils) wrench per ampere on the instrument).

    The matrix is in A axes, torques about I's origin. p_ACj (n_coils, 3) coil
    top centres [m]; p_IM (n_magnets, 3) magnet centres in I [m]; magnet_scales
    (n_magnets,) and coil_scales (n_coils,) multiply each pair's wrench (a
    magnet's strength, a coil's wrench per ampere; 1.0 leaves it exact);
    p_AI (3,) [m] and R_AI (3, 3) the instrument pose; scratch (18,) float32 work space.
    Every magnet is magnetized along I's +z. status is POSE_OK, POSE_NOT_FINITE
    or POSE_NOT_ROTATION (then the matrix is zero).
    """
    n_coils = p_ACj.shape[0]
    matrix = np.zeros((6, n_coils))
    status = _pose_status(p_AI, R_AI)
    if status != POSE_OK:
        return status, matrix
    u_A = np.empty(3)
    for k in range(3):
        u_A[k] = R_AI[k, 2]
    # Coil axes are all A's +z, so every pair shares the tilt vector.
    w_x, w_y = tilt_vector(u_A)
    p_CM = np.empty(3)
    r_IM = np.empty(3)
    wrench = np.empty(6)
    for m in range(p_IM.shape[0]):
        # Magnet centre offset from I's origin, A axes [m].
        for k in range(3):
            r_IM[k] = R_AI[k, 0] * p_IM[m, 0] + R_AI[k, 1] * p_IM[m, 1] + R_AI[k, 2] * p_IM[m, 2]
        for j in range(n_coils):
            for k in range(3):
                p_CM[k] = p_AI[k] + r_IM[k] - p_ACj[j, k]
            if not pair_wrench_C(values, axes, p_CM, w_x, w_y, wrench, scratch):
                continue
            scale = magnet_scales[m] * coil_scales[j]
            fx, fy, fz = wrench[0] * scale, wrench[1] * scale, wrench[2] * scale
            matrix[0, j] += fx
            matrix[1, j] += fy
            matrix[2, j] += fz
            matrix[3, j] += wrench[3] * scale + r_IM[1] * fz - r_IM[2] * fy
            matrix[4, j] += wrench[4] * scale + r_IM[2] * fx - r_IM[0] * fz
            matrix[5, j] += wrench[5] * scale + r_IM[0] * fy - r_IM[1] * fx
    return status, matrix


@numba.njit(cache=True, inline="always")
def _pose_status(p_AI, R_AI):
    for k in range(3):
        if not math.isfinite(p_AI[k]):
            return POSE_NOT_FINITE
        for n in range(3):
            if not math.isfinite(R_AI[k, n]):
                return POSE_NOT_FINITE
    # Orthonormal with determinant +1, to a tolerance loose enough for float32 sources.
    for a in range(3):
        for b in range(3):
            dot = R_AI[0, a] * R_AI[0, b] + R_AI[1, a] * R_AI[1, b] + R_AI[2, a] * R_AI[2, b]
            if abs(dot - (1.0 if a == b else 0.0)) > 1e-5:
                return POSE_NOT_ROTATION
    det = (R_AI[0, 0] * (R_AI[1, 1] * R_AI[2, 2] - R_AI[1, 2] * R_AI[2, 1])
           - R_AI[0, 1] * (R_AI[1, 0] * R_AI[2, 2] - R_AI[1, 2] * R_AI[2, 0])
           + R_AI[0, 2] * (R_AI[1, 0] * R_AI[2, 1] - R_AI[1, 1] * R_AI[2, 0]))
    if det < 0.0:
        return POSE_NOT_ROTATION
    return POSE_OK
