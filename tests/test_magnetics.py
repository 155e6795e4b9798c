"""The electromagnetic model: coil field, surface-charge wrench, table, kernel, contract.

The reference throughout is ``direct_coil_magnet_wrench``: magpylib's exact field
of the magnet acting on the coil's winding current (Lorentz force), which shares
no physics with the table (surface charges on the magnet in the coil's field).
"""

import math

import magpylib
import numpy as np
import pytest
from pydrake.math import RigidTransform, RollPitchYaw, RotationMatrix

from maglev_haptics.hardware import DeviceConfig, MagneticsModel, load_magnetics
from maglev_haptics.hardware.charge_model import ChargeModel
from maglev_haptics.hardware.coil_field import (
    coil_field_exact, coil_field_tables, current_density_per_ampere, interpolate_field)
from maglev_haptics.hardware.device import CoilArraySpec, CoilSpec, default_instrument
from maglev_haptics.hardware.direct_wrench import direct_coil_magnet_wrench
from maglev_haptics.hardware.interpolation import axis_nodes
from maglev_haptics.hardware.magnetics import bench_wrench_matrix
from maglev_haptics.hardware.wrench_table import (
    MIRROR_PARITY, WrenchGrid, load_wrench_table, tilt_axis)

KINDS = ("two_magnet", "four_magnet")
COIL = CoilSpec()
GRAVITY = 9.81  # [m/s^2]


@pytest.fixture(scope="module")
def models():
    return {kind: load_magnetics(DeviceConfig(instrument=kind)) for kind in KINDS}


def unit_axis(tilt_rad, direction_rad):
    """Unit axis tilted from +z by tilt toward the horizontal direction [rad]."""
    return np.array([math.sin(tilt_rad) * math.cos(direction_rad),
                     math.sin(tilt_rad) * math.sin(direction_rad), math.cos(tilt_rad)])


def rotation_z(angle_rad):
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


# --- coil field ---------------------------------------------------------------

def loop_sum_field(coil, points, radial_order=48, axial_order=96):
    """Field per ampere from magpylib Circle loops over a 2-D Gauss-Legendre
    quadrature of the winding cross-section, shape (n, 3) [T/A]."""
    inner, outer = coil.inner_diameter_m / 2, coil.outer_diameter_m / 2
    x_r, w_r = np.polynomial.legendre.leggauss(radial_order)
    x_z, w_z = np.polynomial.legendre.leggauss(axial_order)
    radii = (inner + outer) / 2 + (outer - inner) / 2 * x_r
    heights = -coil.height_m / 2 + coil.height_m / 2 * x_z
    radius, height = (a.ravel() for a in np.meshgrid(radii, heights, indexing="ij"))
    # Loop current = J * dA [A].
    currents = current_density_per_ampere(coil) * np.outer(
        (outer - inner) / 2 * w_r, coil.height_m / 2 * w_z).ravel()
    loops = magpylib.current.Circle(
        position=np.stack([0 * radius, 0 * radius, height], axis=1),
        diameter=2 * radius, current=currents)
    return magpylib.getB(loops, points).sum(axis=0)


def test_coil_field_matches_magpylib_current_loops():
    # Points at least 2 mm from the winding, where a loop quadrature converges.
    points = np.array([[0.0, 0.0, 0.002], [0.009, 0.0, 0.003], [0.0, 0.02, 0.005],
                       [0.03, 0.01, 0.02], [0.0, 0.0, -0.015], [0.02, 0.0, -0.01],
                       [0.1, 0.05, 0.08]])
    loops = loop_sum_field(COIL, points)
    rho = np.hypot(points[:, 0], points[:, 1])
    exact = coil_field_exact(COIL, rho, points[:, 2])
    b_z_axis = coil_field_exact(COIL, [0.0], [0.0])[1, 0]
    np.testing.assert_allclose(exact[1], loops[:, 2], atol=1e-4 * b_z_axis)
    np.testing.assert_allclose(exact[0], np.hypot(loops[:, 0], loops[:, 1]), atol=1e-4 * b_z_axis)
    assert 0.01 < b_z_axis < 0.03  # [T/A] at the top-face centre: ~mu0 N I / height scale


def test_coil_field_quadrature_converges_at_and_inside_the_winding():
    rho = np.array([0.0, 0.006, 0.009, 0.0125, 0.009, 0.009, 0.03])
    z = np.array([0.0005, 0.0002, 0.00025, 0.0005, -0.001, -0.015, 0.02])
    reference = coil_field_exact(COIL, rho, z, order=128)
    scale = np.abs(reference).max()
    assert np.abs(coil_field_exact(COIL, rho, z, order=16) - reference).max() < 1e-5 * scale
    assert np.abs(coil_field_exact(COIL, rho, z) - reference).max() < 1e-9 * scale


def test_field_table_interpolation_above_the_coil():
    tables = coil_field_tables(COIL)
    rng = np.random.default_rng(0)
    rho = rng.uniform(0.0, 0.06, 400)
    z = rng.uniform(0.001, 0.06, 400)
    exact = coil_field_exact(COIL, rho, z)
    table = np.array([interpolate_field(*tables, r, h) for r, h in zip(rho, z)]).T
    relative = np.abs(table - exact).max(axis=0) / np.hypot(*exact)
    assert relative.max() < 2e-3
    assert np.median(relative) < 1e-5


def test_coil_field_rejects_bad_input():
    with pytest.raises(ValueError, match="rho"):
        coil_field_exact(COIL, [-0.001], [0.01])
    with pytest.raises(ValueError, match="z"):
        coil_field_exact(COIL, [0.001], [np.nan])


# --- coil-magnet wrench: direct reference and surface-charge model -------------

NEAR_POSES = [  # (rho [m], z [m], tilt [deg], tilt direction [deg]): hardest first
    (0.004, 0.015, 45, 20), (0.0125, 0.015, 30, 180), (0.0, 0.02, 10, 90),
    (0.03, 0.025, 45, 300), (0.08, 0.04, 20, 45)]


def pose_vectors(rho, z, tilt_deg, direction_deg):
    return np.array([rho, 0.0, z]), unit_axis(math.radians(tilt_deg), math.radians(direction_deg))


@pytest.mark.parametrize("kind", KINDS)
def test_direct_wrench_converges(kind):
    magnet = default_instrument(kind).magnet
    for pose in NEAR_POSES[:3]:
        p, u = pose_vectors(*pose)
        coarse = np.concatenate(direct_coil_magnet_wrench(COIL, magnet, p, u))
        fine = np.concatenate(direct_coil_magnet_wrench(COIL, magnet, p, u, order=(16, 32, 128)))
        assert np.linalg.norm(coarse[:3] - fine[:3]) < 1e-5 * np.linalg.norm(fine[:3])
        assert np.linalg.norm(coarse[3:] - fine[3:]) < 1e-4 * np.linalg.norm(fine[3:]) + 1e-9


@pytest.mark.parametrize("kind", KINDS)
def test_surface_charge_model_matches_direct(kind):
    magnet = default_instrument(kind).magnet
    charge = ChargeModel(COIL, magnet)
    for pose in NEAR_POSES:
        p, u = pose_vectors(*pose)
        direct = np.concatenate(direct_coil_magnet_wrench(COIL, magnet, p, u))
        model = charge.wrench(p, u)
        assert np.linalg.norm(model[:3] - direct[:3]) < 1e-4 * np.linalg.norm(direct[:3])
        assert np.linalg.norm(model[3:] - direct[3:]) < 1e-4 * np.linalg.norm(direct[3:]) + 1e-9


def test_direct_wrench_obeys_the_mirror_symmetry():
    """Reflecting the pose in the x-z plane: (F_x, -F_y, F_z, -T_x, T_y, -T_z)."""
    magnet = default_instrument("two_magnet").magnet
    for rho, z, tilt, direction in NEAR_POSES[:3]:
        p, u = pose_vectors(rho, z, tilt, direction)
        mirrored_p, mirrored_u = pose_vectors(rho, z, tilt, -direction)
        wrench = np.concatenate(direct_coil_magnet_wrench(COIL, magnet, p, u))
        mirrored = np.concatenate(direct_coil_magnet_wrench(COIL, magnet, mirrored_p, mirrored_u))
        np.testing.assert_allclose(mirrored, MIRROR_PARITY * wrench,
                                   atol=1e-9 * np.abs(wrench).max())


# --- the table against the direct computation ---------------------------------

def height_maxima(model, z):
    """Largest |F| [N/A] and |T| [N m/A] of one coil on one magnet at height z [m]:
    over radial offsets 0-60 mm, level and tilted 22.5 or 45 deg in 8 directions."""
    axes = [unit_axis(0.0, 0.0)] + [
        unit_axis(math.radians(tilt), math.radians(direction))
        for tilt in (22.5, 45.0) for direction in range(0, 360, 45)]
    force, torque = 0.0, 0.0
    for rho in np.linspace(0.0, 0.06, 21):
        for u in axes:
            f, t = model.coil_magnet_wrench([rho, 0.0, z], u)
            force, torque = max(force, np.linalg.norm(f)), max(torque, np.linalg.norm(t))
    return force, torque


def table_errors(model, n_poses, seed):
    """Per pose: |error| / max(|wrench|, 1 % of the largest at that height), force
    and torque, over centres 15-80 mm above the coil (a third of them below 20 mm,
    where it is hardest), radial offsets 0-150 mm (half of them within 40 mm),
    tilt 0-45 deg in any direction, any azimuth."""
    rng = np.random.default_rng(seed)
    magnet = model.instrument.magnet
    errors = []
    for i in range(n_poses):
        z = rng.uniform(0.015, 0.020) if i % 3 == 0 else rng.uniform(0.015, 0.080)
        rho = rng.uniform(0.0, 0.04) if i % 2 else rng.uniform(0.0, 0.15)
        azimuth = rng.uniform(0.0, 2 * np.pi)
        p = np.array([rho * math.cos(azimuth), rho * math.sin(azimuth), z])
        u = unit_axis(math.radians(rng.uniform(0.0, 45.0)), rng.uniform(0.0, 2 * np.pi))
        force, torque = direct_coil_magnet_wrench(COIL, magnet, p, u)
        table_force, table_torque = model.coil_magnet_wrench(p, u)
        force_max, torque_max = height_maxima(model, z)
        floored_force = max(np.linalg.norm(force), 0.01 * force_max)
        floored_torque = max(np.linalg.norm(torque), 0.01 * torque_max)
        errors.append((np.linalg.norm(table_force - force) / floored_force,
                       np.linalg.norm(table_torque - torque) / floored_torque))
    return np.array(errors)


def check_table_accuracy(model, n_poses, seed):
    errors = table_errors(model, n_poses, seed)
    print(f"\n{model.instrument.kind}: {n_poses} poses, error as % of the floored magnitude: "
          f"force max {100 * errors[:, 0].max():.3f} mean {100 * errors[:, 0].mean():.4f}, "
          f"torque max {100 * errors[:, 1].max():.3f} mean {100 * errors[:, 1].mean():.4f}")
    assert errors.max() <= 0.005


@pytest.mark.parametrize("kind", KINDS)
def test_table_matches_direct_sampled(models, kind):
    check_table_accuracy(models[kind], n_poses=80, seed=1)


@pytest.mark.slow
@pytest.mark.parametrize("kind", KINDS)
def test_table_matches_direct_many_poses(models, kind):
    check_table_accuracy(models[kind], n_poses=600, seed=2)


@pytest.mark.parametrize("kind", KINDS)
def test_table_mirror_plane_components_vanish(models, kind):
    """On w_t = 0 (tilt within the radial plane) F_t, tau_r, tau_z are zero by
    symmetry; those nodes are computed, not mirrored."""
    values = models[kind].table.values
    on_plane = values[:, :, :, values.shape[3] // 2]
    for odd, even in ((1, 0), (3, 4), (5, 4)):
        assert np.abs(on_plane[..., odd]).max() < 1e-9 * np.abs(values[..., even]).max()


# --- the wrench matrix ----------------------------------------------------------

def test_wrench_matrix_contract(models):
    model = models["two_magnet"]
    X_AI = RigidTransform(RollPitchYaw(0.1, -0.2, 0.7), [0.01, -0.02, 0.03])
    matrix = model.wrench_matrix(X_AI)
    assert isinstance(model, MagneticsModel)
    assert matrix.shape == (6, 27) == (6, model.n_coils)
    np.testing.assert_array_equal(
        matrix, model.wrench_matrix_from(X_AI.translation(), X_AI.rotation().matrix()))


def test_positive_current_attracts_a_north_up_magnet(models):
    for model in models.values():
        force, torque = model.coil_magnet_wrench([0.0, 0.0, 0.025], [0.0, 0.0, 1.0])
        assert force[2] < -0.1 and np.abs(force[:2]).max() < 1e-9 and np.abs(torque).max() < 1e-9
        # A magnet of the level instrument right above the centre coil (13): that
        # coil pulls hardest (distant coils' return field pushes up instead).
        p_AI = model.p_ACj[13] - model.p_IM[0] + [0.0, 0.0, 0.025]
        matrix = model.wrench_matrix_from(p_AI, np.eye(3))
        assert matrix[2, 13] < 0 and np.argmin(matrix[2]) == 13


@pytest.mark.parametrize("kind", KINDS)
def test_yaw_about_the_centre_coil_permutes_columns(models, kind):
    """Turning the instrument 60 deg about the centre coil (at A's origin) maps
    each coil of a hexagonal lattice onto a neighbour: W_sigma(j)(R X) = R W_j(X).
    (The default row spacing, 22.517 mm, is 0.3 um off the exact lattice.)"""
    pitch = 0.026
    config = DeviceConfig(instrument=kind, array=CoilArraySpec(
        pitch_m=pitch, row_spacing_m=pitch * math.sqrt(3) / 2))
    model = MagneticsModel(config, models[kind].table)
    yaw = rotation_z(math.radians(60.0))
    p_AI = np.array([0.004, -0.003, 0.028])
    R_AI = RotationMatrix(RollPitchYaw(0.15, -0.1, 0.3)).matrix()
    before = model.wrench_matrix_from(p_AI, R_AI)
    after = model.wrench_matrix_from(yaw @ p_AI, yaw @ R_AI)
    rotated_coils = model.p_ACj @ yaw.T
    mapped = 0
    for j, p in enumerate(rotated_coils):
        distances = np.linalg.norm(model.p_ACj - p, axis=1)
        target = int(np.argmin(distances))
        if distances[target] < 1e-9:
            np.testing.assert_allclose(after[:3, target], yaw @ before[:3, j], atol=1e-10)
            np.testing.assert_allclose(after[3:, target], yaw @ before[3:, j], atol=1e-12)
            mapped += 1
    assert mapped >= 13


@pytest.mark.parametrize("kind", KINDS)
def test_any_yaw_matches_a_rotated_array(models, kind):
    """Yawing the instrument by psi equals turning the array by -psi, rotated back."""
    model = models[kind]
    psi = 0.83
    yaw = rotation_z(psi)
    p_AI = np.array([0.01, 0.005, 0.03])
    R_tilt = RotationMatrix(RollPitchYaw(0.2, 0.1, 0.0)).matrix()
    yawed = model.wrench_matrix_from(p_AI, yaw @ R_tilt)
    turned = MagneticsModel(model.config, model.table)
    turned.p_ACj = np.ascontiguousarray(p_AI + (model.p_ACj - p_AI) @ yaw)  # R(-psi) about p_AI
    reference = turned.wrench_matrix_from(p_AI, R_tilt)
    np.testing.assert_allclose(yawed[:3], yaw @ reference[:3], atol=1e-9)
    np.testing.assert_allclose(yawed[3:], yaw @ reference[3:], atol=1e-11)


def test_columns_sum_the_magnets_about_the_instrument_origin(models):
    model = models["four_magnet"]
    p_AI = np.array([0.005, 0.01, 0.027])
    R_AI = RotationMatrix(RollPitchYaw(0.1, 0.2, -0.4)).matrix()
    matrix = model.wrench_matrix_from(p_AI, R_AI)
    for j in (0, 13, 26):
        expected = np.zeros(6)
        for p_IM in model.p_IM:
            r = R_AI @ p_IM
            force, torque = model.coil_magnet_wrench(p_AI + r - model.p_ACj[j], R_AI[:, 2])
            expected += np.concatenate([force, torque + np.cross(r, force)])
        np.testing.assert_allclose(matrix[:, j], expected, rtol=1e-12, atol=1e-15)


def test_hover_currents_match_the_design_estimate(models):
    """2-magnet instrument level over the array centre, magnet centres 25-30 mm up:
    The reference device (docs/device_model.md) expects ~1.3-1.7 A in the busiest coil, 30-60 W in all."""
    config = DeviceConfig()
    weight = np.array([0.0, 0.0, config.instrument_spec().mass_kg * GRAVITY, 0.0, 0.0, 0.0])
    resistance = config.coil.resistance_ohm
    for height, (current_range, power_range) in {0.025: ((1.2, 1.45), (25.0, 35.0)),
                                                 0.030: ((1.6, 1.9), (52.0, 70.0))}.items():
        matrix = models["two_magnet"].wrench_matrix_from(np.array([0, 0, height]), np.eye(3))
        currents = np.linalg.pinv(matrix) @ weight
        np.testing.assert_allclose(matrix @ currents, weight, atol=1e-9)
        assert current_range[0] < np.abs(currents).max() < current_range[1]
        assert power_range[0] < resistance * np.sum(currents**2) < power_range[1]
    for model in models.values():
        assert np.linalg.matrix_rank(model.wrench_matrix_from(np.array([0, 0, 0.03]),
                                                              np.eye(3))) == 6


def test_pairs_beyond_the_cutoffs_contribute_nothing(models):
    model = models["two_magnet"]
    cutoffs = model.cutoffs()
    up = [0.0, 0.0, 1.0]
    far = cutoffs["rho_max_m"] * 1.01
    assert not np.any(model.coil_magnet_wrench([far, 0.0, 0.03], up)[0])
    assert not np.any(model.coil_magnet_wrench([0.0, 0.0, cutoffs["z_max_m"] * 1.01], up)[0])
    assert np.any(model.coil_magnet_wrench([0.0, 0.0, cutoffs["z_max_m"] * 0.99], up)[0])


def test_bad_poses_raise_clear_errors(models):
    model = models["two_magnet"]
    with pytest.raises(ValueError, match="p_AI"):
        model.wrench_matrix_from(np.array([0.0, np.nan, 0.03]), np.eye(3))
    with pytest.raises(ValueError, match="R_AI"):
        model.wrench_matrix_from(np.array([0.0, 0.0, 0.03]), 2 * np.eye(3))
    with pytest.raises(ValueError, match="R_AI"):
        model.wrench_matrix_from(np.array([0.0, 0.0, 0.03]), np.eye(3)[:, :2])
    with pytest.raises(ValueError, match="u_C"):
        model.coil_magnet_wrench([0.0, 0.0, 0.03], [0.0, 0.0, 2.0])
    with pytest.raises(ValueError, match="p_CM"):
        model.coil_magnet_wrench([0.0, np.inf, 0.03], [0.0, 0.0, 1.0])


def test_bench_runs(models):
    for kind in KINDS:
        result = bench_wrench_matrix(DeviceConfig(instrument=kind), n=300)
        print(f"\n{kind}: {result}")
        assert result["pairs"] == 27 * len(models[kind].p_IM)
        assert result["mean_us"] > 0


# --- table build and cache -------------------------------------------------------

COARSE_GRID = WrenchGrid(rho_max_m=0.05, rho_step=0.5, z_min_m=0.02, z_max_m=0.05,
                         z_log_step=0.4, tilt_max_rad=math.radians(20.0),
                         tilt_step_rad=math.radians(10.0))


def test_table_cache_round_trip(tmp_path, monkeypatch):
    monkeypatch.setenv("MAGLEV_CACHE_DIR", str(tmp_path))
    magnet = default_instrument("four_magnet").magnet
    built = load_wrench_table(COIL, magnet, COARSE_GRID, progress=False)
    assert len(list(tmp_path.glob("wrench_table_*.npz"))) == 1
    loaded = load_wrench_table(COIL, magnet, COARSE_GRID, progress=False)
    np.testing.assert_array_equal(built.values, loaded.values)
    np.testing.assert_array_equal(built.axes, loaded.axes)
    # A different magnet is a different table.
    load_wrench_table(COIL, default_instrument("two_magnet").magnet, COARSE_GRID, progress=False)
    assert len(list(tmp_path.glob("wrench_table_*.npz"))) == 2


def test_table_nodes_are_charge_model_wrenches(tmp_path, monkeypatch):
    monkeypatch.setenv("MAGLEV_CACHE_DIR", str(tmp_path))
    magnet = default_instrument("four_magnet").magnet
    table = load_wrench_table(COIL, magnet, COARSE_GRID, progress=False)
    charge = ChargeModel(COIL, magnet)
    rho_nodes, z_nodes, w_nodes = (axis_nodes(a) for a in table.axes[:3])
    for i, j, k, m in ((1, 0, 0, 4), (2, 1, 3, 1), (0, 1, 2, 2)):
        p = np.array([rho_nodes[i], 0.0, z_nodes[j]])
        u = np.array(tilt_axis(w_nodes[k], w_nodes[m]))
        np.testing.assert_allclose(table.values[i, j, k, m], charge.wrench(p, u),
                                   rtol=2e-4, atol=1e-4 * np.abs(table.values[:, j]).max())

