"""Scenario schema of the simulated user's hand, and the scripted hand's plan.

Two variants, chosen in YAML by tag (``!ScriptedHand``, ``!MeshcatHand``, as
Drake's hardware_sim picks its drivers): a scripted hand that moves its target
through waypoints and grips and releases at set times, and an interactive one
driven by Meshcat sliders (``systems/meshcat_hand.py``). Both carry the hand's
impedance (``systems/hand.py``). The hand target starts at the start pose, the
instrument's hover pose, where the hand grips it (frame H then coincides with I).
"""

import math
from dataclasses import dataclass, field
from typing import List

import numpy as np
from pydrake.trajectories import PiecewisePolynomial

from maglev_haptics.diagrams.waypoints import Waypoint
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


@dataclass
class MeshcatHand:
    """A hand driven from Meshcat: sliders set its target, a button (or G) grips and releases."""

    impedance: HandImpedanceConfig = field(default_factory=HandImpedanceConfig)
    # The target follows the sliders through a critically damped filter with this time
    # constant (s): a 50 mm slider jump then peaks at 92 mm/s, 0.2 s after it.
    filter_time_constant_s: float = 0.2
    input_rate_hz: float = 30.0  # the sliders and the button are read at this rate (Hz)
    grip_at_start: bool = False  # gripping from t = 0, before any click


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


def _check(ok: bool, label: str, path: str, value, allowed: str) -> None:
    if not ok:
        raise ValueError(f"{label}: {path} = {value!r}: {allowed}")


def _finite(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def _finite_list(values, length: int, minimum: float = -math.inf) -> bool:
    return (isinstance(values, list) and len(values) == length
            and all(_finite(v) and v >= minimum for v in values))


def validate_hand(hand, label: str) -> None:
    """Raise ValueError naming ``label: hand.<field> = value: what is allowed`` for a
    value out of range in ``hand`` (a ScriptedHand or a MeshcatHand)."""
    impedance = hand.impedance
    _check(_finite(impedance.mass_kg) and impedance.mass_kg > 0, label,
           "hand.impedance.mass_kg", impedance.mass_kg, "must be a finite number > 0")
    for name in ("arm_translational_stiffness", "arm_translational_damping",
                 "arm_rotational_stiffness", "arm_rotational_damping",
                 "grip_translational_stiffness", "grip_translational_damping",
                 "grip_rotational_stiffness", "grip_rotational_damping"):
        value = getattr(impedance, name)
        _check(_finite_list(value, 3, 0.0), label, f"hand.impedance.{name}", value,
               "must be 3 finite numbers >= 0 (x, y, z)")
    if isinstance(hand, MeshcatHand):
        _check(_finite(hand.filter_time_constant_s) and hand.filter_time_constant_s > 0, label,
               "hand.filter_time_constant_s", hand.filter_time_constant_s,
               "must be a finite number > 0")
        _check(_finite(hand.input_rate_hz) and hand.input_rate_hz > 0, label,
               "hand.input_rate_hz", hand.input_rate_hz, "must be a finite number > 0")
        return
    _check(_finite(hand.start_s) and hand.start_s >= 0, label, "hand.start_s", hand.start_s,
           "must be a finite number >= 0")
    for i, waypoint in enumerate(hand.waypoints):
        path = f"hand.waypoints[{i}]"
        _check(_finite_list(waypoint.pose, 6), label, f"{path}.pose", waypoint.pose,
               "must be 6 finite numbers [x, y, z, roll, pitch, yaw] (m, rad)")
        _check(_finite(waypoint.move_s) and waypoint.move_s > 0, label, f"{path}.move_s",
               waypoint.move_s, "must be a finite number > 0")
        _check(_finite(waypoint.hold_s) and waypoint.hold_s >= 0, label, f"{path}.hold_s",
               waypoint.hold_s, "must be a finite number >= 0")
    for i, event in enumerate(hand.events):
        _check(_finite(event.at_s) and event.at_s >= 0, label, f"hand.events[{i}].at_s",
               event.at_s, "must be a finite number >= 0")
