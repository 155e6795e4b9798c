"""The 4-D table of coil-on-magnet wrenches per ampere, its build and its cache.

By the coil's axial symmetry the wrench of a coil on a magnet depends only on
rho (radial offset of the magnet centre from the coil axis) [m], z (height of the
magnet centre above the coil top) [m] and the magnet axis u seen from the local
basis (e_r radial, e_t tangential, e_z up): tilt theta from +z [rad] toward the
direction psi, measured from e_r toward e_t [rad]. The tilt is tabulated as the
vector w = theta * (cos psi, sin psi) [rad] on a uniform Cartesian grid (the
azimuthal-equidistant map of u), which is smooth through theta = 0 and equally
fine in every direction: a polar (theta, psi) grid crowds nodes at small tilts
and is coarse across the tilt direction at large ones (measured: 15 deg psi steps
give 0.4 % torque errors where 5 deg steps in w give 0.08 %, with fewer nodes).

The table holds the six local components (F_r, F_t, F_z [N/A], tau_r, tau_t,
tau_z [N m/A], torque about the magnet centre) on: rho stretched (sinh, dense near
the coil), z log-uniform, w_r and w_t uniform over [-tilt_max, tilt_max]. Entries
come from the surface-charge model (``charge_model``), built in parallel with numba
and cached as .npz under $MAGLEV_CACHE_DIR (default ~/.cache/maglev_haptics),
keyed by a hash of everything that sets them.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import pathlib
import tempfile

import numba
import numpy as np
from tqdm import tqdm

from maglev_haptics.hardware import coil_field
from maglev_haptics.hardware.charge_model import (
    CAP_RULES, charge_model_wrench, clearance, tiered_disk_quadrature)
from maglev_haptics.hardware.device import CoilSpec, MagnetSpec
from maglev_haptics.hardware.interpolation import (
    AXIS_LOG, AXIS_SINH, AXIS_UNIFORM, axis_nodes, make_axis)

# Bump when the method (physics, quadrature, layout) changes: it keys the cache.
TABLE_VERSION = 5
# Sign of each local component under the mirror w_t -> -w_t: reflecting the pose
# in the plane of e_r and e_z maps (F_r, F_t, F_z, tau_r, tau_t, tau_z) to
# (F_r, -F_t, F_z, -tau_r, tau_t, -tau_z) (force is a polar vector, torque and
# magnetization axial ones, and the reflected coil current is reversed).
MIRROR_PARITY = np.array([1.0, -1.0, 1.0, -1.0, 1.0, -1.0])


@dataclasses.dataclass(frozen=True)
class WrenchGrid:
    """Extent and resolution of the wrench table."""

    rho_max_m: float = 0.200  # beyond: the pair contributes nothing (past the array's far corner)
    rho_scale_m: float = 0.010  # sinh stretching scale: spacing ~ scale * step near the axis
    rho_step: float = 0.10  # step in asinh(rho / scale): 1 mm at the axis, 20 mm at 200 mm
    z_min_m: float = 0.006  # lower magnets are read here (they would be inside the display)
    z_max_m: float = 0.130  # beyond: the pair contributes nothing
    z_log_step: float = 0.10  # step in ln z (10 % spacing)
    tilt_max_rad: float = math.radians(55.0)  # |w_r|, |w_t| beyond are clamped to this
    tilt_step_rad: float = math.radians(2.5)  # fine: the kernel's tilt stencils are quadratic

    def axes(self) -> np.ndarray:
        """Axis descriptors (``interpolation.make_axis``) rho, z, w_r, w_t, stacked (4, 6)."""
        rho = make_axis(AXIS_SINH, 0.0, self.rho_max_m, self.rho_step, scale=self.rho_scale_m)
        z = make_axis(AXIS_LOG, self.z_min_m, self.z_max_m, self.z_log_step)
        # An even number of steps puts a node at w = 0, the mirror plane.
        steps = 2 * math.ceil(self.tilt_max_rad / self.tilt_step_rad - 1e-9)
        tilt = make_axis(AXIS_UNIFORM, -self.tilt_max_rad, self.tilt_max_rad,
                         2 * self.tilt_max_rad / steps)
        return np.stack([rho, z, tilt, tilt])


@dataclasses.dataclass(frozen=True)
class WrenchTable:
    """A built table: ``values[i_rho, i_z, i_wr, i_wt]`` = (F_r, F_t, F_z [N/A],
    tau_r, tau_t, tau_z [N m/A]) and ``axes`` (4, 6): rho, z, w_r, w_t.

    Values are float32 (1e-7 relative, far below the interpolation error): half
    the memory (59 MB) and cache traffic of float64, and float32 SIMD sums in
    the run-time kernel.
    """

    values: np.ndarray
    axes: np.ndarray

    @property
    def kernel_values(self) -> np.ndarray:
        """``values`` with (w_t, component) merged, as the run-time kernel wants (a view)."""
        return self.values.reshape(*self.values.shape[:3], -1)


def tilt_axis(w_r: float, w_t: float) -> tuple[float, float, float]:
    """Unit magnet axis (u_r, u_t, u_z) of the tilt vector (w_r, w_t) [rad]."""
    theta = math.hypot(w_r, w_t)
    # sin(theta) / theta, finite at theta = 0.
    scale = math.sin(theta) / theta if theta > 0.0 else 1.0
    return w_r * scale, w_t * scale, math.cos(theta)


tilt_axis_jit = numba.njit(cache=True, inline="always")(tilt_axis)


@numba.njit(parallel=True, cache=True)
def _wrench_slice(field_tables, outer_radius, half_height, cap_radius, surface_charge,
                  rule_points, rule_weights, rule_starts, rule_clearances,
                  rho_nodes, z, w_r_nodes, w_t_nodes, out):
    """Fill out[i_rho, i_wr, i_wt, :] for one height z [m], each pose with the
    coarsest cap rule its clearance allows."""
    n_rho, n_r, n_t = rho_nodes.size, w_r_nodes.size, w_t_nodes.size
    # rho varies fastest so that every thread's contiguous share of the range
    # mixes cheap (far) and costly (near) poses.
    for flat in numba.prange(n_rho * n_r * n_t):
        i_rho = flat % n_rho
        i_t = (flat // n_rho) % n_t
        i_r = flat // (n_rho * n_t)
        rho = rho_nodes[i_rho]
        u_r, u_t, u_z = tilt_axis_jit(w_r_nodes[i_r], w_t_nodes[i_t])
        gap = clearance(outer_radius, half_height, cap_radius, rho, z, u_z,
                        math.sqrt(u_r * u_r + u_t * u_t))
        tier = 0
        while gap < rule_clearances[tier]:
            tier += 1
        first, last = rule_starts[tier], rule_starts[tier + 1]
        # Magnet at azimuth 0, so e_r = x, e_t = y and C components are local ones.
        out[i_rho, i_r, i_t, :] = charge_model_wrench(
            field_tables, half_height, surface_charge, rule_points[first:last],
            rule_weights[first:last], np.array([rho, 0.0, z]), np.array([u_r, u_t, u_z]))


def build_wrench_table(coil: CoilSpec, magnet: MagnetSpec, grid: WrenchGrid = WrenchGrid(),
                       progress: bool = True) -> WrenchTable:
    """Compute the table (no cache); 10-20 s per magnet kind on 2 cores.

    Only w_t >= 0 is computed; the rest follows by the mirror (MIRROR_PARITY).
    """
    field_tables = coil_field.coil_field_tables(coil)
    cap_radius = magnet.diameter_m / 2
    rules = tiered_disk_quadrature(cap_radius)
    axes = grid.axes()
    rho_nodes, z_nodes, w_nodes = (axis_nodes(a) for a in axes[:3])
    mirror = w_nodes.size // 2  # index of w = 0
    values = np.empty((rho_nodes.size, z_nodes.size, w_nodes.size, w_nodes.size, 6))
    slice_values = np.empty((rho_nodes.size, w_nodes.size, w_nodes.size - mirror, 6))
    for i_z in tqdm(range(z_nodes.size), desc=f"wrench table ({magnet.diameter_m * 1e3:.1f} mm"
                    f" magnet)", unit="height", disable=not progress):
        _wrench_slice(field_tables, coil.outer_diameter_m / 2, magnet.height_m / 2, cap_radius,
                      magnet.remanence_t / coil_field.MU0, *rules, rho_nodes, z_nodes[i_z],
                      w_nodes, w_nodes[mirror:], slice_values)
        values[:, i_z, :, mirror:] = slice_values
    values[:, :, :, :mirror] = values[:, :, :, :mirror:-1] * MIRROR_PARITY  # w_t = -w_t'
    return WrenchTable(values.astype(np.float32), axes)


def table_key(coil: CoilSpec, magnet: MagnetSpec, grid: WrenchGrid) -> str:
    """Canonical description of everything that sets the table's values."""
    return json.dumps({
        "version": TABLE_VERSION,
        "coil": [coil.inner_diameter_m, coil.outer_diameter_m, coil.height_m, coil.turns],
        "magnet": [magnet.diameter_m, magnet.height_m, magnet.remanence_t],
        "grid": dataclasses.asdict(grid),
        "field": [coil_field.FIELD_RHO_MAX_M, coil_field.FIELD_Z_MAX_M,
                  coil_field.FIELD_RHO_SCALE_M, coil_field.FIELD_Z_SCALE_M,
                  coil_field.FIELD_STEP, coil_field.FIELD_ORDER],
        "cap": [list(rule) for rule in CAP_RULES],
    }, sort_keys=True)


def cache_dir() -> pathlib.Path:
    """$MAGLEV_CACHE_DIR, default ~/.cache/maglev_haptics."""
    return pathlib.Path(os.environ.get("MAGLEV_CACHE_DIR",
                                       pathlib.Path.home() / ".cache" / "maglev_haptics"))


def cache_path(coil: CoilSpec, magnet: MagnetSpec, grid: WrenchGrid) -> pathlib.Path:
    digest = hashlib.sha256(table_key(coil, magnet, grid).encode()).hexdigest()[:16]
    return cache_dir() / f"wrench_table_{digest}.npz"


def load_wrench_table(coil: CoilSpec, magnet: MagnetSpec, grid: WrenchGrid = WrenchGrid(),
                      progress: bool = True) -> WrenchTable:
    """The table from the cache, building and caching it when absent."""
    path = cache_path(coil, magnet, grid)
    key = table_key(coil, magnet, grid)
    if path.exists():
        with np.load(path) as stored:
            if str(stored["key"]) == key:
                return WrenchTable(stored["values"], stored["axes"])
    table = build_wrench_table(coil, magnet, grid, progress)
    path.parent.mkdir(parents=True, exist_ok=True)
    # Write then rename, so concurrent processes never read a partial file.
    with tempfile.NamedTemporaryFile(dir=path.parent, suffix=".npz", delete=False) as handle:
        np.savez(handle, key=key, values=table.values, axes=table.axes)
    os.chmod(handle.name, 0o644)  # readable by others sharing the cache, like any cache file
    os.replace(handle.name, path)
    return table
