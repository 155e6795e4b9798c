"""A scripted hand that waits for the application before it runs (``maglev device-sim``).

The device's simulated hand picks the instrument up on the application's clock,
not on the device's, which ran before the application came. Until ``start`` the
hand holds its script's start target and grip; from then on its outputs are the
script at the script's own time, t - ``started_at_s``.

The script is evaluated at that time rather than shifted and handed to a
``TrajectorySource``: a source copies its trajectory and builds its derivative at
each update, 12-14 ms for peg_in_hole's 3112 segments (measured), a stall of a dozen
ticks at the application's first command. ``start`` only records the time; the
price is a Python output each tick (~8 us more than a TrajectorySource, measured).
"""

from typing import Optional

import numpy as np
from pydrake.systems.framework import LeafSystem
from pydrake.trajectories import PiecewisePolynomial


class WaitingHandScript(LeafSystem):
    """The hand's target and grip from its script, held at the start until ``start``.

    .. pydrake_system::

        name: WaitingHandScript
        output_ports:
        - hand_target
        - grip

    ``target`` (6 rows: pose [x, y, z, roll, pitch, yaw] of H in W, m and rad) and
    ``grip`` (1 row, 1.0 while gripping) are the script in its own time (``hand_plan``).
    ``hand_target`` (12) is the pose and its rates (m/s, rad/s), the rates zero
    outside the script's time span, as ``TrajectorySource(target,
    output_derivative_order=1)`` gives them; ``grip`` (1) the grip.
    """

    def __init__(self, *, target: PiecewisePolynomial, grip: PiecewisePolynomial):
        LeafSystem.__init__(self)
        self._target = target
        self._target_rate = target.derivative(1)
        self._grip = grip
        self._rows = target.rows()
        self._script_span_s = (target.start_time(), target.end_time())
        self._held_target = np.concatenate(
            (target.value(self._script_span_s[0])[:, 0], np.zeros(self._rows)))
        self._held_grip = grip.value(grip.start_time())[:, 0]
        self.started_at_s: Optional[float] = None  # this diagram's time of the script's 0 (s)
        self.DeclareVectorOutputPort("hand_target", 2 * self._rows, self._calc_hand_target,
                                     prerequisites_of_calc={self.time_ticket()})
        self.DeclareVectorOutputPort("grip", 1, self._calc_grip,
                                     prerequisites_of_calc={self.time_ticket()})

    def start(self, script_zero_s: float) -> None:
        """Run the script from ``script_zero_s`` (s, this diagram's clock) on; only
        the first call counts."""
        if self.started_at_s is None:
            self.started_at_s = float(script_zero_s)

    def _calc_hand_target(self, context, output):
        if self.started_at_s is None:
            output.SetFromVector(self._held_target)
            return
        script_s = context.get_time() - self.started_at_s
        value = output.get_mutable_value()
        rows = self._rows
        value[:rows] = self._target.value(script_s)[:, 0]
        first_s, last_s = self._script_span_s
        if first_s <= script_s <= last_s:  # a TrajectorySource's rates are zero outside
            value[rows:] = self._target_rate.value(script_s)[:, 0]
        else:
            value[rows:] = 0.0

    def _calc_grip(self, context, output):
        if self.started_at_s is None:
            output.SetFromVector(self._held_grip)
        else:
            output.SetFromVector(self._grip.value(context.get_time() - self.started_at_s)[:, 0])
