"""The coils' thermal model: one first-order RC to ambient per coil.

Each coil's winding is one lumped heat capacity C [J/K] connected to ambient
through a thermal resistance R_th [K/W] and heated by I^2 R(T), with copper's
resistance rising linearly with temperature,
R(T) = R_ref (1 + alpha (T - T_ref)). Writing theta = T - T_amb [K], for a
constant current I [A]

    C dtheta/dt = P_amb + k theta - theta / R_th,
    P_amb = I^2 R(T_amb) [W],  k = I^2 R_ref alpha [W/K],

which is linear in theta: it relaxes with rate lambda = (1/R_th - k) / C [1/s]
towards theta_ss = P_amb / (1/R_th - k) [K]. For lambda <= 0 (about 4 A with
the defaults) no steady state exists: the winding runs away. Every function
below uses this closed form, so the sampled update is exact when the current
is held over the sample period (the amplifiers hold it between ticks).
Coils are thermally independent: R_th is the effective value of a coil among
equally loaded neighbours. C and R_th are one number for every coil, or one each
(``thermal_resistances_k_per_w``, ``heat_capacities_j_per_k``): every function
broadcasts them against the coils' axis (the last).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numba
import numpy as np
from numba.extending import register_jitable

from maglev_haptics.hardware.device import CoilSpec, DeviceConfig, ThermalSpec
from maglev_haptics.hardware.kernels import MATRIX, SCALAR, VECTOR, kernel

COPPER_DENSITY_KG_M3 = 8960.0
COPPER_SPECIFIC_HEAT_J_PER_KG_K = 385.0


@dataclass(frozen=True)
class CoilThermal:
    """The parameters of one coil's thermal RC, derived from a DeviceConfig."""

    heat_capacity_j_per_k: float | tuple  # C [J/K]; a tuple: each coil's
    thermal_resistance_k_per_w: float | tuple  # R_th to ambient [K/W]; a tuple: each coil's
    resistance_ref_ohm: float  # winding resistance at the reference temperature [ohm]
    reference_temperature_c: float  # [deg C]
    alpha_per_k: float  # resistance temperature coefficient [1/K]
    ambient_c: float  # [deg C]
    max_c: float  # largest allowed winding temperature [deg C]

    @property
    def time_constant_s(self):
        """R_th C [s]: the cooling time constant (and heating's at small currents); each
        coil's where they differ."""
        return np.asarray(self.heat_capacity_j_per_k) * np.asarray(self.thermal_resistance_k_per_w)

    def per_coil(self, n_coils: int) -> tuple:
        """(C (n_coils,) [J/K], R_th (n_coils,) [K/W]): each coil's."""
        return tuple(np.ascontiguousarray(np.broadcast_to(np.asarray(value, dtype=float),
                                                          (n_coils,)))
                     for value in (self.heat_capacity_j_per_k, self.thermal_resistance_k_per_w))


def winding_volume_m3(coil: CoilSpec) -> float:
    """Volume of the annular winding [m^3]."""
    return math.pi / 4 * (coil.outer_diameter_m**2 - coil.inner_diameter_m**2) * coil.height_m


def coil_heat_capacity_j_per_k(coil: CoilSpec, thermal: ThermalSpec) -> float:
    """C [J/K]: the override if set, else the winding's copper mass times copper's
    specific heat (bobbin and potting ignored, which errs on the hot side)."""
    if thermal.heat_capacity_j_per_k is not None:
        return float(thermal.heat_capacity_j_per_k)
    copper_mass_kg = winding_volume_m3(coil) * thermal.copper_fill_factor * COPPER_DENSITY_KG_M3
    return copper_mass_kg * COPPER_SPECIFIC_HEAT_J_PER_KG_K


def coil_thermal(config: DeviceConfig) -> CoilThermal:
    """The thermal RC of one coil of ``config``; ValueError names a bad field."""
    coil, thermal = config.coil, config.thermal
    checks = {
        "thermal.thermal_resistance_k_per_w": thermal.thermal_resistance_k_per_w,
        "thermal.copper_fill_factor": thermal.copper_fill_factor,
        "thermal.resistance_temperature_coefficient_per_k":
            thermal.resistance_temperature_coefficient_per_k,
        "coil.resistance_ohm": coil.resistance_ohm,
    }
    if thermal.heat_capacity_j_per_k is not None:
        checks["thermal.heat_capacity_j_per_k"] = thermal.heat_capacity_j_per_k
    for name, value in checks.items():
        if not (math.isfinite(value) and value > 0):
            raise ValueError(f"device.{name} = {value!r}: must be a positive number")
    if not thermal.max_winding_temperature_c > thermal.ambient_temperature_c:
        raise ValueError(
            f"device.thermal.max_winding_temperature_c = {thermal.max_winding_temperature_c!r}: "
            f"must exceed ambient_temperature_c = {thermal.ambient_temperature_c!r}")
    capacities, resistances = thermal.heat_capacities_j_per_k, thermal.thermal_resistances_k_per_w
    result = CoilThermal(
        heat_capacity_j_per_k=(coil_heat_capacity_j_per_k(coil, thermal) if capacities is None
                               else tuple(float(v) for v in capacities)),
        thermal_resistance_k_per_w=(float(thermal.thermal_resistance_k_per_w)
                                    if resistances is None
                                    else tuple(float(v) for v in resistances)),
        resistance_ref_ohm=float(coil.resistance_ohm),
        reference_temperature_c=float(thermal.resistance_reference_temperature_c),
        alpha_per_k=float(thermal.resistance_temperature_coefficient_per_k),
        ambient_c=float(thermal.ambient_temperature_c),
        max_c=float(thermal.max_winding_temperature_c))
    if not winding_resistance_ohm(result, result.max_c) > 0:
        raise ValueError("device.thermal: the winding resistance at max_winding_temperature_c "
                         "must be positive")
    return result


def winding_resistance_ohm(model: CoilThermal, temperature_c):
    """R(T) [ohm] at winding temperature T [deg C] (array in, array out)."""
    excess_k = np.asarray(temperature_c, dtype=float) - model.reference_temperature_c
    return model.resistance_ref_ohm * (1 + model.alpha_per_k * excess_k)


def _rate_and_drive(model: CoilThermal, current_a):
    """(lambda [1/s], P_amb / C [K/s]) of the linear ODE for a held current [A]."""
    squared = np.square(np.asarray(current_a, dtype=float))
    c = np.asarray(model.heat_capacity_j_per_k)
    rate = (1 / np.asarray(model.thermal_resistance_k_per_w)
            - squared * model.resistance_ref_ohm * model.alpha_per_k) / c
    return rate, squared * winding_resistance_ohm(model, model.ambient_c) / c


def steady_state_temperature_c(model: CoilThermal, current_a):
    """Winding temperature [deg C] a constant current [A] settles at; inf where it runs away."""
    rate, drive = _rate_and_drive(model, current_a)
    with np.errstate(divide="ignore"):
        rise = np.where(rate > 0, drive / np.where(rate > 0, rate, 1.0), np.inf)
    return model.ambient_c + rise


def continuous_current_limit_a(model: CoilThermal, steady_c=None):
    """I_cont [A]: the largest constant current whose steady state is T_max (or
    ``steady_c`` [deg C]); each coil's where their R_th differ.

    At steady state I^2 R(T) = (T - T_amb) / R_th, exactly.
    """
    steady_c = model.max_c if steady_c is None else steady_c
    heat_w = (steady_c - model.ambient_c) / np.asarray(model.thermal_resistance_k_per_w)
    return np.sqrt(heat_w / float(winding_resistance_ohm(model, steady_c)))[()]


def weakest_coil_current_limit_a(model: CoilThermal) -> float:
    """The smallest coil's ``continuous_current_limit_a`` [A]."""
    return float(np.min(continuous_current_limit_a(model)))


def temperature_after_c(model: CoilThermal, temperature_c, current_a, duration_s):
    """Winding temperature [deg C] after ``duration_s`` [s] at a held current [A].

    The exact solution of the ODE above; with ``duration_s`` the sample period
    it is the exact discrete update T[k+1] = f(T[k], I[k]) for currents held
    over each period. Arrays broadcast (e.g. 27 coils at once).
    """
    return _temperature_after_c(temperature_c, current_a, duration_s, model.ambient_c,
                                np.asarray(model.heat_capacity_j_per_k),
                                np.asarray(model.thermal_resistance_k_per_w),
                                model.resistance_ref_ohm, model.alpha_per_k,
                                float(winding_resistance_ohm(model, model.ambient_c)))


def winding_numbers(model: CoilThermal, n_coils: int) -> tuple:
    """The numbers ``step_temperatures_c`` takes after the duration for ``n_coils``:
    T_amb [deg C], each coil's C [J/K] and R_th [K/W], R_ref [ohm], alpha [1/K],
    R(T_amb) [ohm]."""
    return (model.ambient_c, *model.per_coil(n_coils), model.resistance_ref_ohm,
            model.alpha_per_k, float(winding_resistance_ohm(model, model.ambient_c)))


@register_jitable
def winding_temperature_after_c(temperature_c, current_a, duration_s, ambient_c,
                                heat_capacity_j_per_k, thermal_resistance_k_per_w,
                                resistance_ref_ohm, alpha_per_k, ambient_resistance_ohm):
    """``temperature_after_c`` of one winding, with its C [J/K] and R_th [K/W] and the
    model's other numbers."""
    squared = current_a * current_a
    rate = (1 / thermal_resistance_k_per_w - squared * resistance_ref_ohm * alpha_per_k) \
        / heat_capacity_j_per_k  # lambda [1/s]
    drive = squared * ambient_resistance_ohm / heat_capacity_j_per_k  # P_amb / C [K/s]
    # theta(t) = theta0 e^{-lambda t} + drive (1 - e^{-lambda t}) / lambda
    x = -rate * duration_s
    phi = 1 + x / 2 if abs(x) < 1e-8 else math.expm1(x) / x  # expm1(x) / x
    return ambient_c + (temperature_c - ambient_c) * math.exp(x) + drive * duration_s * phi


# A compiled ufunc for Python's arrays: in numpy, the 27 coils' update took ~110 us.
_temperature_after_c = numba.vectorize(
    ["float64(float64, float64, float64, float64, float64, float64, float64, float64, float64)"],
    cache=True)(winding_temperature_after_c)


@kernel((VECTOR, VECTOR, SCALAR, SCALAR, VECTOR, VECTOR, SCALAR, SCALAR, SCALAR))
def step_temperatures_c(temperature_c, current_a, duration_s, ambient_c, heat_capacity_j_per_k,
                        thermal_resistance_k_per_w, resistance_ref_ohm, alpha_per_k,
                        ambient_resistance_ohm):
    """Each winding's temperature [deg C] in ``temperature_c``, in place, after
    ``duration_s`` [s] at its held current [A] (``winding_temperature_after_c``), each
    with its own C and R_th (``winding_numbers``)."""
    for j in range(temperature_c.size):
        temperature_c[j] = winding_temperature_after_c(
            temperature_c[j], current_a[j], duration_s, ambient_c, heat_capacity_j_per_k[j],
            thermal_resistance_k_per_w[j], resistance_ref_ohm, alpha_per_k,
            ambient_resistance_ohm)


def time_to_temperature_s(model: CoilThermal, temperature_c, current_a, target_c=None):
    """Time [s] from ``temperature_c`` [deg C] to ``target_c`` [deg C] (default
    T_max) at a held current [A]: 0 if already there, inf if never reached."""
    target = model.max_c if target_c is None else target_c
    rate, drive = _rate_and_drive(model, current_a)
    rise0 = np.asarray(temperature_c, dtype=float) - model.ambient_c
    rise1 = np.asarray(target, dtype=float) - model.ambient_c
    rate, drive, rise0, rise1 = np.broadcast_arrays(rate, drive, rise0, rise1)
    # theta(t) - theta_ss = (theta0 - theta_ss) e^{-lambda t}, so
    # t = ln((theta0 - theta_ss) / (theta1 - theta_ss)) / lambda; written with
    # drive and log1p it stays finite as lambda -> 0 (where it tends to the
    # linear-heating time (theta1 - theta0) / drive).
    gap = rise1 - rise0
    growth = drive - rate * rise1  # C dtheta/dt at the target, / C [K/s]
    with np.errstate(divide="ignore", invalid="ignore"):
        x = rate * gap / growth
        ratio = np.where(np.abs(x) < 1e-8, 1 - x / 2, np.log1p(x) / np.where(x == 0, 1.0, x))
        time = gap / growth * ratio
    # Reached only if the winding heats all the way: at the target (growth)
    # and at the start (1 + x > 0, as the rate is linear in theta).
    time = np.where((growth > 0) & (1 + x > 0), time, np.inf)
    return np.where(gap <= 0, 0.0, time)[()]


@dataclass(frozen=True)
class ThermalBudget:
    """Each coil's current bound [A] as its winding warms: the largest current that,
    held, would not take the winding past ``target_c`` [deg C] within ``horizon_s``
    [s], and never above ``current_limit_a`` [A]. At and above ``target_c`` it is
    the current that holds the winding at ``target_c``. Tabulated over temperature
    (``bound_a[j, k]`` at ``lowest_c + k * step_c``: one row for every coil, or coil
    j's), read by ``current_bounds_a``."""

    horizon_s: float
    target_c: float
    current_limit_a: float
    lowest_c: float
    step_c: float
    bound_a: np.ndarray


def thermal_budget(model: CoilThermal, *, horizon_s: float, margin_c: float,
                   current_limit_a: float, points: int = 512) -> ThermalBudget:
    """The budget that keeps each winding ``margin_c`` [K] under its limit, tabulated
    from 50 K below ambient to the target (bisection on ``time_to_temperature_s``);
    a row for each coil where their C or R_th differ."""
    if np.ndim(model.heat_capacity_j_per_k) or np.ndim(model.thermal_resistance_k_per_w):
        n = max(len(np.atleast_1d(v)) for v in (model.heat_capacity_j_per_k,
                                                model.thermal_resistance_k_per_w))
        rows = [_budget_row(dataclasses.replace(model, heat_capacity_j_per_k=float(c),
                                                thermal_resistance_k_per_w=float(r)),
                            horizon_s, margin_c, current_limit_a, points)
                for c, r in zip(*model.per_coil(n))]
        return dataclasses.replace(rows[0], bound_a=np.vstack([row.bound_a for row in rows]))
    return _budget_row(model, horizon_s, margin_c, current_limit_a, points)


def _budget_row(model: CoilThermal, horizon_s: float, margin_c: float, current_limit_a: float,
                points: int) -> ThermalBudget:
    """``thermal_budget`` of a model whose coils are alike: one row."""
    target_c = model.max_c - margin_c
    if not target_c > model.ambient_c:
        raise ValueError(f"controller.thermal_margin_c = {margin_c!r}: must leave the target "
                         f"above ambient ({model.max_c} - margin > {model.ambient_c} C)")
    lowest_c = model.ambient_c - 50.0
    temperature_c = np.linspace(lowest_c, target_c, points)
    steady = continuous_current_limit_a(model, target_c)  # holds target_c
    low = np.full(points, min(steady, current_limit_a))  # never reaches the target
    high = np.full(points, float(current_limit_a))
    for _ in range(60):
        middle = 0.5 * (low + high)
        allowed = time_to_temperature_s(model, temperature_c, middle, target_c) >= horizon_s
        low = np.where(allowed, middle, low)
        high = np.where(allowed, high, middle)
    allowed = time_to_temperature_s(model, temperature_c, current_limit_a, target_c) >= horizon_s
    bound = np.where(allowed, current_limit_a, low)
    bound[-1] = min(steady, current_limit_a)
    return ThermalBudget(horizon_s=float(horizon_s), target_c=target_c,
                         current_limit_a=float(current_limit_a), lowest_c=lowest_c,
                         step_c=float(temperature_c[1] - temperature_c[0]),
                         bound_a=bound[np.newaxis, :])


@kernel((VECTOR, SCALAR, SCALAR, MATRIX))
def _interpolated(x, lowest, step, table):
    """Row j of ``table`` (at lowest + k step; its one row for every j if it has one)
    linearly interpolated at each x[j], held at its ends."""
    result = np.empty(x.size)
    last = table.shape[1] - 1
    for j in range(x.size):
        row = min(j, table.shape[0] - 1)
        position = min(max((x[j] - lowest) / step, 0.0), float(last))
        k = min(int(position), last - 1)
        fraction = position - k
        result[j] = (1.0 - fraction) * table[row, k] + fraction * table[row, k + 1]
    return result


def current_bounds_a(budget: ThermalBudget, temperature_c: np.ndarray) -> np.ndarray:
    """Each coil's bound [A] at its winding temperature [deg C]."""
    return _interpolated(temperature_c, budget.lowest_c, budget.step_c, budget.bound_a)
