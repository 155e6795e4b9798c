"""The force a sphere meets pressed slowly into tissue, and the felt stiffness.

The sphere is the scene's probe (``tissue_fem.add_contact_forces``: the penalty
pressure k_p g(depth) on the boundary triangles' quadrature points inside it, along
the normal from its centre, each point's force shared by its triangle's nodes). It
moves straight down over a point (x, y) in W; its depth d (m) is measured from the
undeformed surface there (the reference mesh's top face under the sphere's centre)
to the sphere's lowest point, so the centre lies at z = z_top + R - d. The tissue
starts at rest under its gravity.

Quasi-static: at each depth the tissue is in static equilibrium, found by Newton's
method on the free nodes' forces, the same forces the haptic kernel integrates
(``tissue_fem.elastic_forces``: Drake's linear_corotated element, its rotations
taken at the current positions as the kernel takes them at each tick's start, the
lumped weights, the probe's penalty at rest). The Newton matrix is the corotated
linear stiffness at the current rotations (``linear_stiffness_matrix``) plus the
probe's normal stiffness, k_p a g'(depth) (b b^T) x (n n^T) of each point inside the
sphere (area a, barycentric weights b on its triangle's nodes); it leaves out the
rotations' own change and the normals' turning, so Newton converges linearly near
the end instead of quadratically, but it converges to the kernel's own equilibrium
(the residual is exact). The sphere descends in steps of at most ``max_step_m`` so
that the contact set changes a little a step.

The felt stiffness dF/dd (N/m) at a depth is the central difference of the force
between the equilibria a small step above and below it: the contact stiffness
linearized at the pressed state, what the tool meets for small motions there.
The force F (N) is the push up on the sphere (W's +z component of the contact
force on the tool), the sum of the nodes' reactions.
"""

import dataclasses
from typing import List, NamedTuple, Sequence

import numpy as np
import scipy.sparse
import scipy.sparse.linalg

from maglev_haptics.hardware.config_checks import positive, require
from maglev_haptics.systems.tissue_fem import (
    TissueModel, TissueProbe, add_contact_forces, boundary_triangles, contact_quadrature,
    elastic_forces, free_coordinates, linear_stiffness_matrix)

# The Newton iteration stops when every free node's force balance is within this
# fraction of the largest node weight or probe force (-).
RELATIVE_TOLERANCE = 1e-8
MAX_NEWTON_ITERATIONS = 60
# Newton steps with one factored matrix before it is refactored at the current state.
REFRESH_ITERATIONS = 8
MAX_PRESS_STEP_M = 2.5e-4  # the sphere descends at most this far between equilibria (m)
STIFFNESS_STEP_M = 1e-4  # half the span of the central difference of dF/dd (m)
_PERIOD_S = 1e-3  # the probe law's step (s): it sets only a damping cap, idle at rest


class PressedState(NamedTuple):
    """The tissue in equilibrium with the sphere at one depth."""

    depth_m: float  # below the undeformed surface (m)
    p_WP_m: np.ndarray  # (3,) the sphere's centre in W (m)
    positions_m: np.ndarray  # (n, 3) the nodes in W (m)
    force_n: float  # the push up on the sphere (N)
    points_in_contact: int  # the contact's quadrature points inside the sphere


def surface_top_m(rest_positions_m, tetrahedra, p_xy_m) -> float:
    """z (m) of the highest upward-facing boundary triangle of the undeformed mesh
    over the point ``p_xy_m`` (x, y in W, m); a ValueError if none lies over it."""
    points = np.asarray(rest_positions_m, float)
    triangles, _ = boundary_triangles(tetrahedra)
    corners = points[triangles]  # (k, 3, 3)
    normal_z = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])[:, 2]
    corners = corners[normal_z > 0]
    a, b, c = corners[:, 0, :2], corners[:, 1, :2], corners[:, 2, :2]
    p = np.asarray(p_xy_m, float)[:2]
    area = _cross_z(b - a, c - a)
    # Barycentric coordinates of p in each triangle's projection on the xy plane.
    weight_b = _cross_z(p - a, c - a) / area
    weight_c = _cross_z(b - a, p - a) / area
    weight_a = 1.0 - weight_b - weight_c
    weights = np.column_stack([weight_a, weight_b, weight_c])
    over = (weights >= -1e-12).all(axis=1)
    require(bool(over.any()), "p_xy_m", p.tolist(),
            "must lie over the tissue's top surface (x, y in W, m)")
    return float(np.max(np.einsum("ka,ka->k", weights[over], corners[over, :, 2])))


def _cross_z(u, v):
    """The z component of u x v for rows of planar vectors (k, 2)."""
    return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]


def probe_force(model: TissueModel, positions_m, probe: TissueProbe, p_WP_m):
    """(forces on the nodes (n, 3) N, force on the sphere (3,) N, points touching):
    the probe law at rest (no velocity, so no dissipation or friction)."""
    x = np.ascontiguousarray(positions_m, float)
    forces = np.zeros_like(x)
    still = np.zeros(3)
    p_WP = np.asarray(p_WP_m, float)
    wrench, touching = add_contact_forces(
        x, np.zeros_like(x), model.triangles, model.triangle_rows, contact_quadrature(), p_WP,
        still, p_WP, probe.radius_m, probe.stiffness_n_per_m3, probe.onset_depth_m,
        probe.dissipation_s_per_m, probe.friction, probe.slip_speed_m_s, _PERIOD_S, forces)
    return forces, wrench[:3], touching


class _Tangent:
    """The Newton matrix on the free coordinates: the corotated linear stiffness at
    the rotations of some positions, factored once (sparse LU), plus the probe's
    normal stiffness C on the few coordinates it touches, added by the Woodbury
    identity, (K + P C P^T)^-1 = K^-1 - K^-1 P (I + C P^T K^-1 P)^-1 C P^T K^-1, with
    K^-1 of each touched coordinate's unit vector kept. So a Newton step costs one
    solve with the factors, not a factorization."""

    def __init__(self, model: TissueModel, positions_m, held_coordinates=()):
        self.held = held_coordinates
        self.free = np.setdiff1d(free_coordinates(model), held_coordinates)
        self.where = np.full(3 * model.num_nodes, -1)
        self.where[self.free] = np.arange(len(self.free))
        stiffness = linear_stiffness_matrix(model, positions_m)[self.free][:, self.free]
        # A symmetric ordering: far less fill than the default COLAMD on a stiffness.
        self.factors = scipy.sparse.linalg.splu(stiffness.tocsc(), permc_spec="MMD_AT_PLUS_A")
        self.columns = {}  # coordinate (into 3 n) -> K^-1 of its unit vector (f,)

    def _spread(self, coordinates) -> np.ndarray:
        """K^-1 P (f, c): the kept columns of ``coordinates``, the missing solved at once."""
        missing = [c for c in coordinates if c not in self.columns]
        if missing:
            unit = np.zeros((len(self.free), len(missing)))
            unit[self.where[missing], np.arange(len(missing))] = 1.0
            for c, column in zip(missing, self.factors.solve(unit).T):
                self.columns[c] = column
        return np.column_stack([self.columns[c] for c in coordinates])

    def solve(self, residual, coordinates, contact) -> np.ndarray:
        """(K + P C P^T)^-1 residual, C = ``contact`` (c, c) N/m on ``coordinates``
        (indices into 3 n; those not free are dropped with their rows and columns)."""
        base = self.factors.solve(residual)
        kept = self.where[coordinates] >= 0
        coordinates, contact = coordinates[kept], contact[kept][:, kept]
        if len(coordinates) == 0:
            return base
        spread = self._spread(coordinates)
        rows = self.where[coordinates]
        shift = np.linalg.solve(np.eye(len(rows)) + contact @ spread[rows],
                                contact @ base[rows])
        return base - spread @ shift


def _contact_normal_stiffness(model: TissueModel, positions_m, probe: TissueProbe, p_WP_m):
    """(coordinates (3 k,) into 3 n, C (3 k, 3 k) N/m): -d(probe force)/dx along the
    normals on the k nodes of the triangles with points inside the sphere, the sum
    over those points of k_p a g'(depth) (b b^T) x (n n^T), g' = depth / onset on the
    ramp, 1 past it (the normals' own turning left out)."""
    quadrature = contact_quadrature()
    corners = np.asarray(positions_m, float)[model.triangles]  # (t, 3, 3)
    offset = np.einsum("qa,tak->tqk", quadrature, corners) - np.asarray(p_WP_m, float)
    distance = np.linalg.norm(offset, axis=2)
    triangle, point = np.nonzero((distance < probe.radius_m) & (distance > 0.0))
    depth = probe.radius_m - distance[triangle, point]
    slope = (probe.stiffness_n_per_m3 * model.triangle_rows[triangle, 0] / len(quadrature)
             * np.minimum(depth / probe.onset_depth_m, 1.0))
    normal = offset[triangle, point] / distance[triangle, point, None]
    nodes, local = np.unique(model.triangles[triangle], return_inverse=True)
    local = local.reshape(-1, 3)
    weights = quadrature[point]  # (p, 3)
    # Entry (3 local_a + i, 3 local_b + j) of each point: slope b_a b_b n_i n_j.
    values = (slope[:, None, None, None, None] * weights[:, :, None, None, None]
              * weights[:, None, :, None, None] * normal[:, None, None, :, None]
              * normal[:, None, None, None, :])
    rows = 3 * local[:, :, None, None, None] + np.arange(3)[:, None]
    cols = 3 * local[:, None, :, None, None] + np.arange(3)[None, :]
    rows, cols = np.broadcast_arrays(rows, cols, values)[:2]
    contact = np.zeros((3 * len(nodes), 3 * len(nodes)))
    np.add.at(contact, (rows.ravel(), cols.ravel()), values.ravel())
    return (3 * nodes[:, None] + np.arange(3)).ravel(), contact


def static_equilibrium(model: TissueModel, positions_m, probe: TissueProbe, p_WP_m,
                       tangent: _Tangent = None, held_coordinates=()):
    """(positions (n, 3) m, force on the sphere (3,) N, points touching, the Newton
    matrix used): the tissue at rest under gravity with the sphere held at
    ``p_WP_m`` (W, m), by Newton's method from ``positions_m`` (module docstring).
    ``tangent``: the Newton matrix to start with (default: at ``positions_m``); it is
    refactored at the current positions whenever REFRESH_ITERATIONS steps have not
    converged. A RuntimeError if MAX_NEWTON_ITERATIONS do not. ``held_coordinates``:
    indices into the 3 n coordinates (node i's axis a at 3 i + a) held where
    ``positions_m`` has them, besides the fixed nodes' (a symmetry plane's normal ones),
    where no ``tangent`` (which has its own) is given."""
    x = np.array(positions_m, dtype=float)
    tangent = tangent or _Tangent(model, x, held_coordinates)
    free = tangent.free
    weight = (model.mass_kg[:, None] * model.gravity_m_s2).ravel()

    def residual(y):
        contact, on_sphere, touching = probe_force(model, y, probe, p_WP_m)
        total = elastic_forces(model, y).ravel() + weight + contact.ravel()
        return total[free], on_sphere, touching

    r, on_sphere, touching = residual(x)
    for iteration in range(1, MAX_NEWTON_ITERATIONS + 1):
        scale = max(float(np.abs(weight).max()), float(np.linalg.norm(on_sphere)), 1e-12)
        if np.abs(r).max() <= RELATIVE_TOLERANCE * scale:
            return x, on_sphere, touching, tangent
        if iteration % REFRESH_ITERATIONS == 0:
            tangent = _Tangent(model, x, tangent.held)
        step = tangent.solve(r, *_contact_normal_stiffness(model, x, probe, p_WP_m))
        # Backtrack while the step raises the force imbalance (a node entering or
        # leaving the sphere can overshoot).
        for _ in range(8):
            trial = x.copy()
            trial.ravel()[free] += step
            r_trial, on_trial, touching_trial = residual(trial)
            if np.linalg.norm(r_trial) < np.linalg.norm(r):
                break
            step = 0.5 * step
        x, r, on_sphere, touching = trial, r_trial, on_trial, touching_trial
    raise RuntimeError(f"static_equilibrium: the force imbalance is still "
                       f"{np.abs(r).max():.3g} N after {MAX_NEWTON_ITERATIONS} Newton steps")


def press_states(model: TissueModel, probe: TissueProbe, p_xy_m,
                 depths_m: Sequence[float], *,
                 max_step_m: float = MAX_PRESS_STEP_M,
                 held_coordinates=()) -> List[PressedState]:
    """The equilibria of the tissue with the sphere pressed straight down over
    ``p_xy_m`` (x, y in W, m) to each of ``depths_m`` (m below the undeformed
    surface there), in the order given. The tissue starts at rest under gravity
    from its reference nodes (``model.rest_positions_m``), the sphere above it, and follows the sphere down through the sorted depths.
    ``held_coordinates`` as ``static_equilibrium``'s (a symmetry plane's normal
    coordinates: a quarter of a body pressed where its two planes meet)."""
    probe.validate("probe")
    positive("max_step_m", max_step_m)
    depths = np.asarray(depths_m, dtype=float).ravel()
    require(depths.size > 0 and bool(np.isfinite(depths).all()), "depths_m",
            np.asarray(depths_m).tolist(), "must be finite depths (m), at least one")
    rest = model.rest_positions_m
    top_z = surface_top_m(rest, model.tetrahedra, p_xy_m)

    def centre(depth):
        return np.array([p_xy_m[0], p_xy_m[1], top_z + probe.radius_m - depth])

    lowest_rest = min(0.0, float(depths.min()))
    x, _, _, tangent = static_equilibrium(model, rest, probe,
                                          centre(lowest_rest - probe.radius_m),
                                          held_coordinates=held_coordinates)
    states = {}
    reached = lowest_rest - probe.radius_m
    for depth in np.unique(depths):
        # From the depth reached to this one in equal steps no longer than max_step_m.
        count = max(1, int(np.ceil((depth - reached) / max_step_m)))
        for stop in np.linspace(reached, depth, count + 1)[1:]:
            x, on_sphere, touching, tangent = static_equilibrium(model, x, probe,
                                                                 centre(stop), tangent)
        reached = depth
        states[depth] = PressedState(float(depth), centre(depth), x.copy(),
                                     float(on_sphere[2]), int(touching))
    return [states[depth] for depth in depths]


def press_curve(model: TissueModel, probe: TissueProbe, p_xy_m,
                depths_m: Sequence[float], **options) -> np.ndarray:
    """The push up on the sphere (N) at each of ``depths_m`` (``press_states``)."""
    return np.array([state.force_n for state in press_states(
        model, probe, p_xy_m, depths_m, **options)])


def contact_stiffness(model: TissueModel, probe: TissueProbe, p_xy_m,
                      depth_m: float, *, step_m: float = STIFFNESS_STEP_M,
                      **options) -> float:
    """The felt stiffness dF/dd (N/m) at ``depth_m`` (m below the undeformed surface
    over ``p_xy_m``): the central difference of ``press_curve`` over depth_m +- step_m,
    the contact linearized at the pressed state."""
    positive("step_m", step_m)
    below, above = press_curve(model, probe, p_xy_m,
                               [depth_m - step_m, depth_m + step_m], **options)
    return float((above - below) / (2.0 * step_m))


def hertz_force(depths_m, radius_m: float, youngs_modulus_pa: float,
                poissons_ratio: float) -> np.ndarray:
    """Hertz's force (N) of a rigid sphere of ``radius_m`` (m) pressed ``depths_m``
    (m) into an elastic half-space: 4/3 E* sqrt(R) d^(3/2), E* = E / (1 - nu^2)."""
    reduced = youngs_modulus_pa / (1.0 - poissons_ratio ** 2)
    depths = np.clip(np.asarray(depths_m, dtype=float), 0.0, None)
    return 4.0 / 3.0 * reduced * np.sqrt(radius_m) * depths ** 1.5


def scene_probe(scene, path: str = "haptics.scene") -> TissueProbe:
    """The probe law a ``ModelScene``'s tissue meets: its ``tissue.probe`` with the
    radius of the sphere ``tissue.sphere`` places on the tool (m)."""
    _, radius_m = scene.tissue.sphere(scene.tool, f"{path}.tissue")
    return dataclasses.replace(scene.tissue.probe, radius_m=radius_m)
