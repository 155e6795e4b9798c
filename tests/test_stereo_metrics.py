"""Head speed from a run's log: a still head reads exactly 0, not differencing round-off."""

import numpy as np

from maglev_haptics.analysis.stereo_metrics import SPEED_RESOLUTION_M_S, head_speed

LOG_PERIOD_S = 1e-3


def test_a_still_head_with_round_off_in_its_logged_position_has_zero_speed():
    rng = np.random.default_rng(0)
    samples = 1000
    t = np.arange(samples) * LOG_PERIOD_S
    position_m = np.array([0.0, -0.30, 0.45])
    # One unit in the last place of jitter, as a pose recomputed from the script each tick has.
    jitter_m = np.spacing(position_m) * rng.integers(-1, 2, size=(samples, 3))
    head_pose = np.hstack([position_m + jitter_m, np.zeros((samples, 5))])
    assert np.all(head_speed({"t": t, "head_pose": head_pose}) == 0.0)


def test_a_moving_head_keeps_its_speed():
    t = np.arange(1000) * LOG_PERIOD_S
    speed_m_s = 10 * SPEED_RESOLUTION_M_S
    head_pose = np.zeros((len(t), 8))
    head_pose[:, 0] = speed_m_s * t
    np.testing.assert_allclose(head_speed({"t": t, "head_pose": head_pose}), speed_m_s, rtol=1e-9)
