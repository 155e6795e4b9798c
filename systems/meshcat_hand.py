"""Meshcat sliders and a button that drive the simulated hand interactively.

Six sliders set the hand's goal pose in W, x, y, z in millimetres and roll,
pitch, yaw in degrees (Drake's extrinsic X-Y-Z convention); a button (or the
G key) grips and releases. The hand target follows the slider goal through a
critically damped second-order filter, y'' = w^2 (goal - y) - 2 w y' with
w = 1 / time constant, evaluated in closed form between slider samples, so a
slider jump moves the target smoothly with continuous position and rate (a
step of size d peaks at rate d w / e after one time constant) instead of
jolting the hand.
"""

import math
import sys
import time

import numpy as np
from pydrake.systems.framework import LeafSystem

# (name, SI units per slider unit, min, max, step) of the slider of each target
# coordinate; a range is widened to include the start pose.
SLIDERS = (
    ("Hand x (mm)", 1e-3, -150.0, 150.0, 0.1),
    ("Hand y (mm)", 1e-3, -100.0, 100.0, 0.1),
    ("Hand z (mm)", 1e-3, 0.0, 150.0, 0.1),
    ("Hand roll (deg)", math.pi / 180, -60.0, 60.0, 0.1),
    ("Hand pitch (deg)", math.pi / 180, -60.0, 60.0, 0.1),
    ("Hand yaw (deg)", math.pi / 180, -180.0, 180.0, 0.1),
)
GRIP_BUTTON = "Grip / release"
GRIP_KEY = "KeyG"


def wait_for_browser(meshcat, *, poll_s: float = 0.1) -> None:
    """Block until a browser has Meshcat's page open (Ctrl-C gives up): the sliders
    drive the run, so its clock starts only once someone can move them."""
    if meshcat.GetNumActiveConnections() > 0:
        return
    print(f"interactive: open {meshcat.web_url()} in a browser; the run starts when it "
          "connects", file=sys.stderr, flush=True)
    while meshcat.GetNumActiveConnections() == 0:
        time.sleep(poll_s)


def critically_damped_response(value, rate, goal, omega, elapsed_s):
    """(value, rate) of y'' = omega^2 (goal - y) - 2 omega y' after ``elapsed_s`` (s)
    from (value, rate), with ``goal`` held and ``omega`` in 1/s."""
    error = value - goal
    slope = rate + omega * error
    decay = math.exp(-omega * elapsed_s)
    return goal + (error + slope * elapsed_s) * decay, (rate - omega * slope * elapsed_s) * decay


def grip_from_clicks(clicks: float, grip_at_start: bool) -> float:
    """1.0 while gripping: each click of the button toggles the grip."""
    return 1.0 if grip_at_start != (int(clicks) % 2 == 1) else 0.0


class MeshcatHandInput(LeafSystem):
    """Hand target and grip from Meshcat sliders and a button.

    .. pydrake_system::

        name: MeshcatHandInput
        output_ports:
        - hand_target
        - grip

    On construction it adds the sliders ``SLIDERS`` (initialised to
    ``start_pose``, [x, y, z, roll, pitch, yaw] in W, m and rad) and the button
    ``GRIP_BUTTON`` (key ``GRIP_KEY``) to ``meshcat``; ``Delete()`` removes them.
    Every ``period_s`` it samples the sliders and the button's click count into
    its discrete state [target (6), rate (6), goal (6), clicks, sample time].
    ``hand_target`` (12: pose in m, rad, then rates in m/s, rad/s) is the
    filter's exact response since the last sample, starting at ``start_pose``
    at rest; ``grip`` (1) is 1.0 while gripping (``grip_at_start`` toggled by
    each click).
    """

    def __init__(self, meshcat, *, start_pose, filter_time_constant_s: float, period_s: float,
                 grip_at_start: bool = False):
        LeafSystem.__init__(self)
        self._meshcat = meshcat
        self._omega = 1.0 / filter_time_constant_s
        self._grip_at_start = bool(grip_at_start)
        start = np.asarray(start_pose, dtype=float)
        self._scales = np.array([scale for _, scale, _, _, _ in SLIDERS])
        for (name, scale, low, high, step), value in zip(SLIDERS, start):
            shown = value / scale
            meshcat.AddSlider(name, min(low, shown), max(high, shown), step, shown)
        meshcat.AddButton(GRIP_BUTTON, GRIP_KEY)
        self._state = self.DeclareDiscreteState(
            np.concatenate((start, np.zeros(6), start, [0.0, 0.0])))
        self.DeclarePeriodicDiscreteUpdateEvent(period_s, 0.0, self._update)
        self.DeclareVectorOutputPort("hand_target", 12, self._calc_hand_target,
                                     prerequisites_of_calc={self.time_ticket(),
                                                            self.xd_ticket()})
        self.DeclareVectorOutputPort("grip", 1, self._calc_grip,
                                     prerequisites_of_calc={self.xd_ticket()})

    def Delete(self):
        """Remove this system's sliders and button from the shared Meshcat."""
        for name, _, _, _, _ in SLIDERS:
            self._meshcat.DeleteSlider(name)
        self._meshcat.DeleteButton(GRIP_BUTTON)

    def _filtered(self, context):
        """(target, rate) of the filter at the context's time."""
        state = context.get_discrete_state(self._state).CopyToVector()
        return critically_damped_response(state[0:6], state[6:12], state[12:18], self._omega,
                                          context.get_time() - state[19])

    def _update(self, context, discrete_state):
        target, rate = self._filtered(context)
        goal = self._scales * np.array([self._meshcat.GetSliderValue(name)
                                        for name, _, _, _, _ in SLIDERS])
        clicks = self._meshcat.GetButtonClicks(GRIP_BUTTON)
        discrete_state.get_mutable_vector(self._state).SetFromVector(
            np.concatenate((target, rate, goal, [clicks, context.get_time()])))

    def _calc_hand_target(self, context, output):
        output.SetFromVector(np.concatenate(self._filtered(context)))

    def _calc_grip(self, context, output):
        clicks = context.get_discrete_state(self._state).CopyToVector()[18]
        output.SetFromVector([grip_from_clicks(clicks, self._grip_at_start)])
