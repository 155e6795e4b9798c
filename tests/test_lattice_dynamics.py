"""Physics of the lattice kernels: statics against an assembled stiffness solve,
settling, energy, stability limits of the integrators, probe contact balance."""

import numpy as np
import pytest
import scipy.sparse
import scipy.sparse.linalg

from maglev_haptics.systems.lattice_construction import build_lattice
from maglev_haptics.systems.lattice_dynamics import (
    LINK_BLOCK, ProbeContact, add_probe_forces, implicit_workspace, lattice_energy,
    lattice_model, linearly_implicit_tick, max_stable_link_stiffness, probe_point,
    symplectic_euler_tick)

TICK_S = 1e-3
FAR = np.array([0.0, 0.0, 10.0])  # a probe centre far from the lattice (m)
NODE_MASS_KG = 1e-3


def small_lattice(nx=7, ny=7, bumpy=False):
    x = np.linspace(-0.0075, 0.0075, nx)
    y = np.linspace(-0.0075, 0.0075, ny)
    heights = np.zeros((nx, ny))
    if bumpy:
        heights += 0.002 * np.sin(x[:, None] / 0.004) * np.cos(y[None, :] / 0.005)
    return build_lattice(heights, x, y, base_z_m=-0.012, level_spacing_m=0.003)


class Run:
    """A lattice with its kernel arrays and state, stepped by one integrator."""

    def __init__(self, lattice, *, k, b, integrator="symplectic_euler", substeps=1,
                 gravity=(0.0, 0.0, 0.0)):
        self.lattice = lattice
        self.model = lattice_model(lattice.links, lattice.rest_lengths_m, lattice.fixed,
                                   lattice.surface, node_mass_kg=NODE_MASS_KG,
                                   link_stiffness_n_per_m=k, link_damping_n_s_per_m=b,
                                   gravity_m_s2=gravity)
        self.x = lattice.positions_m.copy()
        self.v = np.zeros_like(self.x)
        self.external = np.zeros_like(self.x)
        self.integrator = integrator
        self.substeps = substeps
        n = lattice.num_masses
        self.forces = np.zeros((n, 3))
        self.workspace = implicit_workspace(n, lattice.num_links)
        self.iterations = []

    def step(self, probe_centre=FAR, probe_velocity=np.zeros(3), probe=ProbeContact()):
        m = self.model
        common = (self.x, self.v, *m.topology, m.rest_lengths_m, m.stiffness_n_per_m,
                  m.damping_n_s_per_m, m.mass_kg, m.inv_mass_per_kg, m.gravity_m_s2,
                  m.surface, self.external, np.asarray(probe_centre, float),
                  np.asarray(probe_velocity, float), np.zeros(3), probe.radius_m,
                  probe.stiffness_n_per_m, probe.onset_depth_m, probe.dissipation_s_per_m, probe.friction,
                  probe.slip_speed_m_s, TICK_S)
        if self.integrator == "symplectic_euler":
            return symplectic_euler_tick(*common, self.substeps, self.forces)
        wrench, touching, iterations = linearly_implicit_tick(*common, 1e-8, 200,
                                                              *self.workspace)
        self.iterations.append(iterations)
        return wrench, touching

    def energy(self):
        m = self.model
        return lattice_energy(self.x, self.v, m.links, m.rest_lengths_m, m.stiffness_n_per_m,
                              m.mass_kg, m.inv_mass_per_kg, m.gravity_m_s2)


def assembled_free_stiffness(lattice, k):
    """K (N/m) on the free masses' coordinates, assembled link by link here, apart
    from the code under test."""
    free = np.flatnonzero(~lattice.fixed)
    row_of = {int(i): r for r, i in enumerate(free)}
    K = scipy.sparse.lil_matrix((3 * len(free), 3 * len(free)))
    for (i, j), length in zip(lattice.links, lattice.rest_lengths_m):
        u = (lattice.positions_m[j] - lattice.positions_m[i]) / length
        block = k * np.outer(u, u)
        for a, b_, sign in ((i, i, 1), (j, j, 1), (i, j, -1), (j, i, -1)):
            if a in row_of and b_ in row_of:
                ra, rb = 3 * row_of[a], 3 * row_of[b_]
                K[ra:ra + 3, rb:rb + 3] += sign * block
    return K.tocsc(), row_of


def centre_surface_vertex(lattice):
    nx, ny = lattice.surface.shape
    return int(lattice.surface[nx // 2, ny // 2])


@pytest.mark.parametrize("integrator", ["symplectic_euler", "linearly_implicit"])
@pytest.mark.parametrize("force_n", [[0.0, 0.0, -0.05], [0.025, -0.0125, -0.04]])
def test_static_push_matches_assembled_stiffness(integrator, force_n):
    lattice = small_lattice(bumpy=True)
    run = Run(lattice, k=40.0, b=0.05, integrator=integrator)
    node = centre_surface_vertex(lattice)
    run.external[node] = force_n
    for _ in range(4000):
        run.step()
    assert np.abs(run.v).max() < 1e-7  # settled
    K, row_of = assembled_free_stiffness(lattice, 40.0)
    load = np.zeros(K.shape[0])
    load[3 * row_of[node]:3 * row_of[node] + 3] = force_n
    expected = scipy.sparse.linalg.spsolve(K, load)[3 * row_of[node]:3 * row_of[node] + 3]
    moved = run.x[node] - lattice.positions_m[node]
    assert np.linalg.norm(moved - expected) < 0.05 * np.linalg.norm(expected)
    assert np.linalg.norm(expected) > 1e-4  # a real deflection (m), not round-off


@pytest.mark.parametrize("integrator", ["symplectic_euler", "linearly_implicit"])
def test_settles_under_gravity_without_drift(integrator):
    lattice = small_lattice(bumpy=True)
    run = Run(lattice, k=40.0, b=0.05, integrator=integrator, gravity=(0.0, 0.0, -9.81))
    for _ in range(3000):
        run.step()
    settled = run.x.copy()
    sag = lattice.positions_m[:, 2] - settled[:, 2]
    assert sag.max() > 1e-4  # it does sag under its weight (m)
    for _ in range(1000):
        run.step()
    assert np.abs(run.x - settled).max() < 1e-9  # no drift over 1 s (m)
    assert np.abs(run.v).max() < 1e-8
    assert np.all(run.x[lattice.fixed] == lattice.positions_m[lattice.fixed])


@pytest.mark.parametrize("integrator", ["symplectic_euler", "linearly_implicit"])
def test_energy_decays_with_damping_and_never_grows(integrator):
    lattice = small_lattice(bumpy=True)
    run = Run(lattice, k=40.0, b=0.05, integrator=integrator)
    rng = np.random.default_rng(3)
    run.v[~lattice.fixed] = 0.05 * rng.standard_normal((lattice.num_free, 3))
    energies = [run.energy()]
    for _ in range(2000):
        run.step()
        energies.append(run.energy())
    energies = np.array(energies)
    assert energies[-1] < 0.05 * energies[0]
    # Symplectic Euler's energy oscillates a little about its decay; it never rises
    # above where it started, nor by more than 1 % of it from one tick to the next.
    assert energies.max() <= energies[0] * (1 + 1e-9)
    assert np.diff(energies).max() < 0.01 * energies[0]
    if integrator == "linearly_implicit":
        assert np.diff(energies).max() <= 1e-12 * energies[0]  # backward Euler: monotone


def test_undamped_symplectic_euler_keeps_its_energy():
    lattice = small_lattice()
    run = Run(lattice, k=40.0, b=0.0)
    run.v[~lattice.fixed] = 0.02 * np.random.default_rng(4).standard_normal((lattice.num_free, 3))
    energies = [run.energy()]
    for _ in range(3000):
        run.step()
        energies.append(run.energy())
    # Its measured energy swings with the modes (h w up to 0.8 here) but does not drift.
    first, last = np.mean(energies[:1000]), np.mean(energies[-1000:])
    assert abs(last - first) < 0.02 * first
    assert max(energies) < 2.0 * energies[0]


def energy_growth(lattice, k, integrator, substeps=1):
    """Energy after 1 s over the energy of a small start perturbation."""
    run = Run(lattice, k=k, b=0.01, integrator=integrator, substeps=substeps)
    run.v[~lattice.fixed] = 1e-3 * np.random.default_rng(5).standard_normal((lattice.num_free, 3))
    start = run.energy()
    for _ in range(1000):
        run.step()
    return run.energy() / start


@pytest.mark.parametrize("substeps", [1, 3])
def test_symplectic_euler_stability_limit(substeps):
    lattice = small_lattice()
    k_max = max_stable_link_stiffness(lattice.positions_m, lattice.links, lattice.fixed,
                                      node_mass_kg=NODE_MASS_KG, link_damping_n_s_per_m=0.01,
                                      time_step_s=TICK_S, substeps=substeps)
    assert energy_growth(lattice, 0.9 * k_max, "symplectic_euler", substeps) < 2.0
    growth = energy_growth(lattice, 1.1 * k_max, "symplectic_euler", substeps)
    assert not np.isfinite(growth) or growth > 1e6


def test_linearly_implicit_is_stable_far_beyond_the_explicit_limit():
    lattice = small_lattice()
    k_max = max_stable_link_stiffness(lattice.positions_m, lattice.links, lattice.fixed,
                                      node_mass_kg=NODE_MASS_KG, link_damping_n_s_per_m=0.01,
                                      time_step_s=TICK_S)
    assert energy_growth(lattice, 100 * k_max, "linearly_implicit") < 1.0


def test_substeps_raise_the_limit_by_their_square():
    lattice = small_lattice()

    def limit(substeps):
        return max_stable_link_stiffness(lattice.positions_m, lattice.links, lattice.fixed,
                                         node_mass_kg=NODE_MASS_KG, link_damping_n_s_per_m=0.0,
                                         time_step_s=TICK_S, substeps=substeps)

    assert limit(2) == pytest.approx(4 * limit(1), rel=1e-9)


def test_probe_forces_balance_the_wrench_on_the_tool():
    lattice = small_lattice(bumpy=True)
    model = lattice_model(lattice.links, lattice.rest_lengths_m, lattice.fixed, lattice.surface,
                          node_mass_kg=NODE_MASS_KG, link_stiffness_n_per_m=40.0,
                          link_damping_n_s_per_m=0.1)
    x = lattice.positions_m.copy()
    v = 0.01 * np.random.default_rng(6).standard_normal(x.shape)
    node = centre_surface_vertex(lattice)
    p_WP = x[node] + [0.0004, -0.0003, 0.0015]
    p_WT = p_WP + [0.002, 0.001, 0.030]
    probe = ProbeContact(radius_m=0.004, friction=0.3)
    forces = np.zeros_like(x)
    wrench, touching = add_probe_forces(x, v, model.surface, p_WP, np.array([0.02, 0.0, -0.01]),
                                        p_WT, probe.radius_m, probe.stiffness_n_per_m,
                                        probe.onset_depth_m, probe.dissipation_s_per_m, probe.friction,
                                        probe.slip_speed_m_s, model.mass_kg, TICK_S, forces)
    assert touching >= 3
    touched = np.flatnonzero(np.abs(forces).sum(axis=1))
    assert len(touched) == touching
    np.testing.assert_allclose(wrench[0:3], -forces.sum(axis=0), atol=1e-15)
    torque = -np.cross(x[touched] - p_WT, forces[touched]).sum(axis=0)
    np.testing.assert_allclose(wrench[3:6], torque, atol=1e-15)
    assert wrench[2] > 0.0  # the surface pushes the probe up
    # Friction opposes the probe's slip along +x: on the surface along +x, on the tool -x.
    assert forces[touched, 0].sum() > 0.0 > wrench[0]


def test_contact_in_a_tick_matches_the_momentum_given_to_the_masses():
    lattice = small_lattice()
    run = Run(lattice, k=40.0, b=0.1)
    node = centre_surface_vertex(lattice)
    probe_centre = lattice.positions_m[node] + [0.0, 0.0, 0.0015]
    wrench, touching = run.step(probe_centre)
    assert touching >= 1
    # Links at rest and no gravity: the masses' momentum after one tick is the contact's impulse.
    impulse = NODE_MASS_KG * run.v.sum(axis=0)
    np.testing.assert_allclose(impulse, -wrench[0:3] * TICK_S, rtol=1e-9, atol=1e-15)


def test_probe_point_follows_the_tool_pose():
    angle = 0.3
    X_WT = np.array([np.cos(angle / 2), 0.0, 0.0, np.sin(angle / 2), 0.01, 0.02, 0.03])
    V_WT = np.array([0.0, 0.0, 2.0, 0.1, 0.0, 0.0])  # spinning about z at 2 rad/s
    p_WP, v_WP = probe_point(X_WT, V_WT, np.array([0.01, 0.0, -0.02]))
    np.testing.assert_allclose(p_WP, [0.01 + 0.01 * np.cos(angle), 0.02 + 0.01 * np.sin(angle),
                                      0.01])
    r = p_WP - X_WT[4:7]
    np.testing.assert_allclose(v_WP, V_WT[3:6] + np.cross(V_WT[0:3], r))


@pytest.mark.parametrize("integrator", ["symplectic_euler", "linearly_implicit"])
def test_a_still_probe_pressed_in_settles_without_chatter(integrator):
    lattice = small_lattice(bumpy=True)
    run = Run(lattice, k=40.0, b=0.05, integrator=integrator)
    node = centre_surface_vertex(lattice)
    probe = ProbeContact(friction=0.3)  # friction strong enough to chatter if stepped naively
    centre = lattice.positions_m[node] + [0.0005, 0.0, probe.radius_m - 0.0015]
    forces = np.array([run.step(centre, probe=probe)[0] for _ in range(1500)])
    last = forces[-200:, 2]
    assert last.mean() > 0.01  # pressed (N)
    assert np.ptp(last) < 1e-4 * last.mean()  # and still: no tick-to-tick alternation


def numpy_link_forces(x, v, links, rest, k, b):
    """Every link's spring-damper force on each mass (N), written plainly in numpy
    (the module docstring's formula), apart from the blocked kernel under test."""
    d = x[links[:, 1]] - x[links[:, 0]]
    length = np.linalg.norm(d, axis=1)
    u = d / length[:, None]
    closing = np.einsum("ij,ij->i", u, v[links[:, 1]] - v[links[:, 0]])
    force = (k * (length - rest) + b * closing)[:, None] * u
    f = np.zeros_like(x)
    np.add.at(f, links[:, 0], force)
    np.add.at(f, links[:, 1], -force)
    return f


@pytest.mark.parametrize("substeps", [1, 3])
def test_a_tick_matches_a_plain_numpy_step_to_1e_12(substeps):
    # The shipped scene's kind of lattice (bumpy, so columns differ), scrambled link order
    # and direction: lattice_model sorts them for the blocked kernel.
    lattice = small_lattice(nx=9, ny=8, bumpy=True)
    rng = np.random.default_rng(40)
    order = rng.permutation(lattice.num_links)
    links = lattice.links[order]
    flip = rng.random(len(links)) < 0.5
    links[flip] = links[flip][:, ::-1]
    run = Run(lattice, k=40.0, b=0.05, substeps=substeps, gravity=(0.0, 0.0, -9.81))
    run.model = lattice_model(links, lattice.rest_lengths_m[order], lattice.fixed,
                              lattice.surface, node_mass_kg=NODE_MASS_KG,
                              link_stiffness_n_per_m=40.0, link_damping_n_s_per_m=0.05,
                              gravity_m_s2=(0.0, 0.0, -9.81))
    free = ~lattice.fixed[:, None]
    run.x += np.where(free, 5e-5 * rng.standard_normal(run.x.shape), 0.0)
    run.v += np.where(free, 5e-3 * rng.standard_normal(run.v.shape), 0.0)
    x, v = run.x.copy(), run.v.copy()
    v_start = v.copy()
    m = run.model
    node = centre_surface_vertex(lattice)
    probe = ProbeContact()
    p_WP = x[node] + [0.0003, -0.0002, probe.radius_m - 0.0012]
    p_WT = p_WP + [0.0, 0.0, 0.03]
    v_WP = np.array([0.01, 0.0, -0.02])
    common = (*m.topology, m.rest_lengths_m, m.stiffness_n_per_m, m.damping_n_s_per_m,
              m.mass_kg, m.inv_mass_per_kg, m.gravity_m_s2, m.surface, run.external, p_WP,
              v_WP, p_WT, probe.radius_m, probe.stiffness_n_per_m, probe.onset_depth_m,
              probe.dissipation_s_per_m, probe.friction, probe.slip_speed_m_s, TICK_S)
    wrench, touching = symplectic_euler_tick(run.x, run.v, *common, substeps, run.forces)
    assert touching > 0
    h_s = TICK_S / substeps
    expected_wrench = None
    for _ in range(substeps):
        f = numpy_link_forces(x, v, m.links, m.rest_lengths_m, m.stiffness_n_per_m,
                              m.damping_n_s_per_m)
        w, _ = add_probe_forces(x, v, m.surface, p_WP, v_WP, p_WT, probe.radius_m,
                                probe.stiffness_n_per_m, probe.onset_depth_m,
                                probe.dissipation_s_per_m, probe.friction,
                                probe.slip_speed_m_s, m.mass_kg, h_s, f)
        expected_wrench = w if expected_wrench is None else expected_wrench
        total = m.mass_kg[:, None] * m.gravity_m_s2 + run.external + f
        v = np.where(free, v + h_s * m.inv_mass_per_kg[:, None] * total, v)
        x = np.where(free, x + h_s * v, x)
    assert np.abs(run.x - x).max() <= 1e-12 * np.abs(x).max()
    assert np.abs(run.v - v).max() <= 1e-12 * np.abs(v).max()
    # The change a tick makes, not only the state, to 1e-12 of its size.
    assert np.abs(run.v - v).max() <= 1e-12 * np.abs(v - v_start).max()
    np.testing.assert_allclose(wrench, expected_wrench, rtol=1e-12, atol=0.0)


def test_lattice_model_orders_links_by_their_first_mass_in_blocks():
    lattice = small_lattice(nx=9, ny=8, bumpy=True)
    links = lattice.links[::-1, ::-1]  # reversed and each written second-first
    m = lattice_model(links, lattice.rest_lengths_m[::-1], lattice.fixed, lattice.surface,
                      node_mass_kg=NODE_MASS_KG, link_stiffness_n_per_m=40.0,
                      link_damping_n_s_per_m=0.05)
    assert np.all(m.links[:, 0] < m.links[:, 1]) and np.all(np.diff(m.links[:, 0]) >= 0)
    np.testing.assert_array_equal(m.link_ends, m.links[:, 1])
    for i in range(lattice.num_masses):
        assert np.all(m.links[m.link_offsets[i]:m.link_offsets[i + 1], 0] == i)
    per_block = np.diff(m.link_offsets[m.link_blocks])
    assert per_block.max() <= LINK_BLOCK and m.link_blocks[-1] == lattice.num_masses
    # Each link kept its own rest length.
    rest = {tuple(sorted(map(int, link))): r
            for link, r in zip(links, lattice.rest_lengths_m[::-1])}
    assert all(rest[tuple(map(int, link))] == r for link, r in zip(m.links, m.rest_lengths_m))
