"""A scripted pose to move to and hold: the motion script's and the hand script's step."""

from dataclasses import dataclass, field
from typing import List


@dataclass
class Waypoint:
    """A pose to move to and hold."""

    pose: List[float] = field(default_factory=lambda: [0.0, 0.0, 0.020, 0.0, 0.0, 0.0])
    # [x, y, z, roll, pitch, yaw] in W of the frame being moved: the instrument's I in
    # the motion script, the hand's H in the hand script (m, rad; yaw unwrapped:
    # 6.283 is a full turn)
    move_s: float = 1.0  # duration of the minimum-jerk move into this pose (s)
    hold_s: float = 1.0  # time held at the pose (s)
