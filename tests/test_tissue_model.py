"""Deformable bodies read from model files by Drake (diagrams/tissue_model.py) and
the shipped tissue meshes (plant_models/tissue_meshes.py)."""

import itertools
from pathlib import Path

import meshio
import numpy as np
import pytest
from pydrake.multibody.parsing import LoadModelDirectivesFromString

from maglev_haptics.diagrams.scene_models import holds_tissue
from maglev_haptics.diagrams.scene import TissueContact
from maglev_haptics.diagrams.tissue_model import read_scene_tissue
from maglev_haptics.systems.tissue_fem import stable_substeps, tissue_model
from maglev_haptics.plant_models import tissue_meshes as tm

TABLE_SDF = Path(tm.__file__).parents[1] / "scenarios" / "models" / "table.sdf"
TABLE = f"""
- add_model: {{name: table, file: "file://{TABLE_SDF}"}}
- add_weld: {{parent: world, child: table::top, X_PC: {{translation: [0.0, 0.0, -0.05]}}}}
"""


def directives(text: str):
    return LoadModelDirectivesFromString("directives:\n" + text).directives


def add_model(name: str, url: str, extra: str = "") -> str:
    return f'- add_model: {{name: {name}, file: "{url}"{extra}}}\n'


@pytest.fixture(scope="module")
def shipped():
    """The shipped slab and organ, beside a rigid table, as read."""
    text = (TABLE + add_model("slab", "package://maglev_haptics/tissue/palpation_slab.sdf")
            + add_model("organ", "package://maglev_haptics/tissue/organ.sdf"))
    return read_scene_tissue(directives(text))


def test_shipped_slab_fixed_bottom_and_lump(shipped):
    slab = shipped.bodies[0]
    nx, ny, nz = tm.SLAB_CELLS
    assert (slab.model, slab.name) == ("slab", "palpation_slab")
    assert slab.tetrahedra.shape == (6 * nx * ny * nz, 4)
    assert slab.positions_m.shape == ((nx + 1) * (ny + 1) * (nz + 1), 3)
    top_z = tm.SCENE_SURFACE_Z_M
    bottom_z = top_z - tm.SLAB_SIZE_M[2]
    np.testing.assert_allclose(slab.positions_m.min(axis=0)[2], bottom_z, atol=1e-12)
    np.testing.assert_allclose(slab.positions_m.max(axis=0)[2], top_z, atol=1e-12)
    # Exactly the bottom layer of nodes is fixed.
    np.testing.assert_array_equal(slab.fixed, np.isclose(slab.positions_m[:, 2], bottom_z))
    assert slab.material_model == "linear_corotated"
    assert slab.poissons_ratio == pytest.approx(0.45)
    np.testing.assert_allclose(slab.rgba, tm.TISSUE_RGBA, atol=1e-6)
    # The lump: stiffer cells, all within the sphere 10 mm under the middle of the top.
    stiff = slab.youngs_modulus_pa > tm.TISSUE_YOUNGS_MODULUS_PA
    assert 20 < stiff.sum() < 200
    np.testing.assert_array_equal(np.unique(slab.youngs_modulus_pa),
                                  [tm.TISSUE_YOUNGS_MODULUS_PA, tm.LUMP_YOUNGS_MODULUS_PA])
    centroids = slab.positions_m[slab.tetrahedra].mean(axis=1)
    centre = [*tm.TISSUE_CENTRE_XY_M, top_z - tm.LUMP_DEPTH_M - tm.LUMP_RADIUS_M]
    np.testing.assert_array_equal(
        stiff, np.linalg.norm(centroids - centre, axis=1) < tm.LUMP_RADIUS_M)
    lump_nodes = slab.positions_m[np.unique(slab.tetrahedra[stiff])]
    assert lump_nodes[:, 2].max() == pytest.approx(top_z - tm.LUMP_DEPTH_M)


def test_shipped_organ_closed_and_fixed_underneath(shipped):
    organ = shipped.bodies[1]
    assert 1000 < len(organ.tetrahedra) < 8000
    # Its smallest cells keep the explicit step within the scene's default substeps.
    model = tissue_model(organ.positions_m, organ.tetrahedra,
                         youngs_modulus_pa=organ.youngs_modulus_pa,
                         poissons_ratio=organ.poissons_ratio,
                         mass_density_kg_m3=organ.mass_density_kg_m3, fixed=organ.fixed,
                         mass_damping_per_s=organ.mass_damping_per_s,
                         stiffness_damping_s=organ.stiffness_damping_s)
    probe = TissueContact().probe
    assert stable_substeps(model, 1e-3, probe_stiffness_n_per_m3=probe.stiffness_n_per_m3) \
        <= TissueContact().max_substeps
    bottom_z = organ.positions_m[:, 2].min()
    np.testing.assert_array_equal(
        organ.fixed, organ.positions_m[:, 2] < bottom_z + tm.ORGAN_FIXED_HEIGHT_M)
    assert 10 < organ.fixed.sum() < 0.3 * len(organ.fixed)
    assert tm.tetrahedron_quality(organ.positions_m, organ.tetrahedra).min() > 0.2
    # Closed: every boundary triangle's edges are shared by two boundary triangles.
    faces = np.sort(organ.tetrahedra[:, list(itertools.combinations(range(4), 3))]
                    .reshape(-1, 3), axis=1)
    unique, count = np.unique(faces, axis=0, return_counts=True)
    assert count.max() == 2
    boundary = unique[count == 1]
    edges = np.sort(boundary[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    assert (np.unique(edges, axis=0, return_counts=True)[1] == 2).all()
    np.testing.assert_allclose(organ.rgba, tm.ORGAN_RGBA, atol=1e-6)


def test_rigid_directives_keep_the_rest(shipped):
    kept = shipped.rigid_directives
    assert [d.add_model.name if d.add_model else d.add_weld.child for d in kept] == [
        "table", "table::top"]


def test_holds_tissue_is_cheap_and_right():
    rigid = directives(TABLE)
    assert not holds_tissue(rigid)
    assert read_scene_tissue(rigid).bodies == []
    assert holds_tissue(directives(add_model("s", "package://maglev_haptics/tissue/organ.sdf")))


def test_shipped_files_regenerate_identically(tmp_path):
    for path in tm.write_shipped(tmp_path):
        shipped = tm.TISSUE_FOLDER / path.name
        if path.suffix == ".sdf":
            assert path.read_text() == shipped.read_text(), path.name
            continue
        # The .vtk's header names the meshio version; its data must match exactly.
        new, old = meshio.read(str(path)), meshio.read(str(shipped))
        np.testing.assert_array_equal(new.points, old.points)
        np.testing.assert_array_equal(new.cells_dict["tetra"], old.cells_dict["tetra"])
        np.testing.assert_array_equal(new.cell_data["youngs_modulus"][0],
                                      old.cell_data["youngs_modulus"][0])


@pytest.mark.parametrize("mirrored", [False, True])
def test_grid_tetrahedra_fill_the_box_conformingly(mirrored):
    xs, ys, zs = tm.graded_edges(0, 0.02, 4, 3.0), np.linspace(0, 0.01, 3), [0, 0.004, 0.01]
    points, tetrahedra = tm.grid_tetrahedra(xs, ys, zs, mirrored=mirrored)
    volumes = tm.tetrahedron_volumes(points, tetrahedra)
    assert (volumes > 0).all()
    assert volumes.sum() == pytest.approx(0.02 * 0.01 * 0.01)
    faces = np.sort(tetrahedra[:, list(itertools.combinations(range(4), 3))].reshape(-1, 3),
                    axis=1)
    unique, count = np.unique(faces, axis=0, return_counts=True)
    assert count.max() == 2  # conforming: no face of three tetrahedra, no hanging ones
    # A face of one tetrahedron only lies on a side of the box: its three vertices
    # share a coordinate at the box's bounds.
    single = points[unique[count == 1]]  # (faces, 3 vertices, 3)
    box = np.array([0.02, 0.01, 0.01])
    on_side = (np.isclose(single, 0) | np.isclose(single, box)).all(axis=1).any(axis=1)
    assert on_side.all()
    assert len(single) == 2 * 2 * (4 * 2 + 4 * 2 + 2 * 2)  # two triangles a side's square
    assert tm.tetrahedron_quality(points, tetrahedra).min() > 0.3


def test_graded_edges():
    edges = tm.graded_edges(-0.01, 0.02, 5, 4.0)
    lengths = np.diff(edges)
    assert edges[0] == -0.01 and edges[-1] == pytest.approx(0.02)
    assert lengths[0] / lengths[-1] == pytest.approx(4.0)
    with pytest.raises(ValueError, match="count"):
        tm.graded_edges(0, 1, 0, 1.0)


# Refusals, on a small box written beside its model file.
SMALL = tm.TissueMesh(*tm.box_tetrahedra((0.04, 0.04, 0.02), (4, 4, 2)),
                      np.full(192, 5e3))


def small_model(tmp_path, mesh=SMALL, mesh_file="box.vtk", wall_z=0.001,
                material=tm.TissueMaterial(), extra_link="") -> str:
    if mesh is not None:
        tm.write_vtk(tmp_path / mesh_file, mesh)
    text = tm.tissue_sdf("box", "box", mesh_file, (0, 0, 0), material, (0, 0, wall_z),
                         tm.TISSUE_RGBA)
    (tmp_path / "box.sdf").write_text(text.replace("  </model>", extra_link + "  </model>"))
    return add_model("box", f"file://{tmp_path}/box.sdf")


def refusal(text: str) -> str:
    with pytest.raises(ValueError) as error:
        read_scene_tissue(directives(text))
    message = str(error.value)
    assert "\n" not in message
    return message


def test_small_box_reads(tmp_path):
    body = read_scene_tissue(directives(small_model(tmp_path))).bodies[0]
    np.testing.assert_array_equal(body.fixed, body.positions_m[:, 2] == 0)
    np.testing.assert_array_equal(body.youngs_modulus_pa, 5e3)


def test_surface_mesh_refused(tmp_path):
    (tmp_path / "tri.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\n"
                                      "f 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n")
    message = refusal(small_model(tmp_path, None, "tri.obj"))
    assert "tetrahedral volume mesh" in message and "tri.obj" in message
    assert message.startswith("scene.directives[0].add_model.file = ")
    meshio.write(str(tmp_path / "tri.vtk"), meshio.read(str(tmp_path / "tri.obj")))
    assert "tetrahedral volume mesh" in refusal(small_model(tmp_path, None, "tri.vtk"))


def test_inverted_tetrahedron_refused(tmp_path):
    tetrahedra = SMALL.tetrahedra.copy()
    tetrahedra[7] = tetrahedra[7][[1, 0, 2, 3]]
    message = refusal(small_model(tmp_path, SMALL._replace(tetrahedra=tetrahedra)))
    assert "tetrahedron 7" in message and "volume -" in message


def test_no_fixed_or_all_fixed_refused(tmp_path):
    assert "fall forever" in refusal(small_model(tmp_path, wall_z=-0.001))
    assert "all 75 nodes" in refusal(small_model(tmp_path, wall_z=0.03))


def test_material_refused(tmp_path):
    message = refusal(small_model(tmp_path, material=tm.TissueMaterial(
        material_model="neohookean")))
    assert "'neohookean'" in message and "linear_corotated" in message
    message = refusal(small_model(tmp_path, material=tm.TissueMaterial(poissons_ratio=-0.2)))
    assert "drake:poissons_ratio = -0.2" in message
    message = refusal(small_model(tmp_path, material=tm.TissueMaterial(
        youngs_modulus_pa=float("inf"))))
    assert "drake:youngs_modulus = inf" in message
    # Drake's own checks, wrapped: the file and the field.
    message = refusal(small_model(tmp_path, material=tm.TissueMaterial(
        stiffness_damping_s=-1e-3)))
    assert "box.sdf" in message and "Stiffness damping must be non-negative" in message


def test_cell_data_refused(tmp_path):
    message = refusal(small_model(tmp_path, SMALL._replace(youngs_modulus_pa=np.r_[
        np.full(191, 5e3), 0.0])))
    assert "youngs_modulus[191] = 0.0" in message


def test_mixed_model_and_weld_refused(tmp_path):
    rigid_link = ("    <link name='handle'><collision name='c'><geometry><sphere><radius>0.01"
                  "</radius></sphere></geometry></collision></link>\n")
    message = refusal(small_model(tmp_path, extra_link=rigid_link))
    assert "rigid links (handle)" in message
    welded = small_model(tmp_path) + "- add_weld: {parent: world, child: box::__model__}\n"
    assert "no frame to weld" in refusal(welded)


def test_tissue_inside_add_directives_refused(tmp_path):
    (tmp_path / "nested.yaml").write_text("directives:\n" + small_model(tmp_path))
    nested = directives(f'- add_directives: {{file: "file://{tmp_path}/nested.yaml"}}\n')
    assert holds_tissue(nested)
    with pytest.raises(ValueError, match=r"\[0\]\.add_directives\.file = .*own add_model"):
        read_scene_tissue(nested)
