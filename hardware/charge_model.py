"""Exact wrench of one coil on one cylindrical magnet: the surface-charge model.

A uniformly axially magnetized cylinder (remanence Br [T], magnetization
M = Br / mu0 [A/m] along its unit axis u) carries magnetic surface charge
sigma = M . n only on its end caps: +Br/mu0 on the top cap (outward normal u),
-Br/mu0 on the bottom one. In the coil's field B (curl-free wherever the magnet
can be) the force and the torque about the magnet centre c are exactly

    F   = (Br/mu0) [ int_top B dA - int_bottom B dA ]                      [N]
    tau = (Br/mu0) [ int_top (r - c) x B dA - int_bottom (r - c) x B dA ]  [N m]

with no dipole approximation. Each cap is integrated with a polar Gauss rule:
Gauss-Legendre in radius (weight r dr), uniform in angle. B comes from the
coil's field tables (``coil_field``), so everything here is per ampere.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from maglev_haptics.hardware.coil_field import MU0, coil_field_tables, interpolate_field
from maglev_haptics.hardware.device import CoilSpec, MagnetSpec

# Cap quadrature (Gauss-Legendre nodes in radius, uniform angles) by the magnet's
# clearance from the coil (``clearance``): (minimum clearance [m], radial, angular).
# Each tier is converged to ~1e-4 of the wrench (and of 1 % of its largest value
# at that height) over its clearance range. Closer poses (mostly ones with the
# magnet inside the display or the coil) get the finest tier; using (12, 48)
# there instead changes the table's errors at 15-18 mm by less than 1e-5.
CAP_RULES = ((0.015, 4, 12), (0.005, 6, 16), (-np.inf, 8, 24))
# ChargeModel's default: converged to ~1e-6 down to 2 mm clearance.
CAP_RADIAL_ORDER, CAP_ANGULAR_ORDER = 12, 48


def disk_quadrature(radius_m: float, radial_order: int, angular_order: int
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Polar Gauss rule on a disk: points (n, 2) [m] in the disk plane, weights (n,) [m^2].

    Exact for polynomials of degree < 2 * radial_order in r and trigonometric
    ones of degree < angular_order in angle.
    """
    x, w = np.polynomial.legendre.leggauss(radial_order)
    r = radius_m * (1 + x) / 2
    radial_weights = radius_m / 2 * w * r
    # Angles symmetric about 0 (half-step offset) so the rule is mirror-symmetric
    # about the tilt plane.
    angles = 2 * np.pi * (np.arange(angular_order) + 0.5) / angular_order
    points = np.stack([np.outer(r, np.cos(angles)), np.outer(r, np.sin(angles))], axis=-1)
    weights = np.outer(radial_weights, np.full(angular_order, 2 * np.pi / angular_order))
    return points.reshape(-1, 2), weights.ravel()


def tiered_disk_quadrature(radius_m: float, rules=CAP_RULES) -> tuple[np.ndarray, ...]:
    """All tiers of ``rules`` on a disk of ``radius_m`` [m], concatenated.

    Returns (points (n, 2) [m], weights (n,) [m^2], starts (n_tiers + 1,) into
    them, minimum clearances (n_tiers,) [m]).
    """
    rules_points, rules_weights = zip(*(disk_quadrature(radius_m, radial, angular)
                                        for _, radial, angular in rules))
    starts = np.cumsum([0] + [len(w) for w in rules_weights])
    return (np.concatenate(rules_points), np.concatenate(rules_weights), starts,
            np.array([minimum for minimum, _, _ in rules]))


@numba.njit(cache=True, inline="always")
def clearance(outer_radius, half_height, cap_radius, rho, z, cos_theta, sin_theta):
    """Lower bound [m] on the distance between a magnet and the coil's winding.

    The larger of the height of the magnet's lowest point above the coil's top
    face and the horizontal gap between the magnet's bounding sphere and the
    winding's outer radius; rho, z [m] locate the magnet centre.
    """
    lowest = z - half_height * cos_theta - cap_radius * sin_theta
    sideways = rho - outer_radius - math.sqrt(half_height * half_height + cap_radius * cap_radius)
    return max(lowest, sideways)


@numba.njit(cache=True)
def charge_model_wrench(field_tables, half_height, surface_charge, disk_points, disk_weights,
                        p_CM, u_C):
    """Wrench per ampere on a magnet at p_CM [m] with unit axis u_C, coil frame C.

    ``surface_charge`` = Br / mu0 [A/m]; ``disk_points`` (n, 2) [m] and
    ``disk_weights`` (n,) [m^2] a rule on the cap disk (``disk_quadrature``).
    Returns (6,): force [N/A] then torque about the magnet centre [N m/A], C axes.
    """
    rho_axis, above_axis, above_table, below_axis, below_table = field_tables
    ux, uy, uz = u_C[0], u_C[1], u_C[2]
    # Cap-plane axes: e1 in the tilt plane, e2 horizontal. Tying them to the tilt
    # direction keeps the rule mirror-symmetric about the tilt plane.
    tilt = math.sqrt(ux * ux + uy * uy)
    if tilt > 1e-12:
        cos_dir, sin_dir = ux / tilt, uy / tilt
    else:
        cos_dir, sin_dir = 1.0, 0.0
    e1 = (uz * cos_dir, uz * sin_dir, -tilt)
    e2 = (-sin_dir, cos_dir, 0.0)
    wrench = np.zeros(6)
    for cap_sign in (1.0, -1.0):
        for k in range(disk_weights.shape[0]):
            a, b = disk_points[k, 0], disk_points[k, 1]
            # Point relative to the magnet centre, then in the coil frame.
            dx = cap_sign * half_height * ux + a * e1[0] + b * e2[0]
            dy = cap_sign * half_height * uy + a * e1[1] + b * e2[1]
            dz = cap_sign * half_height * uz + a * e1[2] + b * e2[2]
            x, y, z = p_CM[0] + dx, p_CM[1] + dy, p_CM[2] + dz
            rho = math.sqrt(x * x + y * y)
            b_rho, b_z = interpolate_field(rho_axis, above_axis, above_table,
                                           below_axis, below_table, rho, z)
            if rho > 0.0:
                bx, by = b_rho * x / rho, b_rho * y / rho
            else:
                bx, by = 0.0, 0.0
            q = cap_sign * surface_charge * disk_weights[k]  # charge [A m]
            wrench[0] += q * bx
            wrench[1] += q * by
            wrench[2] += q * b_z
            wrench[3] += q * (dy * b_z - dz * by)
            wrench[4] += q * (dz * bx - dx * b_z)
            wrench[5] += q * (dx * by - dy * bx)
    return wrench


class ChargeModel:
    """The surface-charge wrench of one coil kind on one magnet kind, per ampere."""

    def __init__(self, coil: CoilSpec, magnet: MagnetSpec,
                 radial_order: int = CAP_RADIAL_ORDER, angular_order: int = CAP_ANGULAR_ORDER):
        self.field_tables = coil_field_tables(coil)
        self.half_height_m = magnet.height_m / 2
        self.surface_charge_a_per_m = magnet.remanence_t / MU0
        self.disk_points, self.disk_weights = disk_quadrature(
            magnet.diameter_m / 2, radial_order, angular_order)

    def wrench(self, p_CM: np.ndarray, u_C: np.ndarray) -> np.ndarray:
        """(6,) force [N/A] and torque about the magnet centre [N m/A] in C."""
        return charge_model_wrench(self.field_tables, self.half_height_m,
                                   self.surface_charge_a_per_m, self.disk_points,
                                   self.disk_weights, np.array(p_CM, dtype=float),
                                   np.array(u_C, dtype=float))
