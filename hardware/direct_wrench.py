"""Independent reference: coil-magnet wrench from magpylib's magnet field.

The magnet (``magpylib`` cylinder of polarization Br along its axis u, placed at
p_CM) acts on the coil's winding current with the Lorentz force
dF = J x B dV, J = turns * I / winding_area along +phi [A/m^2]. The closed system
exerts no net force or torque on itself, so the magnet feels F = -sum dF and, about
its centre c, tau = -sum (r - c) x dF. The winding volume is integrated with
Gauss-Legendre nodes in radius and height and uniform angles. It shares no
physics or quadrature with the tabulated model; at ~5 ms per pose it is for tests
and studies, not for the loop.
"""

from __future__ import annotations

import numpy as np
from magpylib.func import cylinder_field
from scipy.spatial.transform import Rotation

from maglev_haptics.hardware.device import CoilSpec, MagnetSpec
from maglev_haptics.hardware.magnetics import check_magnet_pose

# (radial, axial, angular) nodes over the winding: converged to ~1e-6 of the
# wrench for magnets clear of the coil's top face by 1.5 mm or more.
DIRECT_ORDER = (10, 20, 64)


def _axis_rotation(u: np.ndarray) -> Rotation:
    """The rotation taking +z to the unit vector u by the shortest arc."""
    axis = np.cross([0.0, 0.0, 1.0], u)
    sin_angle = np.linalg.norm(axis)
    angle = np.arctan2(sin_angle, u[2])
    if sin_angle < 1e-15:
        return Rotation.from_rotvec([np.pi, 0.0, 0.0] if u[2] < 0 else [0.0, 0.0, 0.0])
    return Rotation.from_rotvec(axis / sin_angle * angle)


def winding_quadrature(coil: CoilSpec, order=DIRECT_ORDER) -> tuple[np.ndarray, np.ndarray]:
    """Points (n, 3) [m] in C over the winding and their volumes (n,) [m^3]."""
    radial_order, axial_order, angular_order = order
    inner, outer = coil.inner_diameter_m / 2, coil.outer_diameter_m / 2
    x_r, w_r = np.polynomial.legendre.leggauss(radial_order)
    x_z, w_z = np.polynomial.legendre.leggauss(axial_order)
    rho = (inner + outer) / 2 + (outer - inner) / 2 * x_r
    z = -coil.height_m / 2 + coil.height_m / 2 * x_z
    phi = 2 * np.pi * np.arange(angular_order) / angular_order
    rho_g, z_g, phi_g = np.meshgrid(rho, z, phi, indexing="ij")
    volume = (np.multiply.outer(np.outer((outer - inner) / 2 * w_r * rho, coil.height_m / 2 * w_z),
                                np.full(angular_order, 2 * np.pi / angular_order)))
    points = np.stack([rho_g * np.cos(phi_g), rho_g * np.sin(phi_g), z_g], axis=-1)
    return points.reshape(-1, 3), volume.ravel()


def direct_coil_magnet_wrench(coil: CoilSpec, magnet: MagnetSpec, p_CM, u_C,
                              order=DIRECT_ORDER) -> tuple[np.ndarray, np.ndarray]:
    """(force [N/A], torque about the magnet centre [N m/A]) on the magnet, C axes.

    For +1 A in the coil; p_CM [m] is the magnet centre and u_C its unit
    magnetization axis in the coil frame C. ``order`` = (radial, axial, angular)
    quadrature nodes over the winding.
    """
    p, u = check_magnet_pose(p_CM, u_C)
    points, volumes = winding_quadrature(coil, order)
    field = cylinder_field("B", observers=points,
                           dimensions=(magnet.diameter_m, magnet.height_m),
                           polarizations=(0.0, 0.0, magnet.remanence_t),
                           positions=p, orientations=_axis_rotation(u))
    inner, outer = coil.inner_diameter_m / 2, coil.outer_diameter_m / 2
    current_density = coil.turns / ((outer - inner) * coil.height_m)  # [A/m^2] at 1 A
    rho = np.hypot(points[:, 0], points[:, 1])
    j = current_density * np.stack([-points[:, 1] / rho, points[:, 0] / rho,
                                    np.zeros(len(rho))], axis=1)
    force_on_coil = np.cross(j, field) * volumes[:, None]
    force = -force_on_coil.sum(axis=0)
    torque = -np.cross(points - p, force_on_coil).sum(axis=0)
    return force, torque
