"""Tetrahedral meshes of tissue, the files Drake reads them from, and the shipped
tissue models (``plant_models/tissue/``), regenerated deterministically by
``python -m maglev_haptics.plant_models.tissue_meshes``.

A mesh is ``points`` (n, 3) (m) and ``tetrahedra`` (m, 4) int64 indices, each
positively oriented: (p1 - p0) x (p2 - p0) . (p3 - p0) > 0, as Drake's VolumeMesh
and VTK's tetra order them. Boxes are split into tetrahedra by Kuhn's rule (six a
cube about one diagonal; every cube's faces split alike, so neighbours conform),
which makes no slivers; a closed blob is a grid of cubes mapped smoothly onto it,
never a Delaunay triangulation of a point cloud (which makes slivers).

A stiffer inclusion is per-tetrahedron material: the VTK file's cell data
``youngs_modulus`` (Pa, one value a tetrahedron) overrides the body's
``drake:youngs_modulus`` tetrahedron by tetrahedron (Drake itself ignores cell
data). Why not a second body embedded in the first: Drake's DeformableModel gives a
body one material, and two bodies would need every node of the inner one's surface
tied to the outer one's elements (Drake's fixed constraints tie deformable bodies to
rigid ones only), with two meshes that must match at the interface. One mesh with a
material a cell keeps one set of nodes, one kernel and no ties; the lump's boundary
follows the cells (a tetrahedron is stiff when its centroid lies in the lump).

Placement: the mesh is in the link's frame (origin at the centre of the body's
underside), the link's ``<pose>`` puts it in W and the wall boundary condition is
written in W (as Drake reads it). Drake 1.58 fixes the wall's nodes at their
reference positions, which the link's pose moves but a directive's
``default_free_body_pose`` does not, so a tissue is placed in its file.
"""

import argparse
import itertools
from pathlib import Path
from typing import NamedTuple, Optional, Sequence

import meshio
import numpy as np

TISSUE_FOLDER = Path(__file__).with_name("tissue")
YOUNGS_MODULUS_CELL_DATA = "youngs_modulus"  # the VTK cell data of a per-tetrahedron E (Pa)

# The six tetrahedra of a unit cube about its diagonal from corner 0 to corner 7,
# corners numbered i + 2 j + 4 k: each walks from corner 0 to corner 7 along the
# axes in one order (a permutation), so each has the permutation's orientation.
_KUHN_AXIS_ORDERS = list(itertools.permutations(range(3)))

# The shipped tissue: W's z = 0 is the display's top; the virtual scene lies under it
# (the deformable surface's mean is 15 mm down, where a probe 30 mm below the
# instrument reaches with the instrument ~19 mm above the glass). (m)
SCENE_SURFACE_Z_M = -0.015
SLAB_SIZE_M = (0.070, 0.060, 0.030)  # x, y, z (m)
SLAB_CELLS = (14, 12, 6)  # cubes along x, y, z: 6,048 tetrahedra
# Where the tissue's middle lies in W (m): off the display's centre along +x, so the
# instrument takes off beside it (40 mm left of the centre in the shipped scenarios)
# and the hand carries the probe over it, as the paper's deformable surface does.
TISSUE_CENTRE_XY_M = (0.015, 0.0)
LUMP_RADIUS_M = 0.008
LUMP_DEPTH_M = 0.010  # from the slab's top down to the lump's top (m)
TISSUE_YOUNGS_MODULUS_PA = 5.0e3
LUMP_YOUNGS_MODULUS_PA = 40.0e3
ORGAN_SEMI_AXES_M = (0.040, 0.025)  # half length (x) and half width (y) (m)
ORGAN_BEND_M = 0.008  # the kidney's centre line bows this far along -y at its middle (m)
# z of the blob over its unit-ball coordinate w in [-1, 1]: TOP w + ROUND w^2 (m);
# its top 18 mm above the middle, its flatter underside 10 mm below.
ORGAN_HEIGHT_TOP_M, ORGAN_HEIGHT_ROUND_M = 0.014, 0.004
# Even: the grid is split symmetrically about its centre. Coarse: the ball map squeezes
# the cells near its poles, whose stable explicit step sets the substeps (12 x 8 x 6:
# 3,456 tetrahedra, 13 substeps a 1 ms tick; this: 1,440, 6).
ORGAN_CELLS = (10, 6, 4)
# The wall fixes the nodes below a plane this high above the underside (m): the
# slab's bottom layer of nodes (the next is 5 mm up); the organ's flattest patch.
SLAB_FIXED_HEIGHT_M = 0.001
ORGAN_FIXED_HEIGHT_M = 0.003
TISSUE_RGBA = (0.85, 0.45, 0.45, 1.0)
ORGAN_RGBA = (0.55, 0.18, 0.16, 1.0)


class TissueMaterial(NamedTuple):
    """A body's material, as ``<drake:deformable_properties>`` declares it."""

    youngs_modulus_pa: float = TISSUE_YOUNGS_MODULUS_PA
    poissons_ratio: float = 0.45  # (-); soft tissue is nearly incompressible
    mass_density_kg_m3: float = 1000.0
    # Rayleigh damping D = alpha M + beta K: alpha damps the slab's lowest mode
    # (~11 Hz at 5 kPa) at ~15% of critical; beta stays small because it shortens
    # the explicit stable step of the stiffest elements (2e-4 s: 6 substeps a tick
    # for the slab instead of 4, its highest mode damped at 60 % of critical).
    mass_damping_per_s: float = 20.0
    stiffness_damping_s: float = 2.0e-5
    material_model: str = "linear_corotated"


class TissueMesh(NamedTuple):
    """A body's mesh in its link's frame, and its Young's modulus per tetrahedron."""

    points_m: np.ndarray  # (n, 3) (m)
    tetrahedra: np.ndarray  # (m, 4) int64
    youngs_modulus_pa: np.ndarray  # (m,) (Pa)


def graded_edges(start_m: float, stop_m: float, count: int, ratio: float) -> np.ndarray:
    """``count + 1`` grid coordinates from ``start_m`` to ``stop_m`` (m) whose cells
    shrink geometrically, the first ``ratio`` times as long as the last (ratio 1:
    even; ratio < 1 grows them)."""
    if count < 1 or not ratio > 0:
        raise ValueError(f"graded_edges: count = {count!r}, ratio = {ratio!r}: need "
                         "count >= 1 and ratio > 0")
    growth = ratio ** (-1.0 / max(count - 1, 1))
    lengths = growth ** np.arange(count)
    return start_m + (stop_m - start_m) * np.r_[0.0, np.cumsum(lengths)] / lengths.sum()


def grid_tetrahedra(x_m: Sequence[float], y_m: Sequence[float], z_m: Sequence[float],
                    mirrored: bool = False) -> tuple:
    """(points (n, 3), tetrahedra (m, 4) int64) filling the grid of boxes between
    the increasing coordinates ``x_m``, ``y_m``, ``z_m`` (m), six positively
    oriented tetrahedra a box. Points are numbered x fastest, then y, then z.

    ``mirrored``: each box's diagonal runs from its corner nearest the grid's centre
    (the split reflected about the centre planes, which must be grid planes: even
    cell counts), so that a box at the grid's rim keeps a vertex inside when the
    grid is mapped onto a round body; else every diagonal runs the same way."""
    axes = [np.asarray(c, dtype=float) for c in (x_m, y_m, z_m)]
    counts = [len(c) - 1 for c in axes]
    if min(counts) < 1 or any(np.any(np.diff(c) <= 0) for c in axes):
        raise ValueError("grid_tetrahedra: each axis needs >= 2 increasing coordinates")
    if mirrored and any(n % 2 for n in counts):
        raise ValueError(f"grid_tetrahedra: cell counts {counts} must be even when mirrored")
    z, y, x = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    points = np.column_stack([x.ravel(), y.ravel(), z.ravel()])
    stride = np.array([1, counts[0] + 1, (counts[0] + 1) * (counts[1] + 1)])
    k, j, i = np.meshgrid(*(np.arange(n) for n in counts[::-1]), indexing="ij")
    cell = np.column_stack([i.ravel(), j.ravel(), k.ravel()])  # (cubes, 3) lower corners
    # Per cube and axis, whether the split is reflected: its diagonal then starts at
    # the cube's upper face along that axis.
    flip = (cell >= np.array(counts) // 2) if mirrored else np.zeros_like(cell, dtype=bool)
    tetrahedra = []
    for order in _KUHN_AXIS_ORDERS:
        walk = np.zeros((len(cell), 4, 3), dtype=np.int64)  # corner offsets along the path
        for step, axis in enumerate(order):
            walk[:, step + 1:, axis] = 1
        offsets = np.where(flip[:, None, :], 1 - walk, walk)
        tetrahedra.append(((cell[:, None, :] + offsets) * stride).sum(axis=2))
    tetrahedra = np.concatenate(tetrahedra)
    negative = tetrahedron_volumes(points, tetrahedra) < 0
    tetrahedra[negative] = tetrahedra[negative][:, [0, 2, 1, 3]]
    return points, tetrahedra


def box_tetrahedra(size_m: Sequence[float], counts: Sequence[int],
                   origin_m: Sequence[float] = (0.0, 0.0, 0.0)) -> tuple:
    """grid_tetrahedra of a box ``size_m`` (x, y, z) (m) of ``counts`` equal cells a
    side, its underside centred on ``origin_m`` (m)."""
    x0, y0, z0 = origin_m
    sx, sy, sz = size_m
    return grid_tetrahedra(np.linspace(x0 - sx / 2, x0 + sx / 2, counts[0] + 1),
                           np.linspace(y0 - sy / 2, y0 + sy / 2, counts[1] + 1),
                           np.linspace(z0, z0 + sz, counts[2] + 1))


def tetrahedron_volumes(points: np.ndarray, tetrahedra: np.ndarray) -> np.ndarray:
    """Signed volumes (m^3) (m,): positive when p3 lies on the side of the face
    (p0, p1, p2) its right-hand normal points to."""
    p = np.asarray(points, dtype=float)[np.asarray(tetrahedra)]
    return np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]),
                     p[:, 3] - p[:, 0]) / 6.0


def tetrahedron_quality(points: np.ndarray, tetrahedra: np.ndarray) -> np.ndarray:
    """Mean-ratio quality (m,) in (0, 1]: 1 for a regular tetrahedron, ~0 for a
    sliver, 12 (3 V)^(2/3) / (sum of squared edge lengths); negative if inverted."""
    p = np.asarray(points, dtype=float)[np.asarray(tetrahedra)]
    edges = [p[:, b] - p[:, a] for a, b in itertools.combinations(range(4), 2)]
    squared = sum(np.einsum("ij,ij->i", e, e) for e in edges)
    volume = tetrahedron_volumes(points, tetrahedra)
    return 12.0 * np.sign(volume) * np.cbrt(3.0 * np.abs(volume)) ** 2 / squared


def centroids_within(points: np.ndarray, tetrahedra: np.ndarray, centre_m: Sequence[float],
                     radius_m: float) -> np.ndarray:
    """(m,) bool: whether each tetrahedron's centroid lies within the sphere."""
    centroid = np.asarray(points, dtype=float)[np.asarray(tetrahedra)].mean(axis=1)
    return np.linalg.norm(centroid - np.asarray(centre_m), axis=1) < radius_m


def palpation_slab(cells: Sequence[int] = SLAB_CELLS) -> TissueMesh:
    """The palpation slab, SLAB_SIZE_M, its underside at z = 0 of its frame, with
    a spherical lump LUMP_RADIUS_M whose top lies LUMP_DEPTH_M under the middle of
    the top (LUMP_YOUNGS_MODULUS_PA in the tetrahedra whose centroids it holds)."""
    points, tetrahedra = box_tetrahedra(SLAB_SIZE_M, cells)
    centre = (0.0, 0.0, SLAB_SIZE_M[2] - LUMP_DEPTH_M - LUMP_RADIUS_M)
    lump = centroids_within(points, tetrahedra, centre, LUMP_RADIUS_M)
    return TissueMesh(points, tetrahedra,
                      np.where(lump, LUMP_YOUNGS_MODULUS_PA, TISSUE_YOUNGS_MODULUS_PA))


def cube_to_ball(p: np.ndarray) -> np.ndarray:
    """The smooth map of the cube [-1, 1]^3 onto the unit ball that takes each face
    to a sixth of the sphere (x sqrt(1 - y^2/2 - z^2/2 + y^2 z^2/3), cyclically)."""
    x2 = np.asarray(p, dtype=float) ** 2
    shifted = [np.roll(x2, -s, axis=1) for s in (1, 2)]
    return p * np.sqrt(1 - shifted[0] / 2 - shifted[1] / 2 + shifted[0] * shifted[1] / 3)


def organ(cells: Sequence[int] = ORGAN_CELLS) -> TissueMesh:
    """A kidney-like closed blob: a grid of cubes mapped onto the unit ball, then
    stretched to ORGAN_SEMI_AXES_M, bowed along y and given a rounder top than
    underside; its lowest point at z = 0 of its frame. Uniform material."""
    unit = [np.linspace(-1.0, 1.0, n + 1) for n in cells]
    grid, tetrahedra = grid_tetrahedra(*unit, mirrored=True)
    u, v, w = cube_to_ball(grid).T
    # Each new coordinate grows with its own ball coordinate (a triangular Jacobian
    # with a positive diagonal), so no tetrahedron turns over.
    a, b = ORGAN_SEMI_AXES_M
    points = np.column_stack([a * u, b * v - ORGAN_BEND_M * (1 - u ** 2),
                              ORGAN_HEIGHT_TOP_M * w + ORGAN_HEIGHT_ROUND_M * w ** 2])
    points[:, 2] -= points[:, 2].min()
    return TissueMesh(points, tetrahedra, np.full(len(tetrahedra), TISSUE_YOUNGS_MODULUS_PA))


def write_vtk(path: Path, mesh: TissueMesh) -> None:
    """``mesh`` as a legacy VTK UNSTRUCTURED_GRID of tetra cells (binary, as
    Drake's reader takes it) with cell data ``youngs_modulus``."""
    meshio.write(str(path), meshio.Mesh(
        points=np.asarray(mesh.points_m, dtype=float),
        cells=[("tetra", np.asarray(mesh.tetrahedra, dtype=np.int64))],
        cell_data={YOUNGS_MODULUS_CELL_DATA: [np.asarray(mesh.youngs_modulus_pa, float)]}),
        file_format="vtk", binary=True)


def read_cell_youngs_modulus(path: str) -> tuple:
    """(tetrahedra (m, 4) int64, Young's modulus per tetrahedron (m,) (Pa) or None)
    from the VTK file ``path``: its tetra cells in the file's order, and its cell
    data ``youngs_modulus`` if it has one."""
    mesh = meshio.read(path)
    blocks = [i for i, block in enumerate(mesh.cells) if block.type == "tetra"]
    tetrahedra = np.concatenate([mesh.cells[i].data for i in blocks]).astype(np.int64) \
        if blocks else np.zeros((0, 4), dtype=np.int64)
    data = mesh.cell_data.get(YOUNGS_MODULUS_CELL_DATA)
    if data is None:
        return tetrahedra, None
    return tetrahedra, np.concatenate([np.ravel(data[i]) for i in blocks]).astype(float)


def tissue_sdf(model: str, link: str, mesh_file: str, p_WL_m: Sequence[float],
               material: TissueMaterial, wall_point_W_m: Sequence[float],
               rgba: Sequence[float]) -> str:
    """SDFormat text of model ``model`` with one deformable link ``link``: its
    tetrahedral mesh ``mesh_file`` (a path beside the .sdf), its frame at
    ``p_WL_m`` in W (m), ``material``, every node below the horizontal plane
    through ``wall_point_W_m`` (m, in W) fixed, and its colour ``rgba``."""
    def numbers(values) -> str:
        return " ".join(f"{v:.9g}" for v in values)

    return f"""<?xml version="1.0"?>
<!-- Generated by python -m maglev_haptics.plant_models.tissue_meshes; do not edit. -->
<sdf version="1.9" xmlns:drake="http://drake.mit.edu">
  <model name="{model}">
    <link name="{link}">
      <pose>{numbers(p_WL_m)} 0 0 0</pose>
      <collision name="{link}_collision">
        <geometry><mesh><uri>{mesh_file}</uri></mesh></geometry>
      </collision>
      <!-- A deformable body's visual is its collision mesh: Drake takes only the
           colour from an empty visual. -->
      <visual name="{link}_visual">
        <geometry><empty/></geometry>
        <material><diffuse>{numbers(rgba)}</diffuse></material>
      </visual>
      <drake:deformable_properties>
        <drake:youngs_modulus>{material.youngs_modulus_pa:.9g}</drake:youngs_modulus>
        <drake:poissons_ratio>{material.poissons_ratio:.9g}</drake:poissons_ratio>
        <drake:mass_density>{material.mass_density_kg_m3:.9g}</drake:mass_density>
        <drake:mass_damping>{material.mass_damping_per_s:.9g}</drake:mass_damping>
        <drake:stiffness_damping>{material.stiffness_damping_s:.9g}</drake:stiffness_damping>
        <drake:material_model>{material.material_model}</drake:material_model>
      </drake:deformable_properties>
      <drake:wall_boundary_condition>
        <drake:point_on_plane>{numbers(wall_point_W_m)}</drake:point_on_plane>
        <drake:outward_normal>0 0 1</drake:outward_normal>
      </drake:wall_boundary_condition>
    </link>
  </model>
</sdf>
"""


def write_shipped(folder: Path = TISSUE_FOLDER,
                  slab_cells: Sequence[int] = SLAB_CELLS,
                  organ_cells: Sequence[int] = ORGAN_CELLS) -> list:
    """Write palpation_slab.{vtk,sdf} and organ.{vtk,sdf} into ``folder``; their paths.
    Both rest with their undersides SLAB_SIZE_M[2] under the scene's surface."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    floor_z = SCENE_SURFACE_Z_M - SLAB_SIZE_M[2]  # the tissue's underside in W (m)
    written = []
    for name, mesh, material, fixed_height, rgba in (
            ("palpation_slab", palpation_slab(slab_cells), TissueMaterial(), SLAB_FIXED_HEIGHT_M,
             TISSUE_RGBA),
            ("organ", organ(organ_cells), TissueMaterial(), ORGAN_FIXED_HEIGHT_M, ORGAN_RGBA)):
        write_vtk(folder / f"{name}.vtk", mesh)
        (folder / f"{name}.sdf").write_text(tissue_sdf(
            name, name, f"{name}.vtk", (*TISSUE_CENTRE_XY_M, floor_z), material,
            (*TISSUE_CENTRE_XY_M, floor_z + fixed_height), rgba))
        written += [folder / f"{name}.vtk", folder / f"{name}.sdf"]
    return written


def main(argv: Optional[Sequence[str]] = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--folder", type=Path, default=TISSUE_FOLDER)
    args = parser.parse_args(argv)
    for path in write_shipped(args.folder):
        print(path)


if __name__ == "__main__":
    main()
