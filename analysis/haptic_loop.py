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


def _plant_blocks(p: LoopParameters):
    """(Phi, Gamma_early, Gamma_late, n): over one period the plant state [x, x'] maps
    by Phi, the force sampled n periods ago adds Gamma_early, the one before it
    Gamma_late (the delay is (n - 1 + f) T with 0 < f <= 1, or n = 0 for none)."""
    A = np.array([[0.0, 1.0],
                  [-p.hand_stiffness / p.mass_kg,
                   -(p.device_damping + p.hand_damping) / p.mass_kg]])
    B = np.array([0.0, 1.0 / p.mass_kg])
    T = p.period_s

    def exp_and_integral(duration):
        # [[A, B], [0, 0]] exponentiated gives e^{A t} and int_0^t e^{A s} B ds together.
        M = np.zeros((3, 3))
        M[0:2, 0:2] = A
        M[0:2, 2] = B
        E = scipy.linalg.expm(M * duration)
        return E[0:2, 0:2], E[0:2, 2]

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
    """The loop's one-period map (square matrix) for the state
    [x, x', x_{k-1}, v, f_{k-1}, ..., f_{k-n-1}]."""
    Phi, Gamma_early, Gamma_late, whole = _plant_blocks(p)
    T, K, B = p.period_s, p.stiffness, p.damping
    a = filter_coefficient(p)
    n_forces = whole + 1  # f_{k-1} .. f_{k-whole-1}
    size = 4 + n_forces
    # The force computed this period from the state (x_k and the filter's inputs):
    # v_k = a v_{k-1} + (1 - a)(x_k - x_{k-1}) / T, f_k = -(K x_k + B v_k).
    v_row = np.zeros(size)
    v_row[0] = (1 - a) / T
    v_row[2] = -(1 - a) / T
    v_row[3] = a
    f_row = -K * np.eye(size)[0] - B * v_row
    def force(age):
        """The row giving the force of this age: f_k (0) is f_row, f_{k-j} is state 3 + j."""
        return f_row if age == 0 else np.eye(size)[4 + age - 1]

    M = np.zeros((size, size))
    M[0:2, 0:2] = Phi
    M[0:2] += np.outer(Gamma_early, force(whole)) + np.outer(Gamma_late, force(whole + 1))
    M[2, 0] = 1.0  # x_{k-1} <- x_k
    M[3] = v_row
    M[4] = f_row  # f_{k-1} <- f_k
    for j in range(1, n_forces):
        M[4 + j, 4 + j - 1] = 1.0
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
