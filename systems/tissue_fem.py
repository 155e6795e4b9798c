"""Finite-element tissue at the haptic rate: Drake's ``linear_corotated`` element on
linear tetrahedra, stepped by explicit symplectic Euler (numba).

State: node positions ``x`` (n, 3) in W (m) and velocities ``v`` (n, 3) (m/s); fixed
nodes (``inv_mass`` 0) never move. The state vector's layout is the lattice's
(``lattice_dynamics``): [x; v] flat (6 n), node by node, then the tool.

The element (Drake's LinearCorotatedModel): tetrahedron e has rest edge matrix
Dm = [X1 - X0, X2 - X0, X3 - X0] (m) and rest volume V0 = det(Dm) / 6 (m^3); at
the current edge matrix Ds, F = Ds Dm^-1. R is the rotation of the polar
decomposition of F0, F at the start of the tick (Drake: at the previous time
step); the strain eps = sym(R^T F) - I, the first Piola stress P = R (2 mu eps +
lambda tr(eps) I) (Pa), and the element's nodal forces -V0 P Dm^-T (N): columns
for corners 1..3, corner 0 minus their sum. mu, lambda (Pa) from each
tetrahedron's own (E, nu), so an inclusion is a set of tetrahedra with a larger E.

Masses are lumped: rho V0 / 4 of each tetrahedron to each corner (kg). Drake's
element mass matrix is the one-point-quadrature "consistent" one, rho V0 / 16 in
every corner pair, whose row sums are these lumped masses: so gravity loads and
static displacements agree exactly, and only the vibration modes differ a little.
Rayleigh damping as Drake's DeformableBodyConfig: -alpha m v (alpha, 1/s) and
-beta K v (beta, s), K the element stiffness at the tick's R; since the elastic
force is affine in the positions for a fixed R, the stiffness damping is the
elastic force evaluated at x + beta v, the one pass that computes both.

The probe's contact (``add_contact_forces``) is a pressure on the boundary's
triangles, integrated over them: each triangle split into CONTACT_SUBDIVISIONS^2
equal sub-triangles, a point at each one's centroid carrying its rest area. A point
inside the sphere is pushed out along the normal from the sphere's centre by the
lattice's node law per unit area: the penalty pressure k_p g(depth) (Pa, k_p in
N/m^3, g with the same smoothing onset), Hunt-Crossley dissipation and regularized
friction on the point's velocity interpolated from its triangle's nodes; the force
goes to the three nodes by the point's barycentric weights, its opposite to the tool
at the point. So the force follows the sphere smoothly across the nodes (the node
law's stepped as each node entered the sphere: ~10 % ripple every 5 mm) and its
stiffness on a node is k_p times the node's share of the boundary's area. Its
damping is capped per node at the node's mass over the step, as the node law's: each
point's at its area times the least mass per area of its triangle's nodes, over h.
With rest areas the pressure's force is the gradient of an energy: conservative.
It is evaluated at every substep from that substep's state with the probe held where
the tick started (as the lattice's ``symplectic_euler_tick`` does); the tool's wrench
is the first substep's (``state_contact`` computes it from the tick's start state).

Performance: the per-tetrahedron work runs a block of ``TET_BLOCK`` tetrahedra at a
time: the edge differences gathered into 9 flat rows, the arithmetic in one
branch-free loop over the block that the compiler vectorizes (the per-tetrahedron
rest data is stored as 9 rows of length m, read with unit stride), then the forces
scattered back. The polar decomposition runs once a tick, the same way, a fixed
number of Newton iterations (deterministic, no branch), in float64; it leaves each
element R and the rest stress of E0 = sym(R^T) - I. The element pass (once a
substep) computes in float32 from the displacements' edges (strain E0 + sym(R^T Du
Dm^-1)), so that float32 rounds the strain, not positions it is the small difference
of; the forces sum in float64. ``elastic_forces`` runs the same kernels in float64.
"""

import math
import time
from dataclasses import dataclass
from typing import NamedTuple

import numba
import numpy as np
import scipy.sparse
import scipy.sparse.linalg

from maglev_haptics.hardware.config_checks import finite, nonnegative, positive, require
from maglev_haptics.hardware.constants import GRAVITY_M_S2
from maglev_haptics.hardware.kernels import (
    FLOAT32_VECTOR, INDEX, INDEX_MATRIX, MATRIX, READONLY_VECTOR, SCALAR,
    UINT32_VECTOR, VECTOR, kernel)
from maglev_haptics.systems.lattice_dynamics import (
    LINK_MATH, add_reaction, penalty_force, probe_arguments)

# Tetrahedra per block of the element passes: the block's 9 rows of differences and
# the 20 rows of rotation and rest data it reads stay in the L1 cache.
TET_BLOCK = 128
_TET_ROW = TET_BLOCK + 8  # a row of a block, padded off a power of two
# The per-tetrahedron rest data, block by block: Dm^-1 (row-major, 9 rows), 2 mu V0
# and lambda V0, each a row of _TET_ROW (``element_rows``).
ELEMENT_ROWS = 11
BLOCK_WORK = 18 * _TET_ROW  # the rotation pass's work space (numbers)
# The element pass's own rows, block by block (``pass_rows``): Dm^-1 (9 rows), then
# -2 mu V0, -mu V0 and -lambda V0; and what the rotation pass leaves it each tick
# (``element_rotations``): R (9 rows, row-major), then the rest stress -V0 S0 (6 rows:
# 00, 11, 22, 01, 02, 12) of the strain E0 = sym(R^T) - I that R alone makes.
PASS_ROWS = 12
TICK_ROWS = 15
PASS_WORK = 9 * _TET_ROW  # the element pass's work space (numbers)
# The element pass's arithmetic (float32: twice the numbers a vector instruction and
# half the bytes read; tests/test_tissue_fem.py shows the press and the rest shape
# unchanged). Its strain comes from displacements, not positions, so float32 rounds
# the strain, not the positions it would be the small difference of.
PASS_DTYPE = np.float32
# Newton iterations X <- (g X + (g X)^-T) / 2 of the polar decomposition, the first
# SCALED_POLAR_ITERATIONS with Higham's scaling g, the rest with g = 1 (a scaling
# costs two square roots and two divisions): from principal stretches in [0.3, 3] they
# reach the rotation to 1e-10 (tests/test_tissue_fem.py).
POLAR_ITERATIONS = 5
SCALED_POLAR_ITERATIONS = 1
# The fraction of the symplectic Euler stability limit a substep may use (-).
STABLE_STEP_SAFETY = 0.9

# Sub-triangles along each edge of a boundary triangle in the contact's quadrature:
# CONTACT_SUBDIVISIONS^2 points a triangle. A sweep 3 mm deep over the small slab's 5 mm
# triangles (tests/test_tissue_press.py) ripples 4.1 % peak to peak with 1, 2.7 % with
# 2, 2.1 % with 4 (points 1.25 mm apart): the finite elements' own, which 6 leaves.
CONTACT_SUBDIVISIONS = 4

# tissue_tick_from's argument types: masses in and out, probe, then what
# ``tick_arguments`` returns: corner offsets, element_rows, inv_mass, gravity, the
# contact's triangles, triangle rows and quadrature, alpha, beta, constants, substeps,
# then the work space: tick rows, blend, forces, block work; then the rest positions,
# the pass rows and the pass's work.
TISSUE_TICK_ARGUMENTS = (VECTOR, VECTOR, VECTOR, UINT32_VECTOR, VECTOR, VECTOR, VECTOR,
                         INDEX_MATRIX, MATRIX, MATRIX, SCALAR, SCALAR, VECTOR, INDEX,
                         FLOAT32_VECTOR, VECTOR, MATRIX, VECTOR, VECTOR, FLOAT32_VECTOR,
                         FLOAT32_VECTOR)


@dataclass
class TissueProbe:
    """The probe sphere's contact with tissue: a penalty pressure on the boundary's
    triangles (``add_contact_forces``), the lattice's node law (``ProbeContact``) per
    unit area. The defaults are the shipped scenes': pressed 3 mm over the shipped
    slab's lump, the sphere feels 75.9 N/m, the node law's 300 N/m a node felt 72.5
    (tests/test_tissue_press.py); on the slab's 5 mm nodes (25 mm^2 each) the
    pressure stiffness is 150 N/m a node."""

    radius_m: float = 0.008  # (m)
    stiffness_n_per_m3: float = 6e6  # pressure per depth past the onset (Pa/m = N/m^3)
    onset_depth_m: float = 0.0003  # the stiffness ramps in over this depth (m)
    dissipation_s_per_m: float = 5.0  # Hunt-Crossley, on the approach speed (s/m)
    friction: float = 0.1  # Coulomb coefficient (-)
    slip_speed_m_s: float = 0.002  # friction reaches ~70 % of mu f_n at this slip (m/s)

    def validate(self, path: str = "probe") -> None:
        """Range checks; a ValueError names ``path.field``, its value and what is allowed."""
        for name in ("radius_m", "onset_depth_m", "slip_speed_m_s"):
            positive(f"{path}.{name}", getattr(self, name))
        for name in ("dissipation_s_per_m", "friction"):
            nonnegative(f"{path}.{name}", getattr(self, name))
        # Softer than 1e5 N/m^3 the sphere sinks centimetres under a newton; stiffer
        # than 1e10 the contact's own stiffness needs tens of substeps on 5 mm nodes.
        stiffness = self.stiffness_n_per_m3
        require(finite(stiffness) and 1e5 <= stiffness <= 1e10, f"{path}.stiffness_n_per_m3",
                stiffness, "must be from 1e5 to 1e10 (N/m^3: pressure (Pa) per metre of depth)")

    def constants(self) -> np.ndarray:
        """The radius (m), stiffness (N/m^3), onset (m), dissipation (s/m), friction (-)
        and slip speed (m/s), in the order the contact kernels take them (6,)."""
        return np.array([self.radius_m, self.stiffness_n_per_m3, self.onset_depth_m,
                         self.dissipation_s_per_m, self.friction, self.slip_speed_m_s])


class TissueModel(NamedTuple):
    """The arrays the kernels read; see ``tissue_model``."""

    tetrahedra: np.ndarray  # (m, 4) int64 node indices, each of positive rest volume
    rest_inverse: np.ndarray  # (m, 3, 3) Dm^-1 (1/m)
    two_mu_volume: np.ndarray  # (m,) 2 mu V0 (N*m)
    lambda_volume: np.ndarray  # (m,) lambda V0 (N*m)
    element_rows: np.ndarray  # the three above in the kernels' blocked layout, flat
    volume_m3: np.ndarray  # (m,) rest volumes V0
    youngs_modulus_pa: np.ndarray  # (m,)
    poissons_ratio: np.ndarray  # (m,)
    mass_kg: np.ndarray  # (n,) lumped; fixed nodes keep theirs here
    inv_mass_per_kg: np.ndarray  # (n,); 0 for fixed nodes
    fixed: np.ndarray  # (n,) bool
    gravity_m_s2: np.ndarray  # (3,) in W
    surface: np.ndarray  # (n_s,) int64: the nodes on the boundary's triangles, drawn
    triangles: np.ndarray  # (k, 3) int64 the boundary's triangles, ordered outward
    # (k, 2): each triangle's rest area (m^2) and the least mass per area (kg/m^2) of its
    # nodes (their mass over their share of the boundary's area): the contact's damping cap.
    triangle_rows: np.ndarray
    node_area_m2: np.ndarray  # (n,) each node's share of the boundary's area (0 inside)
    mass_damping_per_s: float  # Rayleigh alpha (1/s)
    stiffness_damping_s: float  # Rayleigh beta (s)
    rest_positions_m: np.ndarray  # (n, 3) the nodes at rest in W (m), where Dm was taken

    @property
    def num_nodes(self) -> int:
        return len(self.mass_kg)

    @property
    def num_tetrahedra(self) -> int:
        return len(self.tetrahedra)


# --- mesh ---------------------------------------------------------------------------

# The faces of a positively oriented tetrahedron (0, 1, 2, 3), each ordered so that its
# right-handed normal points out of the tetrahedron.
_OUTWARD_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])


def boundary_triangles(tetrahedra):
    """(triangles (k, 3) int64, surface nodes (n_s,) int64 sorted): the faces that
    belong to one tetrahedron only, ordered outward (the tetrahedra positively
    oriented, as ``tissue_model`` requires), and the nodes on them."""
    tetrahedra = np.asarray(tetrahedra, dtype=np.int64).reshape(-1, 4)
    faces = tetrahedra[:, _OUTWARD_FACES].reshape(-1, 3)
    keys = np.sort(faces, axis=1)
    _, first, counts = np.unique(keys, axis=0, return_index=True, return_counts=True)
    triangles = faces[np.sort(first[counts == 1])]
    return np.ascontiguousarray(triangles), np.unique(triangles)


def boundary_areas(positions_m, triangles):
    """(each triangle's area (k,) m^2, each node's share (n,) m^2: a third of each of
    its triangles', 0 off the boundary)."""
    corners = np.asarray(positions_m, float)[triangles]
    area = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0],
                                         corners[:, 2] - corners[:, 0]), axis=1)
    node_area = np.zeros(len(positions_m))
    np.add.at(node_area, triangles.ravel(), np.repeat(area / 3.0, 3))
    return area, node_area


def contact_quadrature(subdivisions: int = CONTACT_SUBDIVISIONS) -> np.ndarray:
    """(subdivisions^2, 3): the barycentric coordinates of the centroids of a
    triangle's equal sub-triangles, ``subdivisions`` along each edge; each point
    carries 1 / subdivisions^2 of the triangle's area."""
    s = subdivisions
    points = [((i + 1 / 3) / s, (j + 1 / 3) / s) for i in range(s) for j in range(s - i)]
    points += [((i + 2 / 3) / s, (j + 2 / 3) / s) for i in range(s) for j in range(s - 1 - i)]
    b = np.array(points)
    return np.ascontiguousarray(np.column_stack((1.0 - b.sum(axis=1), b)))


def rest_shapes(positions_m, tetrahedra):
    """(Dm (m, 3, 3) edge matrices (m), volumes (m,) m^3) of the tetrahedra."""
    corners = np.asarray(positions_m, float)[np.asarray(tetrahedra)]
    edges = np.transpose(corners[:, 1:] - corners[:, :1], (0, 2, 1))  # columns X_a - X_0
    return edges, np.linalg.det(edges) / 6.0


def _per_tetrahedron(path, value, m):
    """``value`` (one number or m) as an (m,) array."""
    values = np.asarray(value, dtype=float)
    require(values.shape in ((), (m,)), f"{path}.shape", values.shape,
            f"must be one number or one for each of the {m} tetrahedra")
    return np.ascontiguousarray(np.broadcast_to(values, (m,)))


def _check_each(path, values, ok, allowed, indexed=True):
    """The first value where ``ok`` is false refused: ``path[index] = value`` (or
    ``path = value`` where not ``indexed``: one number given for all)."""
    bad = np.flatnonzero(~ok)
    if len(bad):
        index = int(bad[0])
        require(False, f"{path}[{index}]" if indexed else path, float(values[index]), allowed)


def tissue_model(positions_m, tetrahedra, *, youngs_modulus_pa, poissons_ratio,
                 mass_density_kg_m3, fixed, mass_damping_per_s: float = 0.0,
                 stiffness_damping_s: float = 0.0,
                 gravity_m_s2=(0.0, 0.0, -GRAVITY_M_S2)) -> TissueModel:
    """The kernel arrays of a tetrahedral body.

    ``positions_m`` (n, 3) the nodes at rest in W (m); ``tetrahedra`` (m, 4) node
    indices, each with positive volume (det[X1 - X0, X2 - X0, X3 - X0] > 0, Drake's
    VolumeMesh order); ``youngs_modulus_pa`` (Pa), ``poissons_ratio`` (-) and
    ``mass_density_kg_m3`` (kg/m^3) one number for the body or one a tetrahedron;
    ``fixed`` (n,) bool the nodes that never move (at least three not on one line);
    Rayleigh ``mass_damping_per_s`` alpha (1/s) and ``stiffness_damping_s`` beta (s).
    The probe touches the boundary's triangles (``boundary_triangles``).

    A ValueError names the field, the value and what is allowed: an inverted or
    degenerate tetrahedron by its index and volume."""
    positions_m = np.ascontiguousarray(positions_m, dtype=float)
    require(positions_m.ndim == 2 and positions_m.shape[1] == 3 and len(positions_m) >= 4,
            "positions_m.shape", positions_m.shape, "must be (n, 3) with n >= 4")
    require(bool(np.isfinite(positions_m).all()), "positions_m", "non-finite",
            "must be finite numbers (m)")
    n = len(positions_m)
    tetrahedra = np.asarray(tetrahedra)
    require(tetrahedra.ndim == 2 and tetrahedra.shape[1] == 4 and len(tetrahedra) > 0,
            "tetrahedra.shape", tetrahedra.shape,
            "must be (m, 4): a tetrahedral mesh (a surface mesh has 3 nodes an element)")
    require(np.issubdtype(tetrahedra.dtype, np.integer), "tetrahedra.dtype",
            str(tetrahedra.dtype), "must be integer node indices")
    tetrahedra = np.ascontiguousarray(tetrahedra, dtype=np.int64)
    _check_each("tetrahedra", tetrahedra.ravel(), (tetrahedra.ravel() >= 0)
                & (tetrahedra.ravel() < n), f"must be node indices in [0, {n})")
    used = np.zeros(n, bool)
    used[tetrahedra.ravel()] = True
    unused = np.flatnonzero(~used)
    require(len(unused) == 0, "positions_m", f"node {unused[:1]} in no tetrahedron",
            "every node must belong to a tetrahedron")
    m = len(tetrahedra)
    edges, volume = rest_shapes(positions_m, tetrahedra)
    # Degenerate: flatter than 1e-6 of the regular tetrahedron on its longest edge.
    longest = np.linalg.norm(positions_m[tetrahedra[:, [1, 2, 3, 2, 3, 3]]]
                             - positions_m[tetrahedra[:, [0, 0, 0, 1, 1, 2]]], axis=2).max(1)
    _check_each("volume of tetrahedron", volume, volume > 1e-6 * longest ** 3 / (6 * 2 ** 0.5),
                "must be > 0 (m^3): the tetrahedron is inverted or degenerate")
    youngs = _per_tetrahedron("youngs_modulus_pa", youngs_modulus_pa, m)
    nu = _per_tetrahedron("poissons_ratio", poissons_ratio, m)
    density = _per_tetrahedron("mass_density_kg_m3", mass_density_kg_m3, m)
    _check_each("youngs_modulus_pa", youngs, np.isfinite(youngs) & (youngs > 0),
                "must be a finite number > 0 (Pa)", np.ndim(youngs_modulus_pa) > 0)
    _check_each("poissons_ratio", nu, (nu > 0) & (nu < 0.5), "must be in (0, 0.5)",
                np.ndim(poissons_ratio) > 0)
    _check_each("mass_density_kg_m3", density, np.isfinite(density) & (density > 0),
                "must be a finite number > 0 (kg/m^3)", np.ndim(mass_density_kg_m3) > 0)
    nonnegative("mass_damping_per_s", mass_damping_per_s)
    nonnegative("stiffness_damping_s", stiffness_damping_s)
    gravity = np.asarray(gravity_m_s2, dtype=float)
    require(gravity.shape == (3,) and all(map(finite, gravity)), "gravity_m_s2",
            gravity_m_s2, "must be 3 finite numbers (m/s^2)")
    fixed = np.asarray(fixed)
    require(fixed.shape == (n,) and fixed.dtype == bool, "fixed", f"shape {fixed.shape}",
            f"must be ({n},) bool")
    anchors = positions_m[fixed] - positions_m[fixed][:1]
    require(int(fixed.sum()) >= 3 and np.linalg.matrix_rank(anchors, tol=1e-9) >= 2,
            "fixed", f"{int(fixed.sum())} nodes",
            "must hold at least three nodes not on one line: the body would fall or swing"
            " forever")
    mu = youngs / (2.0 * (1.0 + nu))
    lam = youngs * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
    mass = np.zeros(n)
    np.add.at(mass, tetrahedra.ravel(), np.repeat(density * volume / 4.0, 4))
    triangles, surface = boundary_triangles(tetrahedra)
    triangle_area, node_area = boundary_areas(positions_m, triangles)
    # A triangle's nodes' least mass per area of boundary (kg/m^2): the contact's cap.
    mass_per_area = (mass[triangles] / node_area[triangles]).min(axis=1)
    rest_inverse = np.linalg.inv(edges)
    rows = np.concatenate((rest_inverse.reshape(m, 9).T, [2.0 * mu * volume],
                           [lam * volume]))
    return TissueModel(
        tetrahedra=tetrahedra, rest_inverse=rest_inverse, two_mu_volume=2.0 * mu * volume,
        lambda_volume=lam * volume, element_rows=blocked_rows(rows), volume_m3=volume,
        youngs_modulus_pa=youngs, poissons_ratio=nu, mass_kg=mass,
        inv_mass_per_kg=np.where(fixed, 0.0, 1.0 / mass), fixed=fixed.copy(),
        gravity_m_s2=gravity.copy(),
        surface=surface, triangles=triangles,
        triangle_rows=np.ascontiguousarray(np.column_stack((triangle_area, mass_per_area))),
        node_area_m2=node_area,
        mass_damping_per_s=float(mass_damping_per_s),
        stiffness_damping_s=float(stiffness_damping_s), rest_positions_m=positions_m.copy())


def blocked_rows(rows) -> np.ndarray:
    """(k, m) per-tetrahedron rows in the kernels' layout, flat: block by block of
    TET_BLOCK tetrahedra, its k rows of _TET_ROW each (zero padded)."""
    rows = np.asarray(rows, dtype=float)
    k, m = rows.shape
    blocks = -(-m // TET_BLOCK)
    out = np.zeros((blocks, k, _TET_ROW))
    padded = np.zeros((k, blocks * TET_BLOCK))
    padded[:, :m] = rows
    out[:, :, :TET_BLOCK] = padded.reshape(k, blocks, TET_BLOCK).transpose(1, 0, 2)
    return out.ravel()


def unblocked_rows(flat, k: int, m: int) -> np.ndarray:
    """The (k, m) rows of a ``blocked_rows`` layout."""
    blocks = -(-m // TET_BLOCK)
    out = np.asarray(flat).reshape(blocks, k, _TET_ROW)[:, :, :TET_BLOCK]
    return out.transpose(1, 0, 2).reshape(k, -1)[:, :m]


# --- element kernels ----------------------------------------------------------------
#
# The kernels index flat arrays with the constant row length _TET_ROW: a block's rows
# are then constant offsets from one pointer, so the compiler proves the rows apart
# and vectorizes without run-time overlap checks (with each row its own array, the
# 29 rows needed more checks than LLVM will emit, and the loops stayed scalar).

@numba.njit(cache=True, fastmath=LINK_MATH, error_model="numpy", inline="always")
def _gather_edges(y, corners, e0, count, d):
    """d[(3 (a - 1) + k) _TET_ROW + c] = y[corner a, k] - y[corner 0, k] of tetrahedron
    e0 + c (y flat, 3 a node; ``corners`` as ``corner_offsets``): the columns of its
    edge matrix."""
    for c in range(count):
        i0 = corners[4 * (e0 + c)]
        for a in range(1, 4):
            ia = corners[4 * (e0 + c) + a]
            for k in range(3):
                d[(3 * (a - 1) + k) * _TET_ROW + c] = y[ia + k] - y[i0 + k]


@numba.njit(cache=True, fastmath=LINK_MATH, error_model="numpy", inline="always")
def _rows9(rows, start, c):
    """rows[start + k _TET_ROW + c] for k = 0..8: a block's 3 x 3 matrix of element c."""
    W = _TET_ROW
    return (rows[start + c], rows[start + W + c], rows[start + 2 * W + c],
            rows[start + 3 * W + c], rows[start + 4 * W + c], rows[start + 5 * W + c],
            rows[start + 6 * W + c], rows[start + 7 * W + c], rows[start + 8 * W + c])


@numba.njit(cache=True, fastmath=LINK_MATH, error_model="numpy", inline="always")
def _product3(a00, a01, a02, a10, a11, a12, a20, a21, a22,
              b00, b01, b02, b10, b11, b12, b20, b21, b22):
    """The 3 x 3 product a b, row by row (9 numbers); a transpose is its arguments
    given column by column."""
    return (a00 * b00 + a01 * b10 + a02 * b20, a00 * b01 + a01 * b11 + a02 * b21,
            a00 * b02 + a01 * b12 + a02 * b22, a10 * b00 + a11 * b10 + a12 * b20,
            a10 * b01 + a11 * b11 + a12 * b21, a10 * b02 + a11 * b12 + a12 * b22,
            a20 * b00 + a21 * b10 + a22 * b20, a20 * b01 + a21 * b11 + a22 * b21,
            a20 * b02 + a21 * b12 + a22 * b22)


@numba.njit(cache=True, fastmath=LINK_MATH, error_model="numpy", inline="always")
def _element_arithmetic(d, tick_rows, pass_rows, block, count):
    """d's rows 3 (a - 1) + k = the elastic force (N) on corner a (1..3) along k of
    each tetrahedron of ``block``, from its displacement edge matrix Du (m) in the same
    rows: -V0 R S Dm^-T with S = 2 mu eps + lambda tr(eps) I and eps = sym(R^T F) - I
    = E0 + sym(H), H = R^T Du Dm^-1 (F = I + Du Dm^-1). No branch and no constant
    (which would widen float32 arithmetic to float64): it vectorizes in the rows' type."""
    W = _TET_ROW
    r0 = block * TICK_ROWS * W
    e0 = block * PASS_ROWS * W
    for c in range(count):
        r00, r01, r02, r10, r11, r12, r20, r21, r22 = _rows9(tick_rows, r0, c)
        b00, b01, b02, b10, b11, b12, b20, b21, b22 = _rows9(pass_rows, e0, c)
        # The displacement edge matrix Du, column j = edge j, row k = coordinate k.
        s00, s10, s20, s01, s11, s21, s02, s12, s22 = _rows9(d, 0, c)
        # Q = R^T Du: the edges' displacements in the tetrahedron's rotated frame.
        q00, q01, q02, q10, q11, q12, q20, q21, q22 = _product3(
            r00, r10, r20, r01, r11, r21, r02, r12, r22,
            s00, s01, s02, s10, s11, s12, s20, s21, s22)
        # H = Q Dm^-1.
        h00, h01, h02, h10, h11, h12, h20, h21, h22 = _product3(
            q00, q01, q02, q10, q11, q12, q20, q21, q22,
            b00, b01, b02, b10, b11, b12, b20, b21, b22)
        # -V0 S: the rest stress of R plus that of sym(H).
        minus_two_mu_v = pass_rows[e0 + 9 * W + c]
        minus_mu_v = pass_rows[e0 + 10 * W + c]
        dilation = pass_rows[e0 + 11 * W + c] * (h00 + h11 + h22)
        t00 = tick_rows[r0 + 9 * W + c] + minus_two_mu_v * h00 + dilation
        t11 = tick_rows[r0 + 10 * W + c] + minus_two_mu_v * h11 + dilation
        t22 = tick_rows[r0 + 11 * W + c] + minus_two_mu_v * h22 + dilation
        t01 = tick_rows[r0 + 12 * W + c] + minus_mu_v * (h01 + h10)
        t02 = tick_rows[r0 + 13 * W + c] + minus_mu_v * (h02 + h20)
        t12 = tick_rows[r0 + 14 * W + c] + minus_mu_v * (h12 + h21)
        # T = -V0 S Dm^-T: column a - 1 for corner a.
        w00, w01, w02, w10, w11, w12, w20, w21, w22 = _product3(
            t00, t01, t02, t01, t11, t12, t02, t12, t22,
            b00, b10, b20, b01, b11, b21, b02, b12, b22)
        # The forces R T, corner by corner: column a - 1 of R T in rows 3 (a - 1) + k.
        (d[c], d[3 * W + c], d[6 * W + c], d[W + c], d[4 * W + c], d[7 * W + c], d[2 * W + c],
         d[5 * W + c], d[8 * W + c]) = _product3(
            r00, r01, r02, r10, r11, r12, r20, r21, r22,
            w00, w01, w02, w10, w11, w12, w20, w21, w22)


@numba.njit(cache=True, fastmath=LINK_MATH, error_model="numpy", inline="always")
def _scatter_forces(corners, e0, count, d, f):
    """f (flat) += the forces in d's rows 0..8 on corners 1..3 and minus their sum on
    corner 0."""
    W = _TET_ROW
    for c in range(count):
        i0 = corners[4 * (e0 + c)]
        i1 = corners[4 * (e0 + c) + 1]
        i2 = corners[4 * (e0 + c) + 2]
        i3 = corners[4 * (e0 + c) + 3]
        for k in range(3):
            f1, f2, f3 = d[k * W + c], d[(3 + k) * W + c], d[(6 + k) * W + c]
            f[i1 + k] += f1
            f[i2 + k] += f2
            f[i3 + k] += f3
            f[i0 + k] -= f1 + f2 + f3


@numba.njit(cache=True, fastmath=LINK_MATH, error_model="numpy")
def add_elastic_forces(u, corners, pass_rows, tick_rows, work, f):
    """f (flat, 3 n) += every element's force (N) at node displacements u (flat, m)
    from rest with the rotations (``element_rotations``'s ``tick_rows``) held. The
    arithmetic in the type of ``pass_rows``, ``tick_rows`` and ``work`` (PASS_WORK
    numbers), the sums in f's."""
    m = corners.shape[0] // 4
    for block in range((m + TET_BLOCK - 1) // TET_BLOCK):
        e0 = block * TET_BLOCK
        count = min(TET_BLOCK, m - e0)
        _gather_edges(u, corners, e0, count, work)
        _element_arithmetic(work, tick_rows, pass_rows, block, count)
        _scatter_forces(corners, e0, count, work, f)


@numba.njit(cache=True, fastmath=LINK_MATH, error_model="numpy", inline="always")
def _deformation_gradients(d, element_rows, block, count):
    """d's rows 9 + 3 k + l = F[k, l] = (Ds Dm^-1)[k, l] of the block's tetrahedra,
    from their edge matrices in rows 0..8."""
    W = _TET_ROW
    e0 = block * ELEMENT_ROWS * W
    for c in range(count):
        b00, b01, b02, b10, b11, b12, b20, b21, b22 = _rows9(element_rows, e0, c)
        s00, s10, s20, s01, s11, s21, s02, s12, s22 = _rows9(d, 0, c)
        (d[9 * W + c], d[10 * W + c], d[11 * W + c], d[12 * W + c], d[13 * W + c],
         d[14 * W + c], d[15 * W + c], d[16 * W + c], d[17 * W + c]) = _product3(
            s00, s01, s02, s10, s11, s12, s20, s21, s22,
            b00, b01, b02, b10, b11, b12, b20, b21, b22)


@numba.njit(cache=True, fastmath=LINK_MATH, error_model="numpy", inline="always")
def _newton_polar_step(d, count, scaled):
    """X <- (g X + (g X)^-T) / 2 on the matrices in d's rows 9..17, g = sqrt(|X^-1| /
    |X|) where ``scaled`` (Frobenius norms: Higham's scaling, which brings a
    stretched X in fast), else 1."""
    W = _TET_ROW
    x0 = 9 * W
    for c in range(count):
        x00, x01, x02 = d[x0 + c], d[x0 + W + c], d[x0 + 2 * W + c]
        x10, x11, x12 = d[x0 + 3 * W + c], d[x0 + 4 * W + c], d[x0 + 5 * W + c]
        x20, x21, x22 = d[x0 + 6 * W + c], d[x0 + 7 * W + c], d[x0 + 8 * W + c]
        # The cofactor matrix: X^-T = C / det X.
        c00 = x11 * x22 - x12 * x21
        c01 = x12 * x20 - x10 * x22
        c02 = x10 * x21 - x11 * x20
        c10 = x02 * x21 - x01 * x22
        c11 = x00 * x22 - x02 * x20
        c12 = x01 * x20 - x00 * x21
        c20 = x01 * x12 - x02 * x11
        c21 = x02 * x10 - x00 * x12
        c22 = x00 * x11 - x01 * x10
        det = x00 * c00 + x01 * c01 + x02 * c02
        if scaled:  # the same for the whole loop: it is taken out of it
            norm_x = (x00 * x00 + x01 * x01 + x02 * x02 + x10 * x10 + x11 * x11 + x12 * x12
                      + x20 * x20 + x21 * x21 + x22 * x22)
            norm_c = (c00 * c00 + c01 * c01 + c02 * c02 + c10 * c10 + c11 * c11 + c12 * c12
                      + c20 * c20 + c21 * c21 + c22 * c22)
            # g^2 = |C| / (|det| |X|); the two halves: g X / 2 and C / (2 g det).
            g = math.sqrt(math.sqrt(norm_c / norm_x) / abs(det))
        else:
            g = 1.0
        a = 0.5 * g
        b = 0.5 / (g * det)
        d[x0 + c] = a * x00 + b * c00
        d[x0 + W + c] = a * x01 + b * c01
        d[x0 + 2 * W + c] = a * x02 + b * c02
        d[x0 + 3 * W + c] = a * x10 + b * c10
        d[x0 + 4 * W + c] = a * x11 + b * c11
        d[x0 + 5 * W + c] = a * x12 + b * c12
        d[x0 + 6 * W + c] = a * x20 + b * c20
        d[x0 + 7 * W + c] = a * x21 + b * c21
        d[x0 + 8 * W + c] = a * x22 + b * c22


@numba.njit(cache=True, fastmath=LINK_MATH, error_model="numpy", inline="always")
def _rotation_rows(d, element_rows, tick_rows, block, count):
    """The block's tick rows: R from d's rows 9..17, and the rest stress -V0 S0 of
    E0 = sym(R^T) - I (taken here, in float64: E0 is small, and float32 would keep
    only its rounding)."""
    W = _TET_ROW
    x0 = 9 * W
    out = block * TICK_ROWS * W
    e0 = block * ELEMENT_ROWS * W
    for c in range(count):
        r00, r01, r02 = d[x0 + c], d[x0 + W + c], d[x0 + 2 * W + c]
        r10, r11, r12 = d[x0 + 3 * W + c], d[x0 + 4 * W + c], d[x0 + 5 * W + c]
        r20, r21, r22 = d[x0 + 6 * W + c], d[x0 + 7 * W + c], d[x0 + 8 * W + c]
        tick_rows[out + c] = r00
        tick_rows[out + W + c] = r01
        tick_rows[out + 2 * W + c] = r02
        tick_rows[out + 3 * W + c] = r10
        tick_rows[out + 4 * W + c] = r11
        tick_rows[out + 5 * W + c] = r12
        tick_rows[out + 6 * W + c] = r20
        tick_rows[out + 7 * W + c] = r21
        tick_rows[out + 8 * W + c] = r22
        minus_two_mu_v = -element_rows[e0 + 9 * W + c]
        minus_mu_v = 0.5 * minus_two_mu_v
        dilation = -element_rows[e0 + 10 * W + c] * (r00 + r11 + r22 - 3.0)
        tick_rows[out + 9 * W + c] = minus_two_mu_v * (r00 - 1.0) + dilation
        tick_rows[out + 10 * W + c] = minus_two_mu_v * (r11 - 1.0) + dilation
        tick_rows[out + 11 * W + c] = minus_two_mu_v * (r22 - 1.0) + dilation
        tick_rows[out + 12 * W + c] = minus_mu_v * (r01 + r10)
        tick_rows[out + 13 * W + c] = minus_mu_v * (r02 + r20)
        tick_rows[out + 14 * W + c] = minus_mu_v * (r12 + r21)


@numba.njit(cache=True, fastmath=LINK_MATH, error_model="numpy")
def element_rotations(x, corners, element_rows, work, tick_rows):
    """tick_rows (flat, TICK_ROWS a block) = the rotation R of the polar decomposition
    F = R S of every element at node positions x (flat, m), POLAR_ITERATIONS Newton
    steps from F in float64, and its rest stress. ``work`` is BLOCK_WORK numbers."""
    m = corners.shape[0] // 4
    for block in range((m + TET_BLOCK - 1) // TET_BLOCK):
        e0 = block * TET_BLOCK
        count = min(TET_BLOCK, m - e0)
        _gather_edges(x, corners, e0, count, work)
        _deformation_gradients(work, element_rows, block, count)
        for iteration in range(POLAR_ITERATIONS):
            _newton_polar_step(work, count, iteration < SCALED_POLAR_ITERATIONS)
        _rotation_rows(work, element_rows, tick_rows, block, count)


# --- the probe's contact ------------------------------------------------------------

@numba.njit(cache=True, error_model="numpy")
def add_contact_forces(x, v, triangles, triangle_rows, quadrature, p_WP, v_WP, p_WT, radius,
                       k_p, onset, d_hc, mu, slip_speed, h, f):
    """Add the probe's contact forces on the boundary triangles' nodes into f (n, 3)
    (N) (module docstring); an f with no rows records nothing. x (n, 3) m, v (n, 3)
    m/s; ``triangle_rows`` as ``TissueModel``'s; ``quadrature`` as
    ``contact_quadrature``'s; the probe's centre p_WP (m) moving at v_WP (m/s), the
    tool's origin p_WT (m); the sphere's radius (m), k_p (N/m^3), onset (m), d_hc
    (s/m), mu (-), slip speed (m/s), the step h (s) the damping is applied over.

    Returns (wrench on the tool [f; tau] in W about p_WT (N, N*m), points in contact)."""
    wrench = np.zeros(6)
    touching = 0
    points = quadrature.shape[0]
    for t in range(triangles.shape[0]):
        a, b, c = triangles[t, 0], triangles[t, 1], triangles[t, 2]
        # Skip a triangle whose bounding box the sphere misses (most of them, most on x).
        if (p_WP[0] + radius < min(x[a, 0], x[b, 0], x[c, 0])
                or p_WP[0] - radius > max(x[a, 0], x[b, 0], x[c, 0])
                or p_WP[1] + radius < min(x[a, 1], x[b, 1], x[c, 1])
                or p_WP[1] - radius > max(x[a, 1], x[b, 1], x[c, 1])
                or p_WP[2] + radius < min(x[a, 2], x[b, 2], x[c, 2])
                or p_WP[2] - radius > max(x[a, 2], x[b, 2], x[c, 2])):
            continue
        area = triangle_rows[t, 0] / points  # a point's share (m^2)
        stiffness = k_p * area  # (N/m)
        # Its share of its nodes' mass over h (N s/m): summed over the points about a
        # node, at most the node's mass over h, so the damping stops, never reverses.
        damping_cap = area * triangle_rows[t, 1] / h
        for q in range(points):
            wa, wb, wc = quadrature[q, 0], quadrature[q, 1], quadrature[q, 2]
            px = wa * x[a, 0] + wb * x[b, 0] + wc * x[c, 0]
            py = wa * x[a, 1] + wb * x[b, 1] + wc * x[c, 1]
            pz = wa * x[a, 2] + wb * x[b, 2] + wc * x[c, 2]
            nx, ny, nz = px - p_WP[0], py - p_WP[1], pz - p_WP[2]
            distance = math.sqrt(nx * nx + ny * ny + nz * nz)
            if distance >= radius or distance == 0.0:
                continue
            nx, ny, nz = nx / distance, ny / distance, nz / distance
            fx, fy, fz, pressed = penalty_force(
                nx, ny, nz, wa * v[a, 0] + wb * v[b, 0] + wc * v[c, 0] - v_WP[0],
                wa * v[a, 1] + wb * v[b, 1] + wc * v[c, 1] - v_WP[1],
                wa * v[a, 2] + wb * v[b, 2] + wc * v[c, 2] - v_WP[2], radius - distance,
                stiffness, onset, d_hc, damping_cap, mu, slip_speed)
            if not pressed:
                continue
            touching += 1
            if f.shape[0] > 0:
                f[a, 0] += wa * fx
                f[a, 1] += wa * fy
                f[a, 2] += wa * fz
                f[b, 0] += wb * fx
                f[b, 1] += wb * fy
                f[b, 2] += wb * fz
                f[c, 0] += wc * fx
                f[c, 1] += wc * fy
                f[c, 2] += wc * fz
            # The opposite force on the tool, applied at the point.
            add_reaction(wrench, fx, fy, fz, px - p_WT[0], py - p_WT[1], pz - p_WT[2])
    return wrench, touching


@kernel((READONLY_VECTOR, VECTOR, INDEX_MATRIX, MATRIX, MATRIX, VECTOR, SCALAR))
def state_contact(state, p_TP, triangles, triangle_rows, quadrature, constants, h):
    """(wrench on the tool [f; tau] in W about T's origin, points in contact) for the
    state vector [x; v; X_WT; V_WT], the probe's centre p_TP (m) in T; ``constants``
    as ``TissueProbe.constants``; the (sub)step h (s) as the next step applies it."""
    n = (state.shape[0] - 13) // 6
    x = state[:3 * n].reshape((n, 3))
    v = state[3 * n:6 * n].reshape((n, 3))
    probe = probe_arguments(state[6 * n:], p_TP)
    return add_contact_forces(x, v, triangles, triangle_rows, quadrature, probe[0:3],
                              probe[3:6], probe[6:9], constants[0], constants[1],
                              constants[2], constants[3], constants[4], constants[5], h,
                              np.zeros((0, 3)))


# --- the tick -----------------------------------------------------------------------

@numba.njit(cache=True, error_model="numpy")
def _symplectic_substep(x, v, f, inv_mass, gravity, alpha, h_s):
    """v += h_s (f / m + g - alpha v), then x += h_s v, at the free nodes (flat
    arrays); a select, not a branch, keeps the fixed ones."""
    for i in range(inv_mass.shape[0]):
        free = inv_mass[i] != 0.0
        for k in range(3):
            j = 3 * i + k
            moved = v[j] + h_s * (inv_mass[i] * f[j] + gravity[k] - alpha * v[j])
            v[j] = moved if free else v[j]
            x[j] = x[j] + h_s * v[j] if free else x[j]


@kernel(TISSUE_TICK_ARGUMENTS, nogil=True)
def tissue_tick_from(masses_in, masses_out, probe, corners, element_rows, inv_mass, gravity,
                     triangles, triangle_rows, quadrature, alpha, beta, constants, substeps,
                     tick_rows, blend, forces, work, rest, pass_rows, pass_work):
    """``masses_out`` = one tick from ``masses_in`` ([x; v], 6 n) in ``substeps``
    symplectic Euler substeps. ``probe`` is [p_WP, v_WP, p_WT] (9); ``constants``
    ``TissueProbe.constants`` then the tick h (s); ``rest`` the nodes at rest (flat,
    m); ``pass_rows`` the element pass's (``pass_rows``). ``tick_rows``, ``blend``
    (3 n), ``forces`` (n, 3), ``work`` and ``pass_work`` are work space
    (``tick_arguments`` makes them)."""
    n = masses_in.shape[0] // 6
    masses_out[:] = masses_in
    x = masses_out[:3 * n]
    v = masses_out[3 * n:]
    x3 = x.reshape((n, 3))
    v3 = v.reshape((n, 3))
    f = forces.reshape(3 * n)
    h_s = constants[6] / substeps
    element_rotations(x, corners, element_rows, work, tick_rows)
    for _ in range(substeps):
        # The stiffness damping: the elastic force at x + beta v, from its displacement.
        for j in range(3 * n):
            blend[j] = x[j] + beta * v[j] - rest[j]
        f[:] = 0.0
        add_elastic_forces(blend, corners, pass_rows, tick_rows, pass_work, f)
        add_contact_forces(x3, v3, triangles, triangle_rows, quadrature, probe[0:3],
                           probe[3:6], probe[6:9], constants[0], constants[1], constants[2],
                           constants[3], constants[4], constants[5], h_s, forces)
        _symplectic_substep(x, v, f, inv_mass, gravity, alpha, h_s)


class TickArguments(NamedTuple):
    """``tissue_tick_from``'s arguments after the probe, in its order."""

    corners: np.ndarray
    element_rows: np.ndarray
    inv_mass: np.ndarray
    gravity: np.ndarray
    triangles: np.ndarray
    triangle_rows: np.ndarray
    quadrature: np.ndarray
    alpha: float
    beta: float
    constants: np.ndarray
    substeps: int
    tick_rows: np.ndarray
    blend: np.ndarray
    forces: np.ndarray
    work: np.ndarray
    rest: np.ndarray
    pass_rows: np.ndarray
    pass_work: np.ndarray


def tick_arguments(model: TissueModel, probe: TissueProbe, period_s: float, substeps: int,
                   dtype=PASS_DTYPE) -> TickArguments:
    """The arguments of ``tissue_tick_from`` after ``probe``, fresh work space
    included: ``tissue_tick_from(masses_in, masses_out, probe, *arguments)``; the
    element pass in ``dtype`` (float64 only to compare: ``compile_kernels`` compiles
    the float32 one before the clock)."""
    n, m = model.num_nodes, model.num_tetrahedra
    return TickArguments(
        corner_offsets(model.tetrahedra), model.element_rows, model.inv_mass_per_kg,
        model.gravity_m_s2, model.triangles, model.triangle_rows, contact_quadrature(),
        model.mass_damping_per_s, model.stiffness_damping_s,
        np.append(probe.constants(), float(period_s)), int(substeps),
        tick_row_work(m, dtype), np.zeros(3 * n), np.zeros((n, 3)), np.zeros(BLOCK_WORK),
        np.ascontiguousarray(model.rest_positions_m.ravel()), pass_rows(model, dtype),
        np.zeros(PASS_WORK, dtype))


def pass_rows(model: TissueModel, dtype=PASS_DTYPE) -> np.ndarray:
    """The element pass's rows (PASS_ROWS, blocked) in ``dtype``."""
    half_mu_v = 0.5 * model.two_mu_volume
    rows = np.concatenate((model.rest_inverse.reshape(-1, 9).T, [-model.two_mu_volume],
                           [-half_mu_v], [-model.lambda_volume]))
    return blocked_rows(rows).astype(dtype)


def corner_offsets(tetrahedra) -> np.ndarray:
    """(4 m,) uint32: 3 times each tetrahedron's node indices, corner by corner (the
    offsets of its nodes in a flat 3 n vector): half the bytes of int64 indices and no
    multiplication, which make the element pass's gather and scatter ~10 % faster."""
    return np.ascontiguousarray(3 * np.asarray(tetrahedra).ravel(), dtype=np.uint32)


def tick_row_work(num_tetrahedra: int, dtype=PASS_DTYPE) -> np.ndarray:
    """Room for every element's tick rows (TICK_ROWS, blocked) in ``dtype``."""
    return np.zeros(-(-num_tetrahedra // TET_BLOCK) * TICK_ROWS * _TET_ROW, dtype)


def elastic_forces(model: TissueModel, positions_m, velocities_m_s=None, reference_m=None):
    """(n, 3) the elastic and stiffness-damping forces (N) at ``positions_m`` (n, 3)
    moving at ``velocities_m_s`` (default still), the rotations taken at
    ``reference_m`` (default the positions themselves), the element pass in float64:
    for tests and analysis."""
    x = np.ascontiguousarray(positions_m, dtype=float).ravel()
    reference = x if reference_m is None else np.ascontiguousarray(reference_m, float).ravel()
    v = np.zeros_like(x) if velocities_m_s is None else np.asarray(velocities_m_s, float).ravel()
    tick_rows = tick_row_work(model.num_tetrahedra, np.float64)
    corners = corner_offsets(model.tetrahedra)
    element_rotations(reference, corners, model.element_rows, np.zeros(BLOCK_WORK),
                      tick_rows)
    f = np.zeros_like(x)
    add_elastic_forces(x + model.stiffness_damping_s * v - model.rest_positions_m.ravel(),
                       corners, pass_rows(model, np.float64), tick_rows,
                       np.zeros(PASS_WORK), f)
    return f.reshape(-1, 3)


def polar_rotations(model: TissueModel, positions_m) -> np.ndarray:
    """(m, 3, 3) each element's rotation R at ``positions_m`` (n, 3), as the tick
    computes it."""
    tick_rows = tick_row_work(model.num_tetrahedra, np.float64)
    element_rotations(np.ascontiguousarray(positions_m, dtype=float).ravel(),
                      corner_offsets(model.tetrahedra), model.element_rows,
                      np.zeros(BLOCK_WORK), tick_rows)
    return unblocked_rows(tick_rows, TICK_ROWS, model.num_tetrahedra)[:9].T.reshape(-1, 3, 3)


# --- linearization and stability ----------------------------------------------------

def linear_stiffness_matrix(model: TissueModel, positions_m=None) -> scipy.sparse.csr_matrix:
    """K (N/m), 3 n x 3 n over every node (fixed ones included): the tangent of the
    elastic forces with each element's rotation held at its value at ``positions_m``
    (n, 3) (default the rest positions' rotations, R = I): Drake's linear_corotated
    stiffness. Per element, with g_a the gradient of corner a's shape function (1/m),
    K_ab = R V0 (mu (g_a . g_b) I + mu g_b g_a^T + lambda g_a g_b^T) R^T."""
    inverse = model.rest_inverse  # rows g_1, g_2, g_3
    gradients = np.concatenate((-inverse.sum(axis=1, keepdims=True), inverse), axis=1)
    mu_v = 0.5 * model.two_mu_volume
    lam_v = model.lambda_volume
    dots = np.einsum("eai,ebi->eab", gradients, gradients)
    blocks = (mu_v[:, None, None, None, None] * dots[:, :, :, None, None] * np.eye(3)
              + mu_v[:, None, None, None, None] * np.einsum("ebi,eaj->eabij", gradients,
                                                            gradients)
              + lam_v[:, None, None, None, None] * np.einsum("eai,ebj->eabij", gradients,
                                                             gradients))
    if positions_m is not None:
        R = polar_rotations(model, positions_m)
        blocks = np.einsum("eik,eabkl,ejl->eabij", R, blocks, R)
    rows = 3 * model.tetrahedra[:, :, None, None, None] + np.arange(3)[:, None]
    cols = 3 * model.tetrahedra[:, None, :, None, None] + np.arange(3)[None, :]
    rows, cols = np.broadcast_arrays(rows, cols, blocks)[:2]
    size = 3 * model.num_nodes
    return scipy.sparse.coo_matrix((blocks.ravel(), (rows.ravel(), cols.ravel())),
                                   shape=(size, size)).tocsr()


def free_coordinates(model: TissueModel) -> np.ndarray:
    """The indices (into 3 n) of the free nodes' coordinates."""
    return (3 * np.flatnonzero(~model.fixed)[:, None] + np.arange(3)).ravel()


def highest_angular_frequency(model: TissueModel,
                              probe_stiffness_n_per_m3: float = 0.0) -> float:
    """w_max (rad/s): the largest of the undamped free nodes' sqrt(eig(M^-1 K)) at
    rest, lumped M; K with the probe's pressure stiffness (N/m^3) times each node's
    share of the boundary's area added on the node in every direction, a bound on any
    contact's: the contact's stiffness, sum over its points of k_p a_q (b_q b_q^T) x
    (n_q n_q^T), is under it, as b b^T <= diag(b) for barycentric weights b."""
    free = free_coordinates(model)
    scale = 1.0 / np.sqrt(np.repeat(model.mass_kg, 3)[free])
    contact = probe_stiffness_n_per_m3 * model.node_area_m2  # (N/m)
    K = (linear_stiffness_matrix(model)
         + scipy.sparse.diags(np.repeat(contact, 3)))[free][:, free]
    A = scipy.sparse.diags(scale) @ K @ scipy.sparse.diags(scale)
    largest = scipy.sparse.linalg.eigsh(A, k=1, which="LA", return_eigenvectors=False,
                                        tol=1e-6)[0]
    return math.sqrt(max(float(largest), 0.0))


def stable_step_s(angular_frequency: float, alpha: float, beta: float) -> float:
    """The largest symplectic Euler step (s) stable for a mode of angular frequency
    w (rad/s) under Rayleigh damping: with zeta = beta w / 2 + alpha / (2 w),
    h < (2 / w) (sqrt(1 + zeta^2) - zeta)."""
    w = angular_frequency
    zeta = 0.5 * beta * w + 0.5 * alpha / w
    return (2.0 / w) * (math.sqrt(1.0 + zeta * zeta) - zeta)


def stable_substeps(model: TissueModel, period_s: float, *, probe_stiffness_n_per_m3=0.0,
                    safety: float = STABLE_STEP_SAFETY) -> int:
    """The number of equal substeps of a ``period_s`` (s) tick that keeps symplectic
    Euler stable on this mesh and material: each substep at most ``safety`` times the
    stable step of the highest mode (``stable_step_s``). The probe's contact counts
    as its pressure stiffness (N/m^3) times each node's share of the boundary's area,
    on every boundary node along every axis at once (``highest_angular_frequency``):
    the worst node's ratio of that stiffness to its mass sets it where the contact
    does (the contact's damping is capped so that it never destabilizes,
    ``add_contact_forces``)."""
    w_max = highest_angular_frequency(model, probe_stiffness_n_per_m3)
    step = stable_step_s(w_max, model.mass_damping_per_s, model.stiffness_damping_s)
    return max(1, math.ceil(period_s / (safety * step)))


def lowest_modes(model: TissueModel, count: int = 1):
    """(angular frequencies (count,) rad/s, mode shapes (3 n, count)) of the free
    nodes at rest, undamped: K phi = w^2 M phi with the lumped masses."""
    free = free_coordinates(model)
    K = linear_stiffness_matrix(model)[free][:, free]
    M = scipy.sparse.diags(np.repeat(model.mass_kg, 3)[free])
    values, vectors = scipy.sparse.linalg.eigsh(K.tocsc(), k=count, M=M.tocsc(), sigma=0.0)
    shapes = np.zeros((3 * model.num_nodes, count))
    shapes[free] = vectors
    return np.sqrt(np.maximum(values, 0.0)), shapes


# --- timing -------------------------------------------------------------------------

def tick_timing(model: TissueModel, *, probe: TissueProbe = None,
                period_s: float = 1e-3, substeps: int = 1, ticks: int = 200):
    """(microseconds a tick, tetrahedra a microsecond of one substep's element pass)
    of ``tissue_tick_from`` on this core, the median of ``ticks`` ticks from the
    model's rest positions under gravity, the probe away: for ``maglev bench``."""
    arguments = tick_arguments(model, probe or TissueProbe(), period_s, substeps)
    n = model.num_nodes
    state = np.zeros(6 * n)
    state[:3 * n] = model.rest_positions_m.ravel()
    other = np.empty_like(state)
    far = np.array([0.0, 0.0, 10.0, 0.0, 0.0, 0.0, 0.0, 0.0, 10.0])
    tissue_tick_from(state, other, far, *arguments)
    durations = []
    for _ in range(ticks):
        start = time.perf_counter()
        tissue_tick_from(state, other, far, *arguments)
        durations.append(time.perf_counter() - start)
        state, other = other, state
    tick_us = 1e6 * float(np.median(durations))
    f = np.zeros(3 * n)
    u = state[:3 * n] - arguments.rest
    passes = []
    for _ in range(ticks):
        start = time.perf_counter()
        add_elastic_forces(u, arguments.corners, arguments.pass_rows, arguments.tick_rows,
                           arguments.pass_work, f)
        passes.append(time.perf_counter() - start)
    return tick_us, model.num_tetrahedra / (1e6 * float(np.median(passes)))
