"""Rotation helpers for the numba-compiled kernels of the 1 kHz and tracker-rate path.

Written by hand because Drake's RotationMatrix, RollPitchYaw and Quaternion cannot
be called from numba, and a Python call costs microseconds a tick. Everywhere else
(setup, visualization, whole logs) uses Drake's classes or scipy's Rotation; the
tests check these against Drake's. At the end, for the code off the kernels: pose
vectors to and from Drake's RigidTransform, and quaternion logs to scipy's Rotation.

Conventions: quaternions [w, x, y, z] (Hamilton, Drake's order), as 4-tuples of
floats (no allocation inside a kernel); roll-pitch-yaw is Drake's extrinsic X-Y-Z,
R = Rz(yaw) Ry(pitch) Rx(roll); rotation vectors are axis * angle (rad).

The ``drake_`` kernels are Drake's arithmetic, operation for operation, for the
kernels that stand in for a call to Drake whose result the loop keeps (the
supervisor's pose at a mode change, the hand's latched grip): the other helpers
round differently (``rotation_from_quaternion`` normalizes first and sums
2 (y^2 + z^2) at once), so a run's log would no longer be the same to the bit.
"""

import math

import numba
import numpy as np
from pydrake.common.eigen_geometry import Quaternion
from pydrake.math import RigidTransform, RotationMatrix
from scipy.spatial.transform import Rotation

from maglev_haptics.hardware.exact_arithmetic import euclidean_norm, fused_multiply_add
from maglev_haptics.hardware.kernels import VECTOR, kernel


@kernel((VECTOR,))
def rotation_from_quaternion(q):
    """R (3x3) from a quaternion array [w, x, y, z] (normalized here)."""
    w, x, y, z = q / np.sqrt(q @ q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


@numba.njit(cache=True)
def rotation_from_rpy(rpy):
    """R = Rz(yaw) Ry(pitch) Rx(roll) of [roll, pitch, yaw] (rad)."""
    cr, sr = np.cos(rpy[0]), np.sin(rpy[0])
    cp, sp = np.cos(rpy[1]), np.sin(rpy[1])
    cy, sy = np.cos(rpy[2]), np.sin(rpy[2])
    return np.array([
        [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
        [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
        [-sp, cp * sr, cp * cr],
    ])


@numba.njit(cache=True)
def angular_velocity_from_rpy_rates(rpy, rpy_dot):
    """w_W (rad/s) of R = Rz Ry Rx given roll-pitch-yaw (rad) and their rates (rad/s)."""
    cp, sp = np.cos(rpy[1]), np.sin(rpy[1])
    cy, sy = np.cos(rpy[2]), np.sin(rpy[2])
    return np.array([
        cy * cp * rpy_dot[0] - sy * rpy_dot[1],
        sy * cp * rpy_dot[0] + cy * rpy_dot[1],
        -sp * rpy_dot[0] + rpy_dot[2],
    ])


@numba.njit(cache=True)
def rotation_error_W(R_WD, R_WI):
    """sin(angle) * axis of the rotation taking R_WI to R_WD, in W."""
    R = R_WD @ R_WI.T
    return 0.5 * np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])


@numba.njit(cache=True)
def quaternion_from_rotation_matrix(R):
    """Unit quaternion array [w, x, y, z] of the rotation matrix R (Shepperd's method,
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


@numba.njit(cache=True)
def quaternion_multiply(a, b):
    """Hamilton product a * b of two 4-tuples, so R(a * b) = R(a) R(b)."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw)


@numba.njit(cache=True)
def quaternion_conjugate(q):
    """The conjugate of a 4-tuple: the inverse rotation of a unit quaternion."""
    return (q[0], -q[1], -q[2], -q[3])


@numba.njit(cache=True)
def quaternion_exp(x, y, z):
    """Unit quaternion 4-tuple of the rotation vector (x, y, z) (rad)."""
    angle = math.sqrt(x * x + y * y + z * z)
    # sin(angle / 2) / angle; its Taylor series below 1e-4 rad is exact in double.
    scale = math.sin(angle / 2) / angle if angle > 1e-4 else 0.5 - angle * angle / 48
    return (math.cos(angle / 2), scale * x, scale * y, scale * z)


@numba.njit(cache=True)
def quaternion_log(w, x, y, z):
    """Rotation vector 3-tuple (rad, angle in [0, pi]) of the unit quaternion
    (w, x, y, z); q and -q give the same result, the shorter rotation."""
    if w < 0:
        w, x, y, z = -w, -x, -y, -z
    s = math.sqrt(x * x + y * y + z * z)
    # angle / sin(angle / 2), with its limit 2 / w as s -> 0.
    scale = 2.0 * math.atan2(s, w) / s if s > 1e-12 else 2.0 / w
    return (scale * x, scale * y, scale * z)


# --- Drake's arithmetic, to the last bit (see the module docstring) ---------

@numba.njit(cache=True)
def _numpy_unit_quaternion(q):
    """q / np.linalg.norm(q) of a quaternion array, as numpy rounds it, as a 4-tuple."""
    norm = euclidean_norm(q)
    return q[0] / norm, q[1] / norm, q[2] / norm, q[3] / norm


@numba.njit(cache=True)
def _drake_rotation(w, x, y, z):
    """Drake's RotationMatrix(Quaternion(w, x, y, z)).matrix(): scaled by 2 / |q|^2,
    Eigen summing the squares pairwise (x with z, y with w)."""
    two_over_norm_squared = 2.0 / ((x * x + z * z) + (y * y + w * w))
    sx, sy, sz = two_over_norm_squared * x, two_over_norm_squared * y, two_over_norm_squared * z
    swx, swy, swz = sx * w, sy * w, sz * w
    sxx, sxy, sxz = sx * x, sy * x, sz * x
    syy, syz, szz = sy * y, sz * y, sz * z
    return np.array([[1.0 - syy - szz, sxy - swz, sxz + swy],
                     [sxy + swz, 1.0 - sxx - szz, syz - swx],
                     [sxz - swy, syz + swx, 1.0 - sxx - syy]])


@numba.njit(cache=True)
def drake_roll_pitch_yaw(q):
    """[roll, pitch, yaw] (rad) as ``RollPitchYaw(Quaternion(q / np.linalg.norm(q)))``
    gives it, of a quaternion array [w, x, y, z]."""
    w, x, y, z = _numpy_unit_quaternion(q)
    R = _drake_rotation(w, x, y, z)
    # Pitch from the matrix, roll and yaw from the quaternion (Drake's roll_pitch_yaw.cc).
    abs_cos_pitch = math.sqrt((R[2, 2] * R[2, 2] + R[2, 1] * R[2, 1] + R[1, 0] * R[1, 0]
                               + R[0, 0] * R[0, 0]) / 2)
    pitch = math.atan2(-R[2, 0], abs_cos_pitch)
    y_a, x_a, y_b, x_b = x + z, w - y, z - x, w + y
    epsilon = 2.220446049250313e-16  # Eigen's epsilon of a double
    sum_angle = 0.0 if abs(y_a) <= epsilon and abs(x_a) <= epsilon else math.atan2(y_a, x_a)
    difference_angle = 0.0 if abs(y_b) <= epsilon and abs(x_b) <= epsilon \
        else math.atan2(y_b, x_b)
    roll = sum_angle - difference_angle
    yaw = sum_angle + difference_angle
    if roll > math.pi:
        roll = roll - 2 * math.pi
    if roll < -math.pi:
        roll = roll + 2 * math.pi
    if yaw > math.pi:
        yaw = yaw - 2 * math.pi
    if yaw < -math.pi:
        yaw = yaw + 2 * math.pi
    return np.array([roll, pitch, yaw])


@numba.njit(cache=True)
def _drake_quaternion(R):
    """Drake's RotationMatrix(R).ToQuaternion() as an array [w, x, y, z] (w >= 0); its
    norm sums the squares as Eigen does, x with z and y with w."""
    trace = R[0, 0] + (R[1, 1] + R[2, 2])  # Eigen's order
    if trace >= R[0, 0] and trace >= R[1, 1] and trace >= R[2, 2]:
        w, x, y, z = 1.0 + trace, R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]
    elif R[0, 0] >= R[1, 1] and R[0, 0] >= R[2, 2]:
        w, x, y, z = (R[2, 1] - R[1, 2], 1.0 - (trace - 2 * R[0, 0]), R[0, 1] + R[1, 0],
                      R[0, 2] + R[2, 0])
    elif R[1, 1] >= R[2, 2]:
        w, x, y, z = (R[0, 2] - R[2, 0], R[0, 1] + R[1, 0], 1.0 - (trace - 2 * R[1, 1]),
                      R[1, 2] + R[2, 1])
    else:
        w, x, y, z = (R[1, 0] - R[0, 1], R[0, 2] + R[2, 0], R[1, 2] + R[2, 1],
                      1.0 - (trace - 2 * R[2, 2]))
    scale = (-1.0 if w < 0 else 1.0) / math.sqrt((x * x + z * z) + (y * y + w * w))
    return np.array([w * scale, x * scale, y * scale, z * scale])


@numba.njit(cache=True)
def drake_relative_pose(X_WA, X_WB):
    """X_AB = X_WA^-1 X_WB as a pose vector, of two pose vectors [qw, qx, qy, qz, x, y, z]
    (m), as ``pose_vector(rigid_transform(X_WA).InvertAndCompose(rigid_transform(X_WB)))``
    computes it where Drake composes with AVX2 (a fused multiply-add for each term after
    the first; Drake's portable code, on a CPU without AVX2, rounds each product)."""
    R_WA = _drake_rotation(*_numpy_unit_quaternion(X_WA[0:4]))
    R_WB = _drake_rotation(*_numpy_unit_quaternion(X_WB[0:4]))
    p_AB_W = X_WB[4:7] - X_WA[4:7]
    R_AB = np.empty((3, 3))
    p_AB = np.empty(3)
    for i in range(3):
        for j in range(3):
            R_AB[i, j] = fused_multiply_add(R_WA[2, i], R_WB[2, j], fused_multiply_add(
                R_WA[1, i], R_WB[1, j], R_WA[0, i] * R_WB[0, j]))
        p_AB[i] = fused_multiply_add(R_WA[2, i], p_AB_W[2], fused_multiply_add(
            R_WA[1, i], p_AB_W[1], R_WA[0, i] * p_AB_W[0]))
    return np.concatenate((_drake_quaternion(R_AB), p_AB))


# --- off the kernels: Drake for single poses, scipy for whole logs ----------

def rotation_matrix(q) -> RotationMatrix:
    """Drake's RotationMatrix of a quaternion [w, x, y, z], normalized here (a measured
    one is unit only to rounding, and Drake's Quaternion insists on unit)."""
    q = np.asarray(q, float)
    return RotationMatrix(Quaternion(q / np.linalg.norm(q)))


def rigid_transform(pose) -> RigidTransform:
    """Drake's RigidTransform of a pose vector [qw, qx, qy, qz, x, y, z] (m)."""
    return RigidTransform(rotation_matrix(pose[0:4]), np.asarray(pose[4:7], float))


def pose_vector(X: RigidTransform) -> np.ndarray:
    """The pose vector [qw, qx, qy, qz, x, y, z] (m) of ``X`` (w >= 0)."""
    q = X.rotation().ToQuaternion()
    return np.array([q.w(), q.x(), q.y(), q.z(), *X.translation()])


def rotations_of_quaternions(q) -> Rotation:
    """scipy's Rotation of quaternions [w, x, y, z] ((N, 4) or (4,)), normalized: a
    whole log at once."""
    return Rotation.from_quat(np.asarray(q, float)[..., [1, 2, 3, 0]])
