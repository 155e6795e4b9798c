"""6-DOF PD levitation control with gravity compensation and a feed-forward wrench,
and the coil currents that produce it.

Wrench vectors in the loop are ordered like the rows of the wrench matrix
(``load_magnetics(...).wrench_matrix``): [fx, fy, fz, tx, ty, tz] in W (N, N*m), torque about
the instrument origin. Pose vectors follow Drake's free-body ordering
[qw, qx, qy, qz, x, y, z]; spatial velocities [wx, wy, wz, vx, vy, vz] in W.
Setpoints are [x, y, z, roll, pitch, yaw] followed by their time derivatives
(m, rad, m/s, rad/s), with Drake's extrinsic X-Y-Z roll-pitch-yaw convention
and yaw unwrapped, so a 360 deg turn is a ramp.
"""

from dataclasses import dataclass, field
from typing import List, Optional

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import BasicVector, LeafSystem, ValueProducer

from maglev_haptics.hardware.config_checks import each, nonnegative, positive, require
from maglev_haptics.hardware.constants import GRAVITY_M_S2
from maglev_haptics.hardware.kernels import SCALAR, VECTOR, kernel
from maglev_haptics.hardware.thermal import (
    CoilThermal, current_bounds_a, thermal_budget, winding_resistance_ohm)
from maglev_haptics.systems.current_allocator import (
    ALLOCATIONS, TORQUE_WEIGHT_PER_M, allocate_currents, bounded_minimum_power_currents)
from maglev_haptics.systems.magnetic_actuation import wrench_matrix_at
from maglev_haptics.systems.rotations import (
    angular_velocity_from_rpy_rates, rotation_error_W, rotation_from_quaternion, rotation_from_rpy)


@dataclass
class ControllerConfig:
    """Per-axis PD gains, given as closed-loop natural frequency and damping.

    Axes: x, y, z translation in W, then rotations about the instrument's own
    x, y, z axes (so the gains follow the instrument's principal inertias).
    ``kp``/``kd``, when set, override the derived gains: N/m and N*s/m for
    translation, N*m/rad and N*m*s/rad for rotation.
    """

    natural_frequency_hz: List[float] = field(default_factory=lambda: [10.0] * 6)
    damping_ratio: List[float] = field(default_factory=lambda: [0.7] * 6)
    kp: Optional[List[float]] = None
    kd: Optional[List[float]] = None
    lost_grace_s: float = 0.020  # hold gravity compensation through short dropouts, then cut the lift
    # "thermal": minimum power within each coil's current and thermal budget;
    # "pseudoinverse": minimum norm within the current limit alone, for comparison.
    allocation: str = "thermal"
    # The thermal budget: a coil may hold no current that would take its winding past
    # the limit less thermal_margin_c (K) within thermal_horizon_s (s).
    thermal_horizon_s: float = 10.0
    thermal_margin_c: float = 5.0

    def validate(self, path: str = "controller") -> None:
        """Range checks; a ValueError names ``path.field``, its value and what is allowed."""
        for name in ("natural_frequency_hz", "damping_ratio"):
            each(f"{path}.{name}", getattr(self, name), 6, positive)
        for name in ("kp", "kd"):
            if getattr(self, name) is not None:
                each(f"{path}.{name}", getattr(self, name), 6, nonnegative)
        nonnegative(f"{path}.lost_grace_s", self.lost_grace_s)
        require(self.allocation in ALLOCATIONS, f"{path}.allocation", self.allocation,
                f"must be one of {', '.join(ALLOCATIONS)}")
        positive(f"{path}.thermal_horizon_s", self.thermal_horizon_s)
        nonnegative(f"{path}.thermal_margin_c", self.thermal_margin_c)


def pd_gains(config: ControllerConfig, mass_kg: float, inertia_diag: np.ndarray):
    """(kp, kd), each (6,), from the config and the instrument's mass properties."""
    omega = 2 * np.pi * np.asarray(config.natural_frequency_hz, dtype=float)
    zeta = np.asarray(config.damping_ratio, dtype=float)
    modal_mass = np.concatenate([[mass_kg] * 3, inertia_diag])
    kp = modal_mass * omega**2 if config.kp is None else np.asarray(config.kp, float)
    kd = 2 * zeta * modal_mass * omega if config.kd is None else np.asarray(config.kd, float)
    return kp, kd


# The wrench laws run at 1 kHz: compiled by numba (3 us a call; 27 us in numpy).
@kernel((VECTOR, VECTOR, VECTOR))
def brake_wrench(pose, velocity, kd):
    """The PD's damping alone, toward rest: [f; tau] in W (N, N*m)."""
    R_WI = rotation_from_quaternion(pose[0:4])
    force = -kd[0:3] * velocity[3:6]
    torque = R_WI @ (-kd[3:6] * (R_WI.T @ velocity[0:3]))
    return np.concatenate((force, torque))


@kernel((VECTOR, VECTOR, VECTOR, VECTOR, VECTOR, SCALAR))
def pd_wrench(setpoint, pose, velocity, kp, kd, mass_kg):
    """Wrench [f; tau] in W (N, N*m) that tracks ``setpoint`` and carries the weight.

    Translation is PD in W axes; rotation is PD in the instrument's axes so each
    gain acts on one principal inertia.
    """
    p_WD, rpy_WD = setpoint[0:3], setpoint[3:6]
    v_WD, rpy_dot_WD = setpoint[6:9], setpoint[9:12]
    R_WI = rotation_from_quaternion(pose[0:4])
    p_WI = pose[4:7]
    w_WI, v_WI = velocity[0:3], velocity[3:6]
    force = kp[0:3] * (p_WD - p_WI) + kd[0:3] * (v_WD - v_WI)
    force = force + np.array([0.0, 0.0, mass_kg * GRAVITY_M_S2])
    R_WD = rotation_from_rpy(rpy_WD)
    w_WD = angular_velocity_from_rpy_rates(rpy_WD, rpy_dot_WD)
    angle_error_I = R_WI.T @ rotation_error_W(R_WD, R_WI)
    rate_error_I = R_WI.T @ (w_WD - w_WI)
    torque = R_WI @ (kp[3:6] * angle_error_I + kd[3:6] * rate_error_I)
    return np.concatenate((force, torque))


def carries_weight_while_lost(lost_time_s: float, config: ControllerConfig) -> bool:
    """Whether the weight is still carried after tracking has been lost this long (s).

    A levitated magnet is unstable without feedback (Earnshaw): any lift held on
    a stale pose rolls the instrument over within a few hundred ms. So the lift
    is carried only through short dropouts; after that the coils go dead and the
    instrument, under gravity alone, drops level onto the glass.
    """
    return lost_time_s <= config.lost_grace_s


def commanded_wrenches(setpoint, pose, velocity, tracking_ok: float, enable: float,
                       pd_gain: float, brake_gain: float, feedforward, lost_time_s: float,
                       kp, kd, mass_kg: float, config: ControllerConfig):
    """(commanded, rendered): the wrench [f; tau] in W (N, N*m) asked of the coils, and
    the part of it that acts on the hand (the commanded less the weight it carries).

    ``enable * (pd_gain * PD + brake_gain * D + weight) + feedforward`` while
    tracking is good; the weight alone (within the grace), then nothing, once
    tracking has been lost for ``lost_time_s``.
    """
    weight = np.zeros(6)
    if carries_weight_while_lost(lost_time_s, config):
        weight[2] = enable * mass_kg * GRAVITY_M_S2
    if lost_time_s > 0.0 or tracking_ok < 0.5:
        return weight, np.zeros(6)
    # pd already carries the weight; only its PD part fades with pd_gain.
    commanded = (enable * pd_gain * pd_wrench(setpoint, pose, velocity, kp, kd, mass_kg)
                 + (1.0 - pd_gain) * weight)
    if brake_gain != 0.0:
        commanded += enable * brake_gain * brake_wrench(pose, velocity, kd)
    commanded += feedforward
    return commanded, commanded - weight


# A shortfall past this fraction of the weight (in N, or N*m) is more than the sensor
# noise in the PD's wrench (~0.5 %).
THERMAL_SHORTFALL_OF_WEIGHT = 0.02


def is_thermally_limited(currents, bound_a, shortfall, current_limit_a: float,
                         mass_kg: float) -> bool:
    """Whether the wrench falls short by more than THERMAL_SHORTFALL_OF_WEIGHT of the
    weight while some coil sits at a thermal bound below the amplifiers' limit (A): the
    coils are too warm to carry what is asked."""
    if np.linalg.norm(shortfall) <= THERMAL_SHORTFALL_OF_WEIGHT * mass_kg * GRAVITY_M_S2:
        return False
    at_bound = np.abs(currents) >= bound_a * (1 - 1e-9)
    return bool(np.any(at_bound & (bound_a < current_limit_a)))


class LevitationController(LeafSystem):
    """Levitation controller (MLHI style): PD about a setpoint, gravity
    compensation, feed-forward wrench, safe force ramp, blind landing, and the
    coil currents that produce the wrench (``systems/current_allocator.py``).

    The commanded wrench is ``enable * (pd_gain * PD + brake_gain * D +
    weight) + feedforward`` while tracking is good: ``pd_gain`` 0 leaves
    the instrument to the hand and the feed-forward (haptic mode); D is
    the PD's damping alone, toward rest, which brakes an instrument let go
    while the virtual scene holds it.
    ``wrench_rendered_W`` is what acts on the hand: the commanded wrench
    less the weight it carries. When tracking is lost the measurement is stale, so PD
    stops: the weight is carried for ``lost_grace_s`` (short dropouts are
    ridden through), then every current is cut and the controller latches
    off (fault), so a lost instrument drops level onto the glass instead of
    being rolled over by lift on a stale pose.

    .. pydrake_system::

        name: LevitationController
        input_ports:
        - setpoint
        - X_WI_measured
        - V_WI_measured
        - tracking_ok
        - enable
        - pd_gain
        - brake_gain
        - wrench_feedforward_W
        - tracking_lost_s
        - coil_temperature_c
        - coil_currents
        - coils_stuck
        output_ports:
        - wrench_commanded_W
        - wrench_rendered_W
        - coil_currents_commanded
        - allocation_shortfall_W
        - thermally_limited

    ``coil_currents_commanded`` (n_coils, A) are the allocator's currents for the
    commanded wrench at the estimated pose (``systems/current_allocator.py``, the
    config's ``allocation``), every coil within ``current_limit_a`` and, with the
    thermal allocation, within its thermal budget at its winding temperature
    (``coil_temperature_c``, deg C); ``allocation_shortfall_W`` is the part of the
    wrench they cannot produce, and ``thermally_limited`` (1/0) says that the
    budget of a warm coil is why (``is_thermally_limited``): the device
    supervisor lands then (coil over-temperature). A coil the supervisor marks in
    ``coils_stuck`` (n_coils, 1/0) is allocated nothing (bound 0) and its measured
    current (``coil_currents``, A) is taken as a given: the others produce the
    wrench less what it makes (thermal allocation only).
    The wrench law and the allocation are one computation a tick, whose outputs
    all read it: the Python calls, not the arithmetic, are what a 1 kHz tick
    pays for. Direct feedthrough: the amplifiers sample the currents at the
    control rate, so they always use the newest estimate.

    ``tracking_lost_s`` is how long tracking has been lost (s; 0 while tracking),
    latched once past ``lost_grace_s``: the device supervisor counts it
    (``systems/device_supervisor.py``), which also raises the fault. No state: the PD
    gains ``kp`` and ``kd`` (6 each, ``pd_gains``) are numeric parameters 0 and 1
    (``set_gains``).
    """

    def __init__(self, *, config: ControllerConfig, mass_kg: float, inertia_diag,
                 magnetics, p_WA, current_limit_a: float, thermal: CoilThermal):
        LeafSystem.__init__(self)
        self._config = config
        self._mass_kg = float(mass_kg)
        kp, kd = pd_gains(config, mass_kg, np.asarray(inertia_diag, dtype=float))
        # Parameters, not constants: the device API sets them between ticks.
        self._kp = self.DeclareNumericParameter(BasicVector(kp))
        self._kd = self.DeclareNumericParameter(BasicVector(kd))
        self._magnetics = magnetics
        self._p_WA = np.asarray(p_WA, dtype=float)
        self._current_limit_a = float(current_limit_a)
        self._thermal = thermal
        self._budget = thermal_budget(thermal, horizon_s=config.thermal_horizon_s,
                                      margin_c=config.thermal_margin_c,
                                      current_limit_a=current_limit_a)
        self._setpoint = self.DeclareVectorInputPort("setpoint", 12)
        self._pose = self.DeclareVectorInputPort("X_WI_measured", 7)
        self._velocity = self.DeclareVectorInputPort("V_WI_measured", 6)
        self._tracking_ok = self.DeclareVectorInputPort("tracking_ok", 1)
        self._enable = self.DeclareVectorInputPort("enable", 1)
        self._pd_gain = self.DeclareVectorInputPort("pd_gain", 1)
        self._brake_gain = self.DeclareVectorInputPort("brake_gain", 1)
        self._feedforward = self.DeclareVectorInputPort("wrench_feedforward_W", 6)
        self._tracking_lost = self.DeclareVectorInputPort("tracking_lost_s", 1)
        n = magnetics.n_coils
        self._temperature = self.DeclareVectorInputPort("coil_temperature_c", n)
        self._measured = self.DeclareVectorInputPort("coil_currents", n)
        self._stuck = self.DeclareVectorInputPort("coils_stuck", n)
        # [resistances (ohm); bounds (A)]: they change at the thermal model's rate.
        self._coil_limits = self.DeclareCacheEntry(
            "coil_limits",
            ValueProducer(allocate=lambda: AbstractValue.Make(np.zeros(2 * n)),
                          calc=self._calc_coil_limits),
            {self._temperature.ticket()})
        # The matrix depends on the estimate alone, which changes at the tracker
        # rate; the command on everything, which changes every tick.
        self._matrix = self.DeclareCacheEntry(
            "wrench_matrix",
            ValueProducer(allocate=lambda: AbstractValue.Make(np.zeros((6, n))),
                          calc=self._calc_matrix),
            {self._pose.ticket()})
        # [commanded (6), rendered (6), currents (n), shortfall (6), thermally limited (1)]
        self._command = self.DeclareCacheEntry(
            "command",
            ValueProducer(allocate=lambda: AbstractValue.Make(np.zeros(19 + n)),
                          calc=self._calc_command),
            {self.all_input_ports_ticket(), self.all_parameters_ticket()})
        for name, rows in (("wrench_commanded_W", slice(0, 6)),
                           ("wrench_rendered_W", slice(6, 12)),
                           ("coil_currents_commanded", slice(12, 12 + n)),
                           ("allocation_shortfall_W", slice(12 + n, 18 + n)),
                           ("thermally_limited", slice(18 + n, 19 + n))):
            self.DeclareVectorOutputPort(
                name, rows.stop - rows.start,
                lambda context, output, rows=rows: output.SetFromVector(
                    self._command.Eval(context)[rows]),
                {self._command.ticket()})

    def set_gains(self, context, kp=None, kd=None) -> None:
        """Per-axis gains in ``context`` (N/m, N*m/rad; N*s/m, N*m*s/rad; the axes of
        ``ControllerConfig``), from the next evaluation on; None keeps one."""
        for index, gains, name in ((self._kp, kp, "kp"), (self._kd, kd, "kd")):
            if gains is None:
                continue
            gains = np.asarray(gains, dtype=float)
            if gains.shape != (6,) or not np.all(np.isfinite(gains)) or np.any(gains < 0):
                raise ValueError(f"{name} = {gains.tolist()}: must be 6 finite gains >= 0")
            context.get_mutable_numeric_parameter(index).SetFromVector(gains)

    def gains(self, context):
        """(kp, kd) in ``context``."""
        return (context.get_numeric_parameter(self._kp).CopyToVector(),
                context.get_numeric_parameter(self._kd).CopyToVector())

    def _scalar(self, port, context) -> float:
        # A scalar input without Eval's copy into a new array (~4 us a read).
        return port.EvalBasicVector(context).GetAtIndex(0)

    def _calc_matrix(self, context, matrix):
        matrix.set_value(wrench_matrix_at(self._magnetics, self._p_WA, self._pose.Eval(context)))

    def _calc_coil_limits(self, context, limits):
        temperature_c = self._temperature.Eval(context)
        limits.set_value(np.concatenate((winding_resistance_ohm(self._thermal, temperature_c),
                                         current_bounds_a(self._budget, temperature_c))))

    def _calc_command(self, context, command):
        commanded, rendered = commanded_wrenches(
            self._setpoint.Eval(context), self._pose.Eval(context),
            self._velocity.Eval(context), self._scalar(self._tracking_ok, context),
            self._scalar(self._enable, context), self._scalar(self._pd_gain, context),
            self._scalar(self._brake_gain, context), self._feedforward.Eval(context),
            self._scalar(self._tracking_lost, context),
            context.get_numeric_parameter(self._kp).CopyToVector(),
            context.get_numeric_parameter(self._kd).CopyToVector(), self._mass_kg, self._config)
        A = self._matrix.Eval(context)
        if self._config.allocation == "thermal":
            limits = self._coil_limits.Eval(context)
            n = limits.size // 2
            resistance, bounds = limits[:n], limits[n:]
            wanted, allowed = commanded, bounds
            stuck = self._stuck.EvalBasicVector(context).get_value() > 0.5
            if stuck.any():  # the stuck coils' wrench is a given; they get nothing
                measured = self._measured.Eval(context)
                wanted = commanded - A[:, stuck] @ measured[stuck]
                allowed = np.where(stuck, 0.0, bounds)
            currents, shortfall = bounded_minimum_power_currents(
                A, wanted, resistance, allowed, TORQUE_WEIGHT_PER_M)
            limited = is_thermally_limited(currents, bounds, shortfall,
                                           self._current_limit_a, self._mass_kg)
        else:
            currents, shortfall, _ = allocate_currents(A, commanded, self._current_limit_a)
            limited = False
        command.set_value(np.concatenate((commanded, rendered, currents, shortfall,
                                          [float(limited)])))
