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
from functools import lru_cache
from typing import Callable, List, Optional

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import BasicVector, LeafSystem
from pydrake.trajectories import PiecewisePolynomial

from maglev_haptics.hardware.config_checks import positive, require, vector
from maglev_haptics.hardware.lcm_messages import device_status_t

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
# A coil whose measured current differs from its command of the tick before (clamped
# to the limit) by more than this (A) on every check for STUCK_PERSIST_S (s) has a
# stuck amplifier: the amplifiers follow a command within a tick (1 kHz bandwidth).
# Against the same tick's command a fast allocation change (the active set switching)
# would look like one.
STUCK_MISMATCH_A = 1.0
STUCK_PERSIST_S = 0.01
# With a coil stuck, a force the others cannot produce past this fraction of the
# instrument's weight means they cannot carry it against the stuck one: the power is
# cut and it falls level rather than be pulled or pushed off its landing.
STUCK_SHORTFALL_OF_WEIGHT = 0.1


def mismatched_coils(measured_a, commanded_a, current_limit_a: float) -> np.ndarray:
    """Mask of the coils whose measured current (A) is more than STUCK_MISMATCH_A from
    their command (A) clamped to the amplifiers' limit (A)."""
    commanded = np.clip(commanded_a, -current_limit_a, current_limit_a)
    return np.abs(np.asarray(measured_a) - commanded) > STUCK_MISMATCH_A


def cut_coil_power(*, coils_stuck: bool, carrying: bool, force_shortfall_n: float,
                   weight_n: float) -> bool:
    """Whether to cut the coils' power: a coil is stuck and either the instrument is
    not carried (resting on the glass, where the stuck coil would push it along) or
    the allocation falls short of the wanted force (N) by more than
    STUCK_SHORTFALL_OF_WEIGHT of its weight (N). A lost instrument's coils are off
    already (their amplifiers follow the controller's zero)."""
    return coils_stuck and (not carrying
                            or force_shortfall_n > STUCK_SHORTFALL_OF_WEIGHT * weight_n)


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


def tracking_lost_after(lost_s: float, tracking_ok: float, lost_grace_s: float,
                        period_s: float) -> float:
    """How long tracking has been lost (s) a tick of ``period_s`` (s) after ``lost_s``,
    with the estimator's ``tracking_ok`` (1/0): back to 0 when tracking is good,
    unless it was lost for longer than ``lost_grace_s`` (s): then it latches (the
    controller has cut the coils; ``DeviceSupervisor.reset_faults`` clears it)."""
    if tracking_ok > 0.5 and lost_s <= lost_grace_s:
        return 0.0
    return lost_s + period_s


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
    bits = 0
    if carrying:
        if thermally_limited:
            bits |= FAULT_COIL_OVER_TEMPERATURE
        # Plain floats: math on numpy scalars costs several us a call.
        outside = (limits.boundary_radius_m is not None and math.dist(
            np.asarray(position_m).tolist(), limits.boundary_center_m)
            > limits.boundary_radius_m)
        if tracking_lost or outside:
            bits |= FAULT_SENSOR_OUT_OF_RANGE
        if math.hypot(*np.asarray(velocity_m_s).tolist()) > limits.max_speed_m_s:
            bits |= FAULT_OVER_SPEED
    # Array methods: np.max's dispatch costs ~4 us more a call.
    coil_temperature_c = np.asarray(coil_temperature_c)
    coil_currents_a = np.asarray(coil_currents_a)
    if coil_temperature_c.max() > limits.temperature_limit_c:
        bits |= FAULT_COIL_OVER_TEMPERATURE
    if coils_stuck or max(coil_currents_a.max(), -coil_currents_a.min()) > \
            limits.current_limit_a * (1 + CURRENT_TOLERANCE):
        bits |= FAULT_COIL_OVER_CURRENT
    return bits


class DeviceSupervisor(LeafSystem):
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
      for STUCK_PERSIST_S), latched until ``reset_faults``: the controller allocates
      without it and takes its measured current as a given.
    - ``tracking_lost_s`` (1): how long tracking has been lost (s), counted every
      tick and latched past ``lost_grace_s`` (``tracking_lost_after``): the
      controller carries the weight alone through the grace, then cuts the coils.
    - ``coil_power`` (1): 1 while the coils' supply is on, 0 once ``cut_coil_power``
      cut it (the controller's ``allocation_shortfall_W``, [f; tau] in W, N and
      N*m, against ``weight_n``, N), latched until ``reset_faults``; while it is
      off the stuck-amplifier watchdog rests (no coil follows its command then).

    State: the commanded motion (abstract: ``initial_motion`` until set); the
    outputs as discrete state, each tick's update writing the next tick's command
    (so the loop reads them from C++: one Python call a tick, which past a motion's
    end only reads); the time a fault's landing started (NaN: none); how long
    tracking has been lost (s, the ``tracking_lost_s`` output); how long, at the
    watchdog checks, the controller has been thermally limited (s: the fault once it
    reaches THERMAL_LIMIT_PERSIST_S). The watchdogs check every
    ``watchdog_period_s`` (s, to the nearest whole tick): reading the
    measurements and checking them costs several times a plain tick's work (``maglev
    bench``), and no fault needs a faster answer (the amplifiers
    clamp the current themselves, the coils heat over a minute, the controller lands
    a lost instrument on its own).
    ``plan_landing(pose, enable, period_s) -> commands`` (a Motion's, from the
    landing's start) bring the instrument from ``pose`` onto the glass and ramp its
    force gain from ``enable`` to zero.
    """

    def __init__(self, *, initial_motion: Motion, limits: WatchLimits, lost_grace_s: float,
                 plan_landing: Callable, n_coils: int, watchdog_period_s: float,
                 weight_n: float):
        super().__init__()
        self._weight_n = float(weight_n)
        self._plan_landing = plan_landing
        self._lost_grace_s = float(lost_grace_s)
        self._period_s = initial_motion.period_s
        # Every whole number of ticks nearest watchdog_period_s, at least every tick.
        self._watchdog_ticks = max(1, round(watchdog_period_s / self._period_s))
        self._pose = self.DeclareVectorInputPort("X_WI_measured", 7)
        self._velocity = self.DeclareVectorInputPort("V_WI_measured", 6)
        self._tracking_ok = self.DeclareVectorInputPort("tracking_ok", 1)
        self._currents = self.DeclareVectorInputPort("coil_currents", n_coils)
        self._temperatures = self.DeclareVectorInputPort("coil_temperature_c", n_coils)
        self._thermally_limited = self.DeclareVectorInputPort("thermally_limited", 1)
        self._commanded = self.DeclareVectorInputPort("coil_currents_commanded", n_coils)
        self._shortfall = self.DeclareVectorInputPort("allocation_shortfall_W", 6)
        self._motion = self.DeclareAbstractState(AbstractValue.Make(initial_motion))
        command = initial_motion.at_tick(0)
        self._setpoint = self.DeclareDiscreteState(BasicVector(command[0:12]))
        self._enable = self.DeclareDiscreteState(BasicVector(command[12:13]))
        self._fault_bits = self.DeclareDiscreteState(BasicVector([0.0]))
        self._landing_start = self.DeclareDiscreteState(BasicVector([math.nan]))
        self._lost_s = self.DeclareDiscreteState(BasicVector([0.0]))
        self._thermally_limited_s = self.DeclareDiscreteState(BasicVector([0.0]))
        self._mismatch_s = self.DeclareDiscreteState(n_coils)
        # The command the amplifiers were given the tick before a check (A): what the
        # measured currents of the check follow, a tick late.
        self._sent = self.DeclareDiscreteState(n_coils)
        self._stuck = self.DeclareDiscreteState(n_coils)
        self._power = self.DeclareDiscreteState(BasicVector([1.0]))
        self._limits = self.DeclareAbstractParameter(AbstractValue.Make(limits))
        self.DeclareStateOutputPort("setpoint", self._setpoint)
        self.DeclareStateOutputPort("enable", self._enable)
        self.DeclareStateOutputPort("fault_bits", self._fault_bits)
        self.DeclareStateOutputPort("tracking_lost_s", self._lost_s)
        self.DeclareStateOutputPort("coils_stuck", self._stuck)
        self.DeclareStateOutputPort("coil_power", self._power)
        # A context may start at any time: its command is that tick's from the start.
        self.DeclareInitializationDiscreteUpdateEvent(self._initialize)
        self.DeclarePeriodicDiscreteUpdateEvent(self._period_s, 0.0, self._update)
        # A landing is planned once per (motion, start), not each time it is asked for.
        self._landing = lru_cache(maxsize=4)(self._landing_from)

    # --- what the device API sets between ticks ---------------------------

    def set_motion(self, context, motion: Motion) -> None:
        """Fly ``motion`` from now on (ends a fault's landing: the caller chose)."""
        context.SetAbstractState(self._motion, motion)
        context.SetDiscreteState(self._landing_start, [math.nan])
        self._write_command(context.get_mutable_discrete_state(), motion,
                            self._tick(context))

    def land(self, context) -> Motion:
        """Start a landing from the active setpoint now; returns it."""
        landing = self._landing(self.active_motion(context), context.get_time())
        self.set_motion(context, landing)
        return landing

    def reset_faults(self, context) -> None:
        """Clear the latched bits and stuck coils, power the coils again, and clear a
        latched tracking loss if tracking is good again (the controller then flies); a
        fault's landing stays the commanded motion."""
        self.set_motion(context, self.active_motion(context))
        context.SetDiscreteState(self._fault_bits, [0.0])
        context.SetDiscreteState(self._stuck, np.zeros(context.get_discrete_state(
            self._stuck).size()))
        context.SetDiscreteState(self._power, [1.0])
        if self._tracking_ok.Eval(context)[0] > 0.5:
            context.SetDiscreteState(self._lost_s, [0.0])

    def set_limits(self, context, limits: WatchLimits) -> None:
        context.get_mutable_abstract_parameter(self._limits).set_value(limits)

    def limits(self, context) -> WatchLimits:
        return context.get_abstract_parameter(self._limits).get_value()

    def active_motion(self, context) -> Motion:
        """The commanded motion, or the landing a fault started."""
        motion = context.get_abstract_state(self._motion).get_value()
        landing_start_s = context.get_discrete_state(self._landing_start).GetAtIndex(0)
        return motion if math.isnan(landing_start_s) else self._landing(motion, landing_start_s)

    def coils_powered(self, context) -> bool:
        return context.get_discrete_state(self._power).GetAtIndex(0) > 0.5

    def faults(self, context) -> int:
        return int(context.get_discrete_state(self._fault_bits).GetAtIndex(0))

    # --- the tick ----------------------------------------------------------

    def _tick(self, context) -> int:
        return round(context.get_time() / self._period_s)

    def _landing_from(self, motion: Motion, start_s: float) -> Motion:
        setpoint, enable = motion.at(start_s)
        return Motion(commands=self._plan_landing(setpoint[0:6], enable, self._period_s),
                      first_tick=round(start_s / self._period_s), period_s=self._period_s,
                      start_s=start_s, landing=True)

    def _write_command(self, discrete_state, motion: Motion, tick: int) -> None:
        command = motion.at_tick(tick)
        discrete_state.get_mutable_vector(self._setpoint).SetFromVector(command[0:12])
        discrete_state.get_mutable_vector(self._enable).SetAtIndex(0, command[12])

    def _initialize(self, context, discrete_state):
        self._write_command(discrete_state, self.active_motion(context), self._tick(context))

    def _update(self, context, discrete_state):
        lost_s = context.get_discrete_state(self._lost_s).GetAtIndex(0)
        lost_after_s = tracking_lost_after(
            lost_s, self._tracking_ok.EvalBasicVector(context).GetAtIndex(0),
            self._lost_grace_s, self._period_s)
        if lost_after_s != lost_s:
            discrete_state.get_mutable_vector(self._lost_s).SetAtIndex(0, lost_after_s)
        tick = self._tick(context)
        if (tick + 1) % self._watchdog_ticks == 0:
            discrete_state.get_mutable_vector(self._sent).SetFromVector(
                self._commanded.EvalBasicVector(context).get_value())
        motion = self.active_motion(context)
        started_landing = tick % self._watchdog_ticks == 0 and self._watch(
            context, discrete_state, motion)
        if started_landing:  # from the commanded motion, now
            motion = self._landing(motion, context.get_time())
        # The state holds this tick's command; past the motion's end (or before its
        # start) the next one is the same.
        if started_landing or motion.first_tick <= tick < motion.last_tick:
            self._write_command(discrete_state, motion, tick + 1)

    def _watch(self, context, discrete_state, motion: Motion) -> bool:
        """Check the watchdogs; latch new faults; True if that started a landing."""
        latched = self.faults(context)
        limited_s = 0.0
        if self._thermally_limited.EvalBasicVector(context).GetAtIndex(0) > 0.5:
            limited_s = (context.get_discrete_state(self._thermally_limited_s).GetAtIndex(0)
                         + self._watchdog_ticks * self._period_s)
        discrete_state.get_mutable_vector(self._thermally_limited_s).SetAtIndex(0, limited_s)
        currents = self._currents.EvalBasicVector(context).get_value()
        limits = self.limits(context)
        stuck = context.get_discrete_state(self._stuck).get_value()
        carrying = context.get_discrete_state(self._enable).GetAtIndex(0) > 0.0
        if self.coils_powered(context):
            mismatch_s = np.where(
                mismatched_coils(currents, context.get_discrete_state(self._sent).get_value(),
                                 limits.current_limit_a),
                context.get_discrete_state(self._mismatch_s).get_value()
                + self._watchdog_ticks * self._period_s, 0.0)
            discrete_state.get_mutable_vector(self._mismatch_s).SetFromVector(mismatch_s)
            stuck = np.maximum(stuck, mismatch_s >= STUCK_PERSIST_S - 1e-9)
            discrete_state.get_mutable_vector(self._stuck).SetFromVector(stuck)
            # The shortfall is read only with a coil stuck: nothing else cuts the power.
            if stuck.any() and cut_coil_power(
                    coils_stuck=True, carrying=carrying,
                    force_shortfall_n=float(np.linalg.norm(
                        self._shortfall.EvalBasicVector(context).get_value()[0:3])),
                    weight_n=self._weight_n):
                discrete_state.get_mutable_vector(self._power).SetAtIndex(0, 0.0)
        raised = detect_faults(
            position_m=self._pose.EvalBasicVector(context).get_value()[4:7],
            velocity_m_s=self._velocity.EvalBasicVector(context).get_value()[3:6],
            tracking_lost=context.get_discrete_state(self._lost_s).GetAtIndex(0)
            > self._lost_grace_s,
            coil_currents_a=currents, coils_stuck=bool(stuck.any()),
            coil_temperature_c=self._temperatures.EvalBasicVector(context).get_value(),
            thermally_limited=limited_s >= THERMAL_LIMIT_PERSIST_S,
            carrying=carrying, limits=limits)
        new = raised & ~latched
        if not new:
            return False
        discrete_state.get_mutable_vector(self._fault_bits).SetAtIndex(0, latched | new)
        if motion.landing:
            return False
        # Land from where the setpoint is now.
        discrete_state.get_mutable_vector(self._landing_start).SetAtIndex(0, context.get_time())
        return True
