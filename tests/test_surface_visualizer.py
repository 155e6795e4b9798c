"""A deformable surface's Meshcat drawing: face mapping, force rod, publishing."""

import numpy as np
import pytest
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import ConstantVectorSource

from maglev_haptics.diagrams.application import BuildDiagram
from maglev_haptics.diagrams.scenario import load_scenario
from maglev_haptics.systems.lattice_construction import build_lattice
from maglev_haptics.systems.surface_visualizer import (
    FORCE_PATH, SURFACE_PATH, WIRE_PATH, SurfaceVisualizer, force_rod_transform, surface_faces)

P_TP_M = np.array([0.0, 0.0, -0.030])  # probe centre in T (m)
RADIUS_M = 0.0025  # (m)


@pytest.fixture(scope="module")
def lattice():
    """4 x 3 columns 5 mm apart with uneven heights, so columns hold different counts."""
    x_m, y_m = np.array([0.0, 0.005, 0.010, 0.015]), np.array([0.0, 0.005, 0.010])
    heights = -0.015 + 0.004 * np.array([[0, 1, 0], [2, 0, 1], [1, 2, 0], [0, 0, 2]])
    return build_lattice(heights, x_m, y_m, -0.030, 0.003)


def test_faces_index_the_same_vertices_as_the_mass_triangles(lattice):
    faces = surface_faces(lattice.surface, lattice.surface_triangles)
    assert faces.shape == (3, len(lattice.surface_triangles))
    assert faces.dtype == np.int32 and faces.flags["F_CONTIGUOUS"]
    surface = lattice.surface.ravel()
    np.testing.assert_array_equal(surface[faces.T], lattice.surface_triangles)
    # Counter-clockwise seen from +z, as the mass triangles are.
    p = lattice.positions_m[surface]
    a, b, c = (p[faces[k]] for k in range(3))
    assert np.all(np.cross(b - a, c - a)[:, 2] > 0)


def test_faces_refuse_a_mass_below_the_surface(lattice):
    below = lattice.surface_triangles.copy()
    below[0, 0] = lattice.column_start[0, 0]  # a bottom mass
    with pytest.raises(ValueError, match="not a surface vertex"):
        surface_faces(lattice.surface, below)


def test_force_rod_runs_along_the_force_from_the_contact_side():
    p_WP, f_W = np.array([0.01, -0.02, -0.014]), np.array([0.1, -0.05, 0.3])  # m, N
    X = force_rod_transform(p_WP, RADIUS_M, f_W, scale_m_per_n=0.1)
    u = f_W / np.linalg.norm(f_W)
    # The unit cylinder's end caps, centred at z = +/-0.5.
    top, bottom = X @ [0, 0, 0.5, 1], X @ [0, 0, -0.5, 1]
    contact = p_WP - RADIUS_M * u
    np.testing.assert_allclose(bottom[0:3], contact, atol=1e-15)
    np.testing.assert_allclose(top[0:3], contact + 0.1 * np.linalg.norm(f_W) * u, atol=1e-15)
    # Not stretched across the rod: the radial axes keep unit length.
    np.testing.assert_allclose(np.linalg.norm(X[0:3, 0:2], axis=0), 1.0)


def test_force_rod_hidden_when_the_force_is_tiny():
    X = force_rod_transform(np.zeros(3), RADIUS_M, [0.0, 0.0, 1e-4], shown_n=0.005)
    np.testing.assert_array_equal(X, np.diag([0.0, 0.0, 0.0, 1.0]))


def build(meshcat, lattice, X_WT, wrench):
    builder = DiagramBuilder()
    visualizer = builder.AddSystem(SurfaceVisualizer(
        meshcat=meshcat, faces=surface_faces(lattice.surface, lattice.surface_triangles),
        num_vertices=lattice.surface.size, p_TP_m=P_TP_M, probe_radius_m=RADIUS_M))
    surface = lattice.positions_m[lattice.surface.ravel()]
    for name, value in (("surface_positions_m", surface.ravel()), ("X_WT", X_WT),
                        ("wrench_on_tool_W", wrench)):
        source = builder.AddSystem(ConstantVectorSource(value))
        builder.Connect(source.get_output_port(), visualizer.GetInputPort(name))
    return builder.Build()


def test_forced_publish_draws_the_surface(meshcat, lattice):
    meshcat.Delete("/deformable_surface")
    diagram = build(meshcat, lattice, [1.0, 0, 0, 0, 0.005, 0.005, 0.02],
                    [0.0, 0.0, 0.3, 0.0, 0.0, 0.0])
    assert not meshcat.HasPath(SURFACE_PATH)
    diagram.ForcedPublish(diagram.CreateDefaultContext())
    for path in (SURFACE_PATH, WIRE_PATH, FORCE_PATH):
        assert meshcat.HasPath(path)


def test_simulation_draws_the_surface_at_initialization(meshcat, lattice):
    meshcat.Delete("/deformable_surface")
    diagram = build(meshcat, lattice, [1.0, 0, 0, 0, 0.005, 0.005, 0.03], np.zeros(6))
    Simulator(diagram).Initialize()
    assert meshcat.HasPath(SURFACE_PATH)


def test_deformable_scene_draws_the_lattice_not_plant_contacts(meshcat):
    scenario = load_scenario("deformable_surface", "deformable_surface")
    built = BuildDiagram(scenario, meshcat=meshcat)
    names = [system.get_name() for system in built.diagram.GetSystems()]
    assert "lattice_visualizer" in names
    assert not any("ContactVisualizer" in type(system).__name__
                   for system in built.diagram.GetSystems())
