"""Rotation helpers shared by the loop's systems.

The matrix helpers work on float and AutoDiffXd arrays alike (the controller
converts to AutoDiffXd for linearization); ``*_f64`` is the same source compiled
by numba for the float-only systems on the 1 kHz path. The quaternion algebra
below them is float only, on tuples where speed matters, with ``*_f64`` twins
for the numba-compiled tracker-rate cores (marker sensor, pose estimator).
"""

import math

import numba
import numpy as np


def rotation_from_quaternion(q):
    """R (3x3) from a quaternion [w, x, y, z] (normalized here)."""
    w, x, y, z = q / np.sqrt(q @ q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def rotation_from_rpy(rpy):
    """R = Rz(yaw) Ry(pitch) Rx(roll), Drake's RollPitchYaw convention."""
    cr, sr = np.cos(rpy[0]), np.sin(rpy[0])
    cp, sp = np.cos(rpy[1]), np.sin(rpy[1])
    cy, sy = np.cos(rpy[2]), np.sin(rpy[2])
    return np.array([
        [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
        [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
        [-sp, cp * sr, cp * cr],
    ])


def angular_velocity_from_rpy_rates(rpy, rpy_dot):
    """w_W (rad/s) of R = Rz Ry Rx given roll-pitch-yaw and their rates."""
    cp, sp = np.cos(rpy[1]), np.sin(rpy[1])
    cy, sy = np.cos(rpy[2]), np.sin(rpy[2])
    return np.array([
        cy * cp * rpy_dot[0] - sy * rpy_dot[1],
        sy * cp * rpy_dot[0] + cy * rpy_dot[1],
        -sp * rpy_dot[0] + rpy_dot[2],
    ])


def rotation_error_W(R_WD, R_WI):
    """sin(angle) * axis of the rotation taking R_WI to R_WD, in W."""
    R = R_WD @ R_WI.T
    return 0.5 * np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])


def rpy_from_rotation(R):
    """[roll, pitch, yaw] (rad) of R = Rz(yaw) Ry(pitch) Rx(roll), float only."""
    return np.array([math.atan2(R[2, 1], R[2, 2]),
                     math.atan2(-R[2, 0], math.hypot(R[2, 1], R[2, 2])),
                     math.atan2(R[1, 0], R[0, 0])])


rotation_from_quaternion_f64 = numba.njit(cache=True)(rotation_from_quaternion)


# --- quaternions [w, x, y, z] (Hamilton, Drake's order) ---------------------
# The *_tuple functions work on tuples of floats: for 4-vectors that is several
# times faster than numpy in Python, and numba compiles the same source (the
# *_f64 twins below) for the tracker-rate cores of the sensor and the estimator.

def quaternion_multiply_tuple(a, b):
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw)


def quaternion_conjugate_tuple(q):
    return (q[0], -q[1], -q[2], -q[3])


def quaternion_exp_tuple(x, y, z):
    angle = math.sqrt(x * x + y * y + z * z)
    # sin(angle / 2) / angle; its Taylor series below 1e-4 rad is exact in double.
    scale = math.sin(angle / 2) / angle if angle > 1e-4 else 0.5 - angle * angle / 48
    return (math.cos(angle / 2), scale * x, scale * y, scale * z)


def quaternion_log_tuple(w, x, y, z):
    if w < 0:
        w, x, y, z = -w, -x, -y, -z
    s = math.sqrt(x * x + y * y + z * z)
    # angle / sin(angle / 2), with its limit 2 / w as s -> 0.
    scale = 2.0 * math.atan2(s, w) / s if s > 1e-12 else 2.0 / w
    return (scale * x, scale * y, scale * z)


def quaternion_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product a * b, so R(a * b) = R(a) R(b)."""
    return np.array(quaternion_multiply_tuple(a.tolist(), b.tolist()))


def quaternion_exp(rotvec: np.ndarray) -> np.ndarray:
    """Unit quaternion of the rotation vector ``rotvec`` (axis * angle, rad)."""
    return np.array(quaternion_exp_tuple(*rotvec.tolist()))


def quaternion_log(q: np.ndarray) -> np.ndarray:
    """Rotation vector (rad, angle in [0, pi]) of the unit quaternion ``q``.

    q and -q give the same result: the shorter of the two rotations is taken.
    """
    return np.array(quaternion_log_tuple(*q.tolist()))


def quaternion_from_rotation_matrix(R: np.ndarray) -> np.ndarray:
    """Unit quaternion [w, x, y, z] of the rotation matrix R (Shepperd's method,
    pivoting on the largest of w, x, y, z for accuracy at any angle)."""
    r00, r01, r02 = R[0, 0], R[0, 1], R[0, 2]
    r10, r11, r12 = R[1, 0], R[1, 1], R[1, 2]
    r20, r21, r22 = R[2, 0], R[2, 1], R[2, 2]
    trace = r00 + r11 + r22
    if trace >= max(r00, r11, r22):
        s = 2.0 * math.sqrt(1.0 + trace)
        w, x, y, z = 0.25 * s, (r21 - r12) / s, (r02 - r20) / s, (r10 - r01) / s
    elif r00 >= r11 and r00 >= r22:
        s = 2.0 * math.sqrt(1.0 + r00 - r11 - r22)
        w, x, y, z = (r21 - r12) / s, 0.25 * s, (r01 + r10) / s, (r02 + r20) / s
    elif r11 >= r22:
        s = 2.0 * math.sqrt(1.0 + r11 - r00 - r22)
        w, x, y, z = (r02 - r20) / s, (r01 + r10) / s, 0.25 * s, (r12 + r21) / s
    else:
        s = 2.0 * math.sqrt(1.0 + r22 - r00 - r11)
        w, x, y, z = (r10 - r01) / s, (r02 + r20) / s, (r12 + r21) / s, 0.25 * s
    norm = math.sqrt(w * w + x * x + y * y + z * z)
    return np.array([w / norm, x / norm, y / norm, z / norm])


quaternion_multiply_tuple_f64 = numba.njit(cache=True)(quaternion_multiply_tuple)
quaternion_conjugate_tuple_f64 = numba.njit(cache=True)(quaternion_conjugate_tuple)
quaternion_exp_tuple_f64 = numba.njit(cache=True)(quaternion_exp_tuple)
quaternion_log_tuple_f64 = numba.njit(cache=True)(quaternion_log_tuple)
quaternion_from_rotation_matrix_f64 = numba.njit(cache=True)(quaternion_from_rotation_matrix)
