"""A tissue placed by its add_model's default_free_body_pose: the body as its file
places it, moved rigidly with its wall's nodes (diagrams/tissue_model.py)."""

import meshio
import numpy as np
import pytest
import scipy.sparse.linalg
from pydrake.math import RigidTransform, RollPitchYaw
from pydrake.multibody.parsing import LoadModelDirectivesFromString

from maglev_haptics.diagrams.scene import TissueContact
from maglev_haptics.diagrams.tissue_model import read_scene_tissue
from maglev_haptics.diagrams.tissue_scene import kernel_model
from maglev_haptics.systems.tissue_fem import free_coordinates, linear_stiffness_matrix

ORGAN = "package://maglev_haptics/tissue/organ.sdf"
# The organ's link: 30 mm along y, 90 deg about z and a tilt of 20 deg about x.
POSE = "{translation: [0.0, 0.03, 0.0], rotation: !Rpy {deg: [20.0, 0.0, 90.0]}}"
X_WB = RigidTransform(RollPitchYaw(np.radians([20.0, 0.0, 90.0])), [0.0, 0.03, 0.0])


def read(extra: str = "", name: str = "organ"):
    text = f'directives:\n- add_model: {{name: {name}, file: "{ORGAN}"{extra}}}\n'
    return read_scene_tissue(LoadModelDirectivesFromString(text).directives)


@pytest.fixture(scope="module")
def file_placed():
    return read().bodies[0]


@pytest.fixture(scope="module")
def posed(file_placed):
    return read(f", default_free_body_pose: {{{file_placed.name}: {POSE}}}").bodies[0]


def mesh_points(body) -> np.ndarray:
    """(n, 3) the nodes in the body's own frame B: its .vtk file's points (m)."""
    return np.asarray(meshio.read(body.mesh_file).points, dtype=float)


def test_the_body_and_its_walls_nodes_move_together(file_placed, posed):
    # The file places the organ by a translation alone (its link's <pose>)...
    offset = file_placed.positions_m - mesh_points(file_placed)
    np.testing.assert_allclose(offset, offset[0] + 0 * offset, atol=1e-12)
    assert np.abs(offset[0]).max() > 0.01
    # ... the directive by its own pose, in W, of the link, as Drake places a free body.
    np.testing.assert_allclose(posed.positions_m, X_WB.multiply(mesh_points(posed).T).T,
                               atol=1e-12)
    np.testing.assert_array_equal(posed.fixed, file_placed.fixed)
    np.testing.assert_array_equal(posed.tetrahedra, file_placed.tetrahedra)


def test_its_sag_under_gravity_is_the_sag_of_the_tilted_body(file_placed, posed):
    """Gravity stays W's -z: the posed organ's static sag is the file-placed organ's
    (whose link is not rotated) under the gravity the posed body feels in its own
    axes, turned by the pose: the same elasticity, moved."""
    R_WB = X_WB.rotation().matrix()
    g_W = np.array([0.0, 0.0, -9.81])

    def sag(body, gravity):
        model = kernel_model(body, TissueContact(gravity_m_s2=list(gravity)))
        free = free_coordinates(model)
        K = linear_stiffness_matrix(model)[free][:, free]
        f = (model.mass_kg[:, None] * np.asarray(gravity)).ravel()[free]
        u = np.zeros(3 * model.num_nodes)
        u[free] = scipy.sparse.linalg.spsolve(K.tocsc(), f)
        return u.reshape(-1, 3)

    u_posed = sag(posed, g_W)
    u_file = sag(file_placed, R_WB.T @ g_W)
    np.testing.assert_allclose(u_posed, u_file @ R_WB.T, atol=1e-9 * np.abs(u_posed).max())
    assert np.abs(u_posed).max() > 1e-5  # it sags: the comparison compares something


@pytest.mark.parametrize("extra, field, allowed", [
    (", default_free_body_pose: {kidney: {translation: [0, 0, 0.1]}}",
     "[0].add_model.default_free_body_pose = 'kidney'", "must name a deformable body"),
    (", default_free_body_pose: {organ: {base_frame: table::top, translation: [0, 0, 0]}}",
     "default_free_body_pose.organ.base_frame = 'table::top'", "must be world")
])
def test_a_pose_that_cannot_place_the_tissue_is_refused(extra, field, allowed):
    with pytest.raises(ValueError, match=r"^scene\.directives") as refusal:
        read(extra)
    assert field in str(refusal.value) and allowed in str(refusal.value)
