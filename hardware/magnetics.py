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
    POSE_NOT_FINITE, POSE_OK, coil_magnet_kernel, wrench_matrix_kernel)
from maglev_haptics.hardware.wrench_table import (
    WrenchGrid, WrenchTable, load_wrench_table, table_key)


def check_magnet_pose(p_CM, u_C) -> tuple[np.ndarray, np.ndarray]:
    """Validated float copies of a magnet pose: centre p_CM (3,) [m], unit axis u_C (3,)."""
    p = np.asarray(p_CM, dtype=float)
    u = np.asarray(u_C, dtype=float)
    if p.shape != (3,) or not np.all(np.isfinite(p)):
        raise ValueError(f"p_CM = {p_CM!r}: must be 3 finite numbers [m]")
    if u.shape != (3,) or not np.all(np.isfinite(u)) or abs(np.linalg.norm(u) - 1) > 1e-6:
        raise ValueError(f"u_C = {u_C!r}: must be a unit 3-vector")
    return p, u


class MagneticsModel:
    """Wrench per ampere of every coil on the configured instrument.

    Attributes: ``config``; ``instrument`` (its InstrumentSpec); ``p_ACj``
    (n_coils, 3) coil top centres in A [m]; ``p_IM`` (n_magnets, 3) magnet
    centres in I [m]; ``table`` (the WrenchTable of one coil on one magnet).
    """

    def __init__(self, config: DeviceConfig, table: WrenchTable):
        self.config = config
        self.instrument = config.instrument_spec()
        self.table = table
        self.p_ACj = np.ascontiguousarray(config.array.coil_positions_A())
        self.p_IM = np.ascontiguousarray(self.instrument.p_IM)
        self._values = table.kernel_values
        self._axes = np.ascontiguousarray(table.axes)
        self._scratch = np.empty(24)  # kernel work space (4 tilt nodes x 6 components)

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

        Takes float64 arrays (others are converted, at some cost); raises
        ValueError for a non-finite pose or an R_AI that is not a rotation.
        """
        if not (type(p_AI) is np.ndarray and p_AI.dtype == np.float64):
            p_AI = np.asarray(p_AI, dtype=float)
        if not (type(R_AI) is np.ndarray and R_AI.dtype == np.float64):
            R_AI = np.asarray(R_AI, dtype=float)
        if p_AI.shape != (3,) or R_AI.shape != (3, 3):
            raise ValueError(f"p_AI shape {p_AI.shape}, R_AI shape {R_AI.shape}: "
                             "must be (3,) and (3, 3)")
        status, matrix = wrench_matrix_kernel(self._values, self._axes, self.p_ACj,
                                              self.p_IM, p_AI, R_AI, self._scratch)
        if status != POSE_OK:
            name = "p_AI or R_AI" if status == POSE_NOT_FINITE else "R_AI"
            problem = "must be finite" if status == POSE_NOT_FINITE else "must be a rotation"
            raise ValueError(f"{name} = {p_AI!r}, {R_AI!r}: {problem}")
        return matrix

    def coil_magnet_wrench(self, p_CM, u_C) -> tuple[np.ndarray, np.ndarray]:
        """(force [N/A], torque [N m/A]) of one coil at +1 A on one instrument magnet.

        p_CM [m] is the magnet centre and u_C its unit magnetization axis, both in
        the coil frame C; the torque is about the magnet centre, in C axes. Zero
        beyond the table's reach (``cutoffs``).
        """
        p, u = check_magnet_pose(p_CM, u_C)
        wrench = coil_magnet_kernel(self._values, self._axes, p, u, self._scratch)
        return wrench[:3], wrench[3:]

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
    (~10 s, with a progress bar) unless it is in the disk cache
    ($MAGLEV_CACHE_DIR, default ~/.cache/maglev_haptics); later calls in the
    process share it.
    """
    magnet = config.instrument_spec().magnet
    key = table_key(config.coil, magnet, grid)
    if key not in _TABLES:
        _TABLES[key] = load_wrench_table(config.coil, magnet, grid)
    return MagneticsModel(config, _TABLES[key])


def bench_wrench_matrix(config: DeviceConfig, n: int = 2000, seed: int = 0) -> dict:
    """Time ``wrench_matrix_from`` after warm-up: microseconds per call.

    Poses wander within +/-20 mm and 20 deg tilt of a level hover 25 mm above
    the coil tops, as the 1 kHz loop would see them. Returns instrument, pairs,
    mean_us, median_us, p99_us, n.
    """
    model = load_magnetics(config)
    rng = np.random.default_rng(seed)
    offsets = rng.uniform(-0.02, 0.02, (n, 3)) + [0.0, 0.0, 0.025]
    tilts = rng.normal(0.0, np.radians(10.0), (n, 3))
    poses = [(offsets[i], _rotation_from_vector(tilts[i])) for i in range(n)]
    for p_AI, R_AI in poses[:50]:
        model.wrench_matrix_from(p_AI, R_AI)
    times = np.empty(n)
    for i, (p_AI, R_AI) in enumerate(poses):
        start = time.perf_counter()
        model.wrench_matrix_from(p_AI, R_AI)
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
