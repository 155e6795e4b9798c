"""The device's electromagnetic model: coil currents to wrench on the instrument.

``load_magnetics(config)`` returns a ``MagneticsModel`` whose ``wrench_matrix``
maps the 27 coil currents [A] to the wrench on the instrument: rows Fx, Fy, Fz
[N/A] and Tx, Ty, Tz [N m/A] about the instrument origin, A-frame axes. It is
linear in the currents (air-core coils, rigid magnets), so the allocator can
invert it. Underneath is the 4-D per-ampere wrench table of one coil on one
magnet (``wrench_table``), built once per coil and magnet geometry and cached on
disk, read by a numba kernel (``wrench_kernel``) fast enough for the 1 kHz loop.
"""

from __future__ import annotations

import time

import numpy as np

from maglev_haptics.hardware.device import DeviceConfig
from maglev_haptics.hardware.interpolation import axis_nodes
from maglev_haptics.hardware.wrench_kernel import (
    POSE_NOT_FINITE, POSE_OK, wrench_matrix_kernel)
from maglev_haptics.hardware.wrench_table import (
    WrenchGrid, WrenchTable, load_wrench_table, table_key)


def check_magnet_pose(p_CM, u_C) -> tuple[np.ndarray, np.ndarray]:
    """Validated float copies of a magnet pose: centre p_CM (3,) [m], unit axis u_C (3,)."""
    p = np.array(p_CM, dtype=float)
    u = np.array(u_C, dtype=float)
    if p.shape != (3,) or not np.all(np.isfinite(p)):
        raise ValueError(f"p_CM = {p_CM!r}: must be 3 finite numbers [m]")
    if u.shape != (3,) or not np.all(np.isfinite(u)) or abs(np.linalg.norm(u) - 1) > 1e-6:
        raise ValueError(f"u_C = {u_C!r}: must be a unit 3-vector")
    return p, u


_ORIGIN = np.zeros((1, 3))
_ONE = np.ones(1)


def _rotation_with_z(u: np.ndarray) -> np.ndarray:
    """A rotation matrix whose third column is the (nearly) unit vector u."""
    u = u / np.linalg.norm(u)
    helper = np.array([1.0, 0.0, 0.0]) if abs(u[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, u)
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(u, x), u])


def _kernel_array(value) -> np.ndarray:
    """value as a writeable C-contiguous float64 array, the one layout the kernel
    is compiled for (Drake hands out read-only and Fortran-ordered arrays, each
    of which would cost numba a separate ~4 s compilation)."""
    if (type(value) is np.ndarray and value.dtype == np.float64
            and value.flags.c_contiguous and value.flags.writeable):
        return value
    return np.array(value, dtype=np.float64, order="C")


class MagneticsModel:
    """Wrench per ampere of every coil on the configured instrument.

    Attributes: ``config``; ``instrument`` (its InstrumentSpec); ``p_ACj``
    (n_coils, 3) coil top centres in A [m]; ``p_IM`` (n_magnets, 3) magnet
    centres in I [m]; ``table`` (the WrenchTable of one coil on one magnet).
    Calls share a small work array, so one instance must not be used from two
    threads at once.
    """

    def __init__(self, config: DeviceConfig, table: WrenchTable):
        self.config = config
        self.instrument = config.instrument_spec()
        self.table = table
        self.p_ACj = np.ascontiguousarray(config.array.coil_positions_A())
        self.p_IM = np.ascontiguousarray(self.instrument.p_IM)
        self.magnet_scales, self.coil_scales = config.model_scales()
        self._values = table.kernel_values
        self._axes = np.ascontiguousarray(table.axes)
        # Kernel work space: 3 tilt nodes x 6 components, summed in float32.
        self._scratch = np.empty(18, dtype=np.float32)

    @property
    def n_coils(self) -> int:
        return self.p_ACj.shape[0]

    def wrench_matrix(self, X_AI) -> np.ndarray:
        """(6, n_coils) wrench per ampere for the instrument at X_AI (RigidTransform).

        Rows Fx, Fy, Fz [N/A], Tx, Ty, Tz [N m/A] about I's origin, A axes;
        column j is coil j at +1 A.
        """
        return self.wrench_matrix_from(X_AI.translation(), X_AI.rotation().matrix())

    def wrench_matrix_from(self, p_AI: np.ndarray, R_AI: np.ndarray) -> np.ndarray:
        """``wrench_matrix`` from p_AI (3,) [m] and R_AI (3, 3): the 1 kHz entry point.

        Fastest with writeable C-contiguous float64 arrays (others are copied);
        raises ValueError for a non-finite pose or an R_AI that is not a rotation.
        """
        p_AI = _kernel_array(p_AI)
        R_AI = _kernel_array(R_AI)
        if p_AI.shape != (3,) or R_AI.shape != (3, 3):
            raise ValueError(f"p_AI shape {p_AI.shape}, R_AI shape {R_AI.shape}: "
                             "must be (3,) and (3, 3)")
        status, matrix = wrench_matrix_kernel(self._values, self._axes, self.p_ACj, self.p_IM,
                                              self.magnet_scales, self.coil_scales, p_AI, R_AI,
                                              self._scratch)
        if status == POSE_NOT_FINITE:
            name, value = ("p_AI", p_AI) if not np.all(np.isfinite(p_AI)) else ("R_AI", R_AI)
            raise ValueError(f"{name} = {value!r}: must be finite")
        if status != POSE_OK:
            raise ValueError(f"R_AI = {R_AI!r}: must be a rotation matrix (orthonormal, det +1)")
        return matrix

    def kernel_arguments(self) -> tuple:
        """(values, axes, p_ACj, p_IM, magnet_scales, coil_scales, scratch):
        ``wrench_matrix_kernel``'s model arguments, for a kernel that computes the
        matrix inside its own compiled call."""
        return (self._values, self._axes, self.p_ACj, self.p_IM, self.magnet_scales,
                self.coil_scales, self._scratch)

    def magnet_wrench_matrices(self, p_AI: np.ndarray, R_AI: np.ndarray) -> np.ndarray:
        """(n_magnets, 6, n_coils): each magnet's share of ``wrench_matrix_from`` at
        nominal strength and coil scales, the terms a calibration weighs."""
        p_AI, R_AI = _kernel_array(p_AI), _kernel_array(R_AI)
        ones = np.ones(1), np.ones(self.n_coils)
        shares = []
        for m in range(len(self.p_IM)):
            status, matrix = wrench_matrix_kernel(self._values, self._axes, self.p_ACj,
                                                  self.p_IM[m:m + 1].copy(), *ones, p_AI, R_AI,
                                                  self._scratch)
            if status != POSE_OK:
                self.wrench_matrix_from(p_AI, R_AI)  # raises the pose's own error
            shares.append(matrix)
        return np.array(shares)

    def coil_magnet_wrench(self, p_CM, u_C) -> tuple[np.ndarray, np.ndarray]:
        """(force [N/A], torque [N m/A]) of one coil at +1 A on one instrument magnet.

        p_CM [m] is the magnet centre and u_C its unit magnetization axis, both in
        the coil frame C; the torque is about the magnet centre, in C axes. Zero
        beyond the table's reach (``cutoffs``).
        """
        p, u = check_magnet_pose(p_CM, u_C)
        # The matrix kernel for one coil at the origin and one magnet at I's
        # origin, I's z along u: one compiled kernel serves both entry points.
        _, wrench = wrench_matrix_kernel(self._values, self._axes, _ORIGIN, _ORIGIN, _ONE, _ONE,
                                         p, _rotation_with_z(u), self._scratch)
        return wrench[:3, 0], wrench[3:, 0]

    def cutoffs(self) -> dict:
        """The table's reach: pairs beyond rho_max or z_max [m] contribute nothing;
        lower magnets are read at z_min [m]; each component of the tilt vector
        (tilt angle times its unit direction, local basis) is clamped to
        +/-tilt_max [rad], so every tilt up to tilt_max is covered."""
        rho_axis, z_axis, tilt_axis = (axis_nodes(a) for a in self._axes[:3])
        return {"rho_max_m": float(rho_axis[-1]), "z_max_m": float(z_axis[-1]),
                "z_min_m": float(z_axis[0]), "tilt_max_rad": float(tilt_axis[-1])}


# Tables loaded in this process, by table_key.
_TABLES: dict[str, WrenchTable] = {}


def load_magnetics(config: DeviceConfig, grid: WrenchGrid = WrenchGrid()) -> MagneticsModel:
    """The electromagnetic model for ``config``: coil array, coils and instrument.

    The first call for a coil and magnet geometry builds the wrench table
    (10-20 s, with a progress bar) unless it is in the disk cache
    ($MAGLEV_CACHE_DIR, default ~/.cache/maglev_haptics); later calls in the
    process share it.
    """
    magnet = config.instrument_spec().magnet
    key = table_key(config.coil, magnet, grid)
    if key not in _TABLES:
        _TABLES[key] = load_wrench_table(config.coil, magnet, grid)
    return MagneticsModel(config, _TABLES[key])


def bench_wrench_matrix(config: DeviceConfig, n: int = 2000) -> dict:
    """Time ``wrench_matrix_from`` after warm-up, in microseconds per call.

    The instrument follows a smooth path at 1 kHz steps, as the haptic loop sees
    it: +/-20 mm around a level hover 25 mm above the coil tops (peak speed
    ~0.1 m/s), tilting up to ~15 deg while yawing. Returns instrument, pairs,
    mean_us, median_us, p99_us, n.
    """
    model = load_magnetics(config)
    t = np.arange(n) * 1e-3  # [s]
    p_AI = np.stack([0.02 * np.sin(2 * np.pi * 0.8 * t), 0.02 * np.sin(2 * np.pi * 0.5 * t + 1),
                     0.025 + 0.005 * np.sin(2 * np.pi * 0.3 * t)], axis=1)
    rotation_vectors = np.stack([0.25 * np.sin(2 * np.pi * 0.4 * t),
                                 0.25 * np.cos(2 * np.pi * 0.3 * t), 2.0 * t], axis=1)
    R_AI = [_rotation_from_vector(v) for v in rotation_vectors]
    for i in range(min(n, 100)):
        model.wrench_matrix_from(p_AI[i], R_AI[i])
    times = np.empty(n)
    for i in range(n):
        start = time.perf_counter()
        model.wrench_matrix_from(p_AI[i], R_AI[i])
        times[i] = time.perf_counter() - start
    times *= 1e6
    return {"instrument": config.instrument, "pairs": model.n_coils * len(model.p_IM),
            "mean_us": float(times.mean()), "median_us": float(np.median(times)),
            "p99_us": float(np.percentile(times, 99)), "n": n}


def _rotation_from_vector(rotation_vector: np.ndarray) -> np.ndarray:
    """Rodrigues' formula: the rotation matrix of a rotation vector [rad]."""
    angle = np.linalg.norm(rotation_vector)
    if angle < 1e-12:
        return np.eye(3)
    k = rotation_vector / angle
    cross = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * cross + (1 - np.cos(angle)) * cross @ cross
