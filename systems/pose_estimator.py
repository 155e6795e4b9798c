"""Pose estimator (application): tracker markers -> instrument pose and velocity.

Each tracker sample is fitted by least squares (Kabsch: a 3x3 SVD with the
reflection guard) to the instrument's marker model p_IK; the fitted pose is the
output ``X_WI_measured``. The spatial velocity ``V_WI_measured`` comes from a
steady-state constant-velocity Kalman filter (an alpha-beta filter) run on the
three position axes and, through rotation-vector innovations, on the
orientation, so yaw is unlimited and has no angle wrapping.

Conventions: pose vector [qw, qx, qy, qz, x, y, z] (unit quaternion of R_WI,
p_WI in m); spatial velocity [wx, wy, wz, vx, vy, vz] in W (rad/s, m/s; v of
I's origin); markers as a flat (3 n,) vector of p_WK in m, NaN for a marker the
tracker does not see.

Numbers for the defaults (0.01 mm per coordinate, 860 Hz, the shipped 3-marker
triangle of radius 35 mm, 60 mm above I; ``bandwidth_hz`` = 50):

- fit noise at I's origin: 15.1 um in x and y, 5.8 um in z (22.2 um RMS, 3-D);
  orientation 0.233 mrad about x and y, 0.165 mrad about z (0.369 mrad RMS).
  The x/y position noise is the tilt noise times the 60 mm lever arm.
- filter: alpha = 0.403, beta = 0.103; closed-loop poles at 50 Hz, damping
  0.707. Velocity noise = 112 /s times the pose noise: 1.70 mm/s in x and y,
  0.65 mm/s in z, 26.2 mrad/s about x and y, 18.5 mrad/s about z.
- lag: the velocity estimate is the derivative through a 2nd-order low-pass at
  ``bandwidth_hz``; it trails a velocity ramp by 4.0 ms and lags 14.5 deg at
  10 Hz (gain 0.999). ``alpha_beta_gains`` and ``alpha_beta_noise_gains`` give
  these numbers for other settings. The tracker's latency and the sampling are
  extra.

Cost: the fit, the filter and the state update are one numba-compiled call
(``maglev bench`` lists what an update costs).
"""

import math
from dataclasses import dataclass

import numba
import numpy as np
import scipy.linalg
from pydrake.systems.framework import Diagram, LeafSystem

from maglev_haptics.hardware.config_checks import finite, positive, require
from maglev_haptics.hardware.constants import SAME_INSTANT_S
from maglev_haptics.hardware.device import InstrumentSpec, TrackerSpec
from maglev_haptics.hardware.kernels import FLAG, MATRIX, SCALAR, VECTOR, kernel
from maglev_haptics.systems.rotations import (
    quaternion_conjugate, quaternion_exp, quaternion_from_rotation_matrix, quaternion_log,
    quaternion_multiply)
from maglev_haptics.systems.stacked_ports import BuildHeld

# A fit is refused when the visible markers' second principal spread is below
# this fraction of the first (nearly collinear): the roll about their line is
# then undetermined.
MIN_SPREAD_RATIO = 1e-3
# Noise floor for the residual limit [m]: with zero tracker noise a perfect fit
# still shows ~1e-9 m of residual (round-off of fit_pose's residual formula);
# 10 nm is above that and far below any tracker's resolution.
RESIDUAL_FLOOR_M = 1e-8
_IDENTITY_POSE = np.array([1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])


@dataclass
class PoseEstimatorConfig:
    """Tuning of the pose estimator; defaults suit 0.01 mm noise at 860 Hz and
    a ~10 Hz levitation loop (see the module docstring for the resulting
    noise and lag)."""

    bandwidth_hz: float = 50.0  # velocity filter's natural frequency (damping 0.707) [Hz]
    max_residual_sigma: float = 20.0  # reject fits whose RMS marker residual exceeds this x noise_m
    # The PC's time from a tracker sample's arrival to its estimate (s): the fit and
    # filter's compute time (tens of microseconds an update; ``maglev bench``). A
    # tick reads an estimate whose processing ended before it.
    processing_delay_s: float = 20e-6
    # A fit this far from the filter's prediction is implausible (a reflection taken
    # for a marker, markers swapped) and is read as unseen: 5 mm and 0.2 rad in one
    # sample are 4.3 m/s and 170 rad/s at 860 Hz, beyond any hand [m, rad].
    max_jump_m: float = 0.005
    max_jump_rad: float = 0.2
    # After a jump only a fit that is no jump from the last good pose is taken, for
    # this long [s]; then any (re-acquisition). A jump that persists is a lost
    # instrument: the controller cuts the coils after its grace (20 ms), well before.
    jump_hold_s: float = 0.1

    def validate(self, path: str, tracker_rate_hz: float, tick_s: float) -> None:
        """Range checks against the tracker's rate (Hz) and the loop's tick (s); a
        ValueError names ``path.field``, its value and what is allowed."""
        require(0 < self.bandwidth_hz < tracker_rate_hz / 2, f"{path}.bandwidth_hz",
                self.bandwidth_hz, f"must be in (0, {tracker_rate_hz / 2}) Hz, below the "
                "tracker's Nyquist frequency")
        positive(f"{path}.max_residual_sigma", self.max_residual_sigma)
        for name, unit in (("max_jump_m", "m"), ("max_jump_rad", "rad"), ("jump_hold_s", "s")):
            require(finite(getattr(self, name)) and getattr(self, name) > 0, f"{path}.{name}",
                    getattr(self, name), f"must be > 0 ({unit})")
        period_s = 1.0 / tracker_rate_hz
        require(finite(self.processing_delay_s) and 0 <= self.processing_delay_s < period_s,
                f"{path}.processing_delay_s", self.processing_delay_s,
                f"must be in [0, {period_s}) s (one tracker period)")
        # A tick reads the newest sample only: each must be processed by the first tick
        # after it unless the next is published first.
        if abs(period_s - tick_s) > SAME_INSTANT_S:
            require(self.processing_delay_s <= period_s - tick_s, f"{path}.processing_delay_s",
                    self.processing_delay_s, f"must be at most {period_s - tick_s:.6g} s: the "
                    "tracker's period less the loop's tick, so each sample is processed "
                    "before the next is published")


# --- rigid fit ---------------------------------------------------------------
# The numeric cores are compiled by numba: in numpy a fit was ~20 calls of
# 2-9 us each; compiled, it is mostly the ~3 us of the 3x3 SVD. The public
# functions taking a MarkerModel are thin wrappers over them.

class MarkerModel:
    """The instrument's model markers p_IK (m, 3) [m], stored as the compiled
    fit takes them (float64, C-contiguous)."""

    def __init__(self, p_IK: np.ndarray):
        self.p_IK = np.ascontiguousarray(p_IK, dtype=float)

    def __len__(self) -> int:
        return len(self.p_IK)


def fit_pose(model: MarkerModel, p_WK: np.ndarray):
    """Least-squares rigid fit X_WI of the model markers to measured ones.

    Kabsch: SVD of the 3x3 cross-covariance (numba's, i.e. LAPACK's gesdd).

    Args:
        model: the m >= 3 model markers p_IK [m].
        p_WK: (m, 3) the same markers measured in W [m].
    Returns:
        (q_WI, rms_m): pose vector (7,) [qw qx qy qz x y z] minimizing
        sum |R_WI p_IK + p_WI - p_WK|^2, and the RMS over markers of the 3-D
        residual [m]; rms_m is inf when the markers are nearly collinear (no
        unique fit) or the sample overflows.
    """
    return _rigid_fit(model.p_IK, np.ascontiguousarray(p_WK, dtype=float))


@kernel((MATRIX, MATRIX))
def _rigid_fit(p_IK, p_WK):
    """fit_pose on the model markers p_IK (m, 3) [m] and measured p_WK (m, 3) [m]."""
    m = len(p_IK)
    c_I = np.zeros(3)
    c_W = np.zeros(3)
    for k in range(m):
        c_I += p_IK[k]
        c_W += p_WK[k]
    c_I *= 1.0 / m
    c_W *= 1.0 / m
    d_I = p_IK - c_I
    d_W = p_WK - c_W
    sum_sq_I = np.sum(d_I * d_I)  # [m^2]
    sum_sq_W = np.sum(d_W * d_W)
    H = d_I.T @ d_W  # cross-covariance [m^2]
    if not np.all(np.isfinite(H)):  # overflowed: the SVD would raise
        return _IDENTITY_POSE.copy(), math.inf
    try:
        U, S, Vt = np.linalg.svd(H)
    except Exception:  # LAPACK did not converge
        return _IDENTITY_POSE.copy(), math.inf
    s0, s1, s2 = S[0], S[1], S[2]
    if s1 <= MIN_SPREAD_RATIO**2 * s0:  # S ~ squared spreads of the model
        return _IDENTITY_POSE.copy(), math.inf
    R_WI = Vt.T @ U.T
    # Proper rotation only: for coplanar markers (any 3) the mirror image fits
    # as well, and det = -1 flags it.
    if _det3(R_WI) < 0:
        R_WI -= 2.0 * np.outer(Vt[2], U[:, 2])
        s2 = -s2
    # sum |R d_I - d_W|^2 = |d_I|^2 + |d_W|^2 - 2 trace(R H): cheaper than the
    # residuals, and its cancellation error (~1e-18 m^2, i.e. ~1e-9 m RMS) only
    # matters far below RESIDUAL_FLOOR_M.
    sum_sq = sum_sq_I + sum_sq_W - 2.0 * (s0 + s1 + s2)
    rms_m = math.sqrt(max(sum_sq, 0.0) / m)
    x_WI = np.empty(7)
    x_WI[:4] = quaternion_from_rotation_matrix(R_WI)
    x_WI[4:] = c_W - R_WI @ c_I
    return x_WI, rms_m


@numba.njit(cache=True)
def _det3(M):
    return (M[0, 0] * (M[1, 1] * M[2, 2] - M[1, 2] * M[2, 1])
            - M[0, 1] * (M[1, 0] * M[2, 2] - M[1, 2] * M[2, 0])
            + M[0, 2] * (M[1, 0] * M[2, 1] - M[1, 1] * M[2, 0]))


def measured_pose(markers_W: np.ndarray, model: MarkerModel, residual_limit_m: float):
    """Pose vector (7,) fitted to one tracker sample, or None if it is unusable.

    Args:
        markers_W: (3 n,) measured p_WK [m]; a marker with any NaN coordinate
            is not visible. Any inf marks a corrupt sample.
        model: the n model markers p_IK [m].
        residual_limit_m: largest acceptable RMS marker residual [m].
    Returns None when fewer than 3 markers are visible, the sample is corrupt,
    the visible markers are nearly collinear, or the residual exceeds the limit.
    """
    ok, x_WI = _measured_pose(
        np.ascontiguousarray(markers_W, dtype=float), model.p_IK, residual_limit_m)
    return x_WI if ok else None


@numba.njit(cache=True)
def _measured_pose(markers_W, p_IK, residual_limit_m):
    """measured_pose as (ok, x_WI); x_WI is meaningless when not ok."""
    p_WK = markers_W.reshape((-1, 3))
    visible = np.ones(len(p_IK), dtype=np.bool_)
    for k in range(len(p_IK)):
        for i in range(3):
            if np.isinf(p_WK[k, i]):
                return False, _IDENTITY_POSE.copy()
            if np.isnan(p_WK[k, i]):
                visible[k] = False
    if visible.sum() < 3:
        return False, _IDENTITY_POSE.copy()
    if visible.all():
        x_WI, rms_m = _rigid_fit(p_IK, p_WK)
    else:
        x_WI, rms_m = _rigid_fit(p_IK[visible], p_WK[visible])
    return rms_m <= residual_limit_m, x_WI  # False for NaN too


# --- velocity filter ---------------------------------------------------------

def velocity_lag_s(config: PoseEstimatorConfig) -> float:
    """How far (s) the velocity estimate trails the true velocity at low frequency:
    2 zeta / omega of the filter's poles (damping 0.707 at ``bandwidth_hz``), about
    4.5 ms at 50 Hz (the sampled filter trails a ramp by 4.0 ms)."""
    return math.sqrt(2.0) / (2 * math.pi * config.bandwidth_hz)


def alpha_beta_gains(bandwidth_hz: float, period_s: float):
    """(alpha, beta) of the steady-state constant-velocity Kalman filter.

    Model per axis: white acceleration of power spectral density q, measurement
    noise sigma^2 per sample. Only q / sigma^2 sets the gains; it is chosen as
    (2 pi bandwidth_hz)^4 * period_s, which puts the filter's closed-loop poles
    at ``bandwidth_hz`` with damping 0.707 (the continuous-time Kalman result,
    which the sampled filter reproduces). Update with innovation r:
    position += alpha r, velocity += (beta / period_s) r.
    """
    T = period_s
    omega = 2 * math.pi * bandwidth_hz
    F = np.array([[1.0, T], [0.0, 1.0]])
    H = np.array([[1.0], [0.0]])
    Q = omega**4 * T * np.array([[T**3 / 3, T**2 / 2], [T**2 / 2, T]])
    P = scipy.linalg.solve_discrete_are(F.T, H, Q, np.array([[1.0]]))  # prior covariance / sigma^2
    K = P[:, 0] / (P[0, 0] + 1.0)
    return float(K[0]), float(K[1] * T)


def alpha_beta_noise_gains(alpha: float, beta: float, period_s: float):
    """Steady-state noise of the filter's outputs for unit white measurement noise.

    Returns (position_ratio, velocity_ratio_per_s): standard deviations of the
    filtered position (dimensionless ratio) and velocity [1/s] per unit
    standard deviation of the measurement. Multiply the fit's per-axis pose
    noise (m or rad) by velocity_ratio_per_s for the velocity noise.
    """
    T = period_s
    K = np.array([[alpha], [beta / T]])
    A = (np.eye(2) - K @ np.array([[1.0, 0.0]])) @ np.array([[1.0, T], [0.0, 1.0]])
    covariance = scipy.linalg.solve_discrete_lyapunov(A, K @ K.T)
    return math.sqrt(covariance[0, 0]), math.sqrt(covariance[1, 1])


@kernel((VECTOR, VECTOR, VECTOR, SCALAR, SCALAR, SCALAR))
def filter_update(x_hat: np.ndarray, V: np.ndarray, x_meas: np.ndarray,
                  alpha: float, beta: float, period_s: float):
    """One alpha-beta step on the pose (compiled by numba).

    Args:
        x_hat: filtered pose vector [q; p_WI] (quaternion of R_WI, m) after the
            previous sample.
        V: filtered spatial velocity [w; v] in W (rad/s, m/s).
        x_meas: this sample's fitted pose vector.
        alpha, beta: gains from ``alpha_beta_gains``; period_s: sample period [s].
    Returns (x_hat, V) after this sample. The orientation innovation is the
    rotation vector (rad, in W) from the predicted to the measured orientation,
    so a full turn is just a sum of small increments: no angle ever wraps.
    """
    T = period_s
    wx, wy, wz, vx, vy, vz = V[0], V[1], V[2], V[3], V[4], V[5]
    # Predict at constant V, then the innovation [rotation vector; position].
    q_pred = quaternion_multiply(
        quaternion_exp(wx * T, wy * T, wz * T), (x_hat[0], x_hat[1], x_hat[2], x_hat[3]))
    p_pred = (x_hat[4] + vx * T, x_hat[5] + vy * T, x_hat[6] + vz * T)
    dq = quaternion_multiply(
        (x_meas[0], x_meas[1], x_meas[2], x_meas[3]), quaternion_conjugate(q_pred))
    rx, ry, rz = quaternion_log(dq[0], dq[1], dq[2], dq[3])
    ex, ey, ez = x_meas[4] - p_pred[0], x_meas[5] - p_pred[1], x_meas[6] - p_pred[2]
    nw, nx, ny, nz = quaternion_multiply(
        quaternion_exp(alpha * rx, alpha * ry, alpha * rz), q_pred)
    norm = math.sqrt(nw * nw + nx * nx + ny * ny + nz * nz)
    x_new = np.array([nw / norm, nx / norm, ny / norm, nz / norm,
                      p_pred[0] + alpha * ex, p_pred[1] + alpha * ey, p_pred[2] + alpha * ez])
    gain = beta / T
    V_new = np.array([wx + gain * rx, wy + gain * ry, wz + gain * rz,
                      vx + gain * ex, vy + gain * ey, vz + gain * ez])
    return x_new, V_new


@numba.njit(cache=True)
def _is_jump(x_hat, V, x_WI, period_s, max_jump_m, max_jump_rad):
    """Whether the fit ``x_WI`` is farther than ``max_jump_m`` (m) from the filter's
    predicted position, or turned more than ``max_jump_rad`` (rad) from its
    orientation (the turn predicted in one sample is far below the limit)."""
    dx = x_WI[4] - (x_hat[4] + V[3] * period_s)
    dy = x_WI[5] - (x_hat[5] + V[4] * period_s)
    dz = x_WI[6] - (x_hat[6] + V[5] * period_s)
    cos_half = abs(x_WI[0] * x_hat[0] + x_WI[1] * x_hat[1] + x_WI[2] * x_hat[2]
                   + x_WI[3] * x_hat[3])
    return (math.sqrt(dx * dx + dy * dy + dz * dz) > max_jump_m
            or cos_half < math.cos(max_jump_rad / 2))


@kernel((VECTOR, MATRIX, SCALAR, SCALAR, SCALAR, SCALAR, SCALAR, SCALAR, SCALAR,
         VECTOR, VECTOR, VECTOR, VECTOR, VECTOR))
def _estimator_update(markers_W, p_IK, residual_limit_m, alpha, beta, period_s,
                      max_jump_m, max_jump_rad, jump_hold_s, X, V, ok, x_hat, jump_s):
    """PoseEstimator's update on one tracker sample, in place on its state
    groups X (7), V (6), ok (1), x_hat (7) and jump_s (1: time since a jump was
    refused, s; -1: none), which hold the previous values."""
    good, x_WI = _measured_pose(markers_W, p_IK, residual_limit_m)
    if jump_s[0] >= 0.0:
        jump_s[0] += period_s
        if jump_s[0] > jump_hold_s:
            jump_s[0] = -1.0  # held long enough: the next good fit re-acquires
    if good and (ok[0] > 0.5 or jump_s[0] >= 0.0):
        if _is_jump(x_hat, V, x_WI, period_s, max_jump_m, max_jump_rad):
            good = False
            if jump_s[0] < 0.0:
                jump_s[0] = 0.0
        else:
            jump_s[0] = -1.0
    if not good:
        # Lost: X already holds the last pose; stop moving.
        V[:] = 0.0
        ok[0] = 0.0
        return
    if x_WI[0] * X[0] + x_WI[1] * X[1] + x_WI[2] * X[2] + x_WI[3] * X[3] < 0:
        x_WI[:4] = -x_WI[:4]  # same rotation; keeps the output continuous
    if ok[0] > 0.5:
        x_new, V_new = filter_update(x_hat, V, x_WI, alpha, beta, period_s)
        x_hat[:] = x_new
        V[:] = V_new
    else:
        x_hat[:] = x_WI  # (re-)acquired: restart the filter here
        V[:] = 0.0
    X[:] = x_WI
    ok[0] = 1.0


# --- the system --------------------------------------------------------------

def _check_model(p_IK: np.ndarray) -> np.ndarray:
    if p_IK.ndim != 2 or p_IK.shape[1] != 3 or not np.all(np.isfinite(p_IK)):
        raise ValueError(
            f"instrument.p_IK_m has shape {p_IK.shape}: must be finite (n, 3) positions [m]")
    if len(p_IK) < 3:
        raise ValueError(
            f"instrument.p_IK_m has {len(p_IK)} markers: the pose fit needs at least 3")
    spread = np.linalg.svd(p_IK - p_IK.mean(axis=0), compute_uv=False)
    if spread[1] <= MIN_SPREAD_RATIO * spread[0]:
        raise ValueError(
            f"instrument.p_IK_m = {p_IK.tolist()}: markers are (nearly) collinear, "
            "the rotation about their line would be undetermined")
    return p_IK


def _check_rate(tracker: TrackerSpec) -> float:
    rate = tracker.rate_hz
    if not (math.isfinite(rate) and rate > 0):
        raise ValueError(f"tracker.rate_hz = {rate}: must be a finite value > 0 [Hz]")
    return 1.0 / rate


# The estimator's record (its output, held by a ZeroOrderHold between ticks): the
# outputs X (7), V (6), tracking_ok (1); then the filter's pose (7), the time since a
# jump was refused (1, s; -1: none), the samples processed (1), the newest one's
# time (1, s) and its frame number (1). The zero record is the estimator before its
# first sample.
RECORD_SIZE = 25
_X, _V, _OK, _X_HAT, _JUMP, _PROCESSED, _LAST, _LAST_COUNT = 0, 7, 13, 14, 21, 22, 23, 24
# The rows that count samples, not state (a linearization holds them).
CLOCK_ROWS = (_PROCESSED, _LAST, _LAST_COUNT)


# The estimator's numbers as ``estimator_record`` takes them: an array, by these indices.
(_RESIDUAL_LIMIT_M, _ALPHA, _BETA, _PERIOD_S, _PROCESSING_DELAY_S, _MAX_JUMP_M, _MAX_JUMP_RAD,
 _JUMP_HOLD_S) = range(8)


@kernel((VECTOR, SCALAR, SCALAR, SCALAR, VECTOR, MATRIX, VECTOR, FLAG, MATRIX, VECTOR, VECTOR))
def estimator_record(markers_T, sample_time_s, sample_count, t, held, p_IK, parameters,
                     in_T, R_WT, p_WT, record):
    """The estimator's record at time ``t`` (s) into ``record``: ``held`` (the record at
    the last tick) after the sample ``markers_T`` published at ``sample_time_s`` (s),
    frame ``sample_count``, if the estimator has not processed it yet and its
    processing ended before ``t``. The markers are in the tracker's frame T, taken to
    W by X_WT (R_WT, p_WT [m]) where ``in_T``. The filter steps over the frames since the last
    it processed (a frame missed on the link is two periods, not one).
    ``parameters``: the residual limit (m), the filter's alpha and beta, the tracker's
    period (s), the processing delay (s) and the jump limits (m, rad, s)."""
    if held[_PROCESSED] == 0.0:
        record[:] = 0.0
        record[_X] = record[_X_HAT] = 1.0  # the identity pose
        record[_JUMP] = -1.0
    else:
        record[:] = held
    fresh = held[_PROCESSED] == 0.0 or sample_time_s > held[_LAST]
    if not (fresh and sample_time_s + parameters[_PROCESSING_DELAY_S] < t - SAME_INSTANT_S):
        return
    frames = 1.0
    markers_W = markers_T
    if in_T:
        markers_W = (markers_T.reshape((-1, 3)) @ R_WT.T + p_WT).ravel()
    if held[_PROCESSED] > 0.0 and sample_count - held[_LAST_COUNT] > 1.0:
        frames = sample_count - held[_LAST_COUNT]
    _estimator_update(markers_W, p_IK, parameters[_RESIDUAL_LIMIT_M], parameters[_ALPHA],
                      parameters[_BETA], frames * parameters[_PERIOD_S], parameters[_MAX_JUMP_M],
                      parameters[_MAX_JUMP_RAD], parameters[_JUMP_HOLD_S], record[_X:_X + 7],
                      record[_V:_V + 6], record[_OK:_OK + 1], record[_X_HAT:_X_HAT + 7],
                      record[_JUMP:_JUMP + 1])
    record[_PROCESSED] += 1.0
    record[_LAST] = sample_time_s
    record[_LAST_COUNT] = sample_count


class PoseEstimatorLaw(LeafSystem):
    """``PoseEstimator``'s arithmetic: inputs ``markers_measured``,
    ``markers_sample_time_s``, ``markers_sample_count`` and ``held`` (its own record at
    the last tick), one output ``record`` (``RECORD_SIZE``), one compiled call
    (``estimator_record``).

    .. pydrake_system::

        name: PoseEstimatorLaw
        input_ports:
        - markers_measured
        - markers_sample_time_s
        - markers_sample_count
        - held
        output_ports:
        - record
    """

    def __init__(self, instrument: InstrumentSpec, tracker: TrackerSpec, tick_s: float,
                 config: PoseEstimatorConfig):
        super().__init__()
        self._model = MarkerModel(_check_model(instrument.p_IK))
        period_s = _check_rate(tracker)
        if not (math.isfinite(tick_s) and 0 < tick_s * tracker.rate_hz <= 1 + 1e-9):
            raise ValueError(f"tick_s = {tick_s}: the loop's tick must be > 0 and at most the "
                             f"tracker's period ({period_s:g} s): one sample a tick at most")
        config.validate("estimator", tracker.rate_hz, tick_s)
        if not (math.isfinite(tracker.noise_m) and tracker.noise_m >= 0):
            raise ValueError(
                f"tracker.noise_m = {tracker.noise_m}: must be a finite value >= 0 [m]")
        self.residual_limit_m = \
            config.max_residual_sigma * max(tracker.noise_m, RESIDUAL_FLOOR_M)
        self.gains = alpha_beta_gains(config.bandwidth_hz, period_s)
        self._parameters = np.array([self.residual_limit_m, *self.gains, period_s,
                                     config.processing_delay_s, config.max_jump_m,
                                     config.max_jump_rad, config.jump_hold_s])
        self._markers = self.DeclareVectorInputPort("markers_measured", 3 * len(self._model))
        self._sample_time = self.DeclareVectorInputPort("markers_sample_time_s", 1)
        self._sample_count = self.DeclareVectorInputPort("markers_sample_count", 1)
        self._held = self.DeclareVectorInputPort("held", RECORD_SIZE)
        self.DeclareVectorOutputPort("record", RECORD_SIZE, self._calc_record)
        X_WT = tracker.pose_WT()
        self._in_T = not X_WT.IsExactlyIdentity()
        self._R_WT = np.ascontiguousarray(X_WT.rotation().matrix())
        self._p_WT = np.ascontiguousarray(X_WT.translation())

    def _calc_record(self, context, output):
        # Views, not copies: the kernel only reads them.
        estimator_record(
            self._markers.EvalBasicVector(context).value(),
            self._sample_time.EvalBasicVector(context).GetAtIndex(0),
            self._sample_count.EvalBasicVector(context).GetAtIndex(0), context.get_time(),
            self._held.EvalBasicVector(context).value(), self._model.p_IK, self._parameters,
            self._in_T, self._R_WT, self._p_WT, output.get_mutable_value())


class PoseEstimator(Diagram):
    """Instrument pose and spatial velocity from tracker markers.

    .. pydrake_system::

        name: PoseEstimator
        input_ports:
        - markers_measured
        - markers_sample_time_s
        - markers_sample_count
        output_ports:
        - X_WI_measured
        - V_WI_measured
        - tracking_ok

    - ``markers_measured`` (3 n): p_TK [m] in the tracker's frame T, NaN for markers
      not seen; the estimator takes them to W with ``tracker.X_WT``;
      ``markers_sample_time_s`` (1): when they were published (s);
      ``markers_sample_count`` (1): their frame number (the filter steps over the
      frames since the last it processed: a missed frame is two periods).
    - ``X_WI_measured`` (7): [qw qx qy qz x y z], the latest good fit; held
      while tracking is lost. The quaternion's sign follows the previous
      output, so it is continuous through any number of turns.
    - ``V_WI_measured`` (6): [wx wy wz vx vy vz] in W (rad/s, m/s), filtered;
      zero while tracking is lost.
    - ``tracking_ok`` (1): 1.0 when the latest sample gave a valid fit, else
      0.0 (fewer than 3 visible markers, a non-finite value other than the NaN
      of an unseen marker, collinear markers, or an RMS marker residual above
      ``max_residual_sigma`` * tracker noise).

    Each sample is processed once, ``processing_delay_s`` after it was published:
    the outputs at a time include every sample whose processing ended before it.
    They are computed when read, at the loop's ticks (``tick_s``, s), from the
    estimator's record at the tick before, which a ZeroOrderHold keeps: one
    compiled call a tick and no event between ticks. After a loss, the first good
    sample resets the filter to it with zero velocity. A fit that jumps from the
    filter's prediction by more than ``max_jump_m`` or ``max_jump_rad`` reads as
    unseen (tracking_ok 0), and for ``jump_hold_s`` after it only a fit near the
    last good pose is taken. Before the first sample the outputs are the identity
    pose, zero velocity, tracking_ok 0.
    """

    def __init__(self, instrument: InstrumentSpec, tracker: TrackerSpec, tick_s: float,
                 config: PoseEstimatorConfig | None = None):
        super().__init__()
        config = PoseEstimatorConfig() if config is None else config
        self._law = PoseEstimatorLaw(instrument, tracker, tick_s, config)
        BuildHeld(self, leaf=self._law, leaf_name="law", period_s=tick_s,
                  outputs=(("X_WI_measured", 7), ("V_WI_measured", 6), ("tracking_ok", 1)),
                  unexported_rows=RECORD_SIZE - 14)

    @property
    def gains(self):
        """(alpha, beta) of the velocity filter."""
        return self._law.gains

    @property
    def residual_limit_m(self) -> float:
        """RMS marker residual [m] above which a fit is rejected."""
        return self._law.residual_limit_m
