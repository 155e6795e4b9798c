"""A device API in the spirit of the MLHI library: fly the instrument from Python.

``MaglevDevice`` builds the application's diagram for a levitation scenario (with
the simulated station, or whatever answers on LCM), and steps it tick by tick:

    device = MaglevDevice("levitate")
    device.connect()
    device.takeoff()                       # blocks until hovering, or raises
    device.set_gains(kp=[...], kd=[...])   # per axis, from the next tick
    device.set_desired_pose([0.01, 0, 0.02, 0, 0, 0.5])
    device.set_feedforward_wrench([0, 0, 0.1, 0, 0, 0])
    device.on_tick(lambda state: ...)      # every tick, with a TickState
    device.set_boundary([0, 0, 0.02], 0.03)
    device.on_fault(lambda bits: ...)      # when a fault bit rises
    device.run_for(2.0)
    device.land()
    device.disconnect()

The motions, the watchdogs and the landing on a fault are the diagram's own
``device_supervisor`` (``systems/device_supervisor.py``), the same that flies
``maglev run``'s script: the API sets its motion between ticks. Faults (the bits
of ``device_status_t``): sensor out of range (tracking lost, or the instrument
outside the boundary sphere), coil over-temperature (the thermal model's
estimate from the currents that flow), coil over-current, over-speed. A fault
latches until ``reset_faults``, and a new one lands the instrument (a lost one
the controller lands blind, whatever the setpoint); while any is latched,
takeoff and a new desired pose are refused.

The device ticks only inside calls (``takeoff``, ``land``, ``run_for``): with a
station on LCM, a pause between calls longer than the device's command timeout
(10 ms) turns its coils off, so keep calling ``run_for`` while hovering. A device
that goes silent on LCM (no answer to the lease for its timeout: its process or
host gone) ends the call that is ticking with DeviceSilentError within
WATCH_PERIOD_S of being seen so, as ``maglev run`` stops; every later call but
``disconnect`` raises it again.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass
from typing import Callable, List, Optional, Union

import numpy as np
from pydrake.systems.analysis import Simulator
from pydrake.trajectories import PiecewisePolynomial

from maglev_haptics.diagrams.application import BuildDiagram, RunMode
from maglev_haptics.diagrams.lcm_station import silence_sentence
from maglev_haptics.diagrams.motion import check_pose_reachable
from maglev_haptics.diagrams.runner import SHARED_SPIN_S, wait_until
from maglev_haptics.diagrams.scenario import Scenario, load_scenario
from maglev_haptics.diagrams.scenario_run import run_rate
from maglev_haptics.hardware.config_checks import nonnegative, positive
from maglev_haptics.hardware.kernels import compile_kernels
from maglev_haptics.hardware.link.lease import (  # noqa: F401 (connect raises them)
    DeviceInUseError, InstrumentMismatchError)
from maglev_haptics.systems.blends import minimum_jerk_plan
from maglev_haptics.systems.device_supervisor import (  # noqa: F401 (the API's fault bits)
    FAULT_COIL_OVER_CURRENT, FAULT_COIL_OVER_TEMPERATURE, FAULT_OVER_SPEED,
    FAULT_SENSOR_OUT_OF_RANGE, hold_motion, make_motion)

WATCH_PERIOD_S = 0.05  # the device is checked for silence this often while ticking (s)
HOVER_TOLERANCE_M = 0.5e-3  # takeoff is done within this of the hover pose (m)
SETTLED_SPEED_M_S = 0.01  # ... moving slower than this (m/s)


class DeviceTimeoutError(TimeoutError):
    """takeoff or land did not finish in time; the device was set to land or shut off."""


class DeviceFaultError(RuntimeError):
    """A command refused, or a takeoff ended, by a latched fault."""


class DeviceStateError(RuntimeError):
    """A command the device's state refuses: a pose while the coils carry nothing."""


class DeviceSilentError(RuntimeError):
    """The device on LCM stopped answering (``lcm_station.device_silence``): nothing
    takes the coils' commands any more, so nothing can be flown or landed from here."""


@dataclass
class TickState:
    """What the device knows after a tick."""
    t_s: float
    X_WI: np.ndarray  # measured pose [qw qx qy qz x y z] (m)
    V_WI: np.ndarray  # measured spatial velocity [w; v] in W (rad/s, m/s)
    tracking_ok: bool
    coil_currents_a: np.ndarray  # what flows (A)
    coil_temperature_c: np.ndarray  # estimated winding temperatures (C)
    faults: int  # latched FAULT_* bits


class MaglevDevice:
    """The levitated instrument as a device (see the module docstring).

    ``scenario``: a Scenario, or a shipped file's name or a path (``name`` picks one
    in it); its device, controller, watchdog and station are used, its motion script
    only for the rest place, the hover pose (the first waypoint) and the ramp and
    landing times. ``realtime_rate`` > 0 paces each tick to the wall clock (needed
    with a station on LCM, where it is 1 unless given). The over-speed limit and
    a boundary to start with are the scenario's ``watchdog``.
    """

    def __init__(self, scenario: Union[Scenario, str] = "levitate", *,
                 name: Optional[str] = None, realtime_rate: float = 0.0):
        self.scenario = scenario if isinstance(scenario, Scenario) else load_scenario(
            scenario, name)
        nonnegative("realtime_rate", realtime_rate)
        self._realtime_rate = float(run_rate(self.scenario, realtime_rate))
        self._tick_callbacks: List[Callable[[TickState], None]] = []
        self._fault_callbacks: List[Callable[[int], None]] = []
        self._simulator = None
        self._silent: Optional[str] = None  # how the device went silent, once it did
        self.state: Optional[TickState] = None  # after each tick; None until connect()

    # --- connection ---------------------------------------------------------

    def connect(self) -> None:
        """Build the diagram and start the device: resting on the glass, coils off.
        With a station on LCM, first take the device's lease (``hardware/link/lease.py``):
        if another application holds it, raises DeviceInUseError, and if the device
        carries another instrument than the scenario's, InstrumentMismatchError, having
        commanded no coil."""
        compile_kernels(progress=False)
        self._built = BuildDiagram(self.scenario, mode=RunMode.DEVICE_API, label="device")
        diagram = self._built.diagram
        simulator = Simulator(diagram)
        self._simulator = None
        simulator.Initialize()  # on LCM, DeviceInUseError where another holds the lease
        self._simulator = simulator
        root = self._simulator.get_mutable_context()
        app = self._built.app
        self._supervisor = app.supervisor
        self._feedforward = self._built.levitation.feedforward
        self._controller = app.controller
        estimator = app.estimator
        station = self._built.station.system
        self._temperatures = app.temperatures
        self._contexts = {system: system.GetMyMutableContextFromRoot(root) for system in (
            self._supervisor, self._feedforward, self._controller, estimator, station,
            self._temperatures)}
        self._ports = [estimator.GetOutputPort(name) for name in
                       ("X_WI_measured", "V_WI_measured", "tracking_ok")]
        self._estimator, self._station = estimator, station
        self._shares_cores = self._built.station.shares_cores
        self._clock_zero, self._ticks = time.perf_counter(), 0
        self._silent, self._next_watch_s = None, self._now() + WATCH_PERIOD_S
        self.state = self._read_state()
        lease = self._built.station.lease
        if lease is not None:  # the device's lease before anything else
            try:
                self._run_until(lambda: lease.granted, self.scenario.station.wait_for_station_s,
                                "connect (the device's lease)", on_timeout=lambda: None)
            except Exception:
                self._simulator = None
                raise

    def disconnect(self) -> None:
        """Coils off at once (no landing: land first), and the diagram released; after
        a device went silent, only released (nothing takes the commands)."""
        self._require_connection(heard=False)
        if self._silent is None:
            self._coils_off()
            self.set_feedforward_wrench(np.zeros(6))
            self._tick()
        if self._built.station.lease is not None:
            self._built.station.lease.release()
        self._simulator = None

    # --- commands (each takes effect on the next tick) ---------------------

    @property
    def faults(self) -> int:
        """The latched FAULT_* bits."""
        self._require_connection()
        return self._supervisor.faults(self._contexts[self._supervisor])

    @property
    def coils_powered(self) -> bool:
        """Whether the coils' supply is on: the supervisor cuts it on a stuck
        amplifier (``reset_faults`` restores it)."""
        self._require_connection()
        return self._supervisor.coils_powered(self._contexts[self._supervisor])

    def set_gains(self, kp=None, kd=None) -> None:
        """Per-axis PD gains [x, y, z translation in W; rotations about I's axes]
        (N/m, N*m/rad; N*s/m, N*m*s/rad)."""
        self._require_connection()
        self._controller.set_gains(self._contexts[self._controller], kp, kd)

    def gains(self):
        """(kp, kd) in effect."""
        self._require_connection()
        return self._controller.gains(self._contexts[self._controller])

    def set_desired_pose(self, pose, rates=None) -> None:
        """Hover at ``pose`` [x, y, z, roll, pitch, yaw] (m, rad) with setpoint
        ``rates`` (m/s, rad/s; default zero); ends a takeoff's rise or a landing's
        descent in progress. A pose inside the glass or beyond what the coils can hold
        is refused, and so is any pose while the coils do not carry the instrument
        fully (before ``takeoff``, after ``land``, while either ramps the force)."""
        self._require_no_faults("set_desired_pose")
        pose = _vector("pose", pose, 6)
        check_pose_reachable(pose, self.scenario.device, self._built.magnetics, "pose")
        rates = np.zeros(6) if rates is None else _vector("rates", rates, 6)
        enable = self._current_enable()
        if enable < 1.0:
            raise DeviceStateError(
                "set_desired_pose refused: the coils carry nothing (call takeoff() first)"
                if enable == 0.0 else
                f"set_desired_pose refused: the force is ramping (gain {enable:.2f} of 1): "
                "let takeoff() or land() finish first")
        self._set_motion(hold_motion(np.concatenate((pose, rates)), self._current()[1],
                                     self._now(), self._built.tick_s))

    def set_feedforward_wrench(self, wrench) -> None:
        """Added wrench [f; tau] in W (N, N*m about I's origin)."""
        self._require_connection()
        self._feedforward.get_mutable_source_value(self._contexts[self._feedforward]) \
            .SetFromVector(_vector("wrench", wrench, 6))

    def on_tick(self, callback: Callable[[TickState], None]) -> None:
        """``callback(state)`` after every tick."""
        self._tick_callbacks.append(callback)

    def on_fault(self, callback: Callable[[int], None]) -> None:
        """``callback(bits)`` when a fault bit rises, with the latched bits."""
        self._fault_callbacks.append(callback)

    def set_boundary(self, center_m, radius_m: Optional[float]) -> None:
        """Leaving the sphere (m; None: no boundary) raises sensor out of range."""
        self._require_connection()
        if radius_m is not None and not radius_m > 0:
            raise ValueError(f"radius_m = {radius_m}: must be > 0 (m), or None")
        context = self._contexts[self._supervisor]
        self._supervisor.set_limits(context, dataclasses.replace(
            self._supervisor.limits(context),
            boundary_center_m=tuple(_vector("center_m", center_m, 3)),
            boundary_radius_m=radius_m))

    def reset_faults(self) -> None:
        """Clear the latched faults and power the coils again (a fault's landing stays
        what is flown)."""
        self._require_connection()
        self._supervisor.reset_faults(self._contexts[self._supervisor])

    def coil_temperatures_c(self) -> np.ndarray:
        """The coils' estimated winding temperatures (C)."""
        self._require_connection()
        return self.state.coil_temperature_c.copy()

    # --- motions -----------------------------------------------------------

    def takeoff(self, pose=None, timeout_s: float = 5.0) -> None:
        """Ramp the force up and rise to ``pose`` (default: the scenario's first
        waypoint); blocks until hovering there (``timeout_s``, s), else lands and raises
        DeviceTimeoutError. The force ramps up from what it is: called while flying,
        or landing, it flies to ``pose`` from where the setpoint is."""
        self._require_no_faults("takeoff")
        positive("timeout_s", timeout_s)
        motion = self.scenario.motion
        target = np.asarray(motion.waypoints[0].pose if pose is None else
                            _vector("pose", pose, 6), dtype=float)
        check_pose_reachable(target, self.scenario.device, self._built.magnetics, "pose")
        setpoint, enable = self._current()
        ramp_s = motion.force_ramp_s * (1.0 - enable)
        force_gain = (PiecewisePolynomial.FirstOrderHold([0.0, ramp_s], [[enable, 1.0]])
                      if ramp_s > 0.0 else  # carried already: the gain stays 1
                      PiecewisePolynomial.ZeroOrderHold([0.0, self._built.tick_s], [[1.0, 1.0]]))
        self._set_motion(make_motion(
            minimum_jerk_plan(setpoint[0:6], ramp_s,
                              [(target, motion.waypoints[0].move_s, 0.0)], 0.0),
            force_gain, self._now(), self._built.tick_s))

        def hovering():
            if self.faults:
                raise DeviceFaultError(f"takeoff ended by fault {self.faults:#x}; landing")
            return (self._motion_done()
                    and np.linalg.norm(self.state.X_WI[4:7] - target[0:3]) < HOVER_TOLERANCE_M
                    and np.linalg.norm(self.state.V_WI[3:6]) < SETTLED_SPEED_M_S)
        self._run_until(hovering, timeout_s, "takeoff", on_timeout=self.land)

    def land(self, timeout_s: float = 5.0) -> None:
        """Descend onto the glass and ramp the force down; blocks until done, else
        cuts the coils and raises DeviceTimeoutError."""
        self._require_connection()
        positive("timeout_s", timeout_s)
        context = self._contexts[self._supervisor]
        if not self._supervisor.active_motion(context).landing:
            self._supervisor.land(context)
        self._run_until(self._motion_done, timeout_s, "land", on_timeout=self._coils_off)

    def run_for(self, duration_s: float) -> None:
        """Tick for ``duration_s`` (s), holding or carrying on what was commanded."""
        self._require_connection()
        nonnegative("duration_s", duration_s)
        for _ in range(int(round(duration_s / self._built.tick_s))):
            self._tick()

    # --- the loop ----------------------------------------------------------

    def _run_until(self, done, timeout_s: float, what: str, on_timeout) -> None:
        deadline_s = self._now() + timeout_s
        while not done():
            if self._now() >= deadline_s:
                on_timeout()
                raise DeviceTimeoutError(
                    f"{what} not done within {timeout_s:g} s (faults {self.faults:#x})")
            self._tick()

    def _tick(self) -> None:
        if self._realtime_rate > 0:  # each tick released at its wall-clock slot
            slot_s = self._built.tick_s / self._realtime_rate
            self._ticks += 1
            if time.perf_counter() > self._clock_zero + (self._ticks + 1) * slot_s:
                # Idle between calls, not late: the clock starts again from now.
                self._clock_zero = time.perf_counter() - self._ticks * slot_s
            wait_until(self._clock_zero + self._ticks * slot_s,
                       SHARED_SPIN_S if self._shares_cores else math.inf)
        latched = self.faults
        self._simulator.AdvanceTo(self._now() + self._built.tick_s)
        self.state = self._read_state()
        if self.state.faults & ~latched:
            for callback in self._fault_callbacks:
                callback(self.state.faults)
        for callback in self._tick_callbacks:
            callback(self.state)
        if self._now() >= self._next_watch_s:
            self._next_watch_s += WATCH_PERIOD_S
            silence = self._built.station.silence(self._simulator.get_context())
            if silence is not None:
                self._silent = silence_sentence(silence, "MaglevDevice", self._now())
                raise DeviceSilentError(self._silent)

    def _read_state(self) -> TickState:
        estimator_context = self._contexts[self._estimator]
        X, V, ok = (port.Eval(estimator_context) for port in self._ports)
        currents = self._station.GetOutputPort("coil_currents").Eval(
            self._contexts[self._station])
        temperatures = self._temperatures.get_output_port().Eval(
            self._contexts[self._temperatures])
        return TickState(t_s=self._now(), X_WI=X, V_WI=V, tracking_ok=bool(ok[0] > 0.5),
                         coil_currents_a=currents, coil_temperature_c=temperatures,
                         faults=self.faults)

    def _now(self) -> float:
        return self._simulator.get_context().get_time()

    def _current(self):
        """(setpoint (12), enable) the supervisor outputs now."""
        context = self._contexts[self._supervisor]
        return self._supervisor.active_motion(context).at(self._now())

    def _motion_done(self) -> bool:
        return self._supervisor.active_motion(self._contexts[self._supervisor]).end_s <= \
            self._now()

    def _set_motion(self, motion) -> None:
        self._supervisor.set_motion(self._contexts[self._supervisor], motion)

    def _coils_off(self) -> None:
        self._set_motion(hold_motion(self._current()[0], 0.0, self._now(), self._built.tick_s))

    def _current_enable(self) -> float:
        return self._current()[1]

    def _require_no_faults(self, what: str) -> None:
        self._require_connection()
        if self.faults:
            raise DeviceFaultError(f"{what} refused: fault {self.faults:#x} is latched "
                                   "(reset_faults() once it is cleared)")

    def _require_connection(self, heard: bool = True) -> None:
        """A RuntimeError unless connected, and (``heard``) a DeviceSilentError once the
        device went silent."""
        if self._simulator is None:
            raise RuntimeError("the device is not connected: call connect() first")
        if heard and self._silent is not None:
            raise DeviceSilentError(f"{self._silent}; call disconnect()")


def _vector(name: str, value, size: int) -> np.ndarray:
    array = np.asarray(value, dtype=float).ravel()
    if array.shape != (size,) or not np.all(np.isfinite(array)):
        raise ValueError(f"{name} = {np.asarray(value).tolist()}: must be {size} finite numbers")
    return array
