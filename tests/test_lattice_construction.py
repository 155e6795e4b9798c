"""Heightmaps and the landscape lattice's construction, against the paper's rules
re-derived here with plain loops and a brute-force pass over all mass pairs."""

import itertools
import math

import numpy as np
import pytest

from maglev_haptics.systems.heightmap import (RandomHeightmap, SineHeightmap,
                                              heightmap_heights)
from maglev_haptics.systems.lattice_construction import build_lattice

BASE_Z_M = -0.030
LEVEL_SPACING_M = 0.003


# --- an independent reading of the rules -------------------------------------------------

def reference_masses(h, base, dz):
    """[(ix, iy, j, z, is_surface)] in the lattice's numbering, from the rules."""
    masses = []
    nx, ny = h.shape
    for ix in range(nx):
        for iy in range(ny):
            below = 0
            while base + below * dz < h[ix, iy] - 1e-9 * dz:  # levels strictly below h
                below += 1
            for j in range(below):
                masses.append((ix, iy, j, base + j * (h[ix, iy] - base) / below, False))
            masses.append((ix, iy, below, h[ix, iy], True))
    return masses


def reference_links(h, masses):
    """{(p, q), p < q} deciding every pair of masses from the three phases' rules."""
    links = set()
    for p, q in itertools.combinations(range(len(masses)), 2):
        ixp, iyp, jp, zp, surface_p = masses[p]
        ixq, iyq, jq, zq, surface_q = masses[q]
        if abs(ixp - ixq) > 1 or abs(iyp - iyq) > 1:
            continue
        same_column = (ixp, iyp) == (ixq, iyq)
        neighbours = abs(jp - jq) <= 1
        surfaces = surface_p and surface_q and not same_column
        hp, hq = h[ixp, iyp], h[ixq, iyq]
        side_p = not same_column and surface_q and hp > hq and not surface_p and zp > hq
        side_q = not same_column and surface_p and hq > hp and not surface_q and zq > hp
        if neighbours or surfaces or side_p or side_q:
            links.add((p, q))
    return links


def flat_map(nx, ny, height):
    return np.full((nx, ny), height)


def step_map(nx, ny):
    """A 12 mm step between ix < nx // 2 and the rest; the low side lies exactly on level 5."""
    h = np.full((nx, ny), -0.015)
    h[nx // 2:, :] = -0.003
    return h


def random_map(nx, ny, seed):
    x, y = grid(nx, ny)
    return -0.015 + heightmap_heights(
        RandomHeightmap(seed=seed, amplitude_m=0.005, correlation_length_m=0.004), x, y)


def grid(nx, ny, spacing=0.004):
    return (np.arange(nx) - (nx - 1) / 2) * spacing, (np.arange(ny) - (ny - 1) / 2) * spacing


CASES = {
    "flat": flat_map(4, 3, -0.018),
    "step": step_map(5, 4),
    "random": random_map(6, 5, seed=3),
}


@pytest.fixture(params=sorted(CASES))
def case(request):
    h = CASES[request.param]
    x, y = grid(*h.shape)
    return h, build_lattice(h, x, y, BASE_Z_M, LEVEL_SPACING_M)


# --- counts and positions -------------------------------------------------------------

def test_masses_and_links_match_the_rules(case):
    h, lattice = case
    masses = reference_masses(h, BASE_Z_M, LEVEL_SPACING_M)
    links = reference_links(h, masses)
    assert lattice.num_masses == len(masses)
    assert lattice.num_links == len(links)
    assert set(map(tuple, lattice.links.tolist())) == links
    np.testing.assert_allclose(lattice.positions_m[:, 2], [m[3] for m in masses],
                               rtol=0, atol=1e-15)
    assert [int(i) for i in lattice.surface.ravel()] == [k for k, m in enumerate(masses) if m[4]]


def test_the_random_case_needs_every_phase():
    """The random map has surface links beyond the 26-neighbourhood (phase 2) and
    Fig. 8 links (phase 3), so the reference comparison exercises them."""
    h = CASES["random"]
    masses = reference_masses(h, BASE_Z_M, LEVEL_SPACING_M)
    beyond_26 = [(p, q) for p, q in reference_links(h, masses)
                 if abs(masses[p][2] - masses[q][2]) > 1]
    phase2 = [(p, q) for p, q in beyond_26 if masses[p][4] and masses[q][4]]
    assert len(phase2) > 0 and len(beyond_26) > len(phase2)


def test_flat_map_counts_closed_form():
    """A flat map is a full nx x ny x K grid: links = the 26-neighbour pairs of that grid."""
    nx, ny = 4, 3
    h = flat_map(nx, ny, -0.018)  # 4 levels below (-0.030 ... -0.021), so K = 5
    lattice = build_lattice(h, *grid(nx, ny), BASE_Z_M, LEVEL_SPACING_M)
    dims = (nx, ny, 5)
    pairs = sum(math.prod(d - abs(o) for d, o in zip(dims, offset))
                for offset in itertools.product((-1, 0, 1), repeat=3) if any(offset)) // 2
    assert lattice.num_masses == nx * ny * 5 == 60
    assert lattice.num_links == pairs == 425  # 48 vertical + 104 along y + 273 along x
    assert np.all(lattice.column_count == 5)


def test_surface_exactly_on_a_level_excludes_it():
    h = np.full((3, 3), BASE_Z_M + 6 * LEVEL_SPACING_M)  # (h - base) / dz = 6.000000000000001
    h[1, 1] = BASE_Z_M + 6.001 * LEVEL_SPACING_M  # just above level 6
    lattice = build_lattice(h, *grid(3, 3), BASE_Z_M, LEVEL_SPACING_M)
    assert lattice.column_count[0, 0] == 7
    assert lattice.column_count[1, 1] == 8


def test_columns_are_respaced_uniformly_from_base_to_surface(case):
    h, lattice = case
    x, y = grid(*h.shape)
    for ix, iy in np.ndindex(h.shape):
        start, count = lattice.column_start[ix, iy], lattice.column_count[ix, iy]
        column = lattice.positions_m[start:start + count]
        np.testing.assert_allclose(column[:, 2], np.linspace(BASE_Z_M, h[ix, iy], count),
                                   rtol=0, atol=1e-15)
        assert column[-1, 2] == h[ix, iy]
        assert np.all(column[:, 0] == x[ix]) and np.all(column[:, 1] == y[iy])
        assert lattice.surface[ix, iy] == start + count - 1
        assert count >= 2
    assert lattice.column_start[0, 0] == 0
    # Contiguous columns, x-major.
    ends = (lattice.column_start + lattice.column_count).ravel()
    np.testing.assert_array_equal(lattice.column_start.ravel()[1:], ends[:-1])
    assert ends[-1] == lattice.num_masses


def test_fixed_masses_are_the_bottom_level_and_the_edge_columns(case):
    h, lattice = case
    nx, ny = h.shape
    expected = []
    for ix, iy in np.ndindex(h.shape):
        edge = ix in (0, nx - 1) or iy in (0, ny - 1)
        expected += [edge or j == 0 for j in range(lattice.column_count[ix, iy])]
    np.testing.assert_array_equal(lattice.fixed, expected)
    assert lattice.num_free == (lattice.column_count[1:-1, 1:-1] - 1).sum() > 0


# --- links ------------------------------------------------------------------------------

def test_links_are_unique_sorted_and_of_nonzero_length(case):
    _, lattice = case
    links = lattice.links
    assert links.dtype == np.int64 and links.shape == (lattice.num_links, 2)
    assert np.all(links[:, 0] < links[:, 1])
    assert len(np.unique(links, axis=0)) == len(links)
    np.testing.assert_array_equal(links, links[np.lexsort((links[:, 1], links[:, 0]))])
    lengths = np.linalg.norm(lattice.positions_m[links[:, 1]] - lattice.positions_m[links[:, 0]],
                             axis=1)
    np.testing.assert_allclose(lattice.rest_lengths_m, lengths, rtol=1e-15)
    assert np.all(lattice.rest_lengths_m > 1e-4)


def test_each_surface_vertex_is_linked_to_its_8_neighbours_surface_vertices(case):
    h, lattice = case
    nx, ny = h.shape
    links = set(map(tuple, lattice.links.tolist()))
    checked = 0
    for ix, iy in np.ndindex(h.shape):
        for a, b in itertools.product((-1, 0, 1), repeat=2):
            if (a, b) != (0, 0) and 0 <= ix + a < nx and 0 <= iy + b < ny:
                p, q = sorted((lattice.surface[ix, iy], lattice.surface[ix + a, iy + b]))
                assert (p, q) in links
                checked += 1
    assert checked == 2 * (4 * (nx - 1) * (ny - 1) + (nx - 1) + (ny - 1))  # each pair twice


def test_fig8_links_around_one_high_column():
    """3 x 3 columns, base 0, levels every 0.25: the edge columns reach 0.5 (masses at
    0, 0.25, surface 0.5), the centre 2.0 (masses at 0, 0.25, ..., 1.75, surface 2.0).
    Numbering: (0,0) 0-2, (0,1) 3-5, (0,2) 6-8, (1,0) 9-11, centre 12-20, (1,2) 21-23,
    (2,0) 24-26, (2,1) 27-29, (2,2) 30-32."""
    h = np.full((3, 3), 0.5)
    h[1, 1] = 2.0
    lattice = build_lattice(h, [-1.0, 0.0, 1.0], [-1.0, 0.0, 1.0], 0.0, 0.25)
    edge_surfaces = [2, 5, 8, 11, 23, 26, 29, 32]
    assert lattice.surface.ravel().tolist() == [2, 5, 8, 11, 20, 23, 26, 29, 32]
    np.testing.assert_array_equal(lattice.positions_m[12:21, 2], 0.25 * np.arange(9))
    links = set(map(tuple, lattice.links.tolist()))
    for s in edge_surfaces:
        # Phase 3: centre masses at 1.0 ... 1.75 (levels 4-7), above the edge surface at
        # 0.5 and more than one level from it; level 3 (0.75) is a phase-1 neighbour.
        for centre in (15, 16, 17, 18, 19):
            assert (min(centre, s), max(centre, s)) in links
        # Phase 2: the centre's surface vertex to each edge surface vertex.
        assert (min(20, s), max(20, s)) in links
        # Not linked: the centre's bottom (level 0) to an edge surface (level 2).
        assert (min(12, s), max(12, s)) not in links
    assert (5, 16) in links and (3, 16) not in links  # an edge column's bottom mass is not
    assert (2, 8) not in links  # columns (0,0) and (0,2) are not adjacent
    # Phase 1: 12 edge-edge column pairs x 7, 8 x 2 + 8 vertical, 8 centre-edge pairs x 8;
    # phase 2 adds 8, phase 3 adds 4 levels x 8.
    assert lattice.num_masses == 33
    assert lattice.num_links == 84 + 24 + 64 + 8 + 32 == 212


# --- surface triangles ------------------------------------------------------------------

def _triangle_normals(lattice):
    a, b, c = (lattice.positions_m[lattice.surface_triangles[:, k]] for k in range(3))
    return np.cross(b - a, c - a)


def test_surface_triangles_of_a_flat_map_tile_the_footprint_facing_up():
    nx, ny = 5, 4
    x, y = grid(nx, ny)
    lattice = build_lattice(flat_map(nx, ny, -0.012), x, y, BASE_Z_M, LEVEL_SPACING_M)
    triangles = lattice.surface_triangles
    assert triangles.shape == (2 * (nx - 1) * (ny - 1), 3) and triangles.dtype == np.int64
    assert set(triangles.ravel().tolist()) == set(lattice.surface.ravel().tolist())
    normals = _triangle_normals(lattice)
    np.testing.assert_allclose(normals[:, :2], 0, atol=1e-18)
    assert np.all(normals[:, 2] > 0)
    footprint = (x[-1] - x[0]) * (y[-1] - y[0])
    np.testing.assert_allclose(0.5 * normals[:, 2].sum(), footprint, rtol=1e-12)


def test_surface_triangles_of_a_rough_map_face_up_and_project_onto_the_footprint(case):
    h, lattice = case
    x, y = grid(*h.shape)
    normals = _triangle_normals(lattice)
    assert np.all(normals[:, 2] > 0)
    np.testing.assert_allclose(0.5 * normals[:, 2].sum(), (x[-1] - x[0]) * (y[-1] - y[0]),
                               rtol=1e-12)
    # Each grid cell's four corners are used by its two triangles.
    cells = lattice.surface_triangles.reshape(h.shape[0] - 1, h.shape[1] - 1, 6)
    s = lattice.surface
    for ix, iy in np.ndindex(cells.shape[:2]):
        assert set(cells[ix, iy].tolist()) == {s[ix, iy], s[ix + 1, iy], s[ix, iy + 1],
                                               s[ix + 1, iy + 1]}


# --- size ---------------------------------------------------------------------------------

def test_a_20k_mass_lattice_builds():
    """~20,000 masses (builds in ~0.1 s here; the budget is 2 s)."""
    x = np.linspace(-0.06, 0.06, 49)
    y = np.linspace(-0.05, 0.05, 41)
    h = -0.0075 + heightmap_heights(RandomHeightmap(seed=1), x, y)
    lattice = build_lattice(h, x, y, BASE_Z_M, 0.0025)
    assert 18_000 < lattice.num_masses < 22_000
    # An interior mass has up to 26 links, so ~13 per mass, a few more from phases 2 and 3.
    assert 11 * lattice.num_masses < lattice.num_links < 14 * lattice.num_masses
    assert lattice.num_free == (lattice.column_count[1:-1, 1:-1] - 1).sum()


# --- validation -----------------------------------------------------------------------

@pytest.mark.parametrize("change, message", [
    (dict(x_m=np.linspace(0, 1, 2)), r"x_m has shape \(2,\)"),
    (dict(y_m=[0.0, 0.1, 0.3]), r"y_m spacing ranges from 0\.1 to 0\.\d+ m: must be uniform"),
    (dict(x_m=[0.0, -0.1, -0.2]), r"x_m\[1\] = -0.1 after x_m\[0\] = 0.0: must be strictly"),
    (dict(y_m=[0.0, np.nan, 0.2]), r"y_m\[1\] = nan: must be finite"),
    (dict(surface_z_m=np.zeros((3, 4))), r"surface_z_m has shape \(3, 4\): must be .* \(3, 3\)"),
    (dict(surface_z_m=[[0, 0, 0], [0, np.inf, 0], [0, 0, 0]]),
     r"surface_z_m\[1, 1\] = inf: must be finite"),
    (dict(surface_z_m=[[0, 0, 0], [0, -1.0, 0], [0, 0, 0]]),
     r"surface_z_m\[1, 1\] = -1.0: must be above base_z_m = -0.5"),
    (dict(level_spacing_m=0.0), r"level_spacing_m = 0.0: must be a finite length > 0"),
    (dict(level_spacing_m=1e-9), r"level_spacing_m = 1e-09: gives .* masses"),
    (dict(base_z_m=math.nan), r"base_z_m = nan: must be a finite height"),
])
def test_build_lattice_rejects_bad_arguments(change, message):
    arguments = dict(surface_z_m=np.zeros((3, 3)), x_m=[0.0, 0.1, 0.2], y_m=[0.0, 0.1, 0.2],
                     base_z_m=-0.5, level_spacing_m=0.1)
    arguments.update(change)
    with pytest.raises(ValueError, match=message):
        build_lattice(**arguments)


# --- heightmaps ---------------------------------------------------------------------------

def test_random_heightmap_is_seeded_zero_mean_and_exactly_its_rms():
    x, y = np.linspace(-0.04, 0.04, 33), np.linspace(-0.03, 0.03, 25)
    first = heightmap_heights(RandomHeightmap(seed=7), x, y)
    assert first.shape == (33, 25)
    np.testing.assert_array_equal(first, heightmap_heights(RandomHeightmap(seed=7), x, y))
    other = heightmap_heights(RandomHeightmap(seed=8), x, y)
    assert np.sqrt(np.mean((first - other) ** 2)) > 0.0005
    assert abs(first.mean()) < 1e-15
    np.testing.assert_allclose(np.sqrt(np.mean(first ** 2)), 0.0008, rtol=1e-12)
    np.testing.assert_array_equal(
        heightmap_heights(RandomHeightmap(amplitude_m=0.0), x, y), np.zeros((33, 25)))


def _autocorrelation(h, lag, axis):
    """Normalized periodic autocorrelation at an integer lag (grid cells)."""
    return np.mean(h * np.roll(h, lag, axis)) / np.mean(h * h)


def test_random_heightmap_autocorrelation_falls_to_1_over_e_at_the_correlation_length():
    """Documented: the autocorrelation is exp(-r^2 / L^2). On a 512 x 384 grid with
    0.5 mm x 0.7 mm spacing and L = 4 mm, averaged over 4 seeds."""
    x, y = np.arange(512) * 0.0005, np.arange(384) * 0.0007
    maps = [heightmap_heights(RandomHeightmap(seed=s, correlation_length_m=0.004), x, y)
            for s in range(4)]
    for lag_cells, axis, lag_m in [(8, 0, 0.004), (4, 0, 0.002), (16, 0, 0.008),
                                   (4, 1, 0.0028), (8, 1, 0.0056)]:
        measured = np.mean([_autocorrelation(h, lag_cells, axis) for h in maps])
        assert abs(measured - math.exp(-(lag_m / 0.004) ** 2)) < 0.03, (lag_cells, axis)


def test_random_heightmap_is_as_rough_at_its_edges_as_inside():
    """The noise is smoothed periodically ("wrap"), so the edge rows have the map's RMS;
    "reflect" would count the noise near an edge twice (edge mean square ~1.8x)."""
    x = np.arange(48) * 0.001
    ratios = []
    for seed in range(40):
        h = heightmap_heights(RandomHeightmap(seed=seed, correlation_length_m=0.008), x, x)
        edges = np.concatenate([h[0], h[-1], h[:, 0], h[:, -1]])
        ratios.append(np.mean(edges ** 2) / np.mean(h ** 2))
    assert 0.8 < np.mean(ratios) < 1.25


def test_random_heightmap_shorter_than_the_grid_is_uncorrelated_noise():
    x = y = np.arange(200) * 0.001
    h = heightmap_heights(RandomHeightmap(correlation_length_m=1e-6), x, y)
    assert np.all(np.isfinite(h))
    np.testing.assert_allclose(np.sqrt(np.mean(h ** 2)), 0.0008, rtol=1e-12)
    assert abs(_autocorrelation(h, 1, 0)) < 0.03 and abs(_autocorrelation(h, 1, 1)) < 0.03


def test_sine_heightmap_at_known_points():
    config = SineHeightmap(amplitude_m=[0.002, 0.001], wavelength_m=[0.04, 0.02],
                           phase_rad=[0.0, math.pi / 2])
    x = np.array([0.0, 0.01, 0.02, 0.03])  # 0, 1/4, 1/2, 3/4 of l_x
    y = np.array([0.0, 0.005, 0.01])  # 0, 1/4, 1/2 of l_y
    expected_x = np.array([0.0, 0.002, 0.0, -0.002])
    expected_y = np.array([0.001, 0.0, -0.001])  # cos, from the pi/2 phase
    np.testing.assert_allclose(heightmap_heights(config, x, y),
                               expected_x[:, None] + expected_y[None, :], atol=1e-15)
    default = heightmap_heights(SineHeightmap(), np.array([0.005]), np.array([0.00375]))
    np.testing.assert_allclose(default, [[0.001 + 0.0005]], rtol=1e-12)


@pytest.mark.parametrize("config, message", [
    (RandomHeightmap(seed=-1), r"terrain\.seed = -1: must be an integer >= 0"),
    (RandomHeightmap(seed=1.5), r"terrain\.seed = 1\.5"),
    (RandomHeightmap(amplitude_m=-0.001), r"terrain\.amplitude_m = -0\.001: must be .* >= 0"),
    (RandomHeightmap(amplitude_m=math.inf), r"terrain\.amplitude_m = inf"),
    (RandomHeightmap(correlation_length_m=0.0), r"terrain\.correlation_length_m = 0\.0: .* > 0"),
    (SineHeightmap(amplitude_m=[0.001]), r"terrain\.amplitude_m = \[0\.001\]: .* list of 2"),
    (SineHeightmap(amplitude_m=[0.001, -0.001]), r"terrain\.amplitude_m = .* >= 0"),
    (SineHeightmap(wavelength_m=[0.02, 0.0]), r"terrain\.wavelength_m = \[0\.02, 0\.0\]: .* > 0"),
    (SineHeightmap(phase_rad=[0.0, math.nan]), r"terrain\.phase_rad = \[0\.0, nan\]: .* finite"),
])
def test_validate_heightmap_names_the_field(config, message):
    with pytest.raises(ValueError, match=message):
        config.validate("terrain")


def test_heightmap_heights_rejects_a_bad_config_or_grid():
    x = np.linspace(0, 0.01, 5)
    with pytest.raises(ValueError, match="heightmap = 'flat': must be a RandomHeightmap, a "
                                         "SineHeightmap or an ImageHeightmap"):
        heightmap_heights("flat", x, x)
    with pytest.raises(ValueError, match=r"RandomHeightmap\.amplitude_m = -1"):
        heightmap_heights(RandomHeightmap(amplitude_m=-1), x, x)
    with pytest.raises(ValueError, match=r"y_m spacing"):
        heightmap_heights(RandomHeightmap(), x, np.array([0.0, 0.001, 0.003]))
    with pytest.raises(ValueError, match=r"x_m has shape \(1,\)"):
        heightmap_heights(RandomHeightmap(), x[:1], x)
    assert heightmap_heights(SineHeightmap(), x[:1], x).shape == (1, 5)
