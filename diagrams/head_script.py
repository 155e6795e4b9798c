"""Scenario schema of the user's head (wearing the tracked shutter glasses), and
its scripted plan: like the hand, it holds a start pose, then moves through
waypoints by minimum-jerk moves.

A head pose is where the eyes are and what they look at (``systems/head_sensor.py``
turns it into the glasses' pose): ``position_m`` is the eyes' midpoint in W,
``look_at_m`` the point looked at, ``heading_rad`` the direction of the eye axis
(0: the user sits at the display's near, -y, edge, so the eyes lie along W's x),
``roll_rad`` the head's tilt about the line of sight.
"""

from dataclasses import dataclass, field
from typing import List

import numpy as np

from maglev_haptics.diagrams.hand_script import TAIL_S
from maglev_haptics.hardware.config_checks import (
    finite, nonnegative, positive, require, vector)
from maglev_haptics.systems.blends import minimum_jerk_plan
from maglev_haptics.systems.head_sensor import glasses_pose
from maglev_haptics.systems.stereo import MIN_EYE_DISTANCE_M, eye_distance_m, eye_positions_W

# Where a seated user's head and gaze can be: within this of the display's centre on
# each axis (m), well past the head tracker's reach and any room the display stands in.
HEAD_REACH_M = 5.0


@dataclass
class HeadPose:
    # Seated at the near edge, eyes 0.30 m back and 0.45 m above the display's
    # centre (0.54 m away), looking at it: the paper's "from above and the side".
    position_m: List[float] = field(default_factory=lambda: [0.0, -0.30, 0.45])  # (m)
    look_at_m: List[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])  # (m)
    heading_rad: float = 0.0  # (rad)
    roll_rad: float = 0.0  # (rad)

    def vector(self) -> np.ndarray:
        """The ``head_pose`` vector [position, look-at, heading, roll]."""
        return np.array([*self.position_m, *self.look_at_m, self.heading_rad, self.roll_rad],
                        dtype=float)


@dataclass
class HeadWaypoint(HeadPose):
    move_s: float = 1.0  # duration of the minimum-jerk move into this pose (s)
    hold_s: float = 0.0  # time held there (s)


@dataclass
class HeadScript:
    start: HeadPose = field(default_factory=HeadPose)
    start_s: float = 0.0  # the first move starts here (s)
    waypoints: List[HeadWaypoint] = field(default_factory=list)

    def validate(self, path: str, *, screen, ipd_m: float) -> None:
        """ValueError naming the field for a pose that is not finite or out of reach
        (HEAD_REACH_M), whose line of sight is degenerate, or that puts an eye less than
        MIN_EYE_DISTANCE_M in front of the display (behind it, the display cannot be seen)."""
        poses = [(f"{path}.start", self.start)] + [
            (f"{path}.waypoints[{i}]", w) for i, w in enumerate(self.waypoints)]
        nonnegative(f"{path}.start_s", self.start_s)
        centre_W = (np.asarray(screen.pb) + np.asarray(screen.pc)) / 2  # (m)
        for name, pose in poses:
            for point in ("position_m", "look_at_m"):
                value = getattr(pose, point)
                vector(f"{name}.{point}", value, 3)
                require(np.max(np.abs(np.subtract(value, centre_W))) <= HEAD_REACH_M,
                        f"{name}.{point}", value,
                        f"must be within {HEAD_REACH_M:g} m of the display's centre on each axis")
            for angle in ("heading_rad", "roll_rad"):
                require(finite(getattr(pose, angle)), f"{name}.{angle}", getattr(pose, angle),
                        "must be a finite angle (rad)")
            if isinstance(pose, HeadWaypoint):
                positive(f"{name}.move_s", pose.move_s)
                nonnegative(f"{name}.hold_s", pose.hold_s)
            try:
                q_WG, p_WG = glasses_pose(pose.vector())
            except ValueError as error:
                raise ValueError(f"{name}: {error}") from None
            for side, eye in zip(("left", "right"), eye_positions_W(q_WG, p_WG, ipd_m)):
                distance = eye_distance_m(screen.pa, screen.pb, screen.pc, eye)
                if distance < MIN_EYE_DISTANCE_M:
                    raise ValueError(
                        f"{name}.position_m = {pose.position_m}: the {side} eye would be "
                        f"{distance * 1e3:.1f} mm in front of the display plane (negative: behind "
                        f"it); eyes must be at least {MIN_EYE_DISTANCE_M * 1e3:.0f} mm above the "
                        "screen to see it")


def head_plan(script: HeadScript):
    """The ``head_pose`` trajectory (8 rows) of ``script``: a cubic Hermite fit of
    minimum-jerk moves between held poses, with exact rates at the samples."""
    return minimum_jerk_plan(
        script.start.vector(), script.start_s,
        [(w.vector(), w.move_s, w.hold_s) for w in script.waypoints], TAIL_S)
