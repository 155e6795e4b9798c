"""The simulated user's hand: an arm impedance that follows a target, and a grip.

The hand is a free rigid body H in the station's plant (``plant_models/hand.sdf``,
frame H at the grip point). Its arm pulls it toward a target pose D with a 6-DOF
spring-damper and carries its weight, so an empty hand hovers at its target.
While gripped, a stiff 6-DOF spring-damper (skin and fingers) joins the hand to
the instrument I at the relative pose X_HI latched at the moment of gripping, so
gripping never jerks the instrument. Conventions as in the loop's systems:
pose vectors [qw, qx, qy, qz, x, y, z] (m), spatial velocities
[wx, wy, wz, vx, vy, vz] in W (rad/s, m/s, v of the body's origin), wrenches
[fx, fy, fz, tx, ty, tz] in W (N, N*m); the target is [x, y, z, roll, pitch,
yaw] of H in W and their rates (m, rad, m/s, rad/s), Drake's extrinsic X-Y-Z
roll-pitch-yaw like the levitation controller's setpoint.

Both springs are the virtual coupling's law (``haptic_coupling.coupling_wrenches``):
- the arm: the target D is the coupling's reference body and the hand its
  "tool", so the force k_t (p_WD - p_WH) + b_t (v_WD - v_WH) acts at the
  hand's origin and the couple is minus the gradient of tr(G (I - R_D^T R_H)),
  with the rotational gains about D's axes (the hand's own axes when it is on
  target; the two differ only to second order in the error). The arm's wrench
  is then exactly minus the gradient of a potential, plus damping: passive.
  The hand's weight m g is carried at its origin (its centre of mass).
- the grip: the hand is the reference body and the instrument its "tool",
  relaxed at X_WI = X_WH X_HI, gains in the hand's axes. The pair of wrenches
  (on the instrument about I's origin, on the hand about H's origin) has zero
  net force and zero net moment.

The forces are explicit: the plant (semi-implicit Euler, v+ = v + h f(q, v) / m,
q+ = q + h v+) steps them from the state at the start of its step. A
spring-damper k, b on a mass m is then stable iff k h^2 / m + 2 b h / m < 4;
``explicit_step_spectral_radius`` checks the hand-instrument chain axis by axis.
"""

from dataclasses import dataclass, field
from typing import List

import numba
import numpy as np
from pydrake.multibody.tree import SpatialInertia
from pydrake.systems.framework import Diagram, LeafSystem

from maglev_haptics.hardware.config_checks import finite, positive, require
from maglev_haptics.hardware.constants import GRAVITY_M_S2
from maglev_haptics.hardware.kernels import READONLY_VECTOR, SCALAR, VECTOR, kernel
from maglev_haptics.systems.haptic_coupling import coupling_wrenches
from maglev_haptics.systems.rotations import (
    angular_velocity_from_rpy_rates, drake_relative_pose, quaternion_from_rotation_matrix,
    rotation_from_quaternion, rotation_from_rpy)
from maglev_haptics.systems.stacked_ports import BuildStacked, stacked_size, stacked_slices

HAND_MODEL_URL = "package://maglev_haptics/hand.sdf"
HAND_BODY_NAME = "hand"
# Semi-axes (m) of the hand's solid ellipsoid, along H's x, y, z (as in hand.sdf).
HAND_SEMI_AXES_M = (0.020, 0.040, 0.015)
IDENTITY_POSE = np.array([1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])  # [qw, qx, qy, qz, x, y, z]


@dataclass
class HandImpedanceConfig:
    """The hand's mass and the impedances of its arm and grip.

    The arm: a relaxed human arm holding a stylus has an endpoint stiffness of a
    few hundred N/m (Mussa-Ivaldi, Hogan, Bizzi 1985, planar posture; van Beek
    et al. 2015, Sci. Rep. 5:18004, a 3-D fit of 0.55 kg, 6.5 N*s/m, 135 N/m)
    and damping of 5-10 N*s/m: 300 N/m and 8 N*s/m, damping ratio 0.46 on the
    empty 0.25 kg hand (5.5 Hz), 0.38 holding the 125 g instrument. A 1 N push
    moves the hand 3.3 mm. The wrist's rotational stiffness is of the order of
    1 N*m/rad and its damping a few 0.01 N*m*s/rad (Charles and Hogan 2011,
    J. Biomech. 44:614): 1 N*m/rad and 0.02 N*m*s/rad.

    The mass: the effective mass of a hand in a precision (pen) grip, far below
    the whole arm's ~0.5-2 kg endpoint mass: 0.25 kg. Its inertia is that of the
    drawn ellipsoid (``HAND_SEMI_AXES_M``).

    The grip: finger pads are of the order of 1 N/mm stiff at light grip
    forces, and grasp stiffness rises with grip force (Van Doren 1998, Motor
    Control 2:352); two or three pads in parallel: 2000 N/m, so the 125 g
    instrument's weight, if the hand alone carried it, would sag 0.6 mm in the
    grip. 12 N*s/m damps the hand-instrument mode (reduced mass 83 g, 25 Hz; 58 g
    and 30 Hz for the 75 g instrument) at ratio 0.46-0.56. The rotational grip,
    0.5 N*m/rad (1 N*mm twists it 2 mrad) and 3e-3 N*m*s/rad, puts the lightest
    relative mode (the 2-magnet instrument's x axis, 7.2e-6 kg*m^2 reduced) at
    42 Hz, damping ratio 0.79 (0.35 about z).

    Explicit stability at the plant's 1 ms step (k h^2 / m + 2 b h / m < 4 per
    mode): 0.035 + 0.42 for the translational grip (75 g instrument), 0.07 +
    0.84 for the rotational grip (the 2-magnet instrument's x axis) and, the
    largest, 0.03 + 1.28 for the arm's rotational damping on the empty hand's
    light y axis (3.1e-5 kg*m^2, overdamped at ratio 1.8); the whole chain stays
    stable up to a 2 ms step (``explicit_step_spectral_radius``).
    """

    mass_kg: float = 0.25  # the hand body's mass (kg); must match hand.sdf's
    # The arm, toward the target: translation along W's x, y, z ...
    arm_translational_stiffness: List[float] = field(default_factory=lambda: [300.0] * 3)  # N/m
    arm_translational_damping: List[float] = field(default_factory=lambda: [8.0] * 3)  # N*s/m
    # ... rotation about the target's x, y, z axes.
    arm_rotational_stiffness: List[float] = field(default_factory=lambda: [1.0] * 3)  # N*m/rad
    arm_rotational_damping: List[float] = field(default_factory=lambda: [0.02] * 3)  # N*m*s/rad
    # The grip, instrument toward its latched pose in the hand, along and about H's axes.
    grip_translational_stiffness: List[float] = field(default_factory=lambda: [2000.0] * 3)  # N/m
    grip_translational_damping: List[float] = field(default_factory=lambda: [12.0] * 3)  # N*s/m
    grip_rotational_stiffness: List[float] = field(default_factory=lambda: [0.5] * 3)  # N*m/rad
    grip_rotational_damping: List[float] = field(default_factory=lambda: [3e-3] * 3)  # N*m*s/rad

    def validate(self, path: str = "impedance") -> None:
        """Range checks; a ValueError names ``path.field``, its value and what is allowed."""
        positive(f"{path}.mass_kg", self.mass_kg)
        for name in ("arm_translational_stiffness", "arm_translational_damping",
                     "arm_rotational_stiffness", "arm_rotational_damping",
                     "grip_translational_stiffness", "grip_translational_damping",
                     "grip_rotational_stiffness", "grip_rotational_damping"):
            value = getattr(self, name)
            require(isinstance(value, list) and len(value) == 3
                    and all(finite(v) and v >= 0 for v in value), f"{path}.{name}", value,
                    "must be 3 finite numbers >= 0 (x, y, z)")


def impedance_gains(config: HandImpedanceConfig):
    """(k_arm, b_arm, k_grip, b_grip), each (6,): translational then rotational."""
    return (np.array(config.arm_translational_stiffness + config.arm_rotational_stiffness, float),
            np.array(config.arm_translational_damping + config.arm_rotational_damping, float),
            np.array(config.grip_translational_stiffness + config.grip_rotational_stiffness, float),
            np.array(config.grip_translational_damping + config.grip_rotational_damping, float))


def hand_spatial_inertia(mass_kg: float) -> SpatialInertia:
    """The hand's spatial inertia about H's origin: the solid ellipsoid, centred there."""
    return SpatialInertia.SolidEllipsoidWithMass(mass_kg, *HAND_SEMI_AXES_M)


# The arm and the grip act every plant step (1 kHz): compiled by numba.
@numba.njit(cache=True)
def arm_wrench(X_WH, V_WH, target, k, b, mass_kg):
    """Wrench [f; tau] in W (N, N*m) of the arm on the hand, about H's origin: the
    spring-damper toward ``target`` (12) plus the hand's weight carried."""
    rpy = target[3:6]
    X_WD = np.concatenate((quaternion_from_rotation_matrix(rotation_from_rpy(rpy)), target[0:3]))
    V_WD = np.concatenate((angular_velocity_from_rpy_rates(rpy, target[9:12]), target[6:9]))
    on_hand, _ = coupling_wrenches(X_WD, V_WD, X_WH, V_WH, np.eye(3), np.zeros(3), k, b)
    on_hand[2] += mass_kg * GRAVITY_M_S2
    return on_hand


@numba.njit(cache=True)
def grip_wrenches(X_WH, V_WH, X_WI, V_WI, X_HI, k, b):
    """(wrench on the hand about H's origin, wrench on the instrument about I's
    origin), each [f; tau] in W (N, N*m), of the grip relaxed at ``X_HI`` (7)."""
    on_instrument, on_hand = coupling_wrenches(
        X_WH, V_WH, X_WI, V_WI, rotation_from_quaternion(X_HI[0:4]), X_HI[4:7], k, b)
    return on_hand, on_instrument


@numba.njit(cache=True)
def hand_wrenches(hand_state, instrument_state, target, gripped, X_HI, k_arm, b_arm, k_grip,
                  b_grip, mass_kg):
    """(total wrench on the hand, wrench on the instrument), each [f; tau] in W about the
    body's origin (N, N*m), from the plant's 13-vector states [q; p; w; v]."""
    on_hand = arm_wrench(hand_state[0:7], hand_state[7:13], target, k_arm, b_arm, mass_kg)
    if gripped < 0.5:
        return on_hand, np.zeros(6)
    grip_on_hand, grip_on_instrument = grip_wrenches(
        hand_state[0:7], hand_state[7:13], instrument_state[0:7], instrument_state[7:13], X_HI,
        k_grip, b_grip)
    return on_hand + grip_on_hand, grip_on_instrument


@numba.njit(cache=True)
def latch_X_HI(X_WH, X_WI) -> np.ndarray:
    """X_HI = X_WH^-1 X_WI as a pose vector [qw, qx, qy, qz, x, y, z] (m)."""
    return drake_relative_pose(X_WH, X_WI)


@numba.njit(cache=True)
def grip_update(gripped: float, X_HI, grip_command: float, X_WH, X_WI):
    """(gripped 0/1, X_HI) after one grip-sensor sample: a rising edge of the command
    (> 0.5 grips) latches the current relative pose, a falling edge releases."""
    if grip_command <= 0.5:
        return 0.0, X_HI.copy()
    if gripped >= 0.5:
        return 1.0, X_HI.copy()
    return 1.0, latch_X_HI(X_WH, X_WI)


def _step_map(mass, stiffness, damping, h):
    """The plant's semi-implicit Euler step of M x'' = -K x - B x' as a matrix on [x; v]."""
    n = len(mass)
    Minv_K = stiffness / mass[:, None]
    Minv_B = damping / mass[:, None]
    velocity_gain = np.eye(n) - h * Minv_B
    return np.block([[np.eye(n) - h * h * Minv_K, h * velocity_gain],
                     [-h * Minv_K, velocity_gain]])


def explicit_step_spectral_radius(config: HandImpedanceConfig, instrument_mass_kg: float,
                                  instrument_inertia_diag, time_step_s: float) -> float:
    """Largest spectral radius, over the six axes, of the plant's step of the hand on its
    arm, both gripping the instrument (held at H's origin, axes aligned) and empty.

    Below 1 the explicit forces are stable at ``time_step_s`` (s). Other forces on the
    instrument (levitation, contact) are not part of it.
    """
    k_arm, b_arm, k_grip, b_grip = impedance_gains(config)
    hand_inertia = np.diag(hand_spatial_inertia(config.mass_kg).CalcRotationalInertia()
                           .CopyToFullMatrix3())
    hand_mass = np.concatenate(([config.mass_kg] * 3, hand_inertia))
    instrument_mass = np.concatenate(([instrument_mass_kg] * 3, instrument_inertia_diag))
    chain = np.array([[1.0, -1.0], [-1.0, 1.0]])  # a spring-damper between the two bodies
    radius = 0.0
    for j in range(6):
        empty = _step_map(np.array([hand_mass[j]]), np.array([[k_arm[j]]]),
                          np.array([[b_arm[j]]]), time_step_s)
        gripped = _step_map(np.array([hand_mass[j], instrument_mass[j]]),
                            np.diag([k_arm[j], 0.0]) + k_grip[j] * chain,
                            np.diag([b_arm[j], 0.0]) + b_grip[j] * chain, time_step_s)
        for step in (empty, gripped):
            radius = max(radius, float(np.max(np.abs(np.linalg.eigvals(step)))))
    return radius


# The hand's input ports (name, size), in the order of the law's one input. The grip
# command is the law's own port: it acts only through the grip's update, so the
# wrenches do not depend on it.
HAND_INPUTS = (("hand_state", 13), ("instrument_state", 13), ("hand_target", 12))
_HAND_STATE, _INSTRUMENT_STATE, _HAND_TARGET = (
    rows.start for rows in stacked_slices(HAND_INPUTS).values())
# Its output ports that the law computes (name, size), in the order of the law's one output.
HAND_OUTPUTS = (("generalized_forces", 12), ("wrench_on_instrument_W", 6))


@kernel((VECTOR, SCALAR, VECTOR, VECTOR))
def grip_step(inputs, grip_command, gripped, X_HI):
    """One grip-sensor sample (``grip_update``) in place: ``gripped`` (1) and ``X_HI``
    (7) are the update's copies of the state; ``inputs`` HAND_INPUTS stacked."""
    now_gripped, now_X_HI = grip_update(
        gripped[0], X_HI, grip_command, inputs[_HAND_STATE:_HAND_STATE + 7],
        inputs[_INSTRUMENT_STATE:_INSTRUMENT_STATE + 7])
    gripped[0] = now_gripped
    X_HI[:] = now_X_HI


@kernel((VECTOR, READONLY_VECTOR, READONLY_VECTOR, VECTOR, VECTOR, VECTOR, VECTOR, SCALAR,
         VECTOR))
def hand_outputs(inputs, gripped, X_HI, k_arm, b_arm, k_grip, b_grip, mass_kg, out):
    """HAND_OUTPUTS stacked into ``out`` from ``inputs`` (HAND_INPUTS stacked): the
    wrench on the hand, then on the instrument, as generalized forces [tau; f] each;
    then the instrument's as [f; tau]."""
    on_hand, on_instrument = hand_wrenches(
        inputs[_HAND_STATE:_HAND_STATE + 13], inputs[_INSTRUMENT_STATE:_INSTRUMENT_STATE + 13],
        inputs[_HAND_TARGET:_HAND_TARGET + 12], gripped[0], X_HI, k_arm, b_arm, k_grip, b_grip,
        mass_kg)
    out[0:3], out[3:6] = on_hand[3:6], on_hand[0:3]
    out[6:9], out[9:12] = on_instrument[3:6], on_instrument[0:3]
    out[12:18] = on_instrument


class HandLaw(LeafSystem):
    """``SimulatedHand``'s arithmetic and state: one input, ``inputs`` (HAND_INPUTS
    stacked), and ``grip``; one output, ``wrenches`` (HAND_OUTPUTS stacked), and the
    state output ``handle_gripped``.

    .. pydrake_system::

        name: HandLaw
        input_ports:
        - inputs
        - grip
        output_ports:
        - wrenches
        - handle_gripped
    """

    def __init__(self, *, config: HandImpedanceConfig, period_s: float):
        LeafSystem.__init__(self)
        self._mass_kg = float(config.mass_kg)
        self._k_arm, self._b_arm, self._k_grip, self._b_grip = impedance_gains(config)
        self._inputs = self.DeclareVectorInputPort("inputs", stacked_size(HAND_INPUTS))
        self._grip = self.DeclareVectorInputPort("grip", 1)
        # The grip flag is a group of its own: its port is a plain state output.
        self._gripped = self.DeclareDiscreteState(1)
        self._X_HI = self.DeclareDiscreteState(IDENTITY_POSE)
        self.DeclarePeriodicDiscreteUpdateEvent(period_s, 0.0, self._update_grip)
        self.DeclareVectorOutputPort(
            "wrenches", stacked_size(HAND_OUTPUTS), self._calc_wrenches,
            {self._inputs.ticket(), self.xd_ticket()})
        self.DeclareStateOutputPort("handle_gripped", self._gripped)

    def _update_grip(self, context, discrete_state):
        # The update's state starts as a copy of the context's: stepped in place.
        grip_step(self._inputs.EvalBasicVector(context).value(),
                  self._grip.EvalBasicVector(context).GetAtIndex(0),
                  discrete_state.get_mutable_value(self._gripped),
                  discrete_state.get_mutable_value(self._X_HI))

    def _calc_wrenches(self, context, output):
        hand_outputs(self._inputs.EvalBasicVector(context).value(),
                     context.get_discrete_state(self._gripped).get_value(),
                     context.get_discrete_state(self._X_HI).get_value(), self._k_arm,
                     self._b_arm, self._k_grip, self._b_grip, self._mass_kg,
                     output.get_mutable_value())


class SimulatedHand(Diagram):
    """The user's hand: arm impedance toward ``hand_target``, a latched grip on the
    instrument, and the handle's grip sensor.

    .. pydrake_system::

        name: SimulatedHand
        input_ports:
        - hand_state
        - instrument_state
        - hand_target
        - grip
        output_ports:
        - generalized_forces
        - wrench_on_instrument_W
        - handle_gripped

    ``hand_state`` and ``instrument_state`` are the plant's per-model-instance
    state outputs (13: [qw, qx, qy, qz, x, y, z, wx, wy, wz, vx, vy, vz],
    velocities in W); ``hand_target`` (12) is [x, y, z, roll, pitch, yaw] of H
    in W and their rates; ``grip`` (1) > 0.5 means grip. ``generalized_forces``
    (12) holds, as free-body generalized forces [tau; f] in W about each body's
    origin (N*m, N), the wrench on the hand (arm, weight carried and the grip's
    reaction) then the grip's wrench on the instrument (zero while released): a
    vector, placed into the plant's generalized force by a C++ gain, costs far
    less than a list of ExternallyAppliedSpatialForce made in Python each tick.
    ``wrench_on_instrument_W`` (6) is the
    latter as [f; tau] in W about I's origin, for logging; ``handle_gripped`` (1)
    is 1.0 while gripped.

    The discrete state, the grip flag and X_HI (7) in groups of their own, is
    updated every ``period_s``: on a rising edge of ``grip`` the current
    relative pose X_HI = X_WH^-1 X_WI is latched, so the grip starts relaxed;
    on a falling edge the hand releases.

    A diagram of three blocks (``systems/stacked_ports.py``): the inputs stacked for
    ``HandLaw`` ("law"), which computes both wrenches once a tick, and its result
    split into the named outputs; the discrete state is the law's.
    """

    def __init__(self, *, config: HandImpedanceConfig, period_s: float):
        Diagram.__init__(self)
        BuildStacked(self, leaf=HandLaw(config=config, period_s=period_s), leaf_name="law",
                     inputs=HAND_INPUTS, outputs=HAND_OUTPUTS, leaf_inputs=("grip",),
                     leaf_outputs=("handle_gripped",))
