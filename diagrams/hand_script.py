"""Scenario schema of the simulated user's hand, and the scripted hand's plan.

Two variants, chosen in YAML by tag (``!ScriptedHand``, ``!MeshcatHand``, as
Drake's hardware_sim picks its drivers): a scripted hand that moves its target
through waypoints and grips and releases at set times, and an interactive one
driven by Meshcat sliders (``systems/meshcat_hand.py``). Both carry the hand's
impedance (``systems/hand.py``). The hand target starts at the start pose, the
instrument's hover pose, where the hand grips it (frame H then coincides with I).
"""

from dataclasses import dataclass, field
from typing import List

import numpy as np
from pydrake.trajectories import PiecewisePolynomial

from maglev_haptics.diagrams.waypoints import Waypoint
from maglev_haptics.hardware.config_checks import finite, nonnegative, positive, require
from maglev_haptics.systems.blends import minimum_jerk_plan
from maglev_haptics.systems.hand import HandImpedanceConfig

# The plans end with this long a hold of their last value (s), so each has a segment
# however short the script; beyond its end a PiecewisePolynomial holds its end value.
TAIL_S = 1.0


@dataclass
class GripEvent:
    """The hand grips (true) or releases (false) the instrument at a time."""

    at_s: float = 0.0  # (s)
    grip: bool = True


@dataclass
class ScriptedHand:
    """A hand whose target holds the start pose until ``start_s``, then moves through
    the waypoints; it grips and releases at the events (released before the first)."""

    impedance: HandImpedanceConfig = field(default_factory=HandImpedanceConfig)
    start_s: float = 0.0  # the first move starts here (s)
    waypoints: List[Waypoint] = field(default_factory=list)
    events: List[GripEvent] = field(default_factory=list)

    def validate(self, path: str = "hand") -> None:
        """Range checks; a ValueError names ``path.field``, its value and what is allowed."""
        self.impedance.validate(f"{path}.impedance")
        nonnegative(f"{path}.start_s", self.start_s)
        for i, waypoint in enumerate(self.waypoints):
            here = f"{path}.waypoints[{i}]"
            require(isinstance(waypoint.pose, list) and len(waypoint.pose) == 6
                    and all(map(finite, waypoint.pose)), f"{here}.pose", waypoint.pose,
                    "must be 6 finite numbers [x, y, z, roll, pitch, yaw] (m, rad)")
            positive(f"{here}.move_s", waypoint.move_s)
            nonnegative(f"{here}.hold_s", waypoint.hold_s)
        for i, event in enumerate(self.events):
            nonnegative(f"{path}.events[{i}].at_s", event.at_s)


@dataclass
class MeshcatHand:
    """A hand driven from Meshcat: sliders set its target, a button (or G) grips and releases."""

    impedance: HandImpedanceConfig = field(default_factory=HandImpedanceConfig)
    # The target follows the sliders through a critically damped filter with this time
    # constant (s): a 50 mm slider jump then peaks at 92 mm/s, 0.2 s after it.
    filter_time_constant_s: float = 0.2
    input_rate_hz: float = 30.0  # the sliders and the button are read at this rate (Hz)
    grip_at_start: bool = False  # gripping from t = 0, before any click

    def validate(self, path: str = "hand") -> None:
        """Range checks; a ValueError names ``path.field``, its value and what is allowed."""
        self.impedance.validate(f"{path}.impedance")
        positive(f"{path}.filter_time_constant_s", self.filter_time_constant_s)
        positive(f"{path}.input_rate_hz", self.input_rate_hz)


def hand_plan(script: ScriptedHand, start_pose):
    """(target, grip) trajectories of ``script`` from ``start_pose`` ([x, y, z, roll,
    pitch, yaw] of H in W, m and rad).

    ``target`` has 6 rows: minimum-jerk moves between held poses, exact rates at the
    samples (use it with ``TrajectorySource(..., output_derivative_order=1)`` for the
    12-vector [pose; rates]). ``grip`` has 1 row, 1.0 while gripping, a zero-order
    hold stepping at the event times (later events win at equal times).
    """

    target = minimum_jerk_plan(start_pose, script.start_s,
                               [(w.pose, w.move_s, w.hold_s) for w in script.waypoints], TAIL_S)

    grip_times, grips = [0.0], [0.0]
    for event in sorted(script.events, key=lambda e: e.at_s):
        if event.at_s > grip_times[-1]:
            grip_times.append(event.at_s)
            grips.append(0.0)
        grips[-1] = 1.0 if event.grip else 0.0
    # A zero-order hold's last sample only closes the last segment: repeat it.
    grip_times.append(grip_times[-1] + TAIL_S)
    grips.append(grips[-1])
    grip = PiecewisePolynomial.ZeroOrderHold(grip_times, np.array([grips]))
    return target, grip
