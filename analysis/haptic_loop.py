"""The sampled 1-DOF haptic loop, exactly discretized: the model behind the
passivity, Z-width and stability-map studies.

Continuous side (one axis): the instrument and the hand holding it,

    m x'' = -(b_device + b_hand) x' - k_hand x + f,

with f the device's force, held over each period T (zero-order hold) and
applied ``delay_s`` after its sample (tracker latency plus computation; any
real delay, fractional samples included, by the modified z-transform).
Discrete side, every T: the virtual environment (the coupling spring K and
damper B) on the sampled position, its velocity a backward difference low-
passed to ``velocity_filter_hz`` (first order), as the coupling does:

    v_k = a v_{k-1} + (1 - a) (x_k - x_{k-1}) / T,   f_k = -(K x_k + B v_k).

The loop's state is [x, x', x_{k-1}, v, f_{k-1} .. f_{k-n}] with n the
samples the delay spans; it is stable iff the spectral radius of its one-period
map is below 1.

A maglev device has almost no damping of its own (b_device ~ 0): the
Colgate-Schenkel condition b > K T / 2 + |B| then fails for any K, and what keeps
the loop stable is the hand's damping and the controller's.
"""

import math
from dataclasses import dataclass, replace
from typing import Optional

import numpy as np
import scipy.linalg
import scipy.signal


@dataclass(frozen=True)
class LoopParameters:
    mass_kg: float = 0.375  # instrument (0.125) and hand (0.25) moving together (kg)
    device_damping: float = 0.0  # N s/m: a levitated instrument has none to speak of
    # The simulated hand's arm (systems/hand.py HandImpedanceConfig); its grip, 2000 N/m,
    # is taken as rigid: its 25 Hz mode is far above the loop's.
    hand_damping: float = 8.0  # N s/m
    hand_stiffness: float = 300.0  # N/m
    # The grip between them (N/m, N s/m) and the hand's own mass (kg): when set, the
    # instrument (mass_kg alone then) hangs on the grip from the hand, which hangs on
    # the arm; the grip's mode decides the loop's stability at high stiffness. None:
    # hand and instrument move as one body of mass_kg.
    grip_stiffness: Optional[float] = None
    grip_damping: float = 0.0
    hand_mass_kg: float = 0.25
    stiffness: float = 400.0  # K of the virtual environment (N/m)
    damping: float = 5.0  # B (N s/m)
    period_s: float = 1e-3  # T
    delay_s: float = 2.5e-3  # sample to force (s)
    velocity_filter_hz: float = 30.0  # corner of the first-order low-pass on the velocity (Hz); inf: none


def filter_coefficient(parameters: LoopParameters) -> float:
    """a of the velocity low-pass v_k = a v_{k-1} + (1 - a) u_k (0: no filter)."""
    if math.isinf(parameters.velocity_filter_hz):
        return 0.0
    return math.exp(-2 * math.pi * parameters.velocity_filter_hz * parameters.period_s)


def plant_matrices(p: LoopParameters):
    """(A, B) of the continuous side, x' = A x + B f: state [x, x'] of the instrument
    (and hand) or, with a grip, [x, x', x_hand, x_hand']; f on the instrument."""
    if p.grip_stiffness is None:
        A = np.array([[0.0, 1.0],
                      [-p.hand_stiffness / p.mass_kg,
                       -(p.device_damping + p.hand_damping) / p.mass_kg]])
        return A, np.array([0.0, 1.0 / p.mass_kg])
    m, mh = p.mass_kg, p.hand_mass_kg
    kg, bg = p.grip_stiffness, p.grip_damping
    A = np.array([
        [0.0, 1.0, 0.0, 0.0],
        [-kg / m, -(bg + p.device_damping) / m, kg / m, bg / m],
        [0.0, 0.0, 0.0, 1.0],
        [kg / mh, bg / mh, -(kg + p.hand_stiffness) / mh, -(bg + p.hand_damping) / mh]])
    return A, np.array([0.0, 1.0 / m, 0.0, 0.0])


def _plant_blocks(p: LoopParameters):
    """(Phi, Gamma_early, Gamma_late, n): over one period the plant state [x, x'] maps
    by Phi, the force sampled n periods ago adds Gamma_early, the one before it
    Gamma_late (the delay is (n - 1 + f) T with 0 < f <= 1, or n = 0 for none)."""
    A, B = plant_matrices(p)
    n = len(A)
    T = p.period_s

    def exp_and_integral(duration):
        # [[A, B], [0, 0]] exponentiated gives e^{A t} and int_0^t e^{A s} B ds together.
        M = np.zeros((n + 1, n + 1))
        M[0:n, 0:n] = A
        M[0:n, n] = B
        E = scipy.linalg.expm(M * duration)
        return E[0:n, 0:n], E[0:n, n]

    Phi, _ = exp_and_integral(T)
    samples = p.delay_s / T
    whole = math.floor(samples + 1e-12)
    fraction = samples - whole
    # The force sampled `whole` periods ago acts from fraction T into this period;
    # the one before it until then.
    _, G_first = exp_and_integral(fraction * T)
    E_rest, G_rest = exp_and_integral(T - fraction * T)
    Gamma_early = G_rest  # acts over the last (1 - f) T of the period
    Gamma_late = E_rest @ G_first  # acted over the first f T, then carried
    return Phi, Gamma_early, Gamma_late, whole


def closed_loop_matrix(p: LoopParameters) -> np.ndarray:
    """The loop's one-period map (square matrix) for the state [plant (x first),
    x_{k-1}, v, f_{k-1}, ..., f_{k-n-1}]."""
    Phi, Gamma_early, Gamma_late, whole = _plant_blocks(p)
    T, K, B = p.period_s, p.stiffness, p.damping
    a = filter_coefficient(p)
    n = len(Phi)  # plant states, x first
    n_forces = whole + 1  # f_{k-1} .. f_{k-whole-1}
    size = n + 2 + n_forces
    previous, filtered, forces = n, n + 1, n + 2  # where x_{k-1}, v and f_{k-1} sit
    # The force computed this period from the state (x_k and the filter's inputs):
    # v_k = a v_{k-1} + (1 - a)(x_k - x_{k-1}) / T, f_k = -(K x_k + B v_k).
    v_row = np.zeros(size)
    v_row[0] = (1 - a) / T
    v_row[previous] = -(1 - a) / T
    v_row[filtered] = a
    f_row = -K * np.eye(size)[0] - B * v_row

    def force(age):
        """The row giving the force of this age: f_k (0) is f_row, f_{k-j} a state."""
        return f_row if age == 0 else np.eye(size)[forces + age - 1]

    M = np.zeros((size, size))
    M[0:n, 0:n] = Phi
    M[0:n] += np.outer(Gamma_early, force(whole)) + np.outer(Gamma_late, force(whole + 1))
    M[previous, 0] = 1.0  # x_{k-1} <- x_k
    M[filtered] = v_row
    M[forces] = f_row  # f_{k-1} <- f_k
    for j in range(1, n_forces):
        M[forces + j, forces + j - 1] = 1.0
    return M


def spectral_radius(p: LoopParameters) -> float:
    return float(np.max(np.abs(np.linalg.eigvals(closed_loop_matrix(p)))))


def is_stable(p: LoopParameters) -> bool:
    return spectral_radius(p) < 1.0


def critical_stiffness(p: LoopParameters, *, upper: float = 1e7, rtol: float = 1e-4) -> float:
    """The largest stable K (N/m) for the other parameters of ``p``: bisection on the
    spectral radius. 0 when even K = 0 is unstable; ``upper`` when every K below it is
    stable. Assumes one stable interval (0, K_crit), as for a damped mass."""
    # Not K = 0 itself: without hand stiffness a free mass's position is marginal
    # (a pole at 1), which any K > 0 pulls inside.
    if not is_stable(replace(p, stiffness=rtol)):
        return 0.0
    if is_stable(replace(p, stiffness=upper)):
        return upper
    low, high = 0.0, upper
    while high - low > rtol * high:
        middle = 0.5 * (low + high)
        if is_stable(replace(p, stiffness=middle)):
            low = middle
        else:
            high = middle
    return low


def environment_impedance(p: LoopParameters, *, whole_samples_delay: bool = True):
    """The rendered environment as a ``scipy.signal.dlti``: force over displacement,
    (K + B LP(z) (1 - 1/z) / T) z^-d, the delay rounded up to whole samples (a
    fractional delay is not rational in z; rounding up is the conservative side)."""
    T, K, B = p.period_s, p.stiffness, p.damping
    a = filter_coefficient(p)
    d = math.ceil(p.delay_s / T - 1e-9) if whole_samples_delay else 0
    # (K (z - a) + B (1 - a) (z - 1) / T) / (z - a), times z^-d.
    numerator = np.polyadd(np.polymul([K], [1.0, -a]), np.polymul([B * (1 - a) / T], [1.0, -1.0]))
    denominator = np.polymul([1.0, -a], [1.0] + [0.0] * d)
    return scipy.signal.dlti(numerator, denominator, dt=T)
