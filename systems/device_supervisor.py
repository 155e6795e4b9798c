"""The device's supervisor: what the levitation controller is asked to fly, and the
faults that end it (the MLHI device's state machine, in the diagram).

It holds the commanded motion (a setpoint and a force-ramp trajectory from a start
time; a held pose is a motion that does not move) and the latched fault bits of
``device_status_t``: sensor out of range (tracking lost, or the instrument outside
the boundary sphere), coil over-temperature (the thermal model's estimate past the
windings' limit, or the coils too warm to carry what is asked within their thermal
budget), coil over-current, over-speed. Its watchdogs check the measurements every few ticks; a
new fault latches and, unless a landing is under way, lands the instrument from where
its setpoint is (a lost instrument the controller lands blind, whatever the setpoint).
It also holds the coils' power (the device's enable line, cut by a contactor on the
amplifiers' supply): an amplifier that no longer follows its command cannot be
turned off through it, so on a stuck amplifier the supervisor cuts the power once
the instrument rests, or at once when the other coils cannot carry it against the
stuck one (``cut_coil_power``).

`maglev run`'s scripted flight is its first motion; the device API
(``diagrams/device_api.py``) sets motions between ticks. So both fly, and fault,
through the same system.
"""

import math
from dataclasses import dataclass, field
from functools import cached_property, lru_cache
from typing import Callable, List, Optional, Tuple

import numba
import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import BasicVector, Diagram, LeafSystem
from pydrake.trajectories import PiecewisePolynomial

from maglev_haptics.hardware.config_checks import positive, require, vector
from maglev_haptics.hardware.kernels import (
    FLAG, INDEX, INDEX_VECTOR, MATRIX, SCALAR, VECTOR, kernel)
from maglev_haptics.hardware.exact_arithmetic import euclidean_norm, hypot, largest
from maglev_haptics.hardware.link.lcm_messages import device_status_t
from maglev_haptics.systems.stacked_ports import BuildStacked, stacked_size, stacked_slices

FAULT_SENSOR_OUT_OF_RANGE = device_status_t.FAULT_SENSOR_OUT_OF_RANGE
FAULT_COIL_OVER_TEMPERATURE = device_status_t.FAULT_COIL_OVER_TEMPERATURE
FAULT_COIL_OVER_CURRENT = device_status_t.FAULT_COIL_OVER_CURRENT
FAULT_OVER_SPEED = device_status_t.FAULT_OVER_SPEED
# The amplifiers clamp at the limit: only a measured current past it (by more than
# rounding) is a fault.
CURRENT_TOLERANCE = 1e-6
# The controller's thermally-limited flag raises the fault only once it has held this
# long (s): near the budget's edge the PD's noise-driven corrections fall short now and
# then, which the instrument rides through; a sustained shortfall is the load itself.
THERMAL_LIMIT_PERSIST_S = 0.1
# A coil whose measured current lies farther than this (A) outside the span of the
# commands it may follow (clamped to the limit) on every check for STUCK_PERSIST_S (s)
# has a stuck amplifier: the amplifiers follow a command within a tick (1 kHz
# bandwidth). The commands it may follow: the simulated station's, the tick before's;
# over LCM, those of the link's round trip (measured currents 2-3 ticks behind). Against
# one tick's command alone a fast allocation change (the active set switching, or a
# saturating step) would look like one. A check compares only currents whose command
# (``coil_currents_age_s`` old) lies in that span.
STUCK_MISMATCH_A = 1.0
STUCK_PERSIST_S = 0.01
# A command's age in ticks is a whole number, computed in floats: this much of a tick
# forgives their rounding.
COMMAND_AGE_ROUNDING = 1e-6
# With a coil stuck, a force the others cannot produce past this fraction of the
# instrument's weight means they cannot carry it against the stuck one: the power is
# cut and it falls level rather than be pulled or pushed off its landing.
STUCK_SHORTFALL_OF_WEIGHT = 0.1


@dataclass(frozen=True, eq=False)
class Motion:
    """A setpoint and force-ramp profile sampled at the control ticks (a row a tick:
    the loop looks its command up rather than evaluating trajectories, a tenth of the
    cost); before ``first_tick`` its first row holds, after its last its last.
    Compared by identity (it is state)."""
    # (n, 13): [pose [x y z roll pitch yaw] of I in W (m, rad); its rates (m/s,
    # rad/s); the controller's force gain 0..1] at ticks first_tick .. first_tick+n-1.
    commands: np.ndarray
    first_tick: int
    period_s: float  # the tick (s)
    start_s: float  # commanded from (s)
    landing: bool = False

    def __post_init__(self):
        # C-ordered floats: the argument type the supervisor's kernel is compiled for.
        object.__setattr__(self, "commands", np.ascontiguousarray(self.commands, dtype=float))

    # Immutable: a cloned context (the analyses clone thousands) shares it.
    def __copy__(self):
        return self

    def __deepcopy__(self, memo):
        return self

    @property
    def last_tick(self) -> int:
        return self.first_tick + len(self.commands) - 1

    @property
    def end_s(self) -> float:
        """When its last row starts to hold (s)."""
        return self.last_tick * self.period_s

    def at_tick(self, tick: int) -> np.ndarray:
        """The command row (13) at tick number ``tick`` (time tick * period_s)."""
        return self.commands[min(max(tick - self.first_tick, 0), len(self.commands) - 1)]

    def at(self, t_s: float):
        """(setpoint [pose; rates] (12), enable) at the tick nearest ``t_s`` (s)."""
        row = self.at_tick(round(t_s / self.period_s))
        return row[0:12].copy(), float(row[12])


def first_tick_at(t_s: float, period_s: float) -> int:
    """The first tick at or after ``t_s`` (s), forgiving the rounding of t_s."""
    return math.ceil(round(t_s / period_s, 9))


def make_motion(setpoint: PiecewisePolynomial, enable: PiecewisePolynomial, start_s: float,
                period_s: float, landing: bool = False) -> Motion:
    """A motion of ``setpoint`` (6 rows) and ``enable`` (1 row), both timed from
    ``start_s`` (s), sampled at ticks of ``period_s`` (s) as Drake's TrajectorySource
    evaluates them (value and first derivative at the tick's time); it ends when the
    later of them does."""
    duration_s = max(setpoint.end_time(), enable.end_time())
    first_tick = first_tick_at(start_s, period_s)
    ticks = np.arange(first_tick, first_tick_at(start_s + duration_s, period_s) + 1)
    elapsed_s = np.clip(ticks * period_s - start_s, 0.0, None)

    def sampled(trajectory):  # each held at its own end, as TrajectorySource does
        return trajectory.vector_values(np.minimum(elapsed_s, trajectory.end_time()))
    commands = np.vstack((sampled(setpoint), sampled(setpoint.MakeDerivative(1)),
                          sampled(enable))).T
    return Motion(commands=commands, first_tick=first_tick, period_s=float(period_s),
                  start_s=float(start_s), landing=landing)


def hold_motion(setpoint, enable: float, start_s: float, period_s: float) -> Motion:
    """Hold ``setpoint`` ([pose (6); rates (6)]: the rates are what the controller's
    damping tracks, not integrated) at force gain ``enable`` from ``start_s`` (s) on,
    at ticks of ``period_s`` (s)."""
    commands = np.append(np.asarray(setpoint, dtype=float), enable).reshape(1, 13)
    return Motion(commands=commands, first_tick=first_tick_at(start_s, period_s),
                  period_s=float(period_s), start_s=float(start_s))


@dataclass
class WatchdogConfig:
    """The scenario's limits for the supervisor's watchdogs (the current and
    temperature limits are the device's)."""
    max_speed_m_s: float = 0.5  # faster is an over-speed fault (m/s)
    # The sphere the instrument must stay in while carried, in W (m); null: none.
    boundary_center_m: List[float] = field(default_factory=lambda: [0.0, 0.0, 0.02])
    boundary_radius_m: Optional[float] = None

    def validate(self, path: str = "watchdog") -> None:
        """Range checks; a ValueError names ``path.field``, its value and what is allowed."""
        positive(f"{path}.max_speed_m_s", self.max_speed_m_s)
        vector(f"{path}.boundary_center_m", self.boundary_center_m, 3)
        require(self.boundary_radius_m is None or (
            math.isfinite(self.boundary_radius_m) and self.boundary_radius_m > 0),
            f"{path}.boundary_radius_m", self.boundary_radius_m, "must be > 0 (m), or null")


@dataclass(frozen=True)
class WatchLimits:
    """What the supervisor checks every tick."""
    current_limit_a: float  # the amplifiers' limit (A)
    temperature_limit_c: float  # the windings' (C)
    max_speed_m_s: float  # the instrument's (m/s)
    boundary_center_m: Optional[tuple] = None  # the sphere it must stay in, in W (m)
    boundary_radius_m: Optional[float] = None  # (m); None: no boundary

    @cached_property
    def as_vector(self) -> np.ndarray:
        """What the kernels take: [current_limit_a, temperature_limit_c, max_speed_m_s,
        boundary_center_m (3), boundary_radius_m (NaN: none)]."""
        if self.boundary_radius_m is None:
            return np.array([self.current_limit_a, self.temperature_limit_c,
                             self.max_speed_m_s, math.nan, math.nan, math.nan, math.nan])
        require(self.boundary_center_m is not None, "boundary_center_m", None,
                "must be given with a boundary_radius_m")
        return np.array([self.current_limit_a, self.temperature_limit_c, self.max_speed_m_s,
                         *self.boundary_center_m, self.boundary_radius_m], dtype=float)


# --- the numeric core, compiled into the tick's one call (``supervisor_update``) ----

@numba.njit(cache=True)
def tracking_lost_after(lost_s: float, tracking_ok: float, lost_grace_s: float,
                        period_s: float) -> float:
    """How long tracking has been lost (s) a tick of ``period_s`` (s) after ``lost_s``,
    with the estimator's ``tracking_ok`` (1/0): back to 0 when tracking is good,
    unless it was lost for longer than ``lost_grace_s`` (s): then it latches (the
    controller has cut the coils; ``DeviceSupervisor.reset_faults`` clears it)."""
    if tracking_ok > 0.5 and lost_s <= lost_grace_s:
        return 0.0
    return lost_s + period_s


@numba.njit(cache=True)
def mismatched_coils(measured_a, lowest_a, highest_a, current_limit_a: float) -> np.ndarray:
    """Mask of the coils whose measured current (A) is more than STUCK_MISMATCH_A outside
    the span [``lowest_a``, ``highest_a``] of the commands it may follow (A), each
    clamped to the amplifiers' limit (A)."""
    mismatched = np.empty(len(measured_a), dtype=np.bool_)
    for i in range(len(measured_a)):
        low = min(max(lowest_a[i], -current_limit_a), current_limit_a)
        high = min(max(highest_a[i], -current_limit_a), current_limit_a)
        # A NaN command compares False: no mismatch, as before the span.
        mismatched[i] = (measured_a[i] < low - STUCK_MISMATCH_A
                         or measured_a[i] > high + STUCK_MISMATCH_A)
    return mismatched


@numba.njit(cache=True)
def cut_coil_power(coils_stuck: bool, carrying: bool, force_shortfall_n: float,
                   weight_n: float) -> bool:
    """Whether to cut the coils' power: a coil is stuck and either the instrument is
    not carried (resting on the glass, where the stuck coil would push it along) or
    the allocation falls short of the wanted force (N) by more than
    STUCK_SHORTFALL_OF_WEIGHT of its weight (N). A lost instrument's coils are off
    already (their amplifiers follow the controller's zero)."""
    return coils_stuck and (not carrying
                            or force_shortfall_n > STUCK_SHORTFALL_OF_WEIGHT * weight_n)


@numba.njit(cache=True)
def raised_fault_bits(position_m, velocity_m_s, tracking_lost: bool, coil_currents_a,
                      coil_temperature_c, thermally_limited: bool, carrying: bool,
                      coils_stuck: bool, limits) -> int:
    """``detect_faults`` with its limits as ``WatchLimits.as_vector``."""
    bits = 0
    if carrying:
        if thermally_limited:
            bits |= FAULT_COIL_OVER_TEMPERATURE
        # A NaN radius (no boundary) is never passed.
        outside = hypot(position_m - limits[3:6]) > limits[6]
        if tracking_lost or outside:
            bits |= FAULT_SENSOR_OUT_OF_RANGE
        if hypot(velocity_m_s) > limits[2]:
            bits |= FAULT_OVER_SPEED
    if largest(coil_temperature_c) > limits[1]:
        bits |= FAULT_COIL_OVER_TEMPERATURE
    if coils_stuck or largest(np.abs(coil_currents_a)) > limits[0] * (1 + CURRENT_TOLERANCE):
        bits |= FAULT_COIL_OVER_CURRENT
    return bits


def detect_faults(*, position_m, velocity_m_s, tracking_lost: bool, coil_currents_a,
                  coil_temperature_c, thermally_limited: bool, carrying: bool,
                  limits: WatchLimits, coils_stuck: bool = False) -> int:
    """The FAULT_* bits these measurements raise (before latching), ``tracking_lost``
    for longer than the controller's grace, ``thermally_limited`` the controller's
    flag that warm coils' budgets cut the wrench short, ``coils_stuck`` that a coil's
    amplifier no longer follows its command (over-current: a current not asked for;
    ``mismatched_coils``). The instrument's faults (lost,
    outside the boundary, too fast, the coils too warm to carry it) count only while
    the coils are ``carrying`` it: resting with the coils off it is in no danger."""
    return raised_fault_bits(
        np.asarray(position_m, dtype=float), np.asarray(velocity_m_s, dtype=float),
        tracking_lost, np.asarray(coil_currents_a, dtype=float),
        np.asarray(coil_temperature_c, dtype=float), thermally_limited, carrying,
        coils_stuck, limits.as_vector)


# The supervisor's input ports (name, size), in the order of its logic's one input.
def supervisor_inputs(n_coils: int) -> Tuple[Tuple[str, int], ...]:
    return (("X_WI_measured", 7), ("V_WI_measured", 6), ("tracking_ok", 1),
            ("coil_currents", n_coils), ("coil_temperature_c", n_coils),
            ("thermally_limited", 1), ("coil_currents_commanded", n_coils),
            ("allocation_shortfall_W", 6), ("coil_currents_age_s", 1))


def supervisor_outputs(n_coils: int) -> Tuple[Tuple[str, int], ...]:
    """Its output ports (name, size): the first rows of its logic's state, in order."""
    return (("setpoint", 12), ("enable", 1), ("fault_bits", 1), ("tracking_lost_s", 1),
            ("coils_stuck", n_coils), ("coil_power", 1))


def supervisor_state(n_coils: int) -> Tuple[Tuple[str, int], ...]:
    """Its logic's state (name, size): the outputs, then what only the watchdogs read."""
    return supervisor_outputs(n_coils) + (
        ("landing_start_s", 1), ("thermally_limited_s", 1), ("mismatch_s", n_coils),
        ("sent_low_a", n_coils), ("sent_high_a", n_coils))


# Each entry's place in the lists above: the kernels find its first row at starts[place].
(POSE, VELOCITY, TRACKING_OK, CURRENTS, TEMPERATURES, THERMALLY_LIMITED, COMMANDED,
 SHORTFALL, CURRENTS_AGE_S) = range(9)
(SETPOINT, ENABLE, FAULT_BITS, LOST_S, STUCK, POWER, LANDING_START_S, LIMITED_S,
 MISMATCH_S, SENT_LOW_A, SENT_HIGH_A) = range(11)


@numba.njit(cache=True)
def watchdog_check(inputs, at, state, next_state, rows, limits, lost_grace_s: float,
                   watch_period_s: float, weight_n: float, max_command_age_s: float) -> int:
    """The watchdogs' check, every ``watch_period_s`` (s): their timers, the stuck
    coils and the coils' power into ``next_state``; returns the fault bits raised that
    are not latched yet (``supervisor_update`` names the arguments)."""
    n = at[TEMPERATURES] - at[CURRENTS]
    currents = inputs[at[CURRENTS]:at[CURRENTS] + n]
    limited_s = 0.0
    if inputs[at[THERMALLY_LIMITED]] > 0.5:
        limited_s = state[rows[LIMITED_S]] + watch_period_s
    next_state[rows[LIMITED_S]] = limited_s
    stuck = state[rows[STUCK]:rows[STUCK] + n].copy()
    carrying = state[rows[ENABLE]] > 0.0
    if state[rows[POWER]] > 0.5:  # unpowered, no coil follows its command
        # Currents that follow an older command, or none (the device's own zero),
        # compared, would read as a stuck coil. Their timers hold until fresh ones come.
        if inputs[at[CURRENTS_AGE_S]] <= max_command_age_s:
            mismatched = mismatched_coils(
                currents, state[rows[SENT_LOW_A]:rows[SENT_LOW_A] + n],
                state[rows[SENT_HIGH_A]:rows[SENT_HIGH_A] + n], limits[0])
            for i in range(n):
                mismatch_s = (state[rows[MISMATCH_S] + i] + watch_period_s if mismatched[i]
                              else 0.0)
                next_state[rows[MISMATCH_S] + i] = mismatch_s
                if mismatch_s >= STUCK_PERSIST_S - 1e-9:
                    stuck[i] = 1.0
        next_state[rows[STUCK]:rows[STUCK] + n] = stuck
        # The shortfall is read only with a coil stuck: nothing else cuts the power.
        if np.any(stuck != 0.0) and cut_coil_power(
                True, carrying, euclidean_norm(inputs[at[SHORTFALL]:at[SHORTFALL] + 3]),
                weight_n):
            next_state[rows[POWER]] = 0.0
    raised = raised_fault_bits(
        inputs[at[POSE] + 4:at[POSE] + 7], inputs[at[VELOCITY] + 3:at[VELOCITY] + 6],
        state[rows[LOST_S]] > lost_grace_s, currents,
        inputs[at[TEMPERATURES]:at[TEMPERATURES] + n], limited_s >= THERMAL_LIMIT_PERSIST_S,
        carrying, np.any(stuck != 0.0), limits)
    return raised & ~int(state[rows[FAULT_BITS]])


@kernel((VECTOR, INDEX_VECTOR, VECTOR, VECTOR, INDEX_VECTOR, MATRIX, INDEX, INDEX, FLAG,
         VECTOR, SCALAR, SCALAR, INDEX, INDEX, SCALAR))
def supervisor_update(inputs, at, state, next_state, rows, commands, first_tick, tick,
                      landing, limits, lost_grace_s, period_s, watchdog_ticks,
                      lag_ticks, weight_n) -> bool:
    """One tick (number ``tick``) of the supervisor: ``inputs`` (``supervisor_inputs``
    stacked, each port's first row at its entry of ``at``) and ``state`` (the
    context's, ``supervisor_state`` stacked, each at its entry of ``rows``) into
    ``next_state`` (a copy of ``state`` on entry): the tracking-lost timer; every
    ``watchdog_ticks`` ticks the watchdogs (``watchdog_check``, with ``limits`` as
    ``WatchLimits.as_vector``; measured currents compared with the span of the
    commands of the ``lag_ticks`` ticks before the check, 1 to ``watchdog_ticks``,
    where the command they follow is one of those), which latch a new
    fault; the next tick's command from the active motion (its ``commands`` from ``first_tick``; ``landing``: it is a
    landing). True when a new fault must start a landing: the caller plans it and
    writes its command (Python, once a fault)."""
    next_state[rows[LOST_S]] = tracking_lost_after(
        state[rows[LOST_S]], inputs[at[TRACKING_OK]], lost_grace_s, period_s)
    n = at[TEMPERATURES] - at[CURRENTS]
    # The span of the commands the next check's currents may follow: those of its
    # lag_ticks ticks before it.
    to_check = (watchdog_ticks - tick % watchdog_ticks)  # ticks to the next check
    if to_check <= lag_ticks:
        commanded = inputs[at[COMMANDED]:at[COMMANDED] + n]
        low = next_state[rows[SENT_LOW_A]:rows[SENT_LOW_A] + n]
        high = next_state[rows[SENT_HIGH_A]:rows[SENT_HIGH_A] + n]
        for i in range(n):
            first = to_check == lag_ticks
            low[i] = commanded[i] if first else min(low[i], commanded[i])
            high[i] = commanded[i] if first else max(high[i], commanded[i])
    if tick % watchdog_ticks == 0:
        new = watchdog_check(inputs, at, state, next_state, rows, limits, lost_grace_s,
                             watchdog_ticks * period_s, weight_n,
                             (lag_ticks + COMMAND_AGE_ROUNDING) * period_s)
        if new:
            next_state[rows[FAULT_BITS]] = int(state[rows[FAULT_BITS]]) | new
            if not landing:
                return True
    # The state holds this tick's command; past the motion's end (or before its
    # start) the next one is the same.
    if first_tick <= tick < first_tick + len(commands) - 1:
        next_state[rows[SETPOINT]:rows[SETPOINT] + 13] = commands[tick + 1 - first_tick]
    return False


class SupervisorLogic(LeafSystem):
    """The supervisor's state and its tick, one compiled call (``supervisor_update``):
    one input, ``inputs`` (``supervisor_inputs`` stacked), and one output, ``state``
    (``supervisor_state`` stacked: the outputs first). ``DeviceSupervisor`` wraps it
    with named ports and says what it does.

    .. pydrake_system::

        name: SupervisorLogic
        input_ports:
        - inputs
        output_ports:
        - state

    State: the commanded motion (abstract: ``initial_motion`` until set); one vector
    (``supervisor_state``): the outputs, each tick's update writing the next tick's
    command (so the loop reads them from C++: one Python call a tick), then the time a
    fault's landing started (s; NaN: none), how long, at the watchdog checks, the
    controller has been thermally limited (s: the fault once it reaches
    THERMAL_LIMIT_PERSIST_S), how long each coil's current has been mismatched (s) and
    the span (lowest, highest) of the commands the amplifiers were given in the
    ``measured_lag_ticks`` ticks before a check (A: what the check's measured currents
    may follow). The limits are an abstract
    parameter (``WatchLimits``).
    """

    def __init__(self, *, initial_motion: Motion, limits: WatchLimits, lost_grace_s: float,
                 plan_landing: Callable, n_coils: int, watchdog_period_s: float,
                 weight_n: float, measured_lag_ticks: int = 1):
        super().__init__()
        self._weight_n = float(weight_n)
        self._plan_landing = plan_landing
        self._lost_grace_s = float(lost_grace_s)
        self._period_s = initial_motion.period_s
        # Every whole number of ticks nearest watchdog_period_s, at least every tick.
        self._watchdog_ticks = max(1, round(watchdog_period_s / self._period_s))
        self._lag_ticks = min(max(1, int(measured_lag_ticks)), self._watchdog_ticks)
        inputs = supervisor_inputs(n_coils)
        self._at = np.array([rows.start for rows in stacked_slices(inputs).values()])
        self._rows = stacked_slices(supervisor_state(n_coils))
        self._starts = np.array([rows.start for rows in self._rows.values()])
        # The command rows: the setpoint, then the enable.
        self._command = slice(self._rows["setpoint"].start, self._rows["enable"].stop)
        self._landing_start = self._rows["landing_start_s"].start
        self._inputs = self.DeclareVectorInputPort("inputs", stacked_size(inputs))
        self._motion = self.DeclareAbstractState(AbstractValue.Make(initial_motion))
        initial = np.zeros(stacked_size(supervisor_state(n_coils)))
        initial[self._command] = initial_motion.at_tick(0)
        initial[self._landing_start] = math.nan
        initial[self._rows["coil_power"]] = 1.0
        state = self.DeclareDiscreteState(BasicVector(initial))
        # Plain ints: pybind takes them faster than the typed indices, every tick.
        self._state, self._motion = int(state), int(self._motion)
        self._limits = int(self.DeclareAbstractParameter(AbstractValue.Make(limits)))
        self.DeclareStateOutputPort("state", state)
        # A context may start at any time: its command is that tick's from the start.
        self.DeclareInitializationDiscreteUpdateEvent(self._initialize)
        self.DeclarePeriodicDiscreteUpdateEvent(self._period_s, 0.0, self._update)
        # A landing is planned once per (motion, start), not each time it is asked for.
        self._landing = lru_cache(maxsize=4)(self._landing_from)

    # --- what the device API sets between ticks (``DeviceSupervisor``'s) ---

    def set_motion(self, context, motion: Motion) -> None:
        context.SetAbstractState(self._motion, motion)
        state = context.get_mutable_discrete_state(self._state).get_mutable_value()
        state[self._landing_start] = math.nan
        state[self._command] = motion.at_tick(self._tick(context))

    def land(self, context) -> Motion:
        landing = self._landing(self.active_motion(context), context.get_time())
        self.set_motion(context, landing)
        return landing

    def reset_faults(self, context, tracking_ok: bool) -> None:
        self.set_motion(context, self.active_motion(context))
        state = context.get_mutable_discrete_state(self._state).get_mutable_value()
        state[self._rows["fault_bits"]] = 0.0
        state[self._rows["coils_stuck"]] = 0.0
        state[self._rows["coil_power"]] = 1.0
        if tracking_ok:
            state[self._rows["tracking_lost_s"]] = 0.0

    def set_limits(self, context, limits: WatchLimits) -> None:
        context.get_mutable_abstract_parameter(self._limits).set_value(limits)

    def limits(self, context) -> WatchLimits:
        return context.get_abstract_parameter(self._limits).get_value()

    def active_motion(self, context) -> Motion:
        return self._active(context.get_abstract_state(self._motion).get_value(),
                            context.get_discrete_state(self._state).value())

    def state_entry(self, context, name: str) -> float:
        """The first row of state entry ``name`` (``supervisor_state``)."""
        return context.get_discrete_state(self._state).GetAtIndex(self._rows[name].start)

    # --- the tick ----------------------------------------------------------

    def _tick(self, context) -> int:
        return round(context.get_time() / self._period_s)

    def _active(self, motion: Motion, state) -> Motion:
        """The commanded ``motion``, or the landing a fault started (``state``'s)."""
        landing_start_s = state[self._landing_start]
        return motion if math.isnan(landing_start_s) else self._landing(motion, landing_start_s)

    def _landing_from(self, motion: Motion, start_s: float) -> Motion:
        setpoint, enable = motion.at(start_s)
        return Motion(commands=self._plan_landing(setpoint[0:6], enable, self._period_s),
                      first_tick=round(start_s / self._period_s), period_s=self._period_s,
                      start_s=start_s, landing=True)

    def _initialize(self, context, discrete_state):
        discrete_state.get_mutable_value(self._state)[self._command] = \
            self.active_motion(context).at_tick(self._tick(context))

    def _update(self, context, discrete_state):
        # Inlined (_tick, _active, limits): a Python call costs a tenth of a us here.
        tick = round(context.get_time() / self._period_s)
        state = context.get_discrete_state(self._state).value()
        motion = context.get_abstract_state(self._motion).get_value()
        landing_start_s = state[self._landing_start]
        if not math.isnan(landing_start_s):
            motion = self._landing(motion, landing_start_s)
        next_state = discrete_state.get_mutable_value(self._state)
        if supervisor_update(
                self._inputs.EvalBasicVector(context).value(), self._at, state, next_state,
                self._starts, motion.commands, motion.first_tick, tick, motion.landing,
                context.get_abstract_parameter(self._limits).get_value().as_vector,
                self._lost_grace_s, self._period_s, self._watchdog_ticks, self._lag_ticks,
                self._weight_n):
            # A new fault: land from the commanded motion's setpoint, now.
            now_s = context.get_time()
            next_state[self._landing_start] = now_s
            next_state[self._command] = self._landing(motion, now_s).at_tick(tick + 1)


class DeviceSupervisor(Diagram):
    """The commanded motion, the watchdogs and the landing on a fault (module docstring).

    .. pydrake_system::

        name: DeviceSupervisor
        input_ports:
        - X_WI_measured
        - V_WI_measured
        - tracking_ok
        - coil_currents
        - coil_temperature_c
        - thermally_limited
        - coil_currents_commanded
        - allocation_shortfall_W
        - coil_currents_age_s
        output_ports:
        - setpoint
        - enable
        - fault_bits
        - tracking_lost_s
        - coils_stuck
        - coil_power

    - ``setpoint`` (12): [x y z roll pitch yaw] of I in W and their rates (m, rad;
      m/s, rad/s), the active motion's at the context's tick.
    - ``enable`` (1): the controller's force gain 0..1.
    - ``fault_bits`` (1): the latched FAULT_* bits.
    - ``coils_stuck`` (n_coils): 1 for a coil whose amplifier no longer follows its
      command (its measured current off by more than STUCK_MISMATCH_A at every check
      for STUCK_PERSIST_S, counting only checks whose currents follow one of the
      commands compared, ``coil_currents_age_s`` (s) saying how old theirs is: for
      the simulated station a tick, over LCM the age of the command sequence the
      device reports, infinite for none), latched until
      ``reset_faults``: the controller allocates without it and takes its measured
      current as a given.
    - ``tracking_lost_s`` (1): how long tracking has been lost (s), counted every
      tick and latched past ``lost_grace_s`` (``tracking_lost_after``): the
      controller carries the weight alone through the grace, then cuts the coils.
    - ``coil_power`` (1): 1 while the coils' supply is on, 0 once ``cut_coil_power``
      cut it (the controller's ``allocation_shortfall_W``, [f; tau] in W, N and
      N*m, against ``weight_n``, N), latched until ``reset_faults``; while it is
      off the stuck-amplifier watchdog rests (no coil follows its command then).

    A diagram of three blocks (``systems/stacked_ports.py``), so that a tick pays for
    one Python call: the ports stacked for ``SupervisorLogic`` ("logic"), whose
    update is one compiled call (``supervisor_update``; Python plans a fault's
    landing, once), and its state split into the named outputs. The outputs are
    state, each tick's update writing the next tick's command; past a motion's end
    the update only counts. The watchdogs check every ``watchdog_period_s`` (s, to
    the nearest whole tick): no fault needs a faster answer (the amplifiers clamp
    the current themselves, the coils heat over a minute, the controller lands a
    lost instrument on its own).
    ``plan_landing(pose, enable, period_s) -> commands`` (a Motion's, from the
    landing's start) bring the instrument from ``pose`` onto the glass and ramp its
    force gain from ``enable`` to zero.
    ``measured_lag_ticks``: how many ticks' commands a measured current may follow,
    the checks' span (1: the tick before's, the simulated station's; over LCM, the
    link's round trip: against the tick before's alone a saturating step, measured 2
    ticks late, latched healthy coils as stuck and cut the power in flight); at most
    the ticks between two checks.
    """

    def __init__(self, *, initial_motion: Motion, limits: WatchLimits, lost_grace_s: float,
                 plan_landing: Callable, n_coils: int, watchdog_period_s: float,
                 weight_n: float, measured_lag_ticks: int = 1):
        Diagram.__init__(self)
        self._logic = SupervisorLogic(
            initial_motion=initial_motion, limits=limits, lost_grace_s=lost_grace_s,
            plan_landing=plan_landing, n_coils=n_coils, watchdog_period_s=watchdog_period_s,
            weight_n=weight_n,
            measured_lag_ticks=measured_lag_ticks)
        BuildStacked(self, leaf=self._logic, leaf_name="logic",
                     inputs=supervisor_inputs(n_coils), outputs=supervisor_outputs(n_coils),
                     unexported_rows=stacked_size(supervisor_state(n_coils))
                     - stacked_size(supervisor_outputs(n_coils)))

    # --- what the device API sets between ticks ---------------------------

    def set_motion(self, context, motion: Motion) -> None:
        """Fly ``motion`` from now on (ends a fault's landing: the caller chose)."""
        self._logic.set_motion(self._mutable(context), motion)

    def land(self, context) -> Motion:
        """Start a landing from the active setpoint now; returns it."""
        return self._logic.land(self._mutable(context))

    def reset_faults(self, context) -> None:
        """Clear the latched bits and stuck coils, power the coils again, and clear a
        latched tracking loss if tracking is good again (the controller then flies); a
        fault's landing stays the commanded motion."""
        # The estimator's port alone: the stacked input would evaluate the controller too.
        tracking_ok = self.GetInputPort("tracking_ok").Eval(context)[0] > 0.5
        self._logic.reset_faults(self._mutable(context), tracking_ok=tracking_ok)

    def set_limits(self, context, limits: WatchLimits) -> None:
        self._logic.set_limits(self._mutable(context), limits)

    def limits(self, context) -> WatchLimits:
        return self._logic.limits(self.GetSubsystemContext(self._logic, context))

    def active_motion(self, context) -> Motion:
        """The commanded motion, or the landing a fault started."""
        return self._logic.active_motion(self.GetSubsystemContext(self._logic, context))

    def coils_powered(self, context) -> bool:
        return self._logic.state_entry(self.GetSubsystemContext(self._logic, context),
                                       "coil_power") > 0.5

    def faults(self, context) -> int:
        return int(self._logic.state_entry(self.GetSubsystemContext(self._logic, context),
                                           "fault_bits"))

    def _mutable(self, context):
        return self.GetMutableSubsystemContext(self._logic, context)
