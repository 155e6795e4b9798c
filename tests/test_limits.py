"""Device limits: the LP's currents, the limits' shape, symmetry, bad input."""

import warnings

import numpy as np
import pytest

from maglev_haptics.hardware import DeviceConfig, load_magnetics
from maglev_haptics.hardware.limits import (
    AXIS_DIRECTIONS, coil_current_limit_a, device_limits, hover_current_a,
    hover_workspace_A, max_added_wrench, weight_wrench)
from maglev_haptics.hardware.thermal import coil_thermal, continuous_current_limit_a

CONFIG = DeviceConfig()
LEVEL = np.eye(3)
WRENCH_DIRECTIONS = np.zeros((12, 6))
WRENCH_DIRECTIONS[:6, :3] = AXIS_DIRECTIONS
WRENCH_DIRECTIONS[6:, 3:] = AXIS_DIRECTIONS


@pytest.fixture(scope="module")
def model():
    return load_magnetics(CONFIG)


@pytest.fixture(scope="module")
def workspace(model):
    return hover_workspace_A(CONFIG, coil_current_limit_a(CONFIG, "thermal"), model)


def matrix(model, x=0.0, y=0.0, z=0.025):
    return model.wrench_matrix_from(np.array([x, y, z]), LEVEL)


def test_lp_currents_respect_limits_and_achieve_the_wrench(model):
    rotation = np.array([[np.cos(0.3), 0, np.sin(0.3)], [0, 1, 0], [-np.sin(0.3), 0, np.cos(0.3)]])
    A = model.wrench_matrix_from(np.array([0.012, -0.007, 0.027]), rotation)
    weight = weight_wrench(CONFIG)
    directions = np.vstack([WRENCH_DIRECTIONS, [1.0, 2.0, -0.5, 0.01, 0.0, -0.02]])
    added, currents = max_added_wrench(A, weight, directions, 2.0)
    assert np.all(added > 0)
    assert np.max(np.abs(currents)) <= 2.0 + 1e-9
    units = directions / np.linalg.norm(directions, axis=1)[:, None]
    targets = weight + added[:, None] * units
    assert np.allclose(currents @ A.T, targets, rtol=0, atol=1e-6)
    # Optimal: every maximum pins some coil at the limit.
    assert np.all(np.max(np.abs(currents), axis=1) > 2.0 - 1e-6)


def test_the_lp_raises_no_warning(model):
    # scipy deprecates building sparse matrices from dense blocks (the sparse array interface).
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        max_added_wrench(matrix(model), weight_wrench(CONFIG), WRENCH_DIRECTIONS, 2.0)
        hover_current_a(matrix(model), weight_wrench(CONFIG))


def test_limits_from_peak_and_thermal_currents():
    assert coil_current_limit_a(CONFIG, "peak") == CONFIG.amplifier.current_limit_a
    assert coil_current_limit_a(CONFIG, "thermal") == pytest.approx(
        continuous_current_limit_a(coil_thermal(CONFIG)))


def test_force_limit_shrinks_with_height_and_away_from_the_coils(model, workspace):
    def limits(**where):
        p = np.array([where.get("x", 0.0), 0.0, where.get("z", 0.025)])
        return device_limits(CONFIG, p, LEVEL, magnetics=model, workspace=workspace)
    low, middle, high = (limits(z=z) for z in (0.02, 0.025, 0.03))
    for name in ("force_plus_n", "force_minus_n", "torque_plus_nm", "torque_minus_nm"):
        assert np.all(getattr(low, name) > getattr(middle, name))
        assert np.all(getattr(middle, name) > getattr(high, name))
    # Towards the array's edge (outermost coil centres at x = +/-65 mm) less is
    # left; at 60 mm the thermal limit no longer carries the weight.
    edge = limits(x=0.05)
    assert np.all(edge.force_plus_n < middle.force_plus_n)
    assert 0 < edge.max_force_n < middle.max_force_n


@pytest.mark.parametrize("limit", ["peak", "thermal"])
def test_level_two_magnet_limits_are_symmetric_at_the_centre(model, limit):
    limits = device_limits(CONFIG, np.array([0.0, 0.0, 0.025]), LEVEL, limit=limit,
                           magnetics=model, workspace=((0, 0, 0), (0, 0, 0)))
    plus_minus = [(limits.force_plus_n[:2], limits.force_minus_n[:2]),
                  (limits.torque_plus_nm, limits.torque_minus_nm)]
    for plus, minus in plus_minus:
        assert np.allclose(plus, minus, rtol=1e-3, atol=0)
    # Downward, the coils may also drop the weight they were carrying.
    assert limits.force_minus_n[2] > limits.force_plus_n[2] + weight_wrench(CONFIG)[2] - 1e-6


def test_limit_exactly_the_hover_requirement_leaves_nothing_extra(model):
    A = matrix(model)
    weight = weight_wrench(CONFIG)
    needed = hover_current_a(A, weight)
    assert 0 < needed < coil_current_limit_a(CONFIG, "thermal")
    added, currents = max_added_wrench(A, weight, WRENCH_DIRECTIONS, needed)
    # Lowering the weight (-z) is the one direction that does not need more current.
    assert added[5] == pytest.approx(2 * weight[2], rel=1e-6)
    assert np.allclose(np.delete(added, 5), 0, atol=1e-6)
    assert np.max(np.abs(currents)) <= needed + 1e-9
    with pytest.raises(ValueError, match="base_wrench"):
        max_added_wrench(A, weight, WRENCH_DIRECTIONS, 0.99 * needed)


def test_workspace_covers_the_array_and_the_hover_range(model, workspace):
    lower, upper = workspace
    assert np.allclose(lower[:2], [-0.0775, -0.0575], atol=1e-4)
    assert np.allclose(upper[:2], [0.0775, 0.0575], atol=1e-4)
    rest = CONFIG.display.thickness_m + CONFIG.instrument_spec().rest_height_m
    assert lower[2] == pytest.approx(rest)
    limit = coil_current_limit_a(CONFIG, "thermal")
    weight = weight_wrench(CONFIG)
    assert hover_current_a(matrix(model, z=upper[2]), weight) <= limit
    assert hover_current_a(matrix(model, z=upper[2] + 2e-4), weight) > limit
    peak_upper = hover_workspace_A(CONFIG, coil_current_limit_a(CONFIG, "peak"), model)[1]
    assert peak_upper[2] > upper[2]


def test_no_hover_means_no_force(model):
    limits = device_limits(CONFIG, np.array([0.0, 0.0, 0.06]), LEVEL, magnetics=model,
                           workspace=((0, 0, 0), (0, 0, 0)))
    assert not limits.can_hover
    assert limits.max_force_n == 0 and limits.max_torque_nm == 0


def test_bad_input_names_the_argument(model):
    A = matrix(model)
    weight = weight_wrench(CONFIG)
    with pytest.raises(ValueError, match="p_AI"):
        device_limits(CONFIG, np.array([np.nan, 0, 0.02]), LEVEL, magnetics=model)
    with pytest.raises(ValueError, match="R_AI"):
        device_limits(CONFIG, np.array([0, 0, 0.02]), 2 * LEVEL, magnetics=model)
    with pytest.raises(ValueError, match="directions"):
        max_added_wrench(A, weight, [[1, 0, 0, 0, 0, 0], [0] * 6], 2.0)
    with pytest.raises(ValueError, match="current_limit_a"):
        max_added_wrench(A, weight, WRENCH_DIRECTIONS, -1.0)
    with pytest.raises(ValueError, match="current_limit_a"):
        hover_workspace_A(CONFIG, -1.0, model)
    with pytest.raises(ValueError, match="limit"):
        coil_current_limit_a(CONFIG, "sustained")
