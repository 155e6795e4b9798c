"""passivity_margin against Colgate and Schenkel's closed form, and for environments
with delay and filtering against a brute-force evaluation of the same condition."""

import math

import numpy as np
import pytest
import scipy.signal

from maglev_haptics.analysis.passivity import passivity_margin


def virtual_wall(K, B, T, delay_samples=0):
    """H(z) = (K + B (1 - 1/z) / T) z^-d: spring K (N/m), backward-difference damper
    B (N s/m), sampled every T (s), d samples late."""
    # In powers of z: (K + B/T) z - B/T over z^(1 + d).
    numerator = [K + B / T, -B / T]
    denominator = [1.0, 0.0] + [0.0] * delay_samples
    return scipy.signal.dlti(numerator, denominator, dt=T)


@pytest.mark.parametrize("T", [1e-3, 1 / 860, 5e-3])
@pytest.mark.parametrize("K", [100.0, 1000.0, 5000.0])
@pytest.mark.parametrize("B", [-2.0, 0.0, 0.5, 3.0])
def test_virtual_wall_matches_colgate_schenkel(K, B, T):
    closed_form = K * T / 2 + abs(B)
    b = 0.7 * closed_form + 0.1
    assert passivity_margin(virtual_wall(K, B, T), b) == pytest.approx(
        b - closed_form, rel=0.01, abs=1e-9 * closed_form)


def brute_force_needed_damping(H, n=200_001):
    """max over 0 < wT <= pi of (T/2)/(1 - cos wT) Re{(1 - e^{-jwT}) H(e^{jwT})},
    evaluated directly from H's polynomials on a very fine grid."""
    theta = np.linspace(1e-3, math.pi, n)
    z = np.exp(1j * theta)
    num, den = np.ravel(H.num), np.ravel(H.den)
    response = np.polyval(num, z) / np.polyval(den, z)
    return np.max(H.dt / 2 / (1 - np.cos(theta)) * np.real((1 - 1 / z) * response))


def test_delay_needs_more_damping_than_the_closed_form():
    K, B, T = 2000.0, 1.0, 1e-3
    margins = [passivity_margin(virtual_wall(K, B, T, d), 5.0) for d in range(4)]
    assert margins[0] == pytest.approx(5.0 - (K * T / 2 + B), rel=1e-6)
    assert all(later < earlier for earlier, later in zip(margins, margins[1:]))
    for d in range(4):
        H = virtual_wall(K, B, T, d)
        assert 5.0 - margins[d] == pytest.approx(brute_force_needed_damping(H), rel=1e-6)


def test_filtered_damper_against_brute_force():
    """A damper whose velocity passes a first-order low-pass (as the coupling's), and
    a second-order Butterworth on the whole force: any discrete H, not only the wall."""
    T, K, B = 1e-3, 800.0, 2.0
    a = math.exp(-2 * math.pi * 50 * T)  # 50 Hz low-pass on the velocity
    # F = K x + B (1 - a) / (1 - a/z) * (1 - 1/z) / T x
    wall = scipy.signal.dlti(
        np.polyadd(np.polymul([K], [1.0, -a]), np.polymul([B * (1 - a) / T], [1.0, -1.0])),
        [1.0, -a], dt=T)
    butter_num, butter_den = scipy.signal.butter(2, 100, fs=1 / T)
    filtered = scipy.signal.dlti(np.polymul(np.ravel(wall.num), butter_num),
                                 np.polymul(np.ravel(wall.den), butter_den), dt=T)
    for H in (wall, filtered):
        needed = brute_force_needed_damping(H)
        assert 1.0 - passivity_margin(H, 1.0) == pytest.approx(needed, rel=1e-6)
    assert brute_force_needed_damping(filtered) > brute_force_needed_damping(wall)


def test_bad_input_is_named():
    with pytest.raises(ValueError, match="must be a discrete-time scipy.signal.dlti"):
        passivity_margin(scipy.signal.lti([1.0], [1.0, 1.0]), 1.0)
    with pytest.raises(ValueError, match="device_damping = nan"):
        passivity_margin(virtual_wall(100.0, 0.0, 1e-3), float("nan"))
    with pytest.raises(ValueError, match="on or outside the unit circle"):
        passivity_margin(scipy.signal.dlti([1.0], [1.0, -1.0], dt=1e-3), 1.0)  # an integrator
