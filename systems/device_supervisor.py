"""The device's supervisor: what the levitation controller is asked to fly, and the
faults that end it (the MLHI device's state machine, in the diagram).

It holds the commanded motion (a setpoint and a force-ramp trajectory from a start
time; a held pose is a motion that does not move) and the latched fault bits of
``device_status_t``: sensor out of range (tracking lost, or the instrument outside
the boundary sphere), coil over-temperature (the thermal model's estimate), coil
over-current, over-speed. Every tick it checks the measurements; a new fault latches
and, unless a landing is under way, lands the instrument from where its setpoint is
(a lost instrument the controller lands blind, whatever the setpoint).

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
from pydrake.systems.framework import BasicVector, LeafSystem, ValueProducer
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


@dataclass(frozen=True, eq=False)
class Motion:
    """A setpoint and force-ramp profile from ``start_s`` (s) on; before it and after
    ``end_s`` (s, absolute) its ends hold. Compared by identity (it is state)."""
    setpoint: PiecewisePolynomial  # 6 rows: pose [x y z roll pitch yaw] of I in W (m, rad)
    rates: PiecewisePolynomial  # 6 rows: the setpoint's rates (m/s, rad/s)
    enable: PiecewisePolynomial  # 1 row: the controller's force gain 0..1
    start_s: float
    end_s: float
    landing: bool = False

    # Immutable: a cloned context (the analyses clone thousands) shares it.
    def __copy__(self):
        return self

    def __deepcopy__(self, memo):
        return self

    def at(self, t_s: float):
        """(setpoint [pose; rates] (12), enable) at ``t_s`` (s)."""
        elapsed = min(max(t_s, self.start_s), self.end_s) - self.start_s
        return (np.concatenate((self.setpoint.value(elapsed).ravel(),
                                self.rates.value(elapsed).ravel())),
                self.enable.value(elapsed)[0, 0])


def make_motion(setpoint: PiecewisePolynomial, enable: PiecewisePolynomial, start_s: float,
                landing: bool = False) -> Motion:
    """A motion of ``setpoint`` (6 rows) and ``enable`` (1 row), both timed from
    ``start_s`` (s); it ends when the later of them does."""
    duration_s = max(setpoint.end_time(), enable.end_time())
    return Motion(setpoint=setpoint, rates=setpoint.MakeDerivative(1), enable=enable,
                  start_s=float(start_s), end_s=float(start_s) + duration_s, landing=landing)


def hold_motion(setpoint, enable: float, start_s: float) -> Motion:
    """Hold ``setpoint`` ([pose (6); rates (6)]: the rates are what the controller's
    damping tracks, not integrated) at force gain ``enable`` from ``start_s`` (s)."""
    setpoint = np.asarray(setpoint, dtype=float)
    constant = lambda value: PiecewisePolynomial(np.reshape(value, (-1, 1)))  # noqa: E731
    return Motion(setpoint=constant(setpoint[0:6]), rates=constant(setpoint[6:12]),
                  enable=constant([enable]), start_s=float(start_s), end_s=float(start_s))


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


def detect_faults(*, position_m, velocity_m_s, tracking_ok: bool, coil_currents_a,
                  coil_temperature_c, carrying: bool, limits: WatchLimits) -> int:
    """The FAULT_* bits these measurements raise (before latching). The instrument's
    faults (lost, outside the boundary, too fast) count only while the coils are
    ``carrying`` it: resting with the coils off it is in no danger."""
    bits = 0
    if carrying:
        outside = (limits.boundary_radius_m is not None and math.dist(
            position_m, limits.boundary_center_m) > limits.boundary_radius_m)
        if not tracking_ok or outside:
            bits |= FAULT_SENSOR_OUT_OF_RANGE
        if math.hypot(*velocity_m_s) > limits.max_speed_m_s:
            bits |= FAULT_OVER_SPEED
    # One numpy reduction each: a Python loop over 27 numpy scalars costs ~6 us.
    if np.max(coil_temperature_c) > limits.temperature_limit_c:
        bits |= FAULT_COIL_OVER_TEMPERATURE
    if np.max(np.abs(coil_currents_a)) > limits.current_limit_a * (1 + CURRENT_TOLERANCE):
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
        output_ports:
        - setpoint
        - enable
        - fault_bits

    - ``setpoint`` (12): [x y z roll pitch yaw] of I in W and their rates (m, rad;
      m/s, rad/s), the active motion's at the context's time.
    - ``enable`` (1): the controller's force gain 0..1.
    - ``fault_bits`` (1): the latched FAULT_* bits.

    State: the commanded motion (abstract: ``initial_motion`` until set), and
    [latched bits, the time a fault's landing started (NaN: none)], updated every
    ``period_s`` (s). ``plan_landing(pose, enable) -> (setpoint, enable)``
    trajectories (from 0) bring the instrument from ``pose`` onto the glass and ramp
    its force gain from ``enable`` to zero.
    """

    def __init__(self, *, initial_motion: Motion, limits: WatchLimits,
                 plan_landing: Callable, n_coils: int, period_s: float):
        super().__init__()
        self._plan_landing = plan_landing
        self._pose = self.DeclareVectorInputPort("X_WI_measured", 7)
        self._velocity = self.DeclareVectorInputPort("V_WI_measured", 6)
        self._tracking_ok = self.DeclareVectorInputPort("tracking_ok", 1)
        self._currents = self.DeclareVectorInputPort("coil_currents", n_coils)
        self._temperatures = self.DeclareVectorInputPort("coil_temperature_c", n_coils)
        self._motion = self.DeclareAbstractState(AbstractValue.Make(initial_motion))
        self._faults = self.DeclareDiscreteState(BasicVector([0.0, math.nan]))
        self._limits = self.DeclareAbstractParameter(AbstractValue.Make(limits))
        # (setpoint, enable) now: both outputs and the update read it, computed once a tick.
        self._now = self.DeclareCacheEntry(
            description="setpoint and enable now",
            value_producer=ValueProducer(allocate=AbstractValue.Make(()).Clone,
                                         calc=self._calc_now),
            prerequisites_of_calc={self.xa_ticket(), self.xd_ticket(), self.time_ticket()})
        now_ticket = {self._now.ticket()}
        self.DeclareVectorOutputPort("setpoint", 12, self._calc_setpoint, now_ticket)
        self.DeclareVectorOutputPort("enable", 1, self._calc_enable, now_ticket)
        self.DeclareVectorOutputPort("fault_bits", 1, self._calc_fault_bits,
                                     {self.xd_ticket()})
        self.DeclarePeriodicDiscreteUpdateEvent(period_s, 0.0, self._update)
        # A landing is planned once per (motion, start): the output asks every tick.
        self._landing = lru_cache(maxsize=4)(self._landing_from)

    # --- what the device API sets between ticks ---------------------------

    def set_motion(self, context, motion: Motion) -> None:
        """Fly ``motion`` from now on (ends a fault's landing: the caller chose)."""
        context.SetAbstractState(self._motion, motion)
        context.get_mutable_discrete_state(self._faults).SetAtIndex(1, math.nan)

    def land(self, context) -> Motion:
        """Start a landing from the active setpoint now; returns it."""
        landing = self._landing(self.active_motion(context), context.get_time())
        self.set_motion(context, landing)
        return landing

    def reset_faults(self, context) -> None:
        """Clear the latched bits; a fault's landing stays the commanded motion."""
        self.set_motion(context, self.active_motion(context))
        context.get_mutable_discrete_state(self._faults).SetAtIndex(0, 0.0)

    def set_limits(self, context, limits: WatchLimits) -> None:
        context.get_mutable_abstract_parameter(self._limits).set_value(limits)

    def limits(self, context) -> WatchLimits:
        return context.get_abstract_parameter(self._limits).get_value()

    def active_motion(self, context) -> Motion:
        """The commanded motion, or the landing a fault started."""
        motion = context.get_abstract_state(self._motion).get_value()
        landing_start_s = context.get_discrete_state(self._faults).GetAtIndex(1)
        return motion if math.isnan(landing_start_s) else self._landing(motion, landing_start_s)

    def faults(self, context) -> int:
        return int(context.get_discrete_state(self._faults).GetAtIndex(0))

    # --- the tick ----------------------------------------------------------

    def _landing_from(self, motion: Motion, start_s: float) -> Motion:
        setpoint, enable = motion.at(start_s)
        pose_trajectory, enable_trajectory = self._plan_landing(setpoint[0:6], enable)
        return make_motion(pose_trajectory, enable_trajectory, start_s, landing=True)

    def _update(self, context, discrete_state):
        latched, landing_start_s = context.get_discrete_state(self._faults).get_value()
        pose = self._pose.Eval(context)
        raised = detect_faults(
            position_m=pose[4:7], velocity_m_s=self._velocity.Eval(context)[3:6],
            tracking_ok=self._tracking_ok.Eval(context)[0] > 0.5,
            coil_currents_a=self._currents.Eval(context),
            coil_temperature_c=self._temperatures.Eval(context),
            carrying=self._now.Eval(context)[1] > 0.0, limits=self.limits(context))
        new = raised & ~int(latched)
        if not new:
            return
        if not self.active_motion(context).landing:
            landing_start_s = context.get_time()
        discrete_state.set_value(self._faults, [int(latched) | new, landing_start_s])

    def _calc_now(self, context, value):
        value.set_value(self.active_motion(context).at(context.get_time()))

    def _calc_setpoint(self, context, output):
        output.SetFromVector(self._now.Eval(context)[0])

    def _calc_enable(self, context, output):
        output.SetAtIndex(0, self._now.Eval(context)[1])

    def _calc_fault_bits(self, context, output):
        output.SetAtIndex(0, context.get_discrete_state(self._faults).GetAtIndex(0))
