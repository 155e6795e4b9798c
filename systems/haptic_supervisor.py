"""Mode logic of the haptic device (MLHI style): levitate, haptic, landing.

- **levitate**: the levitation controller's PD tracks the scripted setpoint
  (takeoff, hover, landing of the motion script).
- **haptic**: entered when haptics is requested and the handle is gripped (it
  engages only in the user's hand). The PD fades out over ``handover_s`` while
  the coupling's force ramps in, so the hand takes over from position control;
  then the device renders only the weight compensation plus the coupling.
- leaving haptic mode:
  - the request drops, or the device supervisor latches a fault (``fault_bits``
    non-zero: until its reset, as if the request had dropped): back to levitate.
    The setpoint starts at the pose where haptics ended and blends into the
    script over ``handover_s``, so disabling never yanks the instrument; after a
    fault the script is the device supervisor's landing;
  - the handle is let go (for longer than ``release_debounce_s``) while the
    tool touches the scene (within ``contact_memory_s``): the scene holds it
    (a peg let go in its hole stays up between the virtual walls). Nobody
    holds the instrument now, so the device brakes it (the PD's damping,
    ``brake`` output) until the hand grips again: a weightless instrument let
    go would otherwise keep whatever momentum the let-go gave it;
  - let go with the tool free: **landing**. Haptics is disabled and the PD lands
    the instrument level on the glass below where it was let go. Once it has
    settled, the force ramps to zero. Gravity compensation alone would leave a
    released instrument drifting in mid-air.

Setpoints are [x, y, z, roll, pitch, yaw] of I in W then their rates (m, rad,
m/s, rad/s), as the controller's input.
"""

import dataclasses
from dataclasses import dataclass

import numpy as np
from pydrake.common.eigen_geometry import Quaternion
from pydrake.math import RollPitchYaw
from pydrake.systems.framework import LeafSystem

from maglev_haptics.hardware.config_checks import nonnegative
from maglev_haptics.systems.blends import LANDING_PRESS_M, clipped_minimum_jerk

LEVITATE, HAPTIC, LANDING = 0, 1, 2

# The discrete state vector's layout.
_MODE, _SINCE, _POSE, _OFFSET, _PD, _ENABLE, _RELEASED, _SINCE_CONTACT = (
    0, 1, slice(2, 8), slice(8, 14), 14, 15, 16, 17)
STATE_SIZE = 18


@dataclass
class SupervisorConfig:
    """Timing of the mode changes."""

    handover_s: float = 0.5  # PD fade-out at haptics start, and the blend back to the script (s)
    release_debounce_s: float = 0.05  # a let-go shorter than this is ignored (s)
    contact_memory_s: float = 0.1  # the tool counts as touching this long after its last contact (s)
    landing_s: float = 1.5  # minimum-jerk descent to the glass after a free let-go (s)
    settle_s: float = 0.3  # held on the glass after landing, before the force ramps down (s)
    force_ramp_s: float = 0.2  # the ramp-down of the force after landing (s)

    def validate(self, path: str = "supervisor") -> None:
        """Every time >= 0; a ValueError names ``path.field`` and its value."""
        for f in dataclasses.fields(self):
            nonnegative(f"{path}.{f.name}", getattr(self, f.name))


def initial_supervisor_state() -> np.ndarray:
    state = np.zeros(STATE_SIZE)
    state[_MODE] = LEVITATE
    state[_PD] = 1.0
    state[_ENABLE] = 1.0
    state[_SINCE_CONTACT] = np.inf
    return state


def measured_pose6(X_WI, reference_yaw: float) -> np.ndarray:
    """[x, y, z, roll, pitch, yaw] of a [q; p] pose, yaw unwrapped to within pi of
    ``reference_yaw`` (rad) so a blend from it to the script turns the short way."""
    q_WI = np.asarray(X_WI[0:4], float)
    rpy = RollPitchYaw(Quaternion(q_WI / np.linalg.norm(q_WI))).vector()
    rpy[2] = reference_yaw + (rpy[2] - reference_yaw + np.pi) % (2 * np.pi) - np.pi
    return np.concatenate((np.asarray(X_WI[4:7], float), rpy))


def supervisor_step(state: np.ndarray, t: float, period_s: float, scripted_pose6: np.ndarray,
                    X_WI, tracking_ok: bool, request: bool, gripped: bool, in_contact: bool,
                    config: SupervisorConfig) -> np.ndarray:
    """The supervisor's state one period (s) after ``state`` at time ``t`` (s)."""
    new = state.copy()
    mode = int(state[_MODE])
    new[_SINCE_CONTACT] = 0.0 if in_contact else state[_SINCE_CONTACT] + period_s
    new[_RELEASED] = state[_RELEASED] + period_s if (mode == HAPTIC and not gripped) else 0.0

    def enter(next_mode):
        new[_MODE] = next_mode
        new[_SINCE] = t
        new[_POSE] = measured_pose6(X_WI, scripted_pose6[5])
        new[_OFFSET] = new[_POSE] - scripted_pose6 if next_mode == LEVITATE else 0.0
        new[_RELEASED] = 0.0

    if mode != HAPTIC and request and gripped and tracking_ok:
        enter(HAPTIC)
    elif mode == HAPTIC and not request:
        enter(LEVITATE)
    elif (mode == HAPTIC and new[_RELEASED] > config.release_debounce_s
          and state[_RELEASED] <= config.release_debounce_s
          and new[_SINCE_CONTACT] > config.contact_memory_s):
        enter(LANDING)

    step = period_s / config.handover_s if config.handover_s > 0 else 1.0
    mode = int(new[_MODE])
    if mode == HAPTIC:
        new[_PD] = max(0.0, state[_PD] - step)
    elif mode == LANDING:
        new[_PD] = 1.0
    else:
        new[_PD] = min(1.0, state[_PD] + step)
    landed = mode == LANDING and t - new[_SINCE] > config.landing_s + config.settle_s
    ramp = period_s / config.force_ramp_s if config.force_ramp_s > 0 else 1.0
    new[_ENABLE] = (max(0.0, state[_ENABLE] - ramp) if landed
                    else min(1.0, state[_ENABLE] + ramp))
    return new


# The state-output ports, in the order supervisor_gains returns them.
_GAIN_OUTPUTS = ("pd_gain", "brake_gain", "haptics_enable", "mode")


def supervisor_gains(state: np.ndarray, config: SupervisorConfig):
    """(pd_gain, brake_gain, haptics_enable, mode) in ``state``: the PD's share
    0..1, the brake 0/1 (haptic, let go for longer than the debounce: the scene
    holds the instrument), the coupling's enable 0/1 and the mode number."""
    haptic = state[_MODE] == HAPTIC
    held_by_scene = haptic and state[_RELEASED] > config.release_debounce_s
    return (state[_PD], 1.0 if held_by_scene else 0.0, 1.0 if haptic else 0.0,
            float(state[_MODE]))


def supervisor_setpoint(state: np.ndarray, t: float, scripted, rest_height_m: float,
                        config: SupervisorConfig):
    """The controller's setpoint (12,) in ``state`` at time ``t`` (s), given the
    scripted setpoint (12,); blends are float, the script passes through as it is."""
    mode = int(state[_MODE])
    elapsed = t - state[_SINCE]
    if mode == LANDING:
        start = state[_POSE]
        target = np.array([start[0], start[1], rest_height_m - LANDING_PRESS_M,
                           0.0, 0.0, start[5]])
        blend, rate = clipped_minimum_jerk(elapsed, config.landing_s)
        return np.concatenate((start + blend * (target - start), rate * (target - start)))
    if mode == LEVITATE and elapsed < config.handover_s:
        # The offset at entry fades out, so the setpoint meets the script smoothly.
        blend, rate = clipped_minimum_jerk(elapsed, config.handover_s)
        offset = state[_OFFSET]
        return np.concatenate((scripted[0:6] + (1.0 - blend) * offset,
                               scripted[6:12] - rate * offset))
    return scripted


class HapticSupervisor(LeafSystem):
    """The device's mode logic (see the module docstring).

    .. pydrake_system::

        name: HapticSupervisor
        input_ports:
        - scripted_setpoint
        - scripted_enable
        - X_WI_measured
        - tracking_ok
        - haptics_request
        - handle_gripped
        - tool_in_contact
        - fault_bits
        output_ports:
        - setpoint
        - enable
        - pd_gain
        - brake_gain
        - haptics_enable
        - mode

    The discrete state (updated every ``period_s``) holds the mode, the
    time and measured pose of the last mode change, the PD and force
    gains and the release and contact timers, and, in groups of their
    own, what ``pd_gain``, ``brake_gain``, ``haptics_enable`` and ``mode``
    output (``supervisor_gains``).
    """

    def __init__(self, *, config: SupervisorConfig, period_s: float, rest_height_m: float):
        LeafSystem.__init__(self)
        self._config = config
        self._period_s = float(period_s)
        self._rest_height_m = float(rest_height_m)
        self._scripted = self.DeclareVectorInputPort("scripted_setpoint", 12)
        self._scripted_enable = self.DeclareVectorInputPort("scripted_enable", 1)
        self._X_WI = self.DeclareVectorInputPort("X_WI_measured", 7)
        self._tracking_ok = self.DeclareVectorInputPort("tracking_ok", 1)
        self._request = self.DeclareVectorInputPort("haptics_request", 1)
        self._gripped = self.DeclareVectorInputPort("handle_gripped", 1)
        self._in_contact = self.DeclareVectorInputPort("tool_in_contact", 1)
        self._fault_bits = self.DeclareVectorInputPort("fault_bits", 1)
        self._state = self.DeclareDiscreteState(initial_supervisor_state())
        self.DeclarePeriodicDiscreteUpdateEvent(period_s, 0.0, self._update)
        # Outputs read the state and at most the script: none feeds through the
        # measurements, so the loop through the scene has no algebraic loop.
        state = {self.xd_ticket()}
        self.DeclareVectorOutputPort(
            "setpoint", 12, self._calc_setpoint,
            state | {self.time_ticket(), self._scripted.ticket()})
        self.DeclareVectorOutputPort("enable", 1, self._calc_enable,
                                     state | {self._scripted_enable.ticket()})
        # The gains and the mode are kept as state groups of their own, so their
        # ports are plain state outputs read every tick without calling Python.
        initial = supervisor_gains(initial_supervisor_state(), config)
        self._gains = {name: self.DeclareDiscreteState([value])
                       for name, value in zip(_GAIN_OUTPUTS, initial)}
        for name, group in self._gains.items():
            self.DeclareStateOutputPort(name, group)

    def _values(self, context) -> np.ndarray:
        return context.get_discrete_state(self._state).CopyToVector()

    def _update(self, context, discrete_state):
        new = supervisor_step(
            self._values(context), context.get_time(), self._period_s,
            self._scripted.Eval(context)[0:6], self._X_WI.Eval(context),
            self._tracking_ok.Eval(context)[0] > 0.5,
            self._request.Eval(context)[0] > 0.5 and self._fault_bits.Eval(context)[0] == 0,
            self._gripped.Eval(context)[0] > 0.5, self._in_contact.Eval(context)[0] > 0.5,
            self._config)
        discrete_state.get_mutable_vector(self._state).SetFromVector(new)
        for name, value in zip(_GAIN_OUTPUTS, supervisor_gains(new, self._config)):
            discrete_state.get_mutable_vector(self._gains[name]).SetAtIndex(0, value)

    def _calc_setpoint(self, context, output):
        output.SetFromVector(supervisor_setpoint(
            self._values(context), context.get_time(), self._scripted.Eval(context),
            self._rest_height_m, self._config))

    def _calc_enable(self, context, output):
        gain = self._values(context)[_ENABLE]
        output.SetFromVector(gain * self._scripted_enable.Eval(context))
