"""Head sensor (station): a simulated optical tracker of the shutter glasses
(Polaris-like, paper Section IV).

The user's head comes in as a look-at description, ``head_pose`` = [p_WG (3),
look-at point (3), heading, roll] (m, rad): the eyes' midpoint, the point they
look at, the direction the user faces (0: the user sits at the display's -y edge
facing +y, so G's x, the eye axis, is W's x) and the head's tilt about the line
of sight. ``glasses_pose`` turns it into X_WG.

Each capture (``rate_hz``) measures the glasses' markers with Gaussian noise per
coordinate and fits the glasses' pose to them (as the tracker does, Kabsch);
the result is published ``latency_s`` after its capture, so a sample always
shows the head as it was that long ago. ``glasses_measured`` is [capture time
(s), qw, qx, qy, qz, x, y, z, ok]; ok = 0 (and the pose NaN) while the glasses
are hidden (scripted occlusions) or the head input is not finite.

Randomness: sample k's noise is a pure function of (seed, k).
"""


import math
from dataclasses import dataclass

import numpy as np
from pydrake.math import RotationMatrix
from pydrake.systems.framework import LeafSystem

from maglev_haptics.hardware.constants import SAME_INSTANT_S
from maglev_haptics.hardware.kernels import READONLY_VECTOR, SCALAR, VECTOR, kernel
from maglev_haptics.systems.pose_estimator import MarkerModel, fit_pose
from maglev_haptics.systems.rotations import rotation_matrix

HEAD_POSE_SIZE = 8
MEASUREMENT_SIZE = 9  # [t_capture, q (4), p (3), ok]
# A tracked tool's fit is rejected above this RMS marker residual (m), as a
# Polaris rejects a tool whose markers do not match its definition.
RESIDUAL_LIMIT_M = 1.0e-3


@dataclass
class HeadOcclusion:
    """The glasses are out of the head tracker's view for capture times in
    [start_s, end_s) (s)."""

    start_s: float = 0.0
    end_s: float = math.inf


def glasses_rotation(p_WG, look_at_W, heading_rad: float, roll_rad: float) -> np.ndarray:
    """R_WG: z along the line of sight, x the eye axis (towards the right eye)
    turned ``heading_rad`` about W's z and kept square to the line of sight, y down
    the face; then tilted ``roll_rad`` about the line of sight.

    Looking straight down works (the eye axis stays the heading's); ValueError for
    a line of sight along the eye axis or of zero length.
    """
    sight = np.asarray(look_at_W, float) - np.asarray(p_WG, float)
    length = np.linalg.norm(sight)
    z = sight / length if length > 0 else sight
    heading_axis = np.array([math.cos(heading_rad), math.sin(heading_rad), 0.0])
    x = heading_axis - np.dot(heading_axis, z) * z
    if not (length > 1e-6 and np.linalg.norm(x) > 1e-3):
        raise ValueError(
            f"head at {np.asarray(p_WG).tolist()} looking at {np.asarray(look_at_W).tolist()} "
            f"with heading {heading_rad} rad: the line of sight must have length and not run "
            "along the eye axis")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    c, s = math.cos(roll_rad), math.sin(roll_rad)
    return np.column_stack([c * x + s * y, -s * x + c * y, z])


def glasses_pose(head_pose) -> tuple:
    """(q_WG, p_WG) of a ``head_pose`` vector [p_WG, look-at, heading, roll]: the
    quaternion [w, x, y, z] and the position (m)."""
    head_pose = np.asarray(head_pose, float)
    R_WG = glasses_rotation(head_pose[0:3], head_pose[3:6], head_pose[6], head_pose[7])
    return RotationMatrix(R_WG).ToQuaternion().wxyz(), head_pose[0:3].copy()


def measure_glasses(head_pose, p_GK: np.ndarray, noise_m: float, rng) -> np.ndarray:
    """One noisy capture: the pose vector [q, p] fitted to the markers, or NaN (7)
    when the head input is not finite or the fit is rejected."""
    if not np.all(np.isfinite(head_pose)):
        return np.full(7, np.nan)
    q_WG, p_WG = glasses_pose(head_pose)
    R_WG = rotation_matrix(q_WG).matrix()
    p_WK = p_WG + p_GK @ R_WG.T + rng.normal(0.0, noise_m, p_GK.shape)
    x_WG, rms_m = fit_pose(MarkerModel(p_GK), p_WK)
    if not rms_m <= RESIDUAL_LIMIT_M:
        return np.full(7, np.nan)
    if np.dot(x_WG[0:4], q_WG) < 0:
        x_WG[0:4] = -x_WG[0:4]  # the same rotation, the hemisphere of the truth
    return x_WG


class HeadSensor(LeafSystem):
    """The glasses' tracker: captures at ``rate_hz``, publishes each capture
    ``latency_s`` later.

    .. pydrake_system::

        name: HeadSensor
        input_ports:
        - head_pose
        output_ports:
        - glasses_measured

    Captures wait in a queue (state) until their latency has passed, so any
    latency works, longer than the period too. ``glasses_measured`` is the newest
    capture whose latency has passed at the reader's time: each capture is released
    at exactly its capture time plus the latency, with no release event (whose
    time, an offset from the capture clock, could fall an ulp beside another
    system's tick, and Drake's periodic schedule can then skip it). It holds
    between releases.
    """

    def __init__(self, *, tracker, glasses, occlusions=(), seed: int = 0):
        super().__init__()
        self._p_GK = np.asarray(glasses.p_GK_m, float)
        self._noise_m = tracker.noise_m
        self._latency_s = tracker.latency_s
        self._rate_hz = tracker.rate_hz
        self._occlusions = list(occlusions)
        self._seed = seed
        # The captures still waiting for their latency, and the newest released one.
        self._slots = int(math.floor(tracker.latency_s * tracker.rate_hz + 1e-9)) + 2
        self._head_pose = self.DeclareVectorInputPort("head_pose", HEAD_POSE_SIZE)
        self._queue = self.DeclareDiscreteState(np.tile(_EMPTY_MEASUREMENT, self._slots))
        self.DeclarePeriodicDiscreteUpdateEvent(1.0 / tracker.rate_hz, 0.0, self._capture)
        self.DeclareVectorOutputPort("glasses_measured", MEASUREMENT_SIZE, self._calc_released,
                                     prerequisites_of_calc={self.time_ticket(),
                                                            self.xd_ticket()})

    def _hidden(self, t_s: float) -> bool:
        return any(o.start_s <= t_s < o.end_s for o in self._occlusions)

    def _capture(self, context, discrete_state):
        t = context.get_time()
        k = round(t * self._rate_hz)
        if self._hidden(t):
            measurement = np.concatenate([[t], np.full(7, np.nan), [0.0]])
        else:
            rng = np.random.default_rng((self._seed, k))
            x_WG = measure_glasses(self._head_pose.Eval(context), self._p_GK, self._noise_m, rng)
            measurement = np.concatenate([[t], x_WG, [float(np.all(np.isfinite(x_WG)))]])
        queue = context.get_discrete_state(self._queue).value().reshape(self._slots, -1)
        queue = np.vstack([queue[1:], measurement])  # oldest first
        discrete_state.get_mutable_vector(self._queue).SetFromVector(queue.ravel())

    def _calc_released(self, context, output):
        # Evaluated at every tick that logs it: one compiled call.
        released_capture(context.get_discrete_state(self._queue).value(), self._latency_s,
                         context.get_time(), output.get_mutable_value())


@kernel((READONLY_VECTOR, SCALAR, SCALAR, VECTOR), (VECTOR, SCALAR, SCALAR, VECTOR))
def released_capture(queue, latency_s, t, out) -> None:
    """Into ``out``: the newest capture of ``queue`` (MEASUREMENT_SIZE each, oldest first)
    whose latency (s) has passed by ``t`` (s); the oldest has always passed (the queue
    holds the captures of one latency and one more)."""
    size = out.size
    slot = queue.size // size - 1
    while slot > 0 and not queue[slot * size] + latency_s <= t + SAME_INSTANT_S:
        slot -= 1
    out[:] = queue[slot * size:(slot + 1) * size]


# Nothing captured yet: capture time -inf, no pose, not ok.
_EMPTY_MEASUREMENT = np.array([-np.inf] + [np.nan] * 7 + [0.0])
