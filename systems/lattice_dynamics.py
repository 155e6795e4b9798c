"""Mass-spring-damper lattice dynamics: link forces, probe contact, two integrators (numba).

State: positions ``x`` (n, 3) in W (m) and velocities ``v`` (n, 3) (m/s) of every
mass; fixed masses (``inv_mass`` 0) never move. Link e joins masses i < j with
rest length L0 (m), stiffness k (N/m) and damping b (N*s/m) along the link:
the force on i is (k (L - L0) + b u.(v_j - v_i)) u, u the unit vector from i to
j, and its opposite on j.

The probe is a sphere of radius r (m) at p_WP on the tool. Each surface vertex
inside it is pushed out along n, the unit vector from the sphere's centre to
the vertex, by a Hunt-Crossley penalty k_c g(depth) (1 - d (v_rel . n)) (never
pulling; g rises quadratically over the first ``onset_depth_m``, then linearly
with slope 1, so the force and its stiffness both start from zero), with
regularized Coulomb friction mu f_n against the tangential slip; the tool gets
the opposite force at the vertex, so the wrench on the tool is exactly the
negative sum of the forces on the masses, its torque taken about the tool's
origin T.

The link forces are computed a block of masses at a time (``LINK_BLOCK`` links at
most): their links' coordinate differences gathered into flat per-link arrays, the
arithmetic done on those in one branch-free loop the compiler vectorizes, then the
forces scattered back, each mass's own links summed in registers. So the links are
kept sorted by their first mass, first < second (``lattice_model`` does it).

Integrators, one tick of length h (s):
- symplectic Euler (velocity first, then position) with ``substeps`` equal
  substeps. Per mode of angular frequency w with stiffness-proportional link
  damping it is stable iff h_s^2 w^2 (1 + 2 b / (k h_s)) < 4, h_s = h / substeps
  (``max_stable_link_stiffness``); each substep is one pass over the links.
- linearly implicit Euler (Baraff and Witkin 1998): one Newton step of backward
  Euler, (M - h dF/dv - h^2 dF/dx) dv = h (F + h dF/dx v), solved by
  Jacobi-preconditioned conjugate gradients without assembling the matrix. The
  compressive part of the geometric stiffness is dropped so the matrix stays
  positive definite. Stable for any link stiffness; costs two link passes plus
  one per CG iteration. Contact enters explicitly in F.
"""

import math
from dataclasses import dataclass
from typing import NamedTuple

import numba
import numpy as np
import scipy.sparse
import scipy.sparse.linalg

from maglev_haptics.hardware.config_checks import nonnegative, positive
from maglev_haptics.hardware.constants import GRAVITY_M_S2
from maglev_haptics.hardware.kernels import (
    FLAG, INDEX, INDEX_MATRIX, INDEX_VECTOR, MATRIX, READONLY_VECTOR, SCALAR, TENSOR3,
    UINT32_VECTOR, VECTOR, kernel)

SYMPLECTIC_EULER = "symplectic_euler"
LINEARLY_IMPLICIT = "linearly_implicit"
INTEGRATORS = (SYMPLECTIC_EULER, LINEARLY_IMPLICIT)

# The links' arrays the kernels take: links (m, 2), then LatticeModel's link_offsets,
# link_blocks and link_ends.
TOPOLOGY = (INDEX_MATRIX, INDEX_VECTOR, INDEX_VECTOR, UINT32_VECTOR)
# The argument types the steps share: x, v, the topology, rest, k, b, mass, inv_mass,
# gravity, surface, external, p_WP, v_WP, p_WT, then the probe's six constants and h.
STEP_ARGUMENTS = (MATRIX, MATRIX, *TOPOLOGY, VECTOR, VECTOR, VECTOR, VECTOR, VECTOR, VECTOR,
                  INDEX_VECTOR, MATRIX, VECTOR, VECTOR, VECTOR, *(SCALAR,) * 7)
# tick_from's: masses in and out, probe, the model's arrays, external, constants, the
# integrator's flag and counts, and the work space of both integrators.
TICK_ARGUMENTS = (VECTOR, VECTOR, VECTOR, *TOPOLOGY, VECTOR, VECTOR, VECTOR, VECTOR, VECTOR,
                  VECTOR, INDEX_VECTOR, MATRIX, VECTOR, FLAG, INDEX, INDEX, MATRIX, TENSOR3,
                  MATRIX, MATRIX)


# Links a block of the link-force pass at most: its per-link arrays stay in the L1 cache.
LINK_BLOCK = 256
_LINK_ROW = LINK_BLOCK + 8  # a row of the per-link work space, padded off a 4 KiB multiple


class LatticeModel(NamedTuple):
    """The arrays the kernels read; see ``lattice_model``."""

    links: np.ndarray  # (m, 2) int64 mass indices, first < second, sorted by first
    rest_lengths_m: np.ndarray  # (m,)
    stiffness_n_per_m: np.ndarray  # (m,)
    damping_n_s_per_m: np.ndarray  # (m,)
    mass_kg: np.ndarray  # (n,); fixed masses keep their nominal mass here
    inv_mass_per_kg: np.ndarray  # (n,); 0 for fixed masses
    surface: np.ndarray  # (n_s,) int64 indices of the surface vertices
    gravity_m_s2: np.ndarray  # (3,) in W
    link_offsets: np.ndarray  # (n + 1,) int64: mass i's links are link_offsets[i]..[i + 1] - 1
    link_blocks: np.ndarray  # int64 mass boundaries of blocks of at most LINK_BLOCK links
    link_ends: np.ndarray  # (m,) uint32: each link's second mass

    @property
    def topology(self):
        """(links, link_offsets, link_blocks, link_ends): the kernels' first link arguments."""
        return self.links, self.link_offsets, self.link_blocks, self.link_ends


def link_topology(links, num_masses: int):
    """(order, links, offsets, blocks, ends) for ``links`` (m, 2): each link written
    first < second, sorted (stably) by its first mass; ``order`` the permutation
    applied (the link's index in ``links``); offsets (n + 1) the first link of each
    mass; blocks the mass boundaries of consecutive masses whose links number at most
    LINK_BLOCK (no mass has more than LINK_BLOCK links of its own)."""
    links = np.sort(np.asarray(links, dtype=np.int64).reshape(-1, 2), axis=1)
    order = np.argsort(links[:, 0], kind="stable")
    links = np.ascontiguousarray(links[order])
    offsets = np.searchsorted(links[:, 0], np.arange(num_masses + 1)).astype(np.int64)
    if np.diff(offsets).max(initial=0) > LINK_BLOCK:
        raise ValueError(f"a mass has more than LINK_BLOCK = {LINK_BLOCK} links")
    blocks = [0]
    for i in range(num_masses):
        if offsets[i + 1] - offsets[blocks[-1]] > LINK_BLOCK:
            blocks.append(i)
    blocks.append(num_masses)
    return (order, links, offsets, np.array(blocks, dtype=np.int64),
            np.ascontiguousarray(links[:, 1], dtype=np.uint32))


@dataclass
class ProbeContact:
    """Penalty contact of the probe sphere with the lattice's surface vertices."""

    radius_m: float = 0.004  # (m): several vertices at once, 2.5 mm apart in the scene
    stiffness_n_per_m: float = 400.0  # per vertex, past the onset (N/m)
    onset_depth_m: float = 0.0003  # the stiffness ramps in over this depth (m)
    dissipation_s_per_m: float = 5.0  # Hunt-Crossley, on the approach speed (s/m)
    friction: float = 0.05  # Coulomb coefficient (-): jelly is slippery (the peg's is 0.15)
    slip_speed_m_s: float = 0.002  # friction reaches ~70 % of mu f_n at this slip (m/s)

    def validate(self, path: str = "probe") -> None:
        """Range checks; a ValueError names ``path.field``, its value and what is allowed."""
        for name in ("radius_m", "stiffness_n_per_m", "onset_depth_m", "slip_speed_m_s"):
            positive(f"{path}.{name}", getattr(self, name))
        for name in ("dissipation_s_per_m", "friction"):
            nonnegative(f"{path}.{name}", getattr(self, name))

    def constants(self) -> np.ndarray:
        """The radius (m), stiffness (N/m), onset (m), dissipation (s/m), friction (-)
        and slip speed (m/s), in the order the contact kernels take them (6,)."""
        return np.array([self.radius_m, self.stiffness_n_per_m, self.onset_depth_m,
                         self.dissipation_s_per_m, self.friction, self.slip_speed_m_s])


def lattice_model(links, rest_lengths_m, fixed, surface, *, node_mass_kg: float,
                  link_stiffness_n_per_m: float, link_damping_n_s_per_m: float,
                  gravity_m_s2=(0.0, 0.0, -GRAVITY_M_S2)) -> LatticeModel:
    """Contiguous kernel arrays: every mass ``node_mass_kg`` (kg), every link the
    same stiffness (N/m) and damping (N*s/m), ``fixed`` (n,) bool masses immobile.
    The links are reordered as ``link_topology`` says (a lattice from
    ``build_lattice`` already is), their rest lengths with them."""
    n = len(fixed)
    m = len(links)
    mass = np.full(n, float(node_mass_kg))
    order, links, offsets, blocks, ends = link_topology(links, n)
    return LatticeModel(
        links=links,
        rest_lengths_m=np.ascontiguousarray(np.asarray(rest_lengths_m, dtype=float)[order]),
        stiffness_n_per_m=np.full(m, float(link_stiffness_n_per_m)),
        damping_n_s_per_m=np.full(m, float(link_damping_n_s_per_m)),
        mass_kg=mass,
        inv_mass_per_kg=np.where(np.asarray(fixed, bool), 0.0, 1.0 / mass),
        surface=np.ascontiguousarray(np.asarray(surface).ravel(), dtype=np.int64),
        gravity_m_s2=np.asarray(gravity_m_s2, dtype=float).copy(),
        link_offsets=offsets, link_blocks=blocks, link_ends=ends)


# --- forces -------------------------------------------------------------------------

@numba.njit(cache=True, inline="always")
def _add_opposite(out, i, j, a, b, c):
    """out[i] += (a, b, c) and out[j] -= (a, b, c): a link's pair of forces."""
    out[i, 0] += a
    out[i, 1] += b
    out[i, 2] += c
    out[j, 0] -= a
    out[j, 1] -= b
    out[j, 2] -= c


# Let LLVM fuse multiply-adds and use reciprocals (one division a link); unlike full
# fastmath it keeps IEEE NaN/inf semantics. error_model="numpy": a division by zero
# gives inf instead of raising, so no branch stops the loops from vectorizing.
LINK_MATH = {"contract", "reassoc", "arcp", "nsz"}


@numba.njit(cache=True, fastmath=LINK_MATH, error_model="numpy", inline="always")
def _gather_block(x, v, offsets, ends, m0, m1, e0, d):
    """d[0:3, c], d[3:6, c] = x and v of link e0 + c's second mass minus its first's,
    for the links of masses m0..m1-1 (x, v flat: 3 a mass)."""
    dx, dy, dz, wx, wy, wz = d[0], d[1], d[2], d[3], d[4], d[5]
    for i in range(m0, m1):
        xi0, xi1, xi2 = x[3 * i], x[3 * i + 1], x[3 * i + 2]
        vi0, vi1, vi2 = v[3 * i], v[3 * i + 1], v[3 * i + 2]
        for e in range(offsets[i], offsets[i + 1]):
            c = e - e0
            j3 = 3 * ends[e]
            dx[c] = x[j3] - xi0
            dy[c] = x[j3 + 1] - xi1
            dz[c] = x[j3 + 2] - xi2
            wx[c] = v[j3] - vi0
            wy[c] = v[j3 + 1] - vi1
            wz[c] = v[j3 + 2] - vi2


@numba.njit(cache=True, fastmath=LINK_MATH, error_model="numpy", inline="always")
def _link_arithmetic(d, rest, k, b, e0, count):
    """d[0:3, c] = the force of link e0 + c on its first mass (N), from its differences:
    (k (L - L0) + b u.(v_j - v_i)) u. No branch: the compiler vectorizes it."""
    dx, dy, dz, wx, wy, wz = d[0], d[1], d[2], d[3], d[4], d[5]
    rest, k, b = rest[e0:e0 + count], k[e0:e0 + count], b[e0:e0 + count]
    for c in range(count):
        e = c
        squared = dx[c] * dx[c] + dy[c] * dy[c] + dz[c] * dz[c]
        inverse = 1.0 / math.sqrt(squared)
        length = squared * inverse
        closing = (dx[c] * wx[c] + dy[c] * wy[c] + dz[c] * wz[c]) * inverse
        # The force along the link over its length: times (dx, dy, dz) it is the force.
        s = (k[e] * (length - rest[e]) + b[e] * closing) * inverse
        dx[c] = s * dx[c]
        dy[c] = s * dy[c]
        dz[c] = s * dz[c]


@numba.njit(cache=True, fastmath=LINK_MATH, error_model="numpy", inline="always")
def _scatter_block(offsets, ends, m0, m1, e0, d, f):
    """f (flat) += each link's force d[0:3] on its first mass, minus it on its second;
    a mass's own links summed in registers first."""
    fx, fy, fz = d[0], d[1], d[2]
    for i in range(m0, m1):
        ax, ay, az = 0.0, 0.0, 0.0
        for e in range(offsets[i], offsets[i + 1]):
            c = e - e0
            j3 = 3 * ends[e]
            ax += fx[c]
            ay += fy[c]
            az += fz[c]
            f[j3] -= fx[c]
            f[j3 + 1] -= fy[c]
            f[j3 + 2] -= fz[c]
        f[3 * i] += ax
        f[3 * i + 1] += ay
        f[3 * i + 2] += az


@numba.njit(cache=True, fastmath=LINK_MATH, error_model="numpy")
def link_forces(x, v, links, offsets, blocks, ends, rest, k, b, f):
    """f (n, 3) = every link's spring-damper force on each mass (N); the topology as
    ``LatticeModel.topology`` (``links`` itself is not read here)."""
    size = x.shape[0] * 3
    x_flat = x.reshape(size)
    v_flat = v.reshape(size)
    f_flat = f.reshape(size)
    f_flat[:] = 0.0
    d = np.empty((6, _LINK_ROW))
    for block in range(blocks.shape[0] - 1):
        m0, m1 = blocks[block], blocks[block + 1]
        e0 = offsets[m0]
        _gather_block(x_flat, v_flat, offsets, ends, m0, m1, e0, d)
        _link_arithmetic(d, rest, k, b, e0, offsets[m1] - e0)
        _scatter_block(offsets, ends, m0, m1, e0, d, f_flat)


@numba.njit(cache=True)
def probe_point(X_WT, V_WT, p_TP):
    """(p_WP, v_WP): the probe centre's position (m) and velocity (m/s) in W from the
    tool pose [qw, qx, qy, qz, x, y, z], its spatial velocity [w; v] in W and p_TP (m)."""
    qw, qx, qy, qz = X_WT[0], X_WT[1], X_WT[2], X_WT[3]
    norm = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
    qw, qx, qy, qz = qw / norm, qx / norm, qy / norm, qz / norm
    R = np.empty((3, 3))
    R[0, 0] = 1 - 2 * (qy * qy + qz * qz)
    R[0, 1] = 2 * (qx * qy - qw * qz)
    R[0, 2] = 2 * (qx * qz + qw * qy)
    R[1, 0] = 2 * (qx * qy + qw * qz)
    R[1, 1] = 1 - 2 * (qx * qx + qz * qz)
    R[1, 2] = 2 * (qy * qz - qw * qx)
    R[2, 0] = 2 * (qx * qz - qw * qy)
    R[2, 1] = 2 * (qy * qz + qw * qx)
    R[2, 2] = 1 - 2 * (qx * qx + qy * qy)
    r = R @ p_TP  # from T's origin to the probe centre, W axes
    p_WP = X_WT[4:7] + r
    w = V_WT[0:3]
    v_WP = V_WT[3:6] + np.array([w[1] * r[2] - w[2] * r[1], w[2] * r[0] - w[0] * r[2],
                                 w[0] * r[1] - w[1] * r[0]])
    return p_WP, v_WP


@numba.njit(cache=True, inline="always")
def penalty_force(nx, ny, nz, rx, ry, rz, depth, stiffness, onset, d_hc, damping_cap, mu,
                  slip_speed):
    """The probe's force (N) on a surface point ``depth`` (m) inside it: n (unit) out
    of the sphere through the point, r (m/s) the point's velocity less the probe's;
    ``stiffness`` (N/m) on the depth smoothed over ``onset`` (m), Hunt-Crossley
    dissipation ``d_hc`` (s/m) along n and friction ``mu`` regularized below
    ``slip_speed`` (m/s) across it, the damping capped at ``damping_cap`` (N s/m).
    Returns (fx, fy, fz, pressed); not pressed (no force) where it would pull."""
    approach = rx * nx + ry * ny + rz * nz
    if depth < onset:
        squeeze = 0.5 * depth * depth / onset
    else:
        squeeze = depth - 0.5 * onset
    normal = stiffness * squeeze - min(stiffness * squeeze * d_hc, damping_cap) * approach
    if normal <= 0.0:
        return 0.0, 0.0, 0.0, False
    tx, ty, tz = rx - approach * nx, ry - approach * ny, rz - approach * nz
    # At small slip the friction is a damper mu normal / slip_speed: keep it under the cap.
    regularization = max(slip_speed, mu * normal / damping_cap)
    slip = math.sqrt(tx * tx + ty * ty + tz * tz + regularization * regularization)
    drag = -mu * normal / slip
    return normal * nx + drag * tx, normal * ny + drag * ty, normal * nz + drag * tz, True


@numba.njit(cache=True, inline="always")
def add_reaction(wrench, fx, fy, fz, ax, ay, az):
    """wrench [f; tau] (N, N m) -= the force f (N) applied at a (m) from its origin:
    the reaction on the tool of a contact force on the surface."""
    wrench[0] -= fx
    wrench[1] -= fy
    wrench[2] -= fz
    wrench[3] -= ay * fz - az * fy
    wrench[4] -= az * fx - ax * fz
    wrench[5] -= ax * fy - ay * fx


@numba.njit(cache=True)
def add_probe_forces(x, v, surface, p_WP, v_WP, p_WT, radius, k_c, onset, d_hc, mu, slip_speed,
                     mass, h, f):
    """Add the probe's contact forces on the surface vertices into f (n, 3) (N);
    an f with no rows records nothing.

    The contact's damping on a vertex, Hunt-Crossley along the normal and the
    regularized friction across it, is applied explicitly over the step h (s); so
    each is capped at the vertex's mass (kg) over h, which stops the relative motion
    in one step instead of reversing it (uncapped, a held probe made the surface
    chatter at half the tick rate).

    Returns (wrench on the tool [f; tau] in W about p_WT (N, N*m), number of
    vertices in contact)."""
    wrench = np.zeros(6)
    touching = 0
    for s in range(surface.shape[0]):
        i = surface[s]
        nx, ny, nz = x[i, 0] - p_WP[0], x[i, 1] - p_WP[1], x[i, 2] - p_WP[2]
        distance = math.sqrt(nx * nx + ny * ny + nz * nz)
        if distance >= radius or distance == 0.0:
            continue
        nx, ny, nz = nx / distance, ny / distance, nz / distance
        fx, fy, fz, pressed = penalty_force(
            nx, ny, nz, v[i, 0] - v_WP[0], v[i, 1] - v_WP[1], v[i, 2] - v_WP[2],
            radius - distance, k_c, onset, d_hc, mass[i] / h, mu, slip_speed)
        if not pressed:
            continue
        touching += 1
        if f.shape[0] > 0:
            f[i, 0] += fx
            f[i, 1] += fy
            f[i, 2] += fz
        # The opposite force on the tool, applied at the vertex.
        add_reaction(wrench, fx, fy, fz, x[i, 0] - p_WT[0], x[i, 1] - p_WT[1],
                     x[i, 2] - p_WT[2])
    return wrench, touching


@numba.njit(cache=True)
def _total_force(i, a, mass, gravity, external, f):
    """Force (N) on mass i along axis a: weight, external, and links and contact from f."""
    return mass[i] * gravity[a] + external[i, a] + f[i, a]


# --- integrators ------------------------------------------------------------------------

@numba.njit(cache=True, error_model="numpy")
def _symplectic_substep(x, v, mass, inv_mass, gravity, external, f, h_s):
    """v += h_s F / m, then x += h_s v, at the free masses; a select, not a branch,
    keeps the fixed ones."""
    for i in range(x.shape[0]):
        free = inv_mass[i] != 0.0
        for a in range(3):
            moved = v[i, a] + h_s * inv_mass[i] * _total_force(i, a, mass, gravity, external, f)
            v[i, a] = moved if free else v[i, a]
            x[i, a] = x[i, a] + h_s * v[i, a] if free else x[i, a]


@kernel((*STEP_ARGUMENTS, INDEX, MATRIX))
def symplectic_euler_tick(x, v, links, offsets, blocks, ends, rest, k, b, mass, inv_mass, gravity,
                          surface, external, p_WP, v_WP, p_WT, radius, k_c, onset, d_hc, mu,
                          slip_speed, h, substeps, f):
    """Advance x, v (in place) by h (s) in ``substeps`` symplectic Euler substeps.

    ``external`` (n, 3) N is held over the tick; the probe is held at p_WP moving
    at v_WP. f (n, 3) is work space. Returns (the wrench on the tool of the first
    substep, as ``add_probe_forces``, vertices in contact then)."""
    h_s = h / substeps
    wrench = np.zeros(6)
    touching = 0
    for step in range(substeps):
        link_forces(x, v, links, offsets, blocks, ends, rest, k, b, f)
        w, t = add_probe_forces(x, v, surface, p_WP, v_WP, p_WT, radius, k_c, onset, d_hc,
                                mu, slip_speed, mass, h_s, f)
        if step == 0:
            wrench, touching = w, t
        _symplectic_substep(x, v, mass, inv_mass, gravity, external, f, h_s)
    return wrench, touching


@numba.njit(cache=True)
def _implicit_link_terms(x, links, rest, k, b, h, u, c_iso, c_axial):
    """Per link: unit vector u and the two coefficients of its block of
    h dF/dv + h^2 dF/dx = c_iso I + c_axial u u^T (compression dropped)."""
    for e in range(links.shape[0]):
        i, j = links[e, 0], links[e, 1]
        dx = x[j, 0] - x[i, 0]
        dy = x[j, 1] - x[i, 1]
        dz = x[j, 2] - x[i, 2]
        length = math.sqrt(dx * dx + dy * dy + dz * dz)
        u[e, 0], u[e, 1], u[e, 2] = dx / length, dy / length, dz / length
        geometric = k[e] * max(0.0, 1.0 - rest[e] / length)
        c_iso[e] = h * h * geometric
        c_axial[e] = h * b[e] + h * h * (k[e] - geometric)


@numba.njit(cache=True)
def _apply_link_range(y, links, u, c_iso, c_axial, start, stop, out):
    """out += the blocks of links start..stop-1 acting on y's difference (i - j)."""
    for e in range(start, stop):
        i, j = links[e, 0], links[e, 1]
        d0, d1, d2 = y[i, 0] - y[j, 0], y[i, 1] - y[j, 1], y[i, 2] - y[j, 2]
        along = c_axial[e] * (u[e, 0] * d0 + u[e, 1] * d1 + u[e, 2] * d2)
        _add_opposite(out, i, j, c_iso[e] * d0 + along * u[e, 0],
                      c_iso[e] * d1 + along * u[e, 1], c_iso[e] * d2 + along * u[e, 2])


@numba.njit(cache=True)
def _system_product(y, mass, inv_mass, links, u, c_iso, c_axial, out):
    """out = A y, A = M - h dF/dv - h^2 dF/dx, zero at fixed masses."""
    for i in range(y.shape[0]):
        for a in range(3):
            out[i, a] = mass[i] * y[i, a]
    _apply_link_range(y, links, u, c_iso, c_axial, 0, links.shape[0], out)
    for i in range(y.shape[0]):
        if inv_mass[i] == 0.0:
            for a in range(3):
                out[i, a] = 0.0


@numba.njit(cache=True)
def _dot(a, b):
    total = 0.0
    for i in range(a.shape[0]):
        for c in range(3):
            total += a[i, c] * b[i, c]
    return total


@kernel((*STEP_ARGUMENTS, SCALAR, INDEX, TENSOR3, MATRIX, MATRIX))
def linearly_implicit_tick(x, v, links, offsets, blocks, ends, rest, k, b, mass, inv_mass,
                           gravity, surface, external, p_WP, v_WP, p_WT, radius, k_c, onset,
                           d_hc, mu, slip_speed, h, tolerance, max_iterations, node_work, u,
                           link_work):
    """Advance x, v (in place) by one linearly implicit Euler step of h (s).

    ``node_work``, ``u`` and ``link_work`` are work space from
    ``implicit_workspace``. CG stops when the preconditioned residual is below
    ``tolerance`` times that of the right-hand side, or after ``max_iterations``.
    Returns (wrench on the tool, vertices in contact, CG iterations)."""
    f, rhs, dv, r, z, p, q, inv_diag = (node_work[0], node_work[1], node_work[2], node_work[3],
                                        node_work[4], node_work[5], node_work[6], node_work[7])
    m_links = links.shape[0]
    c_iso, c_axial, stiff_axial = link_work[0], link_work[1], link_work[2]
    link_forces(x, v, links, offsets, blocks, ends, rest, k, b, f)
    wrench, touching = add_probe_forces(x, v, surface, p_WP, v_WP, p_WT, radius, k_c, onset,
                                        d_hc, mu, slip_speed, mass, h, f)
    # rhs = h F + h^2 dF/dx v, zero at fixed masses.
    for i in range(x.shape[0]):
        for a in range(3):
            rhs[i, a] = (0.0 if inv_mass[i] == 0.0
                         else h * _total_force(i, a, mass, gravity, external, f))
    _implicit_link_terms(x, links, rest, k, b, h, u, c_iso, c_axial)
    # The blocks' stiffness part alone (damping removed) is -h^2 dF/dx per link.
    for e in range(m_links):
        stiff_axial[e] = c_axial[e] - h * b[e]
    q[:] = 0.0
    _apply_link_range(v, links, u, c_iso, stiff_axial, 0, m_links, q)
    for i in range(x.shape[0]):
        if inv_mass[i] != 0.0:
            for a in range(3):
                rhs[i, a] -= q[i, a]
    # Jacobi preconditioner: the diagonal of A.
    diag = z  # z holds the diagonal until the iterations start
    for i in range(x.shape[0]):
        for a in range(3):
            diag[i, a] = mass[i]
    for e in range(m_links):
        i, j = links[e, 0], links[e, 1]
        for a in range(3):
            d = c_iso[e] + c_axial[e] * u[e, a] * u[e, a]
            diag[i, a] += d
            diag[j, a] += d
    for i in range(x.shape[0]):
        for a in range(3):
            inv_diag[i, a] = 0.0 if inv_mass[i] == 0.0 else 1.0 / diag[i, a]
            dv[i, a] = 0.0
            r[i, a] = rhs[i, a]
            z[i, a] = r[i, a] * inv_diag[i, a]
            p[i, a] = z[i, a]
    rz = _dot(r, z)
    limit = tolerance * tolerance * rz
    iterations = 0
    while iterations < max_iterations and rz > limit and rz > 0.0:
        _system_product(p, mass, inv_mass, links, u, c_iso, c_axial, q)
        alpha = rz / _dot(p, q)
        for i in range(x.shape[0]):
            for a in range(3):
                dv[i, a] += alpha * p[i, a]
                r[i, a] -= alpha * q[i, a]
                z[i, a] = r[i, a] * inv_diag[i, a]
        rz_next = _dot(r, z)
        beta = rz_next / rz
        rz = rz_next
        for i in range(x.shape[0]):
            for a in range(3):
                p[i, a] = z[i, a] + beta * p[i, a]
        iterations += 1
    for i in range(x.shape[0]):
        for a in range(3):
            v[i, a] += dv[i, a]
            x[i, a] += h * v[i, a]
    return wrench, touching, iterations


@kernel(TICK_ARGUMENTS, nogil=True)
def tick_from(masses_in, masses_out, probe, links, offsets, blocks, ends, rest, k, b, mass,
              inv_mass, gravity, surface, external, constants, implicit, substeps,
              cg_max_iterations, forces, node_work, u, link_work):
    """``masses_out`` = one tick from ``masses_in`` ([x; v], 6 n). ``probe`` is
    [p_WP, v_WP, p_WT] (9); ``constants`` the probe's radius, stiffness, onset,
    dissipation, friction, slip speed, then the tick and the CG tolerance."""
    n = masses_in.shape[0] // 6
    masses_out[:] = masses_in
    x = masses_out[:3 * n].reshape((n, 3))
    v = masses_out[3 * n:].reshape((n, 3))
    if implicit:
        linearly_implicit_tick(
            x, v, links, offsets, blocks, ends, rest, k, b, mass, inv_mass, gravity, surface,
            external, probe[0:3], probe[3:6], probe[6:9], constants[0], constants[1],
            constants[2], constants[3], constants[4], constants[5], constants[6], constants[7],
            cg_max_iterations,
            node_work, u, link_work)
    else:
        symplectic_euler_tick(
            x, v, links, offsets, blocks, ends, rest, k, b, mass, inv_mass, gravity, surface,
            external, probe[0:3], probe[3:6], probe[6:9], constants[0], constants[1],
            constants[2], constants[3], constants[4], constants[5], constants[6], substeps,
            forces)


# The DeformableSurface system's state vector is [x; v; X_WT; V_WT] (6 n + 13).

@kernel((VECTOR, VECTOR), (READONLY_VECTOR, VECTOR))
def probe_arguments(tool, p_TP):
    """[p_WP, v_WP, p_WT] (9) from the stored tool state [X_WT; V_WT] (13)."""
    p_WP, v_WP = probe_point(tool[0:7], tool[7:13], p_TP)
    return np.concatenate((p_WP, v_WP, tool[4:7]))


@kernel((READONLY_VECTOR, INDEX_VECTOR, VECTOR, VECTOR, VECTOR, SCALAR))
def state_contact(state, surface, p_TP, constants, mass, h):
    """(wrench on the tool [f; tau] in W about T's origin, vertices in contact) for the
    state vector [x; v; X_WT; V_WT]; ``constants`` the probe's radius, stiffness,
    onset, dissipation, friction and slip speed; ``mass`` (n,) kg and the (sub)step
    h (s) as the next step applies the contact."""
    n = (state.shape[0] - 13) // 6
    x = state[:3 * n].reshape((n, 3))
    v = state[3 * n:6 * n].reshape((n, 3))
    probe = probe_arguments(state[6 * n:], p_TP)
    return add_probe_forces(x, v, surface, probe[0:3], probe[3:6], probe[6:9], constants[0],
                            constants[1], constants[2], constants[3], constants[4],
                            constants[5], mass, h, np.zeros((0, 3)))


def implicit_workspace(num_masses: int, num_links: int):
    """(node_work, u, link_work): work space for ``linearly_implicit_tick``."""
    return np.zeros((8, num_masses, 3)), np.zeros((num_links, 3)), np.zeros((3, num_links))


# --- energy and stability --------------------------------------------------------------

@numba.njit(cache=True)
def lattice_energy(x, v, links, rest, k, mass, inv_mass, gravity):
    """Kinetic + spring + gravitational energy of the free masses (J); gravity's
    zero at z = 0 of W."""
    energy = 0.0
    for i in range(x.shape[0]):
        if inv_mass[i] == 0.0:
            continue
        energy += 0.5 * mass[i] * (v[i, 0] ** 2 + v[i, 1] ** 2 + v[i, 2] ** 2)
        energy -= mass[i] * (gravity[0] * x[i, 0] + gravity[1] * x[i, 1] + gravity[2] * x[i, 2])
    for e in range(links.shape[0]):
        i, j = links[e, 0], links[e, 1]
        length = math.sqrt((x[j, 0] - x[i, 0]) ** 2 + (x[j, 1] - x[i, 1]) ** 2
                           + (x[j, 2] - x[i, 2]) ** 2)
        energy += 0.5 * k[e] * (length - rest[e]) ** 2
    return energy


def stiffness_matrix(positions_m, links, stiffness_n_per_m, fixed) -> scipy.sparse.csr_matrix:
    """The lattice's linear stiffness K (N/m) at ``positions_m`` with every link at
    rest, on the free masses' coordinates (3 per free mass, in mass order): the
    sum over links of k u u^T blocks."""
    positions_m = np.asarray(positions_m, float)
    links = np.asarray(links)
    free = ~np.asarray(fixed, bool)
    index = np.full(len(free), -1)
    index[free] = np.arange(free.sum())
    d = positions_m[links[:, 1]] - positions_m[links[:, 0]]
    u = d / np.linalg.norm(d, axis=1)[:, None]
    blocks = np.asarray(stiffness_n_per_m, float)[:, None, None] * u[:, :, None] * u[:, None, :]
    rows, cols, values = [], [], []
    for (a, b_), sign in (((0, 0), 1.0), ((1, 1), 1.0), ((0, 1), -1.0), ((1, 0), -1.0)):
        ia, ib = index[links[:, a]], index[links[:, b_]]
        keep = (ia >= 0) & (ib >= 0)
        for r in range(3):
            for c in range(3):
                rows.append(3 * ia[keep] + r)
                cols.append(3 * ib[keep] + c)
                values.append(sign * blocks[keep, r, c])
    size = 3 * int(free.sum())
    return scipy.sparse.coo_matrix((np.concatenate(values), (np.concatenate(rows),
                                                            np.concatenate(cols))),
                                   shape=(size, size)).tocsr()


def max_stable_link_stiffness(positions_m, links, fixed, *, node_mass_kg: float,
                              link_damping_n_s_per_m: float, time_step_s: float,
                              substeps: int = 1) -> float:
    """Largest link stiffness (N/m) for which symplectic Euler with ``substeps``
    substeps of a ``time_step_s`` (s) tick is stable on this lattice at rest.

    From h_s^2 w_max^2 (1 + 2 b / (k h_s)) < 4 with w_max^2 = k lam / m, lam the
    largest eigenvalue of the stiffness matrix with unit link stiffness: k <
    (4 - 2 b h_s lam / m) m / (lam h_s^2); 0 if the damping alone is unstable.
    Contact stiffness on the surface vertices is not included.
    """
    unit = stiffness_matrix(positions_m, links, np.ones(len(links)), fixed)
    lam = float(scipy.sparse.linalg.eigsh(unit, k=1, which="LA", return_eigenvectors=False)[0])
    h_s = time_step_s / substeps
    margin = 4.0 - 2.0 * link_damping_n_s_per_m * h_s * lam / node_mass_kg
    return max(0.0, margin * node_mass_kg / (lam * h_s * h_s))
