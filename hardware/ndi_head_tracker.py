"""The head tracker's driver: an NDI Polaris or Vega publishing the glasses' pose on LCM.

A small adapter: ``scikit-surgerynditracker`` reads the tracker (its ``dummy``
tracker in tests); each frame becomes a ``glasses_t`` message in W on the
channel the application reads. NDI reports the tool's pose in the tracker's
frame N, translation in mm and rotation as a quaternion [w, x, y, z];
``X_WN`` (the tracker's pose in W, from the lab's registration) takes it to W.
A tool the tracker does not see (NaN) is published with ``ok`` false.
"""

from __future__ import annotations

import math
import time

import numpy as np
from pydrake.common.eigen_geometry import Quaternion
from pydrake.math import RigidTransform

from maglev_haptics.hardware.extras import require_extra
from maglev_haptics.hardware.lcm_link import publish
from maglev_haptics.hardware.lcm_messages import glasses_t

MM_PER_M = 1000.0


def glasses_message(sequence: int, capture_s: float, publish_s: float, X_WN: RigidTransform,
                    quaternion_wxyz_N, translation_mm_N) -> glasses_t:
    """One tracker frame of the glasses' tool as a ``glasses_t`` in W (m); ``ok``
    false where the frame holds NaN (not seen) or a quaternion far from unit."""
    message = glasses_t()
    message.sequence = int(sequence)
    message.capture_utime = int(round(capture_s * 1e6))
    message.publish_utime = int(round(publish_s * 1e6))
    q = np.asarray(quaternion_wxyz_N, dtype=float).ravel()
    p_mm = np.asarray(translation_mm_N, dtype=float).ravel()
    seen = q.size == 4 and p_mm.size == 3 and np.all(np.isfinite(q)) and np.all(np.isfinite(p_mm))
    if not seen or abs(np.linalg.norm(q) - 1.0) > 1e-3:
        message.quaternion_wxyz = [1.0, 0.0, 0.0, 0.0]
        message.position_m = [0.0, 0.0, 0.0]
        message.ok = False
        return message
    X_NG = RigidTransform(Quaternion(q / np.linalg.norm(q)), p_mm / MM_PER_M)
    X_WG = X_WN @ X_NG
    q_WG = X_WG.rotation().ToQuaternion()
    message.quaternion_wxyz = [q_WG.w(), q_WG.x(), q_WG.y(), q_WG.z()]
    message.position_m = X_WG.translation().tolist()
    message.ok = True
    return message


class NdiHeadTracker:
    """Reads an NDI tracker and publishes the glasses' pose on LCM.

    ``settings`` is scikit-surgerynditracker's configuration (``{"tracker type":
    "polaris", "serial port": ..., "romfiles": [...]}``, or ``"dummy"``); the
    first tool is the glasses. ``lcm`` is an ``lcm.LCM``.
    """

    def __init__(self, settings: dict, *, lcm, channel: str, X_WN: RigidTransform,
                 latency_s: float = 0.0):
        nditracker = require_extra("sksurgerynditracker.nditracker", "The NDI head tracker")
        # Quaternion rows [qw qx qy qz x y z], not 4x4 matrices.
        self._tracker = nditracker.NDITracker({**settings, "use quaternions": True})
        self._dummy = settings.get("tracker type") == "dummy"
        self._lcm = lcm
        self._channel = channel
        self._X_WN = X_WN
        self._latency_s = float(latency_s)
        self._sequence = 0
        if not self._dummy:  # the dummy has no device to start
            self._tracker.start_tracking()

    def publish_frame(self) -> glasses_t:
        """Read one frame, publish it, and return the message sent."""
        _, _, _, tracking, _ = self._tracker.get_frame()
        now_s = time.time()
        self._sequence += 1
        if tracking:
            pose = np.asarray(tracking[0], dtype=float).ravel()  # [qw qx qy qz x y z] (mm)
            message = glasses_message(self._sequence, now_s - self._latency_s, now_s,
                                      self._X_WN, pose[0:4], pose[4:7])
        else:
            message = glasses_message(self._sequence, now_s, now_s, self._X_WN,
                                      [math.nan] * 4, [math.nan] * 3)
        publish(self._lcm, self._channel, message)
        return message

    def run(self, rate_hz: float, duration_s: float) -> int:
        """Publish a frame every 1 / ``rate_hz`` s for ``duration_s`` s (wall clock);
        returns how many were sent."""
        period_s = 1.0 / rate_hz
        start = time.monotonic()
        sent = 0
        while time.monotonic() - start < duration_s:
            self.publish_frame()
            sent += 1
            time.sleep(max(0.0, start + sent * period_s - time.monotonic()))
        return sent

    def close(self) -> None:
        if not self._dummy:
            self._tracker.stop_tracking()
        self._tracker.close()
