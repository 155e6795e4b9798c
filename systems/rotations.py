"""Rotation helpers shared by the loop's systems, written once for any scalar type.

Each works on float and AutoDiffXd arrays alike (the controller converts to
AutoDiffXd for linearization); ``*_f64`` twins are the same source compiled by
numba for the float-only systems on the 1 kHz path.
"""

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


rotation_from_quaternion_f64 = numba.njit(cache=True)(rotation_from_quaternion)
