"""The head tracker's driver: an NDI Polaris or Vega publishing the glasses' pose on LCM.

A small adapter: ``scikit-surgerynditracker`` reads the tracker (its ``dummy``
tracker in tests); each frame becomes a ``glasses_t`` message in W on the
channel the application reads. NDI reports the tool's pose in the tracker's
frame N, translation in mm and rotation as a quaternion [w, x, y, z];
``X_WN`` (the tracker's pose in W, from the lab's registration) takes it to W.
A tool the tracker does not see (NaN) is published with ``ok`` false. So is a
frame the adapter cannot read (``parse_tool_pose``: the wrong shape, part NaN, an
infinity, a quaternion far from unit, the glasses beyond ``HEAD_RANGE_M`` of the
display): it is counted by reason (``refused``) and the first of each kind logged
in one line, and no number of it is sent.
"""

from __future__ import annotations

import math
import time

import numpy as np
from pydrake.common.eigen_geometry import Quaternion
from pydrake.math import RigidTransform

from maglev_haptics.hardware.link.extras import require_extra
from maglev_haptics.hardware.link.lcm_link import publish
from maglev_haptics.hardware.link.lcm_messages import glasses_t
from maglev_haptics.hardware.link.link_checks import (
    REASONS, UNIT_QUATERNION_TOLERANCE, Refused, check_glasses, log_to_stderr)

MM_PER_M = 1000.0


def parse_tool_pose(row):
    """(q_NG (wxyz), p_NG (mm)) from one tool's row of a scikit-surgerynditracker
    frame ([qw qx qy qz x y z]); None where the tool is not seen (all NaN); raises
    Refused for a row it cannot read."""
    try:
        pose = np.asarray(row, dtype=float).ravel()
    except (TypeError, ValueError, OverflowError) as error:
        raise Refused("malformed", f"tool row {str(row)[:60]!r}: not numbers ({error})") from None
    if pose.size != 7:
        raise Refused("wrong_size", f"tool row of {pose.size} numbers: must be 7 "
                      "([qw qx qy qz x y z])")
    if np.all(np.isnan(pose)):
        return None
    if not np.all(np.isfinite(pose)):
        raise Refused("not_finite", f"tool row = {pose.tolist()}: must be finite, or all NaN "
                      "(not seen)")
    # Scaled by the largest component: a finite quaternion of 1e200 would overflow.
    largest = float(np.max(np.abs(pose[0:4])))
    norm = largest * float(np.linalg.norm(pose[0:4] / largest)) if largest > 0 else 0.0
    if abs(norm - 1.0) > UNIT_QUATERNION_TOLERANCE:
        raise Refused("out_of_range", f"quaternion = {pose[0:4].tolist()}: must have norm 1 "
                      f"(+-{UNIT_QUATERNION_TOLERANCE:g}), not {norm:.6g}")
    return pose[0:4] / norm, pose[4:7]


def _unseen(message: glasses_t) -> glasses_t:
    message.quaternion_wxyz = [1.0, 0.0, 0.0, 0.0]
    message.position_m = [0.0, 0.0, 0.0]
    message.ok = False
    return message


def glasses_message(sequence: int, capture_s: float, publish_s: float, X_WN: RigidTransform,
                    quaternion_wxyz_N, translation_mm_N) -> glasses_t:
    """One tracker frame of the glasses' tool as a ``glasses_t`` in W (m); ``ok``
    false where the frame holds NaN (not seen). Raises Refused for a pose the link
    would refuse (``parse_tool_pose``, ``check_glasses``)."""
    message = glasses_t()
    message.sequence = int(sequence)
    message.capture_utime = int(round(capture_s * 1e6))
    message.publish_utime = int(round(publish_s * 1e6))
    parsed = parse_tool_pose(np.r_[np.asarray(quaternion_wxyz_N, dtype=float).ravel(),
                                   np.asarray(translation_mm_N, dtype=float).ravel()])
    if parsed is None:
        return _unseen(message)
    q, p_mm = parsed
    X_NG = RigidTransform(Quaternion(q), p_mm / MM_PER_M)
    X_WG = X_WN @ X_NG
    q_WG = X_WG.rotation().ToQuaternion()
    message.quaternion_wxyz = [q_WG.w(), q_WG.x(), q_WG.y(), q_WG.z()]
    message.position_m = X_WG.translation().tolist()
    message.ok = True
    check_glasses(message)
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
        self.refused = dict.fromkeys(REASONS, 0)  # frames published as unseen, by reason
        self._logged = set()
        if not self._dummy:  # the dummy has no device to start
            self._tracker.start_tracking()

    def publish_frame(self) -> glasses_t:
        """Read one frame, publish it, and return the message sent."""
        _, _, _, tracking, _ = self._tracker.get_frame()
        message = self.frame_message(tracking, time.time())
        publish(self._lcm, self._channel, message)
        return message

    def frame_message(self, tracking, now_s: float) -> glasses_t:
        """The ``glasses_t`` for a frame's ``tracking`` (one row a tool, the glasses
        first; [qw qx qy qz x y z], mm) read at ``now_s`` (s): unseen, counted, for a
        frame that cannot be read."""
        self._sequence += 1
        try:
            row = tracking[0] if len(tracking) else [math.nan] * 7
            pose = parse_tool_pose(row)
            if pose is None:
                return glasses_message(self._sequence, now_s, now_s, self._X_WN,
                                       [math.nan] * 4, [math.nan] * 3)
            return glasses_message(self._sequence, now_s - self._latency_s, now_s,
                                   self._X_WN, *pose)
        except (TypeError, IndexError, KeyError) as error:
            refusal = Refused("malformed", f"tracking = {str(tracking)[:60]!r}: not a list "
                              f"of tool rows ({error})")
        except Refused as error:
            refusal = error
        self.refused[refusal.reason] += 1
        if refusal.reason not in self._logged:
            self._logged.add(refusal.reason)
            log_to_stderr(f"head tracker: a frame read as unseen ({refusal.reason}): "
                          f"{refusal.detail}; more of this kind are counted, not logged")
        message = glasses_t()
        message.sequence = self._sequence
        message.capture_utime = message.publish_utime = int(round(now_s * 1e6))
        return _unseen(message)

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
