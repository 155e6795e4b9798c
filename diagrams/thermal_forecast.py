"""The coils' heating over a scripted flight, forecast before it flies.

The flight plan's setpoints and accelerations give the wrench the coils must
supply (the weight, scaled by the force ramp, plus m a); the thermal allocation
at each setpoint, with the budget the controller uses, gives the currents; the
thermal model's exact step gives the temperatures. For each waypoint hold it
says whether the coils could hold it for ever (every coil's steady current
within the budget) and, if not, how long they allow it from the moment the plan
arrives there with the temperatures it arrives with: after that the budget cuts
the lift short and the device supervisor lands (coil over-temperature).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import List, Optional

import numpy as np
from pydrake.math import RollPitchYaw

from maglev_haptics.diagrams.motion import check_waypoints_reachable, flight_plan
from maglev_haptics.hardware.constants import GRAVITY_M_S2
from maglev_haptics.hardware.magnetics import load_magnetics
from maglev_haptics.hardware.thermal import (
    coil_thermal, current_bounds_a, temperature_after_c, thermal_budget, winding_resistance_ohm)
from maglev_haptics.systems.current_allocator import (
    TORQUE_WEIGHT_PER_M, bounded_minimum_power_currents)
from maglev_haptics.systems.levitation_controller import is_thermally_limited

FORECAST_STEP_S = 0.01  # along the plan: the thermal model's period (s)
# A hold that cannot last is followed from its arrival for its length, and at least this
# long (s), to say how long the coils allow it.
MAX_EXTENSION_S = 600.0


@dataclass
class HoldForecast:
    """One waypoint hold's thermal outlook."""

    waypoint: int  # index in motion.waypoints
    start_s: float  # when the plan arrives (s)
    hold_s: float  # how long the script holds it (s)
    sustainable: bool  # the coils could hold it for ever within their budget
    allowed_s: Optional[float]  # how long they allow it from arrival (s); None: for ever
    hottest_c: float  # the hottest winding at the hold's end as scripted (deg C)

    @property
    def cut_short(self) -> bool:
        """Whether the script holds it longer than the coils allow."""
        return self.allowed_s is not None and self.allowed_s < self.hold_s


def _lift(mass_kg: float, enable: float, acceleration_m_s2) -> np.ndarray:
    """The wrench [f; tau] (N, N*m) the coils supply to move the instrument along the plan."""
    return np.r_[enable * mass_kg * (np.asarray(acceleration_m_s2) + [0.0, 0.0, GRAVITY_M_S2]),
                 0.0, 0.0, 0.0]


class _Coils:
    """The allocation and thermal step the controller and the thermal model make."""

    def __init__(self, scenario, magnetics):
        device = scenario.device
        self.thermal = coil_thermal(device)
        self.limit_a = device.amplifier.current_limit_a
        self.budget = thermal_budget(
            self.thermal, horizon_s=scenario.controller.thermal_horizon_s,
            margin_c=scenario.controller.thermal_margin_c, current_limit_a=self.limit_a)
        self.magnetics = magnetics
        self.p_WA = np.asarray(device.p_WA, dtype=float)
        self.mass_kg = device.instrument_spec().mass_kg

    def matrix(self, pose) -> np.ndarray:
        R_WI = RollPitchYaw(pose[3:6]).ToRotationMatrix().matrix()
        return self.magnetics.wrench_matrix_from(pose[0:3] - self.p_WA, R_WI)

    def step(self, A, wrench, temperature_c, duration_s):
        """(temperatures after ``duration_s`` (deg C), thermally limited)."""
        bounds = current_bounds_a(self.budget, temperature_c)
        currents, shortfall = bounded_minimum_power_currents(
            A, wrench, winding_resistance_ohm(self.thermal, temperature_c), bounds,
            TORQUE_WEIGHT_PER_M)
        limited = is_thermally_limited(currents, bounds, shortfall, self.limit_a, self.mass_kg)
        return temperature_after_c(self.thermal, temperature_c, currents, duration_s), limited

    def sustainable(self, A, wrench) -> bool:
        """Whether every coil at its steady bound (each at the budget's target) carries it,
        but for a shortfall too small to be thermally limited."""
        hot = np.full(A.shape[1], self.budget.target_c)
        bounds = current_bounds_a(self.budget, hot)
        currents, shortfall = bounded_minimum_power_currents(
            A, wrench, winding_resistance_ohm(self.thermal, hot), bounds, TORQUE_WEIGHT_PER_M)
        return not is_thermally_limited(currents, bounds, shortfall, math.inf, self.mass_kg)


def forecast_holds(scenario, plan, magnetics) -> List[HoldForecast]:
    """Each waypoint hold of ``plan`` (the levitation scenario's flight plan) with the
    coils' outlook there (module docstring)."""
    coils = _Coils(scenario, magnetics)
    n = magnetics.n_coils
    temperature_c = np.full(n, coils.thermal.ambient_c)
    acceleration = plan.setpoint.derivative(2)
    forecasts = []
    t = 0.0
    holds = list(enumerate(plan.holds))
    for index, (start_s, end_s) in holds:
        # Fly to the hold, then through it as scripted.
        while t < start_s:
            pose = plan.setpoint.value(t).ravel()
            wrench = _lift(coils.mass_kg, plan.enable.value(t)[0, 0],
                           acceleration.value(t).ravel()[0:3])
            temperature_c, _ = coils.step(coils.matrix(pose), wrench, temperature_c,
                                          FORECAST_STEP_S)
            t += FORECAST_STEP_S
        pose = plan.setpoint.value(start_s).ravel()
        A = coils.matrix(pose)
        lift = _lift(coils.mass_kg, plan.enable.value(start_s)[0, 0], np.zeros(3))
        sustainable = coils.sustainable(A, lift)
        arrival_c = temperature_c.copy()
        while t < end_s:
            temperature_c, _ = coils.step(A, lift, temperature_c, FORECAST_STEP_S)
            t += FORECAST_STEP_S
        allowed_s = None
        if not sustainable:
            allowed_s = _time_allowed(coils, A, lift, arrival_c, end_s - start_s)
        forecasts.append(HoldForecast(
            waypoint=index, start_s=float(start_s), hold_s=float(end_s - start_s),
            sustainable=sustainable, allowed_s=allowed_s, hottest_c=float(temperature_c.max())))
    return forecasts


def _time_allowed(coils: _Coils, A, wrench, temperature_c, hold_s: float) -> float:
    """How long (s) the coils, from ``temperature_c``, carry ``wrench`` before the budget
    cuts it short, looked for over the hold's ``hold_s`` and at least MAX_EXTENSION_S
    (the horizon is returned when they carry it that long); steps of 1/200 of the time constant (the
    update is exact for held currents)."""
    horizon_s = max(MAX_EXTENSION_S, hold_s)
    step_s = float(np.min(coils.thermal.time_constant_s)) / 200
    t = 0.0
    while t < horizon_s:
        temperature_c, limited = coils.step(A, wrench, temperature_c, step_s)
        if limited:
            return t
        t += step_s
    return horizon_s


def describe(forecast: HoldForecast, label: str) -> str:
    """One line on a hold the script holds longer than the coils allow."""
    return (f"{label}: motion.waypoints[{forecast.waypoint}]: held {forecast.hold_s:g} s, "
            f"but the coils allow {forecast.allowed_s:.1f} s of it within their thermal "
            "budget; the device then lands (coil over-temperature)")


def thermal_outlook(scenario, label: str, duration_s: Optional[float] = None) -> List[str]:
    """``describe``'s line for each hold of a levitation scenario with the thermal
    allocation that the thermal budget would end before the run does (at ``duration_s``,
    else the scenario's ``duration_s``, else the script's end); none for other
    scenarios. A waypoint the coils cannot reach at all is refused first
    (``check_waypoints_reachable``)."""
    if scenario.haptics is not None or scenario.controller.allocation != "thermal":
        return []
    device = scenario.device
    magnetics = load_magnetics(device)
    check_waypoints_reachable(scenario.motion, device, magnetics, label)
    plan = flight_plan(scenario.motion, device.instrument_spec().rest_height_m)
    end_s = next(s for s in (duration_s, scenario.duration_s, plan.end_s) if s is not None)
    return [describe(forecast, label) for forecast in forecast_holds(scenario, plan, magnetics)
            if forecast.cut_short and forecast.start_s + forecast.allowed_s < end_s]
