"""What the device can deliver: force, torque and workspace limits (CHAI3D's
``cHapticDeviceInfo``), from the coil current limits rather than literals.

At an instrument pose the coils' wrench is A(X) I with A the (6, n) wrench
matrix of ``magnetics``. The largest force the coils can add along a unit
direction d on top of carrying the instrument's weight is the linear program

    maximize s  subject to  A I = w_weight + s [d; 0],  |I_j| <= I_limit,  s >= 0,

(torques likewise with [0; d]), solved with HiGHS. The per-coil limit is the
amplifier's peak current or the coils' continuous thermal limit (``thermal``).
These are what the coils can do with the best allocation; the minimum-norm
allocator reaches somewhat less near the limits.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse
from scipy.optimize import linprog

from maglev_haptics.hardware.constants import GRAVITY_M_S2
from maglev_haptics.hardware.device import DeviceConfig
from maglev_haptics.hardware.magnetics import MagneticsModel, load_magnetics
from maglev_haptics.hardware.thermal import coil_thermal, weakest_coil_current_limit_a

LIMIT_KINDS = ("peak", "thermal")
# The six axis directions +x, +y, +z, -x, -y, -z.
AXIS_DIRECTIONS = np.vstack([np.eye(3), -np.eye(3)])
# Tight enough that A I meets its target to ~1e-9 N and no current passes its
# limit by more than ~1e-9 A; HiGHS's default (1e-7) is looser.
_HIGHS_OPTIONS = {"primal_feasibility_tolerance": 1e-10, "dual_feasibility_tolerance": 1e-10}
# Vertical resolution of the workspace's hover ceiling [m].
_HEIGHT_RESOLUTION_M = 1e-4


@dataclass
class DeviceLimits:
    """The device's deliverable wrench at one instrument pose, and its workspace.

    Forces [N] and torques [N m] are what the coils can add on top of carrying
    the instrument's weight, along (about) the A-frame axes; all zero where the
    weight alone is out of reach (``can_hover`` False).
    """

    limit: str  # "peak" (amplifier) or "thermal" (continuous, coil heating)
    current_limit_a: float  # per-coil current bound used [A]
    p_AI_m: np.ndarray  # instrument origin in A where evaluated, (3,) [m]
    R_AI: np.ndarray  # instrument orientation in A, (3, 3)
    hover_current_a: float  # smallest possible largest-coil current carrying the weight [A]
    force_plus_n: np.ndarray  # largest extra force along +x, +y, +z, (3,) [N]
    force_minus_n: np.ndarray  # along -x, -y, -z, (3,) [N]
    torque_plus_nm: np.ndarray  # largest extra torque about +x, +y, +z, (3,) [N m]
    torque_minus_nm: np.ndarray  # about -x, -y, -z, (3,) [N m]
    workspace_min_A_m: np.ndarray  # lower corner of I's reachable box in A, (3,) [m]
    workspace_max_A_m: np.ndarray  # upper corner, (3,) [m]

    @property
    def can_hover(self) -> bool:
        return self.hover_current_a <= self.current_limit_a

    @property
    def max_force_n(self) -> float:
        """The smallest of the six axis force limits [N] (CHAI3D's m_maxLinearForce;
        a direction between the axes may reach somewhat less)."""
        return float(min(self.force_plus_n.min(), self.force_minus_n.min()))

    @property
    def max_torque_nm(self) -> float:
        """The smallest of the six axis torque limits [N m] (m_maxAngularTorque)."""
        return float(min(self.torque_plus_nm.min(), self.torque_minus_nm.min()))


def _check_limit(current_limit_a) -> float:
    value = float(current_limit_a)
    if not (np.isfinite(value) and value >= 0):
        raise ValueError(f"current_limit_a = {current_limit_a!r}: must be a finite number >= 0 [A]")
    return value


def _check_wrench_matrix(A) -> np.ndarray:
    A = np.asarray(A, dtype=float)
    if A.ndim != 2 or A.shape[0] != 6 or not np.all(np.isfinite(A)):
        raise ValueError(f"A shape {A.shape}: must be a finite (6, n_coils) wrench matrix")
    return A


def _check_wrench(name: str, wrench) -> np.ndarray:
    wrench = np.asarray(wrench, dtype=float)
    if wrench.shape != (6,) or not np.all(np.isfinite(wrench)):
        raise ValueError(f"{name} = {wrench!r}: must be 6 finite numbers [N, N m]")
    return wrench


def weight_wrench(config: DeviceConfig) -> np.ndarray:
    """[f; tau] (6,) [N, N m] the coils must supply to carry the instrument."""
    return np.array([0.0, 0.0, config.instrument_spec().mass_kg * GRAVITY_M_S2, 0.0, 0.0, 0.0])


def coil_current_limit_a(config: DeviceConfig, limit: str) -> float:
    """Per-coil current bound [A]: the amplifier's peak, or for ``"thermal"``
    the continuous thermal limit of the weakest coil (never above the peak)."""
    peak = _check_limit(config.amplifier.current_limit_a)
    if limit == "peak":
        return peak
    if limit == "thermal":
        return min(peak, weakest_coil_current_limit_a(coil_thermal(config)))
    raise ValueError(f"limit = {limit!r}: must be one of {', '.join(LIMIT_KINDS)}")


def hover_current_a(A, wrench) -> float:
    """Smallest max_j |I_j| [A] over all currents with A I = wrench; inf if none does.

    The LP: minimize t subject to A I = wrench, -t <= I_j <= t.
    """
    A = _check_wrench_matrix(A)
    wrench = _check_wrench("wrench", wrench)
    n = A.shape[1]
    identity = scipy.sparse.identity(n, format="csr")
    column = scipy.sparse.csr_matrix(np.ones((n, 1)))
    result = linprog(
        np.r_[np.zeros(n), 1.0],
        A_ub=scipy.sparse.bmat([[identity, -column], [-identity, -column]]),
        b_ub=np.zeros(2 * n),
        A_eq=np.c_[A, np.zeros(6)], b_eq=wrench,
        bounds=[(None, None)] * n + [(0, None)], method="highs", options=_HIGHS_OPTIONS)
    return float(result.x[-1]) if result.status == 0 else float("inf")


def max_added_wrench(A, base_wrench, directions, current_limit_a):
    """(s (k,), currents (k, n)): the largest s_i >= 0 [N or N m] with
    A I_i = base_wrench + s_i u_i, |I_ij| <= current_limit_a [A], for each unit
    u_i = directions[i] / |directions[i]| ((k, 6) [f; tau] directions).

    One LP with the k problems as independent diagonal blocks (one HiGHS call
    instead of k). ValueError if even base_wrench is out of reach.
    """
    A = _check_wrench_matrix(A)
    base = _check_wrench("base_wrench", base_wrench)
    limit = _check_limit(current_limit_a)
    D = np.atleast_2d(np.asarray(directions, dtype=float))
    if D.ndim != 2 or D.shape[1] != 6 or not np.all(np.isfinite(D)):
        raise ValueError(f"directions shape {D.shape}: must be finite, (k, 6)")
    norms = np.linalg.norm(D, axis=1)
    if np.any(norms == 0):
        raise ValueError(f"directions rows {np.flatnonzero(norms == 0).tolist()}: zero length")
    D = D / norms[:, None]
    k, n = D.shape[0], A.shape[1]
    blocks = [scipy.sparse.csr_array(np.hstack([A, -d[:, None]])) for d in D]
    cost = np.tile(np.r_[np.zeros(n), -1.0], k)
    bounds = [(-limit, limit)] * n + [(0, None)]
    result = linprog(cost, A_eq=scipy.sparse.block_diag(blocks, format="csr"),
                     b_eq=np.tile(base, k), bounds=bounds * k, method="highs",
                     options=_HIGHS_OPTIONS)
    if result.status != 0:
        raise ValueError(f"base_wrench = {base!r}: out of reach with current_limit_a = {limit} A "
                         f"({result.message})")
    x = result.x.reshape(k, n + 1)
    return x[:, n], x[:, :n]


def hover_workspace_A(config: DeviceConfig, current_limit_a: float,
                      magnetics: MagneticsModel | None = None):
    """(lower, upper) corners (3,) [m] in A of the box the instrument's origin can occupy.

    Horizontally the coil array's extent (outermost coil rims); vertically from
    resting level on the display up to the highest level hover over the array
    centre that the weight allows within ``current_limit_a`` [A], found by
    bisection to 0.1 mm (the hover current grows with height). Where even the
    resting height is out of reach the vertical range is that single height.
    """
    limit = _check_limit(current_limit_a)
    model = magnetics if magnetics is not None else load_magnetics(config)
    radius = config.coil.outer_diameter_m / 2
    centres = config.array.coil_positions_A()
    bottom = config.display.thickness_m + config.instrument_spec().rest_height_m
    weight = weight_wrench(config)

    def hovers(height_m: float) -> bool:
        A = model.wrench_matrix_from(np.array([0.0, 0.0, height_m]), np.eye(3))
        return hover_current_a(A, weight) <= limit

    low, high = bottom, model.cutoffs()["z_max_m"]
    if not hovers(low):
        high = low
    elif hovers(high):
        low = high
    while high - low > _HEIGHT_RESOLUTION_M:
        middle = (low + high) / 2
        low, high = (middle, high) if hovers(middle) else (low, middle)
    lower = np.r_[centres[:, :2].min(axis=0) - radius, bottom]
    upper = np.r_[centres[:, :2].max(axis=0) + radius, low]
    return lower, upper


def device_limits(config: DeviceConfig, p_AI, R_AI, *, limit: str = "thermal",
                  magnetics: MagneticsModel | None = None,
                  workspace: tuple | None = None) -> DeviceLimits:
    """DeviceLimits at the instrument pose p_AI (3,) [m], R_AI (3, 3) in A.

    ``limit`` is "thermal" (sustainable) or "peak" (amplifier). ``magnetics``
    and ``workspace`` (a ``hover_workspace_A`` result for the same limit) may be
    passed to reuse them across poses. ValueError names a bad argument.
    """
    current_limit = coil_current_limit_a(config, limit)
    model = magnetics if magnetics is not None else load_magnetics(config)
    A = model.wrench_matrix_from(p_AI, R_AI)  # validates p_AI and R_AI
    if workspace is None:
        workspace = hover_workspace_A(config, current_limit, model)
    weight = weight_wrench(config)
    hover = hover_current_a(A, weight)
    directions = np.zeros((12, 6))
    directions[:6, :3] = AXIS_DIRECTIONS
    directions[6:, 3:] = AXIS_DIRECTIONS
    if hover <= current_limit:
        added, _ = max_added_wrench(A, weight, directions, current_limit)
    else:
        added = np.zeros(12)
    return DeviceLimits(
        limit=limit, current_limit_a=current_limit,
        p_AI_m=np.array(p_AI, dtype=float), R_AI=np.array(R_AI, dtype=float),
        hover_current_a=hover,
        force_plus_n=added[0:3], force_minus_n=added[3:6],
        torque_plus_nm=added[6:9], torque_minus_nm=added[9:12],
        workspace_min_A_m=np.asarray(workspace[0], dtype=float),
        workspace_max_A_m=np.asarray(workspace[1], dtype=float))
