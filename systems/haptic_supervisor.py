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
  - the request drops (no fault) while the handle is let go (past the debounce,
    the scene holding it): **landing**, where the instrument is. Nobody holds it,
    and the script's pose may be centimetres away (a peg let go in its hole would be
    pulled out and across to it). It stays landed, coils off, whatever the script
    does next, until haptics is requested and the handle gripped again;
  - the handle is let go (for longer than ``release_debounce_s``) while the
    tool touches the scene (within ``contact_memory_s``): the scene holds it
    (a peg let go in its hole stays up between the virtual walls). Nobody
    holds the instrument now, so the device brakes it (a share of the PD's
    damping, ``brake_gain`` output) until the hand grips again: a weightless
    instrument let go would otherwise keep whatever momentum the let-go gave
    it. The share is small (``let_go_brake``) because the coupling's damper
    already acts on it: the free instrument's damping loop crosses over at its
    total damping over its inertia, and the loop's delay eats that loop's
    phase margin (docs/haptic_loop.md, "Let go");
  - let go with the tool free: **landing**. Haptics is disabled and the PD lands
    the instrument level on the glass below where it was let go. Once it has
    settled, the force ramps to zero. Gravity compensation alone would leave a
    released instrument drifting in mid-air.

Setpoints are [x, y, z, roll, pitch, yaw] of I in W then their rates (m, rad,
m/s, rad/s), as the controller's input.
"""

import dataclasses
from dataclasses import dataclass

import numba
import numpy as np
from pydrake.systems.framework import Diagram, LeafSystem

from maglev_haptics.hardware.config_checks import nonnegative, require
from maglev_haptics.hardware.kernels import READONLY_VECTOR, SCALAR, VECTOR, kernel
from maglev_haptics.systems.blends import LANDING_PRESS_M, clipped_minimum_jerk
from maglev_haptics.systems.rotations import drake_roll_pitch_yaw
from maglev_haptics.systems.stacked_ports import BuildStacked, stacked_size, stacked_slices

LEVITATE, HAPTIC, LANDING = 0, 1, 2

# The discrete state vector's layout: single entries, then where the measured pose
# and the offset (6 each) start.
_MODE, _SINCE, _POSE, _OFFSET, _PD, _ENABLE, _RELEASED, _SINCE_CONTACT = (
    0, 1, 2, 8, 14, 15, 16, 17)
STATE_SIZE = 18


@dataclass
class SupervisorConfig:
    """Timing of the mode changes, and the brake on an instrument the scene holds."""

    handover_s: float = 0.5  # PD fade-out at haptics start, and the blend back to the script (s)
    release_debounce_s: float = 0.05  # a let-go shorter than this is ignored (s)
    contact_memory_s: float = 0.1  # the tool counts as touching this long after its last contact (s)
    landing_s: float = 1.5  # minimum-jerk descent to the glass after a free let-go (s)
    settle_s: float = 0.3  # held on the glass after landing, before the force ramps down (s)
    force_ramp_s: float = 0.2  # the ramp-down of the force after landing (s)
    # The brake on an instrument let go that the scene holds: this share of the PD's
    # damping (0..1). With the coupling's damper (b / m = 40 /s on every axis) the
    # free instrument's damping loop then crosses over at 58 /s, not 128 /s at the
    # full PD's: it stays stable with 2 ms more loop delay than in this diagram (the
    # LCM link adds about that), where the full share rang up within 0.7 s.
    let_go_brake: float = 0.2

    def validate(self, path: str = "supervisor") -> None:
        """Every time >= 0, the brake within 0..1; a ValueError names ``path.field``,
        its value and what is allowed."""
        for f in dataclasses.fields(self):
            nonnegative(f"{path}.{f.name}", getattr(self, f.name))
        require(self.let_go_brake <= 1.0, f"{path}.let_go_brake", self.let_go_brake,
                "must be within 0..1 (a share of the PD's damping)")


# ``SupervisorConfig`` as the kernels take it: an array, by these indices.
(_HANDOVER_S, _RELEASE_DEBOUNCE_S, _CONTACT_MEMORY_S, _LANDING_S, _SETTLE_S, _FORCE_RAMP_S,
 _LET_GO_BRAKE) = range(7)


def supervisor_parameters(config: SupervisorConfig) -> np.ndarray:
    """``config``'s times (s) and brake share in the kernels' order."""
    return np.array([config.handover_s, config.release_debounce_s, config.contact_memory_s,
                     config.landing_s, config.settle_s, config.force_ramp_s,
                     config.let_go_brake], dtype=float)


def initial_supervisor_state() -> np.ndarray:
    state = np.zeros(STATE_SIZE)
    state[_MODE] = LEVITATE
    state[_PD] = 1.0
    state[_ENABLE] = 1.0
    state[_SINCE_CONTACT] = np.inf
    return state


@numba.njit(cache=True)
def measured_pose6(X_WI, reference_yaw: float) -> np.ndarray:
    """[x, y, z, roll, pitch, yaw] of a [q; p] pose, yaw unwrapped to within pi of
    ``reference_yaw`` (rad) so a blend from it to the script turns the short way."""
    rpy = drake_roll_pitch_yaw(X_WI[0:4])
    rpy[2] = reference_yaw + (rpy[2] - reference_yaw + np.pi) % (2 * np.pi) - np.pi
    return np.concatenate((X_WI[4:7], rpy))


@numba.njit(cache=True)
def _enter(new, next_mode: int, t: float, scripted_pose6, X_WI) -> None:
    """``new`` switched to ``next_mode`` at time ``t`` (s), at the measured pose."""
    new[_MODE] = next_mode
    new[_SINCE] = t
    new[_POSE:_POSE + 6] = measured_pose6(X_WI, scripted_pose6[5])
    if next_mode == LEVITATE:
        new[_OFFSET:_OFFSET + 6] = new[_POSE:_POSE + 6] - scripted_pose6
    else:
        new[_OFFSET:_OFFSET + 6] = 0.0
    new[_RELEASED] = 0.0


@numba.njit(cache=True)
def supervisor_step(state, t: float, period_s: float, scripted_pose6, X_WI, tracking_ok: bool,
                    request: bool, faulted: bool, gripped: bool, in_contact: bool,
                    parameters) -> np.ndarray:
    """The supervisor's state one period (s) after ``state`` at time ``t`` (s): a latched
    device fault (``faulted``) drops the ``request``; ``parameters`` is
    ``supervisor_parameters(config)``."""
    request = request and not faulted
    new = state.copy()
    mode = int(state[_MODE])
    new[_SINCE_CONTACT] = 0.0 if in_contact else state[_SINCE_CONTACT] + period_s
    new[_RELEASED] = state[_RELEASED] + period_s if (mode == HAPTIC and not gripped) else 0.0

    if mode != HAPTIC and request and gripped and tracking_ok:
        _enter(new, HAPTIC, t, scripted_pose6, X_WI)
    elif mode == HAPTIC and not request:
        # Let go (past the debounce: the scene holds it), nobody is there to hand back to.
        held_by_scene = new[_RELEASED] > parameters[_RELEASE_DEBOUNCE_S]
        _enter(new, LANDING if held_by_scene and not faulted else LEVITATE, t,
               scripted_pose6, X_WI)
    elif (mode == HAPTIC and new[_RELEASED] > parameters[_RELEASE_DEBOUNCE_S]
          and state[_RELEASED] <= parameters[_RELEASE_DEBOUNCE_S]
          and new[_SINCE_CONTACT] > parameters[_CONTACT_MEMORY_S]):
        _enter(new, LANDING, t, scripted_pose6, X_WI)

    step = period_s / parameters[_HANDOVER_S] if parameters[_HANDOVER_S] > 0 else 1.0
    mode = int(new[_MODE])
    if mode == HAPTIC:
        new[_PD] = max(0.0, state[_PD] - step)
    elif mode == LANDING:
        new[_PD] = 1.0
    else:
        new[_PD] = min(1.0, state[_PD] + step)
    landed = mode == LANDING and t - new[_SINCE] > parameters[_LANDING_S] + parameters[_SETTLE_S]
    ramp = period_s / parameters[_FORCE_RAMP_S] if parameters[_FORCE_RAMP_S] > 0 else 1.0
    new[_ENABLE] = (max(0.0, state[_ENABLE] - ramp) if landed
                    else min(1.0, state[_ENABLE] + ramp))
    return new


@numba.njit(cache=True)
def supervisor_gains(state, parameters):
    """(pd_gain, brake_gain, haptics_enable, mode) in ``state``: the PD's share
    0..1, the brake's share of the PD's damping (``let_go_brake`` once haptic and let
    go for longer than the debounce: the scene holds the instrument; else 0), the
    coupling's enable 0/1 and the mode number."""
    haptic = state[_MODE] == HAPTIC
    held_by_scene = haptic and state[_RELEASED] > parameters[_RELEASE_DEBOUNCE_S]
    return (state[_PD], parameters[_LET_GO_BRAKE] if held_by_scene else 0.0,
            1.0 if haptic else 0.0, float(state[_MODE]))


@numba.njit(cache=True)
def supervisor_setpoint(state, t: float, scripted, rest_height_m: float, parameters):
    """The controller's setpoint (12,) in ``state`` at time ``t`` (s), given the
    scripted setpoint (12,); blends are float, the script passes through as it is."""
    mode = int(state[_MODE])
    elapsed = t - state[_SINCE]
    if mode == LANDING:
        start = state[_POSE:_POSE + 6]
        target = np.array([start[0], start[1], rest_height_m - LANDING_PRESS_M,
                           0.0, 0.0, start[5]])
        blend, rate = clipped_minimum_jerk(elapsed, parameters[_LANDING_S])
        return np.concatenate((start + blend * (target - start), rate * (target - start)))
    if mode == LEVITATE and elapsed < parameters[_HANDOVER_S]:
        # The offset at entry fades out, so the setpoint meets the script smoothly.
        blend, rate = clipped_minimum_jerk(elapsed, parameters[_HANDOVER_S])
        offset = state[_OFFSET:_OFFSET + 6]
        return np.concatenate((scripted[0:6] + (1.0 - blend) * offset,
                               scripted[6:12] - rate * offset))
    return scripted


# The supervisor's input ports that only its update reads (name, size), in the order
# of the law's one input. The script is the law's own ports: the outputs read it, and
# must not feed the measurements through (the loop through the scene would be
# algebraic).
SUPERVISOR_INPUTS = (("X_WI_measured", 7), ("tracking_ok", 1), ("haptics_request", 1),
                     ("handle_gripped", 1), ("tool_in_contact", 1), ("fault_bits", 1))
_X_WI, _TRACKING_OK, _REQUEST, _GRIPPED, _IN_CONTACT, _FAULT_BITS = (
    rows.start for rows in stacked_slices(SUPERVISOR_INPUTS).values())
# Its output ports (name, size), in the order of the law's one output.
SUPERVISOR_OUTPUTS = (("setpoint", 12), ("enable", 1), ("pd_gain", 1), ("brake_gain", 1),
                      ("haptics_enable", 1), ("mode", 1))


@kernel((VECTOR, VECTOR, SCALAR, SCALAR, VECTOR, VECTOR))
def supervisor_update(inputs, scripted, t, period_s, parameters, state):
    """One update of ``state`` in place, at time ``t`` (s), from ``inputs``
    (SUPERVISOR_INPUTS stacked) and the scripted setpoint (12)."""
    state[:] = supervisor_step(
        state, t, period_s, scripted[0:6], inputs[_X_WI:_X_WI + 7], inputs[_TRACKING_OK] > 0.5,
        inputs[_REQUEST] > 0.5, inputs[_FAULT_BITS] != 0,
        inputs[_GRIPPED] > 0.5, inputs[_IN_CONTACT] > 0.5, parameters)


@kernel((READONLY_VECTOR, SCALAR, VECTOR, SCALAR, SCALAR, VECTOR, VECTOR))
def supervisor_outputs(state, t, scripted, scripted_enable, rest_height_m, parameters, out):
    """SUPERVISOR_OUTPUTS stacked into ``out``, in ``state`` at time ``t`` (s)."""
    out[0:12] = supervisor_setpoint(state, t, scripted, rest_height_m, parameters)
    out[12] = state[_ENABLE] * scripted_enable
    out[13], out[14], out[15], out[16] = supervisor_gains(state, parameters)


class SupervisorLaw(LeafSystem):
    """``HapticSupervisor``'s arithmetic and state, one compiled call an update and one a
    tick: inputs ``inputs`` (SUPERVISOR_INPUTS stacked), ``scripted_setpoint`` and
    ``scripted_enable``; one output, ``outputs`` (SUPERVISOR_OUTPUTS stacked).

    .. pydrake_system::

        name: SupervisorLaw
        input_ports:
        - inputs
        - scripted_setpoint
        - scripted_enable
        output_ports:
        - outputs
    """

    def __init__(self, *, config: SupervisorConfig, period_s: float, rest_height_m: float):
        LeafSystem.__init__(self)
        self._parameters = supervisor_parameters(config)
        self._period_s = float(period_s)
        self._rest_height_m = float(rest_height_m)
        self._inputs = self.DeclareVectorInputPort("inputs", stacked_size(SUPERVISOR_INPUTS))
        self._scripted = self.DeclareVectorInputPort("scripted_setpoint", 12)
        self._scripted_enable = self.DeclareVectorInputPort("scripted_enable", 1)
        self._state = self.DeclareDiscreteState(initial_supervisor_state())
        self.DeclarePeriodicDiscreteUpdateEvent(period_s, 0.0, self._update)
        # The outputs read the state, the time and the script: none feeds the
        # measurements through, so the loop through the scene has no algebraic loop.
        self.DeclareVectorOutputPort(
            "outputs", stacked_size(SUPERVISOR_OUTPUTS), self._calc_outputs,
            {self.discrete_state_ticket(self._state), self.time_ticket(),
             self._scripted.ticket(), self._scripted_enable.ticket()})

    def _update(self, context, discrete_state):
        # The update's state starts as a copy of the context's: stepped in place.
        supervisor_update(self._inputs.EvalBasicVector(context).value(),
                          self._scripted.EvalBasicVector(context).value(),
                          context.get_time(), self._period_s, self._parameters,
                          discrete_state.get_mutable_value(self._state))

    def _calc_outputs(self, context, output):
        supervisor_outputs(context.get_discrete_state(self._state).get_value(),
                           context.get_time(), self._scripted.EvalBasicVector(context).value(),
                           self._scripted_enable.EvalBasicVector(context).GetAtIndex(0),
                           self._rest_height_m, self._parameters, output.get_mutable_value())


class HapticSupervisor(Diagram):
    """The device's mode logic (see the module docstring).

    .. pydrake_system::

        name: HapticSupervisor
        input_ports:
        - X_WI_measured
        - tracking_ok
        - haptics_request
        - handle_gripped
        - tool_in_contact
        - fault_bits
        - scripted_setpoint
        - scripted_enable
        output_ports:
        - setpoint
        - enable
        - pd_gain
        - brake_gain
        - haptics_enable
        - mode

    The discrete state (updated every ``period_s``) holds the mode, the
    time and measured pose of the last mode change, the offset from the script
    there, the PD and force gains and the release and contact timers;
    ``pd_gain``, ``brake_gain``, ``haptics_enable`` and ``mode`` are read from
    it (``supervisor_gains``).

    A diagram of three blocks (``systems/stacked_ports.py``): the measurements
    stacked for ``SupervisorLaw`` ("law"), whose compiled calls step the state and
    compute every output, and its result split into the named outputs; the
    discrete state is the law's.
    """

    def __init__(self, *, config: SupervisorConfig, period_s: float, rest_height_m: float):
        Diagram.__init__(self)
        BuildStacked(self, leaf=SupervisorLaw(config=config, period_s=period_s,
                                              rest_height_m=rest_height_m),
                     leaf_name="law", inputs=SUPERVISOR_INPUTS, outputs=SUPERVISOR_OUTPUTS,
                     leaf_inputs=("scripted_setpoint", "scripted_enable"))
