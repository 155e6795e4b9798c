"""Magnetic field of one coil per ampere, exact and tabulated.

The coil is a thick air-core solenoid (``CoilSpec``): windings fill the annulus
inner_radius <= rho <= outer_radius, -height <= z <= 0 of its frame C (origin at
the centre of the top face, z up along the axis) with uniform current density
J = turns * I / ((outer_radius - inner_radius) * height) [A/m^2] circulating
counter-clockwise seen from above for I > 0, so B_z > 0 on the axis.

Exact field: the winding is a continuum of thin solenoid sheets of radius a and
surface current J da [A/m]. A sheet's field is, by the Amperian equivalence,
exactly the B-field of an axially magnetized cylinder with polarization
mu0 * J da [T], which magpylib evaluates in closed form (Derby 2010), so the
axial integral is exact and only the radial one is done by Gauss-Legendre
quadrature. Splitting it at the observer's radius (where a sheet's B_z jumps)
makes it converge spectrally everywhere, inside the winding and right at the top
face included; summing current loops over a 2-D quadrature instead converges
slowly within a few tenths of a millimetre of the face and not at all inside it.

Tabulated field: B_rho, B_z per ampere on a (rho, z) grid stretched as
x = scale * sinh(s) with s uniform (fine near the coil, coarse far away), read by
4-point Lagrange interpolation along each axis (``interpolate_field``).
"""

from __future__ import annotations

import functools

import numba
import numpy as np
from magpylib.core import magnet_cylinder_axial_Bfield

from maglev_haptics.hardware.device import CoilSpec
from maglev_haptics.hardware.interpolation import (
    AXIS_SINH, axis_nodes, clamped_position, lagrange4_weights, make_axis, stencil_start)

MU0 = 4e-7 * np.pi  # vacuum permeability [T m/A]

# Field table extent in the coil frame [m]: far enough out for any cap point of
# the wrench table (rho <= 200 mm, magnet centre z <= 130 mm), and down to the
# coil's bottom so that tilted magnets near the coil never leave it. The field
# has kinks at the top face over the winding, so the part above the face
# (z >= 0) and the part below it are separate tables, each interpolated with
# one-sided stencils at z = 0.
FIELD_RHO_MAX_M = 0.240
FIELD_Z_MAX_M = 0.200
# Stretching scales [m] and step in s: spacing ~0.36 mm at the axis, ~0.15 mm at
# the top face, ~7 mm at rho = 240 mm and ~6 mm at z = 200 mm.
FIELD_RHO_SCALE_M = 0.012
FIELD_Z_SCALE_M = 0.005
FIELD_STEP = 0.03
FIELD_ORDER = 32  # Gauss-Legendre nodes per radial sub-interval (converged to 1e-12)


def _check_finite(name: str, value: np.ndarray) -> None:
    if not np.all(np.isfinite(value)):
        raise ValueError(f"{name} = {value!r}: must be finite")


def current_density_per_ampere(coil: CoilSpec) -> float:
    """Winding current density at 1 A [A/m^2]."""
    inner, outer = coil.inner_diameter_m / 2, coil.outer_diameter_m / 2
    return coil.turns / ((outer - inner) * coil.height_m)


def coil_field_exact(coil: CoilSpec, rho: np.ndarray, z: np.ndarray,
                     order: int = FIELD_ORDER) -> np.ndarray:
    """Exact field of ``coil`` at +1 A, shape (2, n): (B_rho, B_z) [T/A].

    ``rho`` >= 0 and ``z`` [m] are observer coordinates in the coil frame C
    (any shape, flattened). ``order`` is the number of Gauss-Legendre nodes on
    each side of the observer's radius.
    """
    rho = np.asarray(rho, dtype=float).ravel()
    z = np.asarray(z, dtype=float).ravel()
    if rho.shape != z.shape:
        raise ValueError(f"rho and z shapes differ: {rho.shape} vs {z.shape}")
    _check_finite("rho", rho)
    _check_finite("z", z)
    if np.any(rho < 0):
        raise ValueError(f"rho = {rho[rho < 0][0]!r}: must be >= 0")
    inner, outer = coil.inner_diameter_m / 2, coil.outer_diameter_m / 2
    nodes, weights = np.polynomial.legendre.leggauss(order)
    split = np.clip(rho, inner, outer)[:, None]
    # Sheet radii and weights [m] on [inner, split] and [split, outer]; an empty
    # interval has zero weight.
    radii = np.concatenate([(inner + split) / 2 + (split - inner) / 2 * nodes,
                            (split + outer) / 2 + (outer - split) / 2 * nodes], axis=1)
    widths = np.concatenate([(split - inner) / 2 * weights,
                             (outer - split) / 2 * weights], axis=1)
    half_height = coil.height_m / 2
    # magpylib's unit-polarization cylinder field in lengths scaled by its radius.
    b_unit = magnet_cylinder_axial_Bfield(
        (half_height / radii).ravel(),
        (rho[:, None] / radii).ravel(),
        ((z[:, None] + half_height) / radii).ravel())
    sheet_polarization = MU0 * current_density_per_ampere(coil) * widths  # [T/A]
    b_rho = (sheet_polarization * b_unit[0].reshape(radii.shape)).sum(axis=1)
    b_z = (sheet_polarization * b_unit[2].reshape(radii.shape)).sum(axis=1)
    return np.stack([b_rho, b_z])


def field_axes(coil: CoilSpec) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Axis descriptors (``interpolation.make_axis``) of the field tables:
    (rho, z above the top face, z below it down to the coil's bottom)."""
    rho_axis = make_axis(AXIS_SINH, 0.0, FIELD_RHO_MAX_M, FIELD_STEP, scale=FIELD_RHO_SCALE_M)
    above_axis = make_axis(AXIS_SINH, 0.0, FIELD_Z_MAX_M, FIELD_STEP, scale=FIELD_Z_SCALE_M)
    below_axis = make_axis(AXIS_SINH, -coil.height_m, 0.0, FIELD_STEP, scale=FIELD_Z_SCALE_M)
    return rho_axis, above_axis, below_axis


def coil_field_tables(coil: CoilSpec) -> tuple[np.ndarray, ...]:
    """(rho_axis, above_axis, above_table, below_axis, below_table).

    ``above_table[i_rho, i_z]`` = (B_rho, B_z) [T/A] at the nodes of
    ``rho_axis`` x ``above_axis`` (z >= 0), likewise below the top face. Built in
    about a second; memoized per coil geometry within the process.
    """
    return _field_tables(coil.inner_diameter_m, coil.outer_diameter_m, coil.height_m,
                         coil.turns)


@functools.lru_cache(maxsize=4)
def _field_tables(inner_diameter_m: float, outer_diameter_m: float, height_m: float,
                  turns: int) -> tuple[np.ndarray, ...]:
    coil = CoilSpec(inner_diameter_m=inner_diameter_m, outer_diameter_m=outer_diameter_m,
                    height_m=height_m, turns=turns)
    rho_axis, above_axis, below_axis = field_axes(coil)
    tables = []
    for z_axis in (above_axis, below_axis):
        rho, z = np.meshgrid(axis_nodes(rho_axis), axis_nodes(z_axis), indexing="ij")
        field = coil_field_exact(coil, rho, z).reshape(2, *rho.shape)
        table = np.ascontiguousarray(np.moveaxis(field, 0, -1))
        table.flags.writeable = False
        tables.append(table)
    return (rho_axis, above_axis, tables[0], below_axis, tables[1])


@numba.njit(cache=True, inline="always")
def _interpolate_table(rho_axis, z_axis, table, rho, z):
    t_rho = clamped_position(rho_axis, rho)
    t_z = clamped_position(z_axis, z)
    i_rho = stencil_start(t_rho, rho_axis)
    i_z = stencil_start(t_z, z_axis)
    wz0, wz1, wz2, wz3 = lagrange4_weights(t_z - i_z)
    b_rho = 0.0
    b_z = 0.0
    # Tuples are iterated, not indexed: numba unrolls this, a run-time index is slow.
    for a, w_rho in enumerate(lagrange4_weights(t_rho - i_rho)):
        row = table[i_rho + a]
        b_rho += w_rho * (wz0 * row[i_z, 0] + wz1 * row[i_z + 1, 0]
                          + wz2 * row[i_z + 2, 0] + wz3 * row[i_z + 3, 0])
        b_z += w_rho * (wz0 * row[i_z, 1] + wz1 * row[i_z + 1, 1]
                        + wz2 * row[i_z + 2, 1] + wz3 * row[i_z + 3, 1])
    return b_rho, b_z


@numba.njit(cache=True, inline="always")
def interpolate_field(rho_axis, above_axis, above_table, below_axis, below_table, rho, z):
    """(B_rho, B_z) [T/A] at (rho, z) [m] in the coil frame from the field tables.

    Positions beyond the tables are clamped to their edges; the wrench table
    never asks for them.
    """
    if z >= 0.0:
        return _interpolate_table(rho_axis, above_axis, above_table, rho, z)
    return _interpolate_table(rho_axis, below_axis, below_table, rho, z)
