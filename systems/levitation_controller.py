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
from typing import List, Optional, Tuple

import numba
import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import BasicVector, Diagram, LeafSystem, ValueProducer

from maglev_haptics.hardware.config_checks import each, nonnegative, positive, require
from maglev_haptics.hardware.constants import GRAVITY_M_S2
from maglev_haptics.hardware.kernels import (
    FLAG, FLOAT32_TENSOR4, FLOAT32_VECTOR, INDEX_VECTOR, MATRIX, SCALAR, VECTOR, kernel)
from maglev_haptics.hardware.thermal import (
    CoilThermal, current_bounds_a, thermal_budget, winding_resistance_ohm)
from maglev_haptics.hardware.wrench_kernel import POSE_OK
from maglev_haptics.systems.current_allocator import (
    ALLOCATIONS, TORQUE_WEIGHT_PER_M, allocate_currents, bounded_minimum_power_currents)
from maglev_haptics.systems.magnetic_actuation import raise_pose_error, wrench_matrix_at_pose
from maglev_haptics.systems.rotations import (
    angular_velocity_from_rpy_rates, rotation_error_W, rotation_from_quaternion, rotation_from_rpy)
from maglev_haptics.systems.stacked_ports import BuildStacked, stacked_size, stacked_slices


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


# The wrench laws, compiled into the tick's one call (``control_law``).
@numba.njit(cache=True)
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


@numba.njit(cache=True)
def carries_weight_while_lost(lost_time_s: float, lost_grace_s: float) -> bool:
    """Whether the weight is still carried after tracking has been lost this long (s).

    A levitated magnet is unstable without feedback (Earnshaw): any lift held on
    a stale pose rolls the instrument over within a few hundred ms. So the lift
    is carried only through short dropouts (``lost_grace_s``); after that the coils
    go dead and the instrument, under gravity alone, drops level onto the glass.
    """
    return lost_time_s <= lost_grace_s


@numba.njit(cache=True)
def commanded_wrenches(setpoint, pose, velocity, tracking_ok: float, enable: float,
                       pd_gain: float, brake_gain: float, feedforward, lost_time_s: float,
                       kp, kd, mass_kg: float, lost_grace_s: float):
    """(commanded, rendered): the wrench [f; tau] in W (N, N*m) asked of the coils, and
    the part of it that acts on the hand (the commanded less the weight it carries).

    ``enable * (pd_gain * PD + brake_gain * D + weight) + feedforward`` while
    tracking is good; the weight alone (within the grace), then nothing, once
    tracking has been lost for ``lost_time_s``.
    """
    weight = np.zeros(6)
    if carries_weight_while_lost(lost_time_s, lost_grace_s):
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


@kernel((VECTOR, VECTOR, VECTOR, SCALAR, SCALAR))
def is_thermally_limited(currents, bound_a, shortfall, current_limit_a: float,
                         mass_kg: float) -> bool:
    """Whether the wrench falls short by more than THERMAL_SHORTFALL_OF_WEIGHT of the
    weight while some coil sits at a thermal bound below the amplifiers' limit (A): the
    coils are too warm to carry what is asked."""
    if np.linalg.norm(shortfall) <= THERMAL_SHORTFALL_OF_WEIGHT * mass_kg * GRAVITY_M_S2:
        return False
    at_bound = np.abs(currents) >= bound_a * (1 - 1e-9)
    return np.any(at_bound & (bound_a < current_limit_a))


# The controller's input ports (name, size) in the order of the law's one input (the
# coils' temperatures are the law's own port: they change at the thermal model's rate).
def controller_inputs(n_coils: int) -> Tuple[Tuple[str, int], ...]:
    return (("setpoint", 12), ("X_WI_measured", 7), ("V_WI_measured", 6), ("tracking_ok", 1),
            ("enable", 1), ("pd_gain", 1), ("brake_gain", 1), ("wrench_feedforward_W", 6),
            ("tracking_lost_s", 1), ("coil_currents", n_coils), ("coils_stuck", n_coils))


def controller_outputs(n_coils: int) -> Tuple[Tuple[str, int], ...]:
    """The controller's output ports (name, size), in the order of the law's one output."""
    return (("wrench_commanded_W", 6), ("wrench_rendered_W", 6),
            ("coil_currents_commanded", n_coils), ("allocation_shortfall_W", 6),
            ("thermally_limited", 1))


# ``pose_seen`` (flag, then the 7 of the pose) memoizes the wrench matrix ``A``: it
# changes at the tracker's rate, the command every tick.
@kernel((VECTOR, INDEX_VECTOR, VECTOR, VECTOR, SCALAR, SCALAR, VECTOR,
         FLOAT32_TENSOR4, MATRIX, MATRIX, MATRIX, VECTOR, VECTOR, FLOAT32_VECTOR, VECTOR, MATRIX,
         FLAG, VECTOR, SCALAR, SCALAR, VECTOR))
def control_law(inputs, starts, kp, kd, mass_kg, lost_grace_s, p_WA,
                values, axes, p_ACj, p_IM, magnet_scales, coil_scales, scratch, pose_seen, A,
                thermal_allocation, limits, current_limit_a, torque_weight, out):
    """One tick of the controller: ``inputs`` (``controller_inputs`` stacked, each port
    from its entry of ``starts``) to ``out`` (``controller_outputs`` stacked), with the
    coils' ``limits`` [resistances (ohm); thermal bounds (A)]. Returns the wrench
    matrix's pose status (``POSE_OK``: done). With ``thermal_allocation`` False only
    the wrenches are written (the pseudoinverse allocation, for comparison, is Python's)."""
    n = A.shape[1]
    setpoint, pose, velocity = (inputs[starts[0]:starts[0] + 12].copy(),
                                inputs[starts[1]:starts[1] + 7].copy(),
                                inputs[starts[2]:starts[2] + 6].copy())
    if pose_seen[0] != 1.0 or np.any(pose_seen[1:] != pose):
        status, matrix = wrench_matrix_at_pose(pose, p_WA, values, axes, p_ACj, p_IM,
                                               magnet_scales, coil_scales, scratch)
        if status != POSE_OK:
            pose_seen[0] = 0.0
            return status
        A[:, :] = matrix
        pose_seen[0] = 1.0
        pose_seen[1:] = pose
    commanded, rendered = commanded_wrenches(
        setpoint, pose, velocity, inputs[starts[3]], inputs[starts[4]], inputs[starts[5]],
        inputs[starts[6]], inputs[starts[7]:starts[7] + 6].copy(), inputs[starts[8]], kp, kd,
        mass_kg, lost_grace_s)
    out[0:6] = commanded
    out[6:12] = rendered
    if not thermal_allocation:
        return POSE_OK
    resistance, bounds = limits[:n].copy(), limits[n:].copy()
    wanted, allowed = commanded, bounds
    stuck = inputs[starts[10]:starts[10] + n] > 0.5
    if np.any(stuck):  # the stuck coils' wrench is a given; they get nothing
        measured = inputs[starts[9]:starts[9] + n].copy()
        wanted = commanded - A[:, stuck] @ measured[stuck]
        allowed = np.where(stuck, 0.0, bounds)
    currents, shortfall = bounded_minimum_power_currents(A, wanted, resistance, allowed,
                                                         torque_weight)
    out[12:12 + n] = currents
    out[12 + n:18 + n] = shortfall
    out[18 + n] = 1.0 if is_thermally_limited(currents, bounds, shortfall, current_limit_a,
                                              mass_kg) else 0.0
    return POSE_OK


class LevitationLaw(LeafSystem):
    """The controller's arithmetic, one compiled call a tick (``control_law``): one
    input, ``inputs`` (``controller_inputs`` stacked), the coils' temperatures
    ``coil_temperature_c`` (deg C) apart, and one output, ``command``
    (``controller_outputs`` stacked). ``LevitationController`` wraps it with named
    ports. The PD gains ``kp`` and ``kd`` (6 each) are numeric parameters 0 and 1.

    .. pydrake_system::

        name: LevitationLaw
        input_ports:
        - inputs
        - coil_temperature_c
        output_ports:
        - command
    """

    def __init__(self, *, config: ControllerConfig, mass_kg: float, inertia_diag,
                 magnetics, p_WA, current_limit_a: float, thermal: CoilThermal):
        LeafSystem.__init__(self)
        n = magnetics.n_coils
        self._config = config
        self._mass_kg = float(mass_kg)
        kp, kd = pd_gains(config, mass_kg, np.asarray(inertia_diag, dtype=float))
        # Parameters, not constants: the device API sets them between ticks.
        self.kp_index = self.DeclareNumericParameter(BasicVector(kp))
        self.kd_index = self.DeclareNumericParameter(BasicVector(kd))
        self._magnetics = magnetics
        self._p_WA = np.asarray(p_WA, dtype=float)
        self._current_limit_a = float(current_limit_a)
        self._thermal = thermal
        self._budget = thermal_budget(thermal, horizon_s=config.thermal_horizon_s,
                                      margin_c=config.thermal_margin_c,
                                      current_limit_a=current_limit_a)
        ports = controller_inputs(n)
        self._starts = np.array([rows.start for rows in stacked_slices(ports).values()])
        # A memo of a pure function of the pose (exact match or recomputed), so any
        # context, cloned or nudged by the analysis, gets the same numbers.
        self._pose_seen = np.zeros(8)
        self._matrix = np.zeros((6, n))
        self._inputs = self.DeclareVectorInputPort("inputs", stacked_size(ports))
        self._temperature = self.DeclareVectorInputPort("coil_temperature_c", n)
        # [resistances (ohm); bounds (A)]: they change at the thermal model's rate.
        self._coil_limits = self.DeclareCacheEntry(
            "coil_limits",
            ValueProducer(allocate=lambda: AbstractValue.Make(np.zeros(2 * n)),
                          calc=self._calc_coil_limits),
            {self._temperature.ticket()})
        self.DeclareVectorOutputPort("command", stacked_size(controller_outputs(n)),
                                     self._calc_command)

    def _calc_coil_limits(self, context, limits):
        temperature_c = self._temperature.Eval(context)
        limits.set_value(np.concatenate((winding_resistance_ohm(self._thermal, temperature_c),
                                         current_bounds_a(self._budget, temperature_c))))

    def _calc_command(self, context, output):
        inputs = self._inputs.EvalBasicVector(context).value()
        out = output.get_mutable_value()
        thermal = self._config.allocation == "thermal"
        status = control_law(
            inputs, self._starts, context.get_numeric_parameter(self.kp_index).value(),
            context.get_numeric_parameter(self.kd_index).value(), self._mass_kg,
            self._config.lost_grace_s, self._p_WA, *self._magnetics.kernel_arguments(),
            self._pose_seen, self._matrix, thermal, self._coil_limits.Eval(context),
            self._current_limit_a, TORQUE_WEIGHT_PER_M, out)
        if status != POSE_OK:
            raise_pose_error(self._magnetics, self._p_WA,
                             inputs[self._starts[1]:self._starts[1] + 7])
        if not thermal:
            currents, shortfall, _ = allocate_currents(self._matrix, out[0:6].copy(),
                                                       self._current_limit_a)
            n = currents.size
            out[12:12 + n] = currents
            out[12 + n:18 + n] = shortfall
            out[18 + n] = 0.0


class LevitationController(Diagram):
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
    Direct feedthrough: the amplifiers sample the currents at the control rate, so
    they always use the newest estimate.

    A diagram of three blocks (``systems/stacked_ports.py``), so that a tick pays for
    one Python call: the ports stacked for ``LevitationLaw`` ("law"), whose one
    compiled call computes the wrench law and the allocation, and its result split
    into the named outputs.

    ``tracking_lost_s`` is how long tracking has been lost (s; 0 while tracking),
    latched once past ``lost_grace_s``: the device supervisor counts it
    (``systems/device_supervisor.py``), which also raises the fault. No state: the PD
    gains (``set_gains``, ``gains``) are the law's numeric parameters.
    """

    def __init__(self, *, config: ControllerConfig, mass_kg: float, inertia_diag,
                 magnetics, p_WA, current_limit_a: float, thermal: CoilThermal):
        Diagram.__init__(self)
        self._law = LevitationLaw(
            config=config, mass_kg=mass_kg, inertia_diag=inertia_diag, magnetics=magnetics,
            p_WA=p_WA, current_limit_a=current_limit_a, thermal=thermal)
        BuildStacked(self, leaf=self._law, leaf_name="law",
                     inputs=controller_inputs(magnetics.n_coils),
                     outputs=controller_outputs(magnetics.n_coils),
                     leaf_inputs=("coil_temperature_c",))

    def set_gains(self, context, kp=None, kd=None) -> None:
        """Per-axis gains in the controller's ``context`` (N/m, N*m/rad; N*s/m,
        N*m*s/rad; the axes of ``ControllerConfig``), from the next evaluation on;
        None keeps one."""
        law_context = self.GetMutableSubsystemContext(self._law, context)
        for index, gains, name in ((self._law.kp_index, kp, "kp"),
                                   (self._law.kd_index, kd, "kd")):
            if gains is None:
                continue
            gains = np.asarray(gains, dtype=float)
            if gains.shape != (6,) or not np.all(np.isfinite(gains)) or np.any(gains < 0):
                raise ValueError(f"{name} = {gains.tolist()}: must be 6 finite gains >= 0")
            law_context.get_mutable_numeric_parameter(index).SetFromVector(gains)

    def gains(self, context):
        """(kp, kd) in the controller's ``context``."""
        law_context = self.GetSubsystemContext(self._law, context)
        return (law_context.get_numeric_parameter(self._law.kp_index).CopyToVector(),
                law_context.get_numeric_parameter(self._law.kd_index).CopyToVector())
