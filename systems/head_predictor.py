"""Head pose predictor (application): glasses samples at ~10 Hz, tens of ms old,
to the glasses pose when the next frame is shown.

The paper's head tracking lagged "noticeably if the user's head moves quickly":
each frame was drawn for where the head had been, on average half a tracker
period plus the latency before. Here a steady-state constant-velocity Kalman
filter (``pose_estimator``'s alpha-beta filter, with rotation-vector
innovations) runs on the samples at their capture times, and each view update
extrapolates its estimate at constant velocity to the time the frame will be
on the screen: capture-to-display is then bridged, not suffered.

``mode: hold`` draws with the latest sample instead (what the paper did); the
``X_WG_latest`` output always carries it, so one run shows both.

Lost glasses: extrapolation stops ``max_extrapolation_s`` after the last good
capture and the view holds there until the glasses are seen again, when the
filter restarts from that sample.
"""


from dataclasses import dataclass
from typing import Optional

import numpy as np
from pydrake.systems.framework import LeafSystem

from maglev_haptics.hardware.config_checks import nonnegative, positive, require
from maglev_haptics.systems.marker_sensor import extrapolate_pose
from maglev_haptics.systems.pose_estimator import alpha_beta_gains, filter_update

PREDICTOR_MODES = ("kalman", "hold")
# A gap of more than this many tracker periods between good samples restarts the
# filter: its velocity is stale and its fixed-period gains do not fit the gap.
RESTART_AFTER_PERIODS = 1.5


@dataclass
class HeadPredictorConfig:
    mode: str = "kalman"  # kalman: predict to the frame's display time; hold: the latest sample
    # Closed-loop bandwidth of the filter (Hz), below the tracker's Nyquist rate. Higher
    # follows head reversals sooner; lower smooths marker noise more. At 0.1 mm the noise
    # hardly matters, lag does: on the head_sweep scenario the mean screen-space error
    # is 2.1 / 0.51 / 0.40 / 0.36 mm at 0.8 / 2.5 / 3.5 / 4.5 Hz, 1.08 mm held.
    bandwidth_hz: float = 3.5
    # From the view update to the frame's display (s); None: half a view period
    # (the frame is on the screen for one view period after its update).
    display_delay_s: Optional[float] = None
    max_extrapolation_s: float = 0.3  # beyond this after the last good sample, hold (s)

    def validate(self, path: str, *, head_tracker_rate_hz: float) -> None:
        """Range checks; a ValueError names ``path.field``, its value and what is allowed."""
        require(self.mode in PREDICTOR_MODES, f"{path}.mode", self.mode,
                f"must be one of {', '.join(PREDICTOR_MODES)}")
        positive(f"{path}.bandwidth_hz", self.bandwidth_hz)
        require(self.bandwidth_hz < head_tracker_rate_hz / 2, f"{path}.bandwidth_hz",
                self.bandwidth_hz,
                f"must be below the head tracker's Nyquist rate ({head_tracker_rate_hz / 2} Hz)")
        if self.display_delay_s is not None:
            nonnegative(f"{path}.display_delay_s", self.display_delay_s)
        positive(f"{path}.max_extrapolation_s", self.max_extrapolation_s)


def predicted_pose(x_hat: np.ndarray, V: np.ndarray, horizon_s: float,
                   max_extrapolation_s: float) -> np.ndarray:
    """The filtered pose [q, p] carried ``horizon_s`` ahead at constant velocity V
    ([w; v] in W, rad/s and m/s), no further than ``max_extrapolation_s``."""
    return extrapolate_pose(x_hat, V, min(max(horizon_s, 0.0), max_extrapolation_s))


class HeadPosePredictor(LeafSystem):
    """Filters the glasses samples and predicts the pose at each frame's display time.

    .. pydrake_system::

        name: HeadPosePredictor
        input_ports:
        - glasses_measured
        output_ports:
        - X_WG_predicted
        - X_WG_latest
        - head_tracking_ok

    Runs at the view rate; outputs are state, held between updates. Poses are
    [qw, qx, qy, qz, x, y, z]; NaN until the glasses are first seen.
    """

    def __init__(self, *, config: HeadPredictorConfig, tracker_rate_hz: float,
                 period_s: float):
        super().__init__()
        if config.mode not in PREDICTOR_MODES:
            raise ValueError(f"stereo.predictor.mode = {config.mode!r}: must be one of "
                             f"{', '.join(PREDICTOR_MODES)}")
        self._config = config
        self._tracker_period_s = 1.0 / tracker_rate_hz
        self._alpha, self._beta = alpha_beta_gains(config.bandwidth_hz, self._tracker_period_s)
        self._display_delay_s = (period_s / 2 if config.display_delay_s is None
                                 else config.display_delay_s)
        self._measured = self.DeclareVectorInputPort("glasses_measured", 9)
        nan7 = np.full(7, np.nan)
        # filter: [x_hat (7), V (6), capture time of x_hat, capture time last seen, tracking]
        self._filter = self.DeclareDiscreteState(
            np.concatenate([nan7, np.zeros(6), [-np.inf, -np.inf, 0.0]]))
        self._predicted = self.DeclareDiscreteState(nan7)
        self._latest = self.DeclareDiscreteState(nan7)
        self._ok = self.DeclareDiscreteState([0.0])
        self.DeclarePeriodicDiscreteUpdateEvent(period_s, 0.0, self._update)
        self.DeclareStateOutputPort("X_WG_predicted", self._predicted)
        self.DeclareStateOutputPort("X_WG_latest", self._latest)
        self.DeclareStateOutputPort("head_tracking_ok", self._ok)

    @property
    def gains(self):
        """(alpha, beta) of the filter at the tracker's period."""
        return self._alpha, self._beta

    def _update(self, context, discrete_state):
        c = self._config
        measured = self._measured.Eval(context)
        t_capture, x_meas, good = measured[0], measured[1:8].copy(), measured[8] > 0.5
        f = context.get_discrete_state(self._filter).value().copy()
        x_hat, V = f[0:7], f[7:13]
        t_filtered, t_seen, tracking = f[13], f[14], f[15] > 0.5
        latest = context.get_discrete_state(self._latest).value()
        if t_capture > t_seen:
            t_seen = t_capture
            if good:
                latest = x_meas
                if tracking and t_capture - t_filtered <= RESTART_AFTER_PERIODS * self._tracker_period_s:
                    if np.dot(x_meas[0:4], x_hat[0:4]) < 0:
                        x_meas[0:4] = -x_meas[0:4]  # same rotation, no jump in the innovation
                    x_hat, V = filter_update(x_hat, V, x_meas, self._alpha, self._beta,
                                             self._tracker_period_s)
                else:
                    x_hat, V = x_meas, np.zeros(6)
                t_filtered, tracking = t_capture, True
            else:
                tracking = False
        discrete_state.get_mutable_vector(self._filter).SetFromVector(
            np.concatenate([x_hat, V, [t_filtered, t_seen, float(tracking)]]))
        discrete_state.get_mutable_vector(self._latest).SetFromVector(latest)
        horizon_s = context.get_time() + self._display_delay_s - t_filtered
        if c.mode == "hold":
            predicted = latest
        else:
            predicted = predicted_pose(x_hat, V, horizon_s, c.max_extrapolation_s)
        discrete_state.get_mutable_vector(self._predicted).SetFromVector(predicted)
        ok = tracking and horizon_s <= c.max_extrapolation_s
        discrete_state.get_mutable_vector(self._ok).SetFromVector([float(ok)])
