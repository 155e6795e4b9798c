"""Image heightmaps: greys resampled onto the lattice's columns as seen from above,
the same picture at 8 and 16 bits, files found beside the scenario file, bad images
refused naming the field; the shipped terrain image and its scenario."""

import numpy as np
import pytest
from PIL import Image
from pydrake.common.eigen_geometry import Quaternion
from pydrake.math import RigidTransform
from pydrake.systems.analysis import Simulator

from maglev_haptics.analysis.run_results import run_scenario
from maglev_haptics.diagrams.application import BuildDiagram
from maglev_haptics.cli import main
from maglev_haptics.diagrams.deformable_scene import build_scene_lattice
from maglev_haptics.diagrams.scenario import load_scenario
from maglev_haptics.scenarios.make_terrain_png import TERRAIN_PNG, write_terrain_png
from maglev_haptics.systems.heightmap import ImageHeightmap, heightmap_heights

HEIGHT_M = 0.004
X_M = np.linspace(-0.02, 0.03, 11)  # lattice columns (m), not on the pixel centres
Y_M = np.linspace(-0.01, 0.02, 7)


def write_png(path, values) -> str:
    Image.fromarray(values).save(path)
    return str(path)


def heights(file, x_m=X_M, y_m=Y_M):
    return heightmap_heights(ImageHeightmap(file=file, height_m=HEIGHT_M), x_m, y_m)


def test_a_gradient_along_the_rows_rises_with_x(tmp_path):
    # 16-bit, 6 columns from black to white (grey c / 5 exactly), 4 rows alike.
    gradient = np.tile(np.arange(6, dtype=np.uint16) * 13107, (4, 1))
    ramp = HEIGHT_M * (X_M - X_M[0]) / (X_M[-1] - X_M[0])
    expected = np.repeat(ramp[:, None], len(Y_M), axis=1)
    np.testing.assert_allclose(heights(write_png(tmp_path / "x.png", gradient)),
                               expected - expected.mean(), rtol=0, atol=1e-12)


def test_the_top_row_is_the_far_edge(tmp_path):
    # White in row 0 (the picture's top) down to black in the last: heights rise with y.
    gradient = np.tile((np.arange(6, dtype=np.uint8)[::-1] * 51)[:, None], (1, 3))
    ramp = HEIGHT_M * (Y_M - Y_M[0]) / (Y_M[-1] - Y_M[0])
    expected = np.repeat(ramp[None, :], len(X_M), axis=0)
    np.testing.assert_allclose(heights(write_png(tmp_path / "y.png", gradient)),
                               expected - expected.mean(), rtol=0, atol=1e-12)


def test_an_asymmetric_picture_lands_as_seen_from_above(tmp_path):
    # 3 rows x 4 columns on a 4 x 3 grid: each column samples one pixel's centre.
    picture = np.zeros((3, 4), dtype=np.uint8)
    picture[0, 0] = 255  # top-left: lowest x, highest y
    picture[2, 3] = 51  # bottom-right: highest x, lowest y
    h = heights(write_png(tmp_path / "corners.png", picture), np.linspace(0.0, 0.03, 4),
                np.linspace(-0.01, 0.01, 3))
    expected = np.zeros((4, 3))
    expected[0, 2], expected[3, 0] = HEIGHT_M, 0.2 * HEIGHT_M
    np.testing.assert_allclose(h - h.min(), expected, rtol=0, atol=1e-15)


def test_8_and_16_bits_of_one_picture_give_the_same_heights(tmp_path):
    picture = np.random.default_rng(3).integers(0, 256, (9, 13)).astype(np.uint8)
    eight = heights(write_png(tmp_path / "8.png", picture))
    sixteen_file = write_png(tmp_path / "16.png", picture.astype(np.uint16) * 257)
    assert Image.open(sixteen_file).mode == "I;16"
    np.testing.assert_allclose(heights(sixteen_file), eight, rtol=0, atol=1e-15)
    assert np.ptp(eight) > 0.5 * HEIGHT_M


# --- scenario files ------------------------------------------------------------------

def scenario_text(heightmap: str) -> str:
    return ("a: {hand: !ScriptedHand {}, haptics: {scene: !DeformableSurface "
            f"{{heightmap: !ImageHeightmap {heightmap}}}}}}}\n")


def test_a_relative_file_is_found_beside_the_scenario_file(tmp_path, monkeypatch):
    folder = tmp_path / "terrains"
    folder.mkdir()
    bump = write_png(folder / "bump.png", np.eye(4, dtype=np.uint8) * 255)
    (folder / "s.yaml").write_text(scenario_text("{file: bump.png}"))
    monkeypatch.chdir(tmp_path)  # elsewhere: the file's folder counts, not this one
    assert load_scenario("terrains/s.yaml", "a").haptics.scene.heightmap.file == bump
    # --scenario-text's files are the working directory's.
    other = write_png(tmp_path / "other.png", np.zeros((2, 2), dtype=np.uint8))
    layered = load_scenario("terrains/s.yaml", "a", "{haptics: {scene: !DeformableSurface "
                            "{heightmap: !ImageHeightmap {file: other.png}}}}")
    assert layered.haptics.scene.heightmap.file == other
    # {here}: the scenario file's folder, in its own text and in --scenario-text.
    here = load_scenario("terrains/s.yaml", "a", "{haptics: {scene: !DeformableSurface "
                         "{heightmap: !ImageHeightmap {file: '{here}/bump.png'}}}}")
    assert here.haptics.scene.heightmap.file == bump


BLACK_2X2 = np.zeros((2, 2), dtype=np.uint8)


@pytest.mark.parametrize("heightmap, image, fragment", [
    ("{file: absent.png}", None, "heightmap.file = '{folder}/absent.png': no such file"),
    ("{height_m: 0.004}", None, "heightmap.file = '': must name an 8- or 16-bit greyscale"),
    ("{file: image.png}", b"not a picture", "heightmap.file = '{folder}/image.png': not an image"),
    ("{file: image.png}", np.zeros((4, 4, 3), dtype=np.uint8),
     "heightmap.file = '{folder}/image.png': has Pillow mode RGB: must be 8- or 16-bit greyscale"),
    ("{file: image.png}", np.zeros((1, 5), dtype=np.uint8),
     "heightmap.file = '{folder}/image.png': is 5 x 1 pixels: must be at least 2 x 2"),
    ("{file: image.png, height_m: 0.0}", BLACK_2X2,
     "heightmap.height_m = 0.0: must be a finite height > 0 (m)"),
    ("{file: image.png, height_m: -0.001}", BLACK_2X2,
     "heightmap.height_m = -0.001: must be a finite height > 0 (m)"),
    ("{file: image.png, height_m: .nan}", BLACK_2X2,
     "heightmap.height_m = nan: must be a finite height > 0 (m)"),
    ("{file: image.png, height_m: .inf}", BLACK_2X2,
     "heightmap.height_m = inf: must be a finite height > 0 (m)"),
    ("{file: image.png, height_m: 0.02}", BLACK_2X2,  # the default lattice is 15 mm deep
     "heightmap.height_m = 0.02: must be below surface_z_m - base_z_m (0.015 m)"),
])
def test_bad_images_are_one_line_errors_naming_the_field(tmp_path, capsys, heightmap, image,
                                                         fragment):
    if isinstance(image, bytes):
        (tmp_path / "image.png").write_bytes(image)
    elif image is not None:
        write_png(tmp_path / "image.png", image)
    (tmp_path / "s.yaml").write_text(scenario_text(heightmap))
    assert main(["run", str(tmp_path / "s.yaml"), "--no-meshcat", "--out",
                 str(tmp_path / "out")]) == 2
    error = capsys.readouterr().err
    assert f"s:a: haptics.scene.{fragment.format(folder=tmp_path)}" in error
    assert error.count("\n") == 1  # one line, no traceback


# --- the shipped terrain ---------------------------------------------------------------

def test_the_shipped_terrain_is_its_scripts_small_16_bit_image(tmp_path):
    write_terrain_png(tmp_path / "terrain.png")
    with Image.open(TERRAIN_PNG) as shipped, Image.open(tmp_path / "terrain.png") as made:
        assert shipped.mode == "I;16" and shipped.size == (64, 64)
        np.testing.assert_array_equal(np.asarray(shipped), np.asarray(made))
    assert TERRAIN_PNG.stat().st_size < 50_000


def test_the_terrain_scenarios_hill_stands_where_the_picture_puts_it():
    scene = load_scenario("deformable_surface", "terrain").haptics.scene
    lattice = build_scene_lattice(scene)
    top = lattice.positions_m[lattice.surface][..., 2]
    ix, iy = np.unravel_index(top.argmax(), top.shape)
    # The hill is centred a third of the way in from the picture's left and top edges.
    hill_x_m = lattice.x_m[0] + (lattice.x_m[-1] - lattice.x_m[0]) / 3
    hill_y_m = lattice.y_m[-1] - (lattice.y_m[-1] - lattice.y_m[0]) / 3
    assert np.hypot(lattice.x_m[ix] - hill_x_m, lattice.y_m[iy] - hill_y_m) \
        < scene.column_spacing_m
    assert top.max() - top.min() == pytest.approx(scene.heightmap.height_m, rel=0.05)


def test_the_terrain_scenario_runs_briefly():
    result = run_scenario(load_scenario("deformable_surface", "terrain"),
                          label="deformable_surface:terrain", progress=False, duration_s=0.1)
    assert result.summary["duration_s"] == pytest.approx(0.1)


@pytest.mark.slow  # 3 s of the lattice: ~20-60 s here
def test_pressing_the_hill_dents_the_lattice_under_the_probe():
    scenario = load_scenario("deformable_surface", "terrain")
    built = BuildDiagram(scenario)
    scene = built.haptics.scene
    lattice, n = scene.lattice, scene.lattice.num_masses
    simulator = Simulator(built.diagram)
    context = scene.surface.GetMyContextFromRoot(simulator.get_context())
    simulator.Initialize()
    # Before the probe touches (the lattice has sagged under its weight by then) and
    # 0.4 s into the hand's press on the hill's top.
    simulator.AdvanceTo(2.5)
    before = context.get_discrete_state(0).get_value().copy()
    simulator.AdvanceTo(3.0)
    after = context.get_discrete_state(0).get_value()
    surface_rows = lattice.surface.ravel()
    dent = (after[:3 * n] - before[:3 * n]).reshape(-1, 3)[surface_rows]
    qw_qx_qy_qz, p_WT = after[6 * n:6 * n + 4], after[6 * n + 4:6 * n + 7]
    p_WP = RigidTransform(Quaternion(qw_qx_qy_qz / np.linalg.norm(qw_qx_qy_qz)), p_WT) @ \
        np.asarray(scenario.haptics.scene.tool_offset_m)
    rest = lattice.positions_m[surface_rows]
    across_m = np.hypot(rest[:, 0] - p_WP[0], rest[:, 1] - p_WP[1])
    deepest = dent[:, 2].argmin()
    assert dent[deepest, 2] < -0.1e-3  # pushed down by more than 0.1 mm (~0.18)
    assert across_m[deepest] < scenario.haptics.scene.probe.radius_m  # under the probe
    assert np.abs(dent[across_m > 0.02]).max() < 0.01e-3  # the far jelly stays put
    wrench = scene.surface.GetOutputPort("wrench_on_tool_W").Eval(context)
    assert wrench[2] > 0.1  # the surface pushes the probe up (N)
