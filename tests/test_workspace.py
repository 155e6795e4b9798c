"""Workspace study: pose metrics against hardware.limits and the allocator, the
limits' ordering, mirror symmetry, the glass, and the quick study end to end."""

import json

import numpy as np
import pytest
from pydrake.math import RollPitchYaw

from maglev_haptics.analysis.workspace import (
    DIRECTIONS, WorkspaceSettings, plot_workspace, pose_metrics, workspace_study)
from maglev_haptics.hardware import DeviceConfig, load_magnetics
from maglev_haptics.hardware.limits import (
    LIMIT_KINDS, device_limits, hover_workspace_A, weight_wrench)
from maglev_haptics.systems.current_allocator import allocate_currents

CONFIG = DeviceConfig()
LEVEL = np.eye(3)
# Mirroring x -> -x swaps the +-x forces, keeps the others, and (torque being a
# pseudovector) keeps the torque about x but swaps the signs of those about y and z.
FORCE_MIRROR = {"+x": "-x", "-x": "+x", "+y": "+y", "-y": "-y", "+z": "+z", "-z": "-z"}
TORQUE_MIRROR = {"+x": "+x", "-x": "-x", "+y": "-y", "-y": "+y", "+z": "-z", "-z": "+z"}


@pytest.fixture(scope="module")
def model():
    return load_magnetics(CONFIG)


@pytest.fixture(scope="module")
def quick():
    """(results, progress calls) of the quick study."""
    calls = []
    results = workspace_study(WorkspaceSettings.quick(),
                              progress=lambda done, total: calls.append((done, total)))
    return results, calls


def test_centre_hover_agrees_with_limits_and_allocator(model):
    p_WI = np.array([0.0, 0.0, 0.020])
    metrics = pose_metrics(model, CONFIG, p_WI, LEVEL)
    p_AI = p_WI - CONFIG.p_WA
    A = model.wrench_matrix_from(p_AI, LEVEL)
    currents, shortfall, n_saturated = allocate_currents(
        A, weight_wrench(CONFIG), CONFIG.amplifier.current_limit_a)
    assert n_saturated == 0 and np.linalg.norm(shortfall) < 1e-9
    assert metrics["hover_current_a"] == pytest.approx(np.max(np.abs(currents)), rel=1e-9)
    # CoilSpec.resistance_ohm is the resistance at 20 C (the thermal model's reference).
    assert CONFIG.thermal.resistance_reference_temperature_c == 20.0
    assert metrics["hover_power_w"] == pytest.approx(
        np.sum(currents**2) * CONFIG.coil.resistance_ohm, rel=1e-9)
    # The 2-magnet instrument's lever length is its magnets' 20 mm offset from I.
    scaled = np.vstack([A[:3], A[3:] / 0.020])
    assert metrics["condition_number"] == pytest.approx(np.linalg.cond(scaled), rel=1e-9)
    for limit in LIMIT_KINDS:
        limits = device_limits(CONFIG, p_AI, LEVEL, limit=limit, magnetics=model)
        assert limits.can_hover
        assert metrics["hover_current_minmax_a"] == pytest.approx(limits.hover_current_a, rel=1e-6)
        forces = [metrics["max_force_n"][limit][d] for d in DIRECTIONS]
        torques = [metrics["max_torque_nm"][limit][d] for d in DIRECTIONS]
        assert np.allclose(forces, np.r_[limits.force_plus_n, limits.force_minus_n],
                           rtol=1e-6, atol=1e-9)
        assert np.allclose(torques, np.r_[limits.torque_plus_nm, limits.torque_minus_nm],
                           rtol=1e-6, atol=1e-9)


def test_thermal_limit_forces_never_exceed_peak_ones(quick):
    results, _ = quick
    n_compared = n_lower = 0
    for data in results["instruments"].values():
        for data_slice in data["slices"].values():
            for key in ("max_force_n", "max_torque_nm"):
                for d in DIRECTIONS:
                    peak = np.array(data_slice["maps"][key]["peak"][d], dtype=float)
                    thermal = np.array(data_slice["maps"][key]["thermal"][d], dtype=float)
                    sustained = np.isfinite(thermal)
                    # Wherever it hovers within the thermal limit it hovers within the peak.
                    assert np.all(np.isfinite(peak[sustained]))
                    assert np.all(thermal[sustained] <= peak[sustained] + 1e-9)
                    n_compared += sustained.sum()
                    n_lower += np.sum(thermal[sustained] < 0.9 * peak[sustained])
    assert n_compared > 100 and n_lower > 0.5 * n_compared


def _mirrored(maps, key, mirror):
    return {d: np.array(maps[key][limit][mirror[d]], dtype=float)[..., ::-1]
            for limit in LIMIT_KINDS for d in DIRECTIONS}


def test_mirror_x_gives_mirrored_maps(quick):
    results, _ = quick
    for data in results["instruments"].values():
        xy = data["slices"]["xy"]
        assert np.allclose(xy["coordinates"]["x_m"], -np.array(xy["coordinates"]["x_m"])[::-1])
        maps = xy["maps"]
        for key in ("condition_number", "hover_current_a", "hover_power_w"):
            values = np.array(maps[key], dtype=float)
            assert np.allclose(values, values[..., ::-1], rtol=1e-6, equal_nan=True), key
        for key, mirror in (("max_force_n", FORCE_MIRROR), ("max_torque_nm", TORQUE_MIRROR)):
            for limit in LIMIT_KINDS:
                for d in DIRECTIONS:
                    values = np.array(maps[key][limit][d], dtype=float)
                    image = np.array(maps[key][limit][mirror[d]], dtype=float)[..., ::-1]
                    assert np.allclose(values, image, rtol=1e-5, atol=1e-7, equal_nan=True), \
                        (key, limit, d)


def test_mirror_x_of_a_tilted_pose(model):
    # Mirroring x -> -x turns roll r, pitch p, yaw y into roll r, pitch -p, yaw -y
    # for the instrument too (its magnets are mirror-symmetric in I's x).
    here = pose_metrics(model, CONFIG, np.array([0.017, -0.023, 0.021]),
                        RollPitchYaw(np.radians([8.0, 12.0, 25.0])).ToRotationMatrix().matrix())
    there = pose_metrics(model, CONFIG, np.array([-0.017, -0.023, 0.021]),
                         RollPitchYaw(np.radians([8.0, -12.0, -25.0])).ToRotationMatrix().matrix())
    assert np.isfinite(here["condition_number"])
    for key in ("base_clearance_m", "condition_number", "hover_current_a", "hover_power_w",
                "hover_current_minmax_a"):
        assert here[key] == pytest.approx(there[key], rel=1e-6), key
    for key, mirror in (("max_force_n", FORCE_MIRROR), ("max_torque_nm", TORQUE_MIRROR)):
        for limit in LIMIT_KINDS:
            for d in DIRECTIONS:
                assert here[key][limit][d] == pytest.approx(
                    there[key][limit][mirror[d]], rel=1e-5, abs=1e-7), (key, limit, d)


def test_pose_inside_the_glass_is_nan(model):
    def numbers(metrics):
        return np.array([metrics[k] for k in ("condition_number", "hover_current_a",
                                              "hover_current_minmax_a", "hover_power_w")]
                        + [v for key in ("max_force_n", "max_torque_nm")
                           for limit in LIMIT_KINDS for v in metrics[key][limit].values()])

    # Level 3 mm up, the 14 mm thick body is 4 mm into the glass.
    sunk = pose_metrics(model, CONFIG, np.array([0.0, 0.0, 0.003]), LEVEL)
    assert sunk["base_clearance_m"] == pytest.approx(0.003 - 0.007)
    assert np.all(np.isnan(numbers(sunk)))
    # At 15 mm level it hovers, but pitched 35 deg the 70 mm body's end dips into the glass.
    level = pose_metrics(model, CONFIG, np.array([0.0, 0.0, 0.015]), LEVEL)
    pitched = pose_metrics(model, CONFIG, np.array([0.0, 0.0, 0.015]),
                           RollPitchYaw(np.radians([0.0, 35.0, 0.0])).ToRotationMatrix().matrix())
    assert np.all(np.isfinite(numbers(level)))
    assert pitched["base_clearance_m"] < 0
    assert np.all(np.isnan(numbers(pitched)))


def test_quick_study_covers_both_instruments_and_writes_plots(quick, tmp_path):
    results, calls = quick
    assert set(results["instruments"]) == {"two_magnet", "four_magnet"}
    assert calls[-1][0] == calls[-1][1] == len(calls)
    # NaN is written as null: strict JSON, and the plots read it back.
    text = json.dumps(results, allow_nan=False)
    assert "null" in text
    loaded = json.loads(text)
    for kind, data in loaded["instruments"].items():
        summary = data["summary"]
        config = DeviceConfig(instrument=kind)
        assert summary["hover_ceiling_m"]["thermal"] < summary["hover_ceiling_m"]["peak"]
        _, upper = hover_workspace_A(config, data["current_limit_a"]["peak"])
        assert summary["hover_ceiling_m"]["peak"] == pytest.approx(upper[2] + config.p_WA[2])
        assert all(t <= p for t, p in zip(summary["hover_fraction_xy"]["thermal"],
                                          summary["hover_fraction_xy"]["peak"]))
        # The height slice starts below the resting height: inside the glass.
        assert data["slices"]["height"]["maps"]["hover_current_a"][0] is None
        condition = summary["condition_number"]
        assert condition["worst"]["value"] >= condition["best"] > 1
    paths = plot_workspace(loaded, tmp_path)
    assert len(paths) == 2 * 6
    for path in paths:
        assert path.parent == tmp_path
        data = path.read_bytes()
        assert data.startswith(b"\x89PNG") and len(data) > 10_000, path


def test_settings_are_checked():
    with pytest.raises(ValueError, match="instruments"):
        workspace_study(WorkspaceSettings(instruments=("three_magnet",)))
    with pytest.raises(ValueError, match="tilt_range_deg"):
        workspace_study(WorkspaceSettings(tilt_range_deg=(0.0, 60.0)))
