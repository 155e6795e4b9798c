"""Marker sensor (station): a simulated optical tracker (Optotrak-like).

Each sample publishes the positions of the instrument's markers in the tracker's
frame T (``tracker.X_WT``: where the tracker is bolted; nominally T is W) with
per-coordinate Gaussian noise, optional quantization, latency and occlusion.
Markers are a flat (3 n,) vector [x0 y0 z0 x1 ...] of p_TK in m; a marker the
tracker does not see is NaN in all three coordinates.

Latency L: the sample published at t_k shows the instrument at t_k - L. The
tracker rate and L are not commensurate, so instead of a delay line the pose
L ago is reconstructed from the current state and spatial velocity:
p_WI <- p_WI - v_WI L and R_WI <- exp(-[w_WI] L) R_WI. This is exact while
V_WI (w and the velocity of I's origin, in W) is constant and first-order
otherwise: a linear acceleration a leaves a position error a L^2 / 2
(1.1 um at 1 m/s^2 and 1.5 ms), an angular acceleration likewise in angle.

Randomness: the noise and dropout of sample k = round(t_k * rate_hz) are a
pure function of (seed, k), so a run, a re-run and a cloned Context all see the
same measurements.

Cost: one numba-compiled call a sample (``maglev bench`` lists what an update costs).
"""

import math
from dataclasses import dataclass
from typing import Optional, Sequence

import numba
import numpy as np
from pydrake.systems.framework import Diagram, LeafSystem

from maglev_haptics.hardware.device import InstrumentSpec, TrackerSpec
from maglev_haptics.hardware.kernels import FLAG, MASK_MATRIX, MATRIX, SCALAR, VECTOR, kernel
from maglev_haptics.systems.fault_injection import (
    CorruptSample, LatencySpike, corrupt, stalled)
from maglev_haptics.systems.rotations import (
    quaternion_exp, quaternion_multiply, rotation_from_quaternion)
from maglev_haptics.systems.stacked_ports import BuildHeld

# Samples per block of pre-drawn random numbers (one generator per block).
NOISE_BLOCK = 1024


@dataclass
class Occlusion:
    """A scripted occlusion: ``marker`` (index into p_IK, or None for all
    markers, i.e. the instrument is lost) is hidden for capture times t with
    start_s <= t < end_s [s]. Capture time = publication time - latency."""

    marker: Optional[int] = None
    start_s: float = 0.0
    end_s: float = math.inf


# The kinematics and the sample's assembly are compiled by numba: in numpy they
# were ~15 small calls of 1-4 us each at the tracker rate. Only the random
# draws (SampleNoise) stay in Python.

@numba.njit(cache=True)
def marker_positions_W(q_WI: np.ndarray, p_IK: np.ndarray) -> np.ndarray:
    """Marker positions p_WK (n, 3) [m] for the pose vector q_WI
    [qw qx qy qz x y z] (m) and the model p_IK (n, 3) [m] in I."""
    return q_WI[4:7] + p_IK @ rotation_from_quaternion(q_WI[:4]).T


@kernel((VECTOR, VECTOR, SCALAR))
def extrapolate_pose(q_WI: np.ndarray, V_WI: np.ndarray, dt_s: float) -> np.ndarray:
    """Pose vector dt_s [s] later (earlier if negative) at constant V_WI.

    V_WI = [w; v] in W (rad/s; m/s of I's origin). Exact for constant V_WI:
    R <- exp([w] dt) R, p <- p + v dt.
    """
    q = quaternion_multiply(
        quaternion_exp(V_WI[0] * dt_s, V_WI[1] * dt_s, V_WI[2] * dt_s),
        (q_WI[0], q_WI[1], q_WI[2], q_WI[3]))
    return np.concatenate((np.array(q), q_WI[4:7] + V_WI[3:6] * dt_s))


@numba.njit(cache=True)
def quantize(values: np.ndarray, step: float) -> np.ndarray:
    """Round to the nearest multiple of ``step`` (unchanged when step is 0)."""
    # rint: round half to even, as np.round.
    return np.rint(values / step) * step if step > 0 else values


@kernel((SCALAR, VECTOR, MATRIX, SCALAR, SCALAR, SCALAR, SCALAR, MATRIX, VECTOR, VECTOR, VECTOR,
         MASK_MATRIX, FLAG, MATRIX, VECTOR, VECTOR))
def _measure(t, instrument_state, p_IK, latency_s, noise_m, quantization_m, dropout_probability,
             normal, uniform, occlusion_start, occlusion_end, occlusion_hides, in_T, R_TW, p_TW,
             p_TK_out):
    """MarkerSensor.measure written into p_TK_out (3 n,) [m], given the sample's
    draws normal (n, 3) and uniform (n,), the occlusion table of _occlusion_table
    and, where ``in_T``, the pose X_TW (R_TW, p_TW [m]) of W in the tracker's frame."""
    q_WI = extrapolate_pose(instrument_state[:7], instrument_state[7:13], -latency_s)
    p_TK = marker_positions_W(q_WI, p_IK)  # T is W unless in_T
    if in_T:
        p_TK = p_TK @ R_TW.T + p_TW
    p_TK = quantize(p_TK + noise_m * normal, quantization_m)
    t_capture = t - latency_s
    for k in range(len(p_IK)):
        hidden = uniform[k] < dropout_probability
        for j in range(len(occlusion_start)):
            if occlusion_hides[j, k] and occlusion_start[j] <= t_capture < occlusion_end[j]:
                hidden = True
        for i in range(3):
            p_TK_out[3 * k + i] = np.nan if hidden else p_TK[k, i]


class SampleNoise:
    """Standard normal (n, 3) and uniform (n,) draws for sample index k.

    Draws come in blocks of NOISE_BLOCK samples from numpy's default generator
    seeded with (seed, block), so they depend on (seed, k) only; the last block
    is cached because samples are usually consecutive. Block 0 is drawn here,
    before a run's clock starts, not by the first tick that reads a sample
    (docs/architecture.md, "Real time").
    """

    def __init__(self, seed: int, n_markers: int):
        self._seed = seed
        self._n = n_markers
        self._block = 0
        self._normal, self._uniform = self._block_draws(0)

    def _block_draws(self, block: int):
        # SeedSequence wants non-negative entropy; wrap negative blocks.
        rng = np.random.default_rng([self._seed, block % 2**64])
        return rng.standard_normal((NOISE_BLOCK, self._n, 3)), rng.random((NOISE_BLOCK, self._n))

    def draw(self, k: int):
        block, i = divmod(k, NOISE_BLOCK)
        if block != self._block:
            self._normal, self._uniform = self._block_draws(block)
            self._block = block
        return self._normal[i], self._uniform[i]


def _occlusion_table(occlusions: Sequence, n_markers: int):
    """(start_s, end_s, hides) arrays: hides[j, K] is True if entry j hides marker K.

    Entries are Occlusion objects or (marker, start_s, end_s) tuples."""
    start = np.empty(len(occlusions))
    end = np.empty(len(occlusions))
    hides = np.zeros((len(occlusions), n_markers), dtype=bool)
    for j, item in enumerate(occlusions):
        occlusion = item if isinstance(item, Occlusion) else Occlusion(*item)
        marker = occlusion.marker
        if marker is None:
            hides[j] = True
        elif isinstance(marker, (int, np.integer)) and not isinstance(marker, bool) \
                and 0 <= marker < n_markers:
            hides[j, marker] = True
        else:
            raise ValueError(
                f"occlusions[{j}].marker = {marker!r}: must be None (all markers) or "
                f"an integer in [0, {n_markers - 1}]")
        if math.isnan(occlusion.start_s) or math.isnan(occlusion.end_s) \
                or occlusion.end_s < occlusion.start_s:
            raise ValueError(
                f"occlusions[{j}] = ({occlusion.start_s}, {occlusion.end_s}) s: "
                "must satisfy start_s <= end_s (end_s may be inf)")
        start[j], end[j] = occlusion.start_s, occlusion.end_s
    return start, end, hides


def _check_nonnegative(name: str, value: float, unit: str) -> float:
    if not (math.isfinite(value) and value >= 0):
        raise ValueError(f"{name} = {value}: must be a finite value >= 0 [{unit}]")
    return float(value)


# A sample at n / rate_hz counts as at a tick's time t within this many samples: a
# tick's time is a sum of periods, a few ulps off the exact n / rate_hz.
SAMPLE_TOLERANCE = 1e-6
# The sensor's record (its output, held by a ZeroOrderHold between ticks): the
# markers (3 n), then the newest sample's time and number + 1 (0: none taken yet).
_TIME, _TAKEN = 0, 1  # rows after the markers


def newest_sample_before(t: float, rate_hz: float) -> int:
    """The number of the newest sample taken before ``t`` (s) at ``rate_hz`` (Hz), from
    sample 0 at t = 0 (-1: none)."""
    return math.ceil(t * rate_hz - SAMPLE_TOLERANCE) - 1


class MarkerSensorLaw(LeafSystem):
    """``MarkerSensor``'s arithmetic: inputs ``instrument_state`` and ``held`` (its own
    record at the last tick), one output ``record`` (see ``MarkerSensor``).

    .. pydrake_system::

        name: MarkerSensorLaw
        input_ports:
        - instrument_state
        - held
        output_ports:
        - record
    """

    def __init__(self, instrument: InstrumentSpec, tracker: TrackerSpec, occlusions: Sequence,
                 seed: int, dropout_probability: float, quantization_m: float,
                 latency_spikes: Sequence[LatencySpike], corruptions: Sequence[CorruptSample]):
        super().__init__()
        p_IK = instrument.p_IK
        if p_IK.ndim != 2 or p_IK.shape[1] != 3 or len(p_IK) < 1 \
                or not np.all(np.isfinite(p_IK)):
            raise ValueError(
                f"instrument.p_IK_m has shape {p_IK.shape}: must be finite (n, 3) "
                "positions [m] with n >= 1")
        if not (math.isfinite(tracker.rate_hz) and tracker.rate_hz > 0):
            raise ValueError(
                f"tracker.rate_hz = {tracker.rate_hz}: must be a finite value > 0 [Hz]")
        if not (0.0 <= dropout_probability <= 1.0):
            raise ValueError(
                f"dropout_probability = {dropout_probability}: must be in [0, 1]")
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
            raise ValueError(f"seed = {seed!r}: must be a non-negative integer")
        self._p_IK = np.ascontiguousarray(p_IK)
        self._n = 3 * len(p_IK)
        self.rate_hz = float(tracker.rate_hz)
        self._noise_m = _check_nonnegative("tracker.noise_m", tracker.noise_m, "m")
        self._latency_s = _check_nonnegative("tracker.latency_s", tracker.latency_s, "s")
        X_TW = tracker.pose_WT().inverse()
        self._in_T = not X_TW.IsExactlyIdentity()
        self._R_TW = np.ascontiguousarray(X_TW.rotation().matrix())
        self._p_TW = np.ascontiguousarray(X_TW.translation())
        self._quantization_m = _check_nonnegative("quantization_m", quantization_m, "m")
        self._dropout = float(dropout_probability)
        self._occlusion_start, self._occlusion_end, self._occlusion_hides = \
            _occlusion_table(list(occlusions), len(p_IK))
        self._noise = SampleNoise(int(seed), len(p_IK))
        self._latency_spikes = list(latency_spikes)
        self._corruptions = list(corruptions)
        self._state = self.DeclareVectorInputPort("instrument_state", 13)
        self._held = self.DeclareVectorInputPort("held", self._n + 2)
        self.DeclareVectorOutputPort("record", self._n + 2, self._calc_record)

    def measure(self, t: float, instrument_state: np.ndarray) -> np.ndarray:
        """The (3 n,) sample published at time t [s] for the current state (13,)."""
        p_TK = np.empty(self._n)
        self._measure_into(t, np.ascontiguousarray(instrument_state, dtype=float), p_TK)
        return p_TK

    def _measure_into(self, t, instrument_state, p_TK_out):
        # Writes in place so the record is filled without a copy.
        sample = round(t * self.rate_hz)
        normal, uniform = self._noise.draw(sample)
        _measure(t, instrument_state, self._p_IK, self._latency_s, self._noise_m,
                 self._quantization_m, self._dropout, normal, uniform,
                 self._occlusion_start, self._occlusion_end, self._occlusion_hides,
                 self._in_T, self._R_TW, self._p_TW, p_TK_out)
        if self._corruptions:
            corrupt(sample, p_TK_out, self._corruptions, self.rate_hz)

    def _calc_record(self, context, output):
        held = self._held.EvalBasicVector(context).value()
        sample = newest_sample_before(context.get_time(), self.rate_hz)
        record = output.get_mutable_value()
        if sample < 0:  # none published yet
            record[:self._n] = np.nan
            record[self._n + _TIME] = -np.inf
            record[self._n + _TAKEN] = 0.0
            return
        if sample + 0.5 < held[self._n + _TAKEN]:  # taken: the count is a whole number
            output.SetFromVector(held)
            return
        # A sample since the last tick: the plant's state, held from the last tick to
        # this one, is the state it saw.
        t_s = sample / self.rate_hz
        if self._latency_spikes and stalled(t_s, self._latency_spikes):
            # Nothing new: the last markers again (NaN before the first).
            record[:self._n] = held[:self._n] if held[self._n + _TAKEN] > 0 else np.nan
        else:
            self._measure_into(t_s, self._state.EvalBasicVector(context).value(),
                               record[:self._n])
        record[self._n + _TIME] = t_s
        record[self._n + _TAKEN] = sample + 1


class MarkerSensor(Diagram):
    """Simulated optical tracker of the instrument's markers.

    .. pydrake_system::

        name: MarkerSensor
        input_ports:
        - instrument_state
        output_ports:
        - markers_measured
        - markers_sample_time_s
        - markers_sample_count

    - ``instrument_state`` (13): the plant's free-body state
      [qw qx qy qz x y z wx wy wz vx vy vz] (m, rad/s, m/s; velocities in W).
    - ``markers_measured`` (3 n): p_TK [m] of the n markers in the tracker's frame T
      (W unless ``tracker.X_WT`` says otherwise), NaN where not seen:
      the newest sample published before now (NaN before the first, at t = 0).
    - ``markers_sample_time_s`` (1): when that sample was published (s); it shows
      the instrument ``tracker.latency_s`` before.
    - ``markers_sample_count`` (1): that sample's number, counted from 1 (0: none
      yet), as a tracker numbers its frames: a gap is a frame missed.

    Samples are published at ``tracker.rate_hz`` from t = 0. The plant is discrete
    at ``tick_s`` (s): its state after the step at one tick holds until the next,
    and a sample taken in that interval saw it. The sensor is read at the ticks;
    each one's output computes the sample published since the tick before (one at
    most), from the state the plant holds until this tick's step, and a
    ZeroOrderHold keeps it for the ticks after. So a sample costs one compiled call
    and the tracker adds no event between ticks: the Simulator takes one step a
    tick. A sample due at a tick's very instant sees the state after that tick's
    step, and is read at the next tick.

    Args:
        instrument: supplies the marker model p_IK [m].
        tracker: rate_hz [Hz], noise_m (std per coordinate) [m], latency_s [s].
        tick_s: the plant's time step (s); the tracker's period must be longer.
        occlusions: scripted occlusion intervals: Occlusion objects or
            (marker, start_s, end_s) tuples.
        seed: non-negative integer; the only source of randomness.
        dropout_probability: chance that a marker is missing from a sample,
            independently per marker and sample, in [0, 1].
        quantization_m: coordinate resolution [m]; 0 for none.
        latency_spikes, corruptions: injected faults (``systems/fault_injection.py``).
    """

    def __init__(self, instrument: InstrumentSpec, tracker: TrackerSpec, tick_s: float,
                 occlusions: Sequence = (), seed: int = 0, *,
                 dropout_probability: float = 0.0, quantization_m: float = 0.0,
                 latency_spikes: Sequence[LatencySpike] = (),
                 corruptions: Sequence[CorruptSample] = ()):
        super().__init__()
        self._law = MarkerSensorLaw(instrument, tracker, occlusions, seed, dropout_probability,
                                    quantization_m, latency_spikes, corruptions)
        if not (math.isfinite(tick_s) and 0 < tick_s * tracker.rate_hz <= 1 + SAMPLE_TOLERANCE):
            raise ValueError(
                f"tick_s = {tick_s}: the plant's step must be > 0 and at most the tracker's "
                f"period ({1.0 / tracker.rate_hz:g} s): one sample a step at most")
        self._n = 3 * len(instrument.p_IK)
        BuildHeld(self, leaf=self._law, leaf_name="law", period_s=tick_s,
                  outputs=(("markers_measured", self._n), ("markers_sample_time_s", 1),
                           ("markers_sample_count", 1)))

    @property
    def sample_period_s(self) -> float:
        """The tracker's period (s): the loop's multirate model samples at it."""
        return 1.0 / self._law.rate_hz

    @property
    def clock_rows(self) -> tuple:
        """The rows of the held record that count samples, not state: the newest
        sample's time and number (a linearization holds them)."""
        return (self._n + _TIME, self._n + _TAKEN)

    def measure(self, t: float, instrument_state: np.ndarray) -> np.ndarray:
        """The (3 n,) sample published at time t [s] for the state (13,) it saw."""
        return self._law.measure(t, instrument_state)
