"""6-DOF virtual coupling (Colgate, Stanley, Brown 1995) between instrument and tool.

A spring-damper joins the measured instrument pose X_WI to the simulated tool's
pose X_WT. Relaxed, the tool sits at X_WI * X_IT (X_IT a fixed offset, identity
by default). Conventions as in the levitation controller: pose vectors
[qw, qx, qy, qz, x, y, z] (m), spatial velocities [wx, wy, wz, vx, vy, vz] in W
(rad/s, m/s, v of the body's origin), wrenches [fx, fy, fz, tx, ty, tz] in W
(N, N*m).

The law (D is the instrument-fixed point where the tool's origin belongs,
p_WD = p_WI + R_WI p_IT; the error rotation R_E = R_WI^T R_WT R_IT^T is the
identity when relaxed; k, b are per-axis gains):

- force on the tool, in W axes, acting at the tool's origin:
  f_T = k_t * (p_WD - p_WT) + b_t * (v_WD - v_WT);
- couple on the tool, in the instrument's axes (so the gains follow the
  instrument's principal axes like the controller's):
  tau_T_I = -2 vee(skew(R_E G)) + b_r * (R_WI^T (w_WI - w_WT)), tau_T = R_WI tau_T_I,
  with G = diag(sum(k_r) / 2 - k_r). This is minus the gradient of the rotational
  potential tr(G (I - R_E)) = (1 - cos angle) u^T diag(k_r) u (angle, u of R_E,
  u in I axes): about each instrument axis it is exactly k_r_i sin(angle), so for
  equal gains it is k_r * rotation_error_W expressed in I; to first order it is
  -k_r * angle per axis. (k_r * sin(angle) * axis itself is not a gradient field
  when the gains differ, so it could not be passive.)
- the wrench on the instrument is the exact opposite of the tool's, moved from
  the tool's origin to the instrument's: f_I = -f_T,
  tau_I_about_Io = -tau_T - (p_WT - p_WI) x f_T. The pair has zero net force and
  zero net moment about any point (momentum is conserved). For the tool this
  wrench is minus the gradient of the potential
  U = 1/2 sum k_t (p_WD - p_WT)^2 + tr(G (I - R_E)); for the instrument it
  differs from that gradient by (p_WT - p_WD) x f_T, second order in the
  deflection and zero for equal translational gains.

The device renders the instrument's wrench: it is the feed-forward input of the
levitation controller (which adds the gravity compensation), so the user's hand
is pulled toward the tool, i.e. feels what holds the tool back.
"""

import dataclasses
from dataclasses import dataclass, field
from typing import List, Optional

import numba
import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform
from pydrake.systems.framework import Diagram, LeafSystem, ValueProducer

from maglev_haptics.hardware.config_checks import each, nonnegative, positive, require
from maglev_haptics.hardware.kernels import MATRIX, SCALAR, VECTOR, kernel
from maglev_haptics.hardware.limits import LIMIT_KINDS
from maglev_haptics.systems.rotations import rotation_from_quaternion
from maglev_haptics.systems.stacked_ports import BuildStacked, stacked_size, stacked_slices


@dataclass
class CouplingConfig:
    """Gains, start-up ramp and wrench limits of the virtual coupling.

    Stiffness 400 N/m is the paper's 0.4 N/mm; at 1 kHz its Colgate-Schenkel
    damping need K T / 2 = 0.2 N*s/m is small. Damping 5 N*s/m is what an
    instrument let go needs: the 125 g instrument on the spring against a held
    tool rings at 9 Hz, and the device adds no damping of its own, so the
    coupling gives it damping ratio 0.35 (the 20 g peg on the spring: 0.88).
    The damper acts on the instrument's measured velocity low-passed at
    ``velocity_filter_hz`` (first order, one tick per update): 30 Hz trims the
    estimator's ~1.7 mm/s velocity noise while lagging the 9 Hz mode by only
    17 deg. Rotational gains, when null, give each of the instrument's axes
    the same natural frequency and damping ratio as the translation: the
    instrument's principal inertia times k / m and b / m (for the 2-magnet
    instrument 0.025, 0.18, 0.19 N*m/rad). One rotational stiffness for all
    axes would make the turn about the magnet row (8e-6 kg*m^2) ring at 28 Hz,
    where the tracker's latency and the velocity filters turn the damper's
    phase around: an instrument let go then spins up. The diagram builder
    fills them in (``resolved_rotational_gains``). The wrench limits, when
    null, are
    what the coils can add on top of the weight at the pose where haptics
    starts, the smallest over the axis directions
    (``hardware.limits.device_limits``), with every coil within
    ``device_limit``: "peak" (the amplifiers' current limit: what the device
    can deliver at any instant; the paper's "higher momentary peak forces") or
    "thermal" (the coils' continuous current: what it can sustain
    indefinitely). The diagram builder fills them in.
    """

    # x, y, z in W
    translational_stiffness: List[float] = field(default_factory=lambda: [400.0] * 3)  # N/m
    translational_damping: List[float] = field(default_factory=lambda: [5.0] * 3)  # N*s/m
    # about the instrument's x, y, z axes
    rotational_stiffness: Optional[List[float]] = None  # N*m/rad; null: from the instrument
    rotational_damping: Optional[List[float]] = None  # N*m*s/rad; null: likewise
    velocity_filter_hz: float = 30.0  # corner of the low-pass on the measured V_WI (Hz)
    ramp_s: float = 0.5  # the user's wrench fades in linearly over this time after enable (s)
    max_force_n: Optional[float] = None  # |f| limit (N); null: from device_limit
    max_torque_nm: Optional[float] = None  # |tau| limit (N*m); null: likewise
    device_limit: str = "peak"  # "peak" or "thermal": the coil current the null limits assume
    # A time-domain passivity observer and controller at the device's port
    # (``passivity_step``): off by default, as the paper's device ran without it.
    passivity_controller: bool = False

    def validate(self, path: str = "coupling") -> None:
        """Range checks; a ValueError names ``path.field``, its value and what is allowed."""
        for name in ("translational_stiffness", "translational_damping"):
            each(f"{path}.{name}", getattr(self, name), 3, positive)
        for name in ("rotational_stiffness", "rotational_damping"):
            if getattr(self, name) is not None:
                each(f"{path}.{name}", getattr(self, name), 3, positive)
        positive(f"{path}.velocity_filter_hz", self.velocity_filter_hz)
        nonnegative(f"{path}.ramp_s", self.ramp_s)
        for name in ("max_force_n", "max_torque_nm"):
            if getattr(self, name) is not None:
                positive(f"{path}.{name}", getattr(self, name))
        require(self.device_limit in LIMIT_KINDS, f"{path}.device_limit", self.device_limit,
                f"must be one of {', '.join(LIMIT_KINDS)}")


def resolved_rotational_gains(config: CouplingConfig, mass_kg: float,
                              inertia_diag) -> CouplingConfig:
    """``config`` with null rotational gains set to the instrument's principal
    inertias ``inertia_diag`` (kg*m^2, about I's axes) times the translational
    gains per unit mass (``mass_kg``, kg): the same modal frequency and damping
    ratio about every axis as along x."""
    inertia = np.asarray(inertia_diag, dtype=float)
    stiffness = config.rotational_stiffness
    damping = config.rotational_damping
    if stiffness is None:
        stiffness = [float(v) for v in inertia * config.translational_stiffness[0] / mass_kg]
    if damping is None:
        damping = [float(v) for v in inertia * config.translational_damping[0] / mass_kg]
    return dataclasses.replace(config, rotational_stiffness=stiffness,
                               rotational_damping=damping)


def coupling_gains(config: CouplingConfig):
    """(k, b), each (6,): translational then rotational stiffness and damping."""
    k = np.array(config.translational_stiffness + config.rotational_stiffness, dtype=float)
    b = np.array(config.translational_damping + config.rotational_damping, dtype=float)
    return k, b


# The coupling's law runs at 1 kHz (and as the hand's arm and grip): compiled by numba.
@numba.njit(cache=True)
def coupling_wrenches(X_WI, V_WI, X_WT, V_WT, R_IT, p_IT, k, b):
    """(wrench on the tool about its origin, wrench on the instrument about its
    origin), each [f; tau] in W (N, N*m); see the module docstring for the law."""
    R_WI = rotation_from_quaternion(X_WI[0:4])
    R_WT = rotation_from_quaternion(X_WT[0:4])
    p_WI, p_WT = X_WI[4:7], X_WT[4:7]
    w_WI, v_WI = V_WI[0:3], V_WI[3:6]
    w_WT, v_WT = V_WT[0:3], V_WT[3:6]
    p_ID_W = R_WI @ p_IT
    v_WD = v_WI + np.cross(w_WI, p_ID_W)
    force = k[0:3] * (p_WI + p_ID_W - p_WT) + b[0:3] * (v_WD - v_WT)
    R_E = R_WI.T @ R_WT @ R_IT.T
    g = 0.5 * (k[3] + k[4] + k[5]) - k[3:6]
    spring_I = np.array([g[2] * R_E[1, 2] - g[1] * R_E[2, 1],
                         g[0] * R_E[2, 0] - g[2] * R_E[0, 2],
                         g[1] * R_E[0, 1] - g[0] * R_E[1, 0]])
    torque = R_WI @ (spring_I + b[3:6] * (R_WI.T @ (w_WI - w_WT)))
    on_tool = np.concatenate((force, torque))
    on_instrument = np.concatenate((-force, -torque - np.cross(p_WT - p_WI, force)))
    return on_tool, on_instrument


@numba.njit(cache=True)
def spring_potential(X_WI, X_WT, R_IT, p_IT, k):
    """Energy (J) stored in the coupling's springs; the spring wrenches derive from it."""
    R_WI = rotation_from_quaternion(X_WI[0:4])
    R_WT = rotation_from_quaternion(X_WT[0:4])
    d = X_WI[4:7] + R_WI @ p_IT - X_WT[4:7]
    R_E = R_WI.T @ R_WT @ R_IT.T
    g = 0.5 * (k[3] + k[4] + k[5]) - k[3:6]
    return 0.5 * (k[0:3] @ (d * d)) + g @ (1.0 - np.array([R_E[0, 0], R_E[1, 1], R_E[2, 2]]))


@numba.njit(cache=True)
def clamp_scale(wrench, max_force_n, max_torque_nm):
    """Factor in (0, 1] that scales the whole wrench to within both limits (N, N*m),
    preserving its direction; 1 when it is within them."""
    f2 = wrench[0:3] @ wrench[0:3]
    t2 = wrench[3:6] @ wrench[3:6]
    scale = 1.0
    if f2 > max_force_n * max_force_n:
        scale = max_force_n / np.sqrt(f2)
    if t2 > max_torque_nm * max_torque_nm:
        scale_t = max_torque_nm / np.sqrt(t2)
        if scale_t < scale:
            scale = scale_t
    return scale


@kernel((VECTOR, VECTOR, VECTOR, VECTOR, MATRIX, VECTOR, VECTOR, VECTOR, SCALAR, SCALAR, SCALAR))
def limited_wrenches(X_WI, V_WI, X_WT, V_WT, R_IT, p_IT, k, b, fraction, max_force_n,
                     max_torque_nm):
    """``coupling_wrenches`` both scaled by the one factor that brings the
    instrument's wrench within the limits (N, N*m), so the tool is never driven
    harder than the device could render; the instrument's then times the ramp
    ``fraction`` (0..1). Returns (on tool, on instrument, factor)."""
    on_tool, on_instrument = coupling_wrenches(X_WI, V_WI, X_WT, V_WT, R_IT, p_IT, k, b)
    scale = clamp_scale(on_instrument, max_force_n, max_torque_nm)
    return scale * on_tool, fraction * scale * on_instrument, scale


@kernel((VECTOR, VECTOR, VECTOR, MATRIX, SCALAR, VECTOR))
def passivity_step(wrench, V_WI, energy_j, sent, period_s, reference_energy_j):
    """One sample of a time-domain passivity observer and controller (after Hannaford
    and Ryu 2002) at the device's port, per axis, with the loop's delay accounted for.

    ``wrench`` [f; tau] in W (N, N*m) is what the coupling asks the device to apply
    to the instrument, ``V_WI`` [w; v] the instrument's measured velocity (rad/s,
    m/s). A wrench sent now acts a sample later and the velocity is measured late by
    the tracker's latency and the estimator's filter, so the observer pairs this
    sample's velocity with the wrench sent ``d`` samples ago: ``sent`` (d, 6) holds
    the last d sent, oldest first. ``energy_j`` (6) is what the user has put into the
    coupling and the virtual world on each axis (J): the observer adds
    ``-sent_j v_j T``. Where it is negative the virtual side has given out energy it
    never received. H&R's controller would then add damping on the velocity; through
    this loop's ~7 ms from motion to measured velocity to force, damping at the ~40 Hz
    an overstiff coupling rings at arrives a quarter period late and feeds the
    oscillation instead. So this controller takes the energy source away: it scales
    the axis' wrench by 1 / (1 + debt / ``reference_energy_j``), less the deeper the
    debt, until the user's own work has paid it back. Returns (wrench to send,
    energy, sent (shifted), the work withheld this sample (J), |change| |v| T).
    """
    out = wrench.copy()
    energy = energy_j.copy()
    d = sent.shape[0]
    withheld = 0.0
    for j in range(6):
        v = V_WI[j + 3] if j < 3 else V_WI[j - 3]  # the velocity wrench j does work on
        energy[j] -= sent[0, j] * v * period_s
        if energy[j] < 0.0:
            out[j] = wrench[j] / (1.0 + (-energy[j]) / reference_energy_j[j])
            withheld += abs(wrench[j] - out[j]) * abs(v) * period_s
    new_sent = np.empty_like(sent)
    new_sent[0:d - 1] = sent[1:d]
    new_sent[d - 1] = out
    return out, energy, new_sent, withheld


def velocity_filter_gain(corner_hz: float, period_s: float) -> float:
    """alpha in v_f <- v_f + alpha (v - v_f): exact sampling of a first-order
    low-pass with corner ``corner_hz`` (Hz) at ``period_s`` (s)."""
    return float(1.0 - np.exp(-2.0 * np.pi * corner_hz * period_s))


def ramp_step(fraction: float, enable: float, period_s: float, ramp_s: float) -> float:
    """The ramp fraction (0..1) after one period (s): grows by period / ramp_s while
    enabled, resets to 0 when disabled so the next enable ramps again."""
    if enable < 0.5:
        return 0.0
    if ramp_s <= 0.0:
        return 1.0
    return min(fraction + period_s / ramp_s, 1.0)


# The coupling's input ports (name, size), in the order of the law's one input.
COUPLING_INPUTS = (("X_WI_measured", 7), ("V_WI_measured", 6), ("X_WT", 7), ("V_WT", 6),
                   ("haptics_enable", 1))
# Its output ports that the law computes (name, size), in the order of the law's one output.
COUPLING_OUTPUTS = (("wrench_on_tool_W", 6), ("wrench_feedforward_W", 6),
                    ("coupling_clamped", 1))


class CouplingLaw(LeafSystem):
    """``HapticCoupling``'s arithmetic and state: one input, ``inputs``
    (COUPLING_INPUTS stacked), one output, ``wrenches`` (COUPLING_OUTPUTS stacked),
    and the state output ``passivity_dissipated_j``.

    .. pydrake_system::

        name: CouplingLaw
        input_ports:
        - inputs
        output_ports:
        - wrenches
        - passivity_dissipated_j
    """

    def __init__(self, *, config: CouplingConfig, period_s: float, X_IT: RigidTransform,
                 port_delay_ticks: int):
        LeafSystem.__init__(self)
        for name in ("max_force_n", "max_torque_nm", "rotational_stiffness",
                     "rotational_damping"):
            if getattr(config, name) is None:
                raise ValueError(f"CouplingConfig.{name} is None: give a value, or let "
                                 "the diagram builder derive it from the device")
        self._config = config
        self._period_s = float(period_s)
        # Writable C-ordered copies: the argument types the kernel is compiled for.
        self._R_IT = np.array(X_IT.rotation().matrix(), order="C")
        self._p_IT = np.array(X_IT.translation())
        self._k, self._b = coupling_gains(config)
        self._inputs = self.DeclareVectorInputPort("inputs", stacked_size(COUPLING_INPUTS))
        self._rows = stacked_slices(COUPLING_INPUTS)
        self._ramp = self.DeclareDiscreteState(1)
        self._V_WI_filtered = self.DeclareDiscreteState(6)
        if port_delay_ticks < 1:
            raise ValueError(f"port_delay_ticks = {port_delay_ticks}: must be >= 1")
        self._port_delay_ticks = int(port_delay_ticks)
        self._energy = self.DeclareDiscreteState(6)
        self._sent = self.DeclareDiscreteState(6 * port_delay_ticks)
        self._dissipated = self.DeclareDiscreteState(1)
        # The energy a debt is measured against: the coupling's spring at the wrench limit;
        # an axis without a spring has none to measure against, and is not scaled.
        limit_squared = np.concatenate((np.full(3, config.max_force_n) ** 2,
                                        np.full(3, config.max_torque_nm) ** 2))
        self._reference_energy_j = np.divide(limit_squared, 2 * self._k,
                                             out=np.full(6, np.inf), where=self._k > 0)
        self._alpha = velocity_filter_gain(config.velocity_filter_hz, period_s)
        self.DeclarePeriodicDiscreteUpdateEvent(period_s, 0.0, self._update)
        # The output and the update (with the passivity controller) read it: compute once.
        self._cache = self.DeclareCacheEntry(
            description="limited wrenches",
            value_producer=ValueProducer(allocate=AbstractValue.Make(()).Clone,
                                         calc=self._calc_cache),
            prerequisites_of_calc={self._inputs.ticket(), self.xd_ticket()})
        self.DeclareVectorOutputPort("wrenches", stacked_size(COUPLING_OUTPUTS),
                                     self._calc_wrenches, {self._cache.ticket()})
        self.DeclareStateOutputPort("passivity_dissipated_j", self._dissipated)

    def _update(self, context, discrete_state):
        inputs, rows = self._inputs.EvalBasicVector(context).value(), self._rows
        fraction = ramp_step(context.get_discrete_state(self._ramp).GetAtIndex(0),
                             inputs[rows["haptics_enable"]][0], self._period_s,
                             self._config.ramp_s)
        discrete_state.get_mutable_vector(self._ramp).SetAtIndex(0, fraction)
        filtered = context.get_discrete_state(self._V_WI_filtered).value()  # read only
        filtered = filtered + self._alpha * (inputs[rows["V_WI_measured"]] - filtered)
        discrete_state.get_mutable_vector(self._V_WI_filtered).SetFromVector(filtered)
        if self._config.passivity_controller:
            _, _, _, (energy, sent, dissipated) = self._cache.Eval(context)
            discrete_state.get_mutable_vector(self._energy).SetFromVector(energy)
            discrete_state.get_mutable_vector(self._sent).SetFromVector(sent.ravel())
            discrete_state.get_mutable_vector(self._dissipated).SetAtIndex(
                0, context.get_discrete_state(self._dissipated).GetAtIndex(0) + dissipated)

    def _calc_cache(self, context, value):
        """(wrench on tool, wrench on instrument, clamp factor, the passivity observer's
        state after this sample and what its controller dissipated in it, or None) after
        ramp and clamp, with the passivity controller's damping on the instrument's."""
        inputs, rows = self._inputs.EvalBasicVector(context).value(), self._rows
        fraction = context.get_discrete_state(self._ramp).GetAtIndex(0)
        if inputs[rows["haptics_enable"]][0] < 0.5:
            fraction = 0.0
        on_tool, on_instrument, scale = limited_wrenches(
            inputs[rows["X_WI_measured"]],
            context.get_discrete_state(self._V_WI_filtered).value(),
            inputs[rows["X_WT"]], inputs[rows["V_WT"]], self._R_IT, self._p_IT, self._k, self._b,
            fraction, self._config.max_force_n, self._config.max_torque_nm)
        observer = None
        if self._config.passivity_controller:
            state = context.get_discrete_state()
            on_instrument, *observer = passivity_step(
                on_instrument, inputs[rows["V_WI_measured"]].copy(),
                state.get_vector(self._energy).CopyToVector(),
                state.get_vector(self._sent).CopyToVector().reshape(self._port_delay_ticks, 6),
                self._period_s, self._reference_energy_j)
        value.set_value((on_tool, on_instrument, scale, observer))

    def _calc_wrenches(self, context, output):
        on_tool, on_instrument, scale, _ = self._cache.Eval(context)
        out = output.get_mutable_value()
        out[0:6] = on_tool
        out[6:12] = on_instrument
        out[12] = 1.0 if scale < 1.0 else 0.0


class HapticCoupling(Diagram):
    """Virtual coupling between the measured instrument and the scene's tool,
    with a safe force ramp at haptics start and a direction-preserving clamp.

    .. pydrake_system::

        name: HapticCoupling
        input_ports:
        - X_WI_measured
        - V_WI_measured
        - X_WT
        - V_WT
        - haptics_enable
        output_ports:
        - wrench_on_tool_W
        - wrench_feedforward_W
        - coupling_clamped
        - passivity_dissipated_j

    ``wrench_on_tool_W`` drives the tool (about its origin): the tool
    always follows the instrument, so the virtual tool is where the hand
    is whether or not haptics is on. ``wrench_feedforward_W`` is its
    opposite on the instrument (about the instrument's origin), for the
    levitation controller's feed-forward input, times the ramp fraction:
    what the user feels. Both are scaled by one factor so the instrument's
    full wrench is within the limits (the tool is never driven harder than
    the device could render); ``coupling_clamped`` is 1 when that factor
    is below 1. The discrete state (updated every period_s) is the ramp
    fraction 0..1, which grows by period / ramp_s each period while
    ``haptics_enable`` > 0.5 and resets to 0 otherwise (so the user feels
    nothing while disabled), the low-passed V_WI_measured the damper
    uses, and the passivity observer's: its energy per axis (J), the last
    ``port_delay_ticks`` wrenches sent (6 per tick, oldest first), and the
    work its controller has withheld in all (J, the
    ``passivity_dissipated_j`` output). ``port_delay_ticks``: the samples
    from a wrench sent to its effect in the measured velocity (the tracker's
    latency and period, the estimator's filter, the amplifiers' tick and
    lag; ``diagrams/haptics.py`` derives it). With
    ``passivity_controller`` the feed-forward is scaled on the axes in
    energy debt (``passivity_step``, which observes this sample's measured
    velocity). Stacked, every input feeds every output through (``V_WI_measured``
    is the estimator's state: no loop).

    A diagram of three blocks (``systems/stacked_ports.py``): the inputs stacked for
    ``CouplingLaw`` ("law"), which computes both wrenches once a tick, and its result
    split into the named outputs; the discrete state is the law's.
    """

    def __init__(self, *, config: CouplingConfig, period_s: float,
                 X_IT: RigidTransform = RigidTransform(), port_delay_ticks: int = 1):
        Diagram.__init__(self)
        BuildStacked(self, leaf=CouplingLaw(config=config, period_s=period_s, X_IT=X_IT,
                                            port_delay_ticks=port_delay_ticks),
                     leaf_name="law", inputs=COUPLING_INPUTS, outputs=COUPLING_OUTPUTS,
                     leaf_outputs=("passivity_dissipated_j",))
