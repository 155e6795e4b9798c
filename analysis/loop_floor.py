"""The least a levitation tick can cost in a Drake diagram with Python systems: the
station's plant closed by one Python leaf system that does, each tick, the physics
floor's kernels and nothing else (``maglev bench``'s "one-system loop").

The shipped loop is some twenty leaf systems (the marker sensor, the estimator, the
controller, the supervisor, the amplifiers, the actuation, each with its ports); this
one is three (the plant, its SceneGraph, ``FloorLoop``) with two Python calls a tick.
What the shipped tick costs beyond this loop is the price of its separate blocks.
"""

from __future__ import annotations

import time

import numpy as np
from pydrake.math import RigidTransform
from pydrake.multibody.plant import AddMultibodyPlant
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder, LeafSystem

from maglev_haptics.diagrams.station import add_station_models, rest_transform
from maglev_haptics.hardware.magnetics import load_magnetics
from maglev_haptics.hardware.thermal import (
    coil_thermal, current_bounds_a, thermal_budget, winding_resistance_ohm)
from maglev_haptics.hardware.wrench_kernel import POSE_OK
from maglev_haptics.systems.current_allocator import (
    TORQUE_WEIGHT_PER_M, bounded_minimum_power_currents)
from maglev_haptics.systems.levitation_controller import ControllerConfig, pd_gains, pd_wrench
from maglev_haptics.systems.magnetic_actuation import (
    instrument_generalized_force, wrench_matrix_at_pose)

HOVER_ABOVE_REST_M = 0.010  # the floor's plants hover the instrument this far above rest
SETTLE_S = 0.2  # simulated before the timing starts (s)


def hover_transform(scenario) -> RigidTransform:
    """X_WI HOVER_ABOVE_REST_M above the instrument's rest pose: where the floor's
    plants hover it, clear of the glass."""
    X_WI = rest_transform(scenario)
    X_WI.set_translation(X_WI.translation() + [0.0, 0.0, HOVER_ABOVE_REST_M])
    return X_WI


class FloorLoop(LeafSystem):
    """Hovers the instrument with the floor's kernels alone: each tick (``tick_s``, s) a
    discrete update computes the PD wrench toward ``setpoint`` (12: p [m], rpy [rad],
    their rates) with ``controller``'s gains, the wrench matrix at the true pose and the
    thermal allocation at ambient temperature into its state (the coil currents, A);
    its output is the currents' wrench at the true pose (the actuation's kernel). The
    floor's allocation is the thermal one: the shipped scenarios' (``maglev bench``
    lists only those).

    .. pydrake_system::

        name: FloorLoop
        input_ports:
        - instrument_state
        output_ports:
        - generalized_force
    """

    def __init__(self, *, config, controller: ControllerConfig, setpoint: np.ndarray,
                 tick_s: float):
        super().__init__()
        self._magnetics = load_magnetics(config)
        self._p_WA = np.asarray(config.p_WA, dtype=float)
        self._setpoint = np.asarray(setpoint, dtype=float)
        spec = config.instrument_spec()
        self._mass_kg = spec.mass_kg
        self._kp, self._kd = pd_gains(controller, spec.mass_kg, np.diag(spec.inertia_about_I()))
        thermal = coil_thermal(config)
        budget = thermal_budget(thermal, horizon_s=controller.thermal_horizon_s,
                                margin_c=controller.thermal_margin_c,
                                current_limit_a=config.amplifier.current_limit_a)
        ambient_c = np.full(self._magnetics.n_coils, thermal.ambient_c)
        self._resistance_ohm = winding_resistance_ohm(thermal, ambient_c)
        self._bound_a = current_bounds_a(budget, ambient_c)
        self._state = self.DeclareVectorInputPort("instrument_state", 13)
        self._currents = self.DeclareDiscreteState(self._magnetics.n_coils)
        self.DeclarePeriodicDiscreteUpdateEvent(tick_s, 0.0, self._allocate)
        self.DeclareVectorOutputPort("generalized_force", 6, self._calc_generalized_force)

    def _allocate(self, context, discrete_state):
        state = self._state.EvalBasicVector(context).value()
        wrench = pd_wrench(self._setpoint, state[0:7], state[7:13], self._kp, self._kd,
                           self._mass_kg)
        status, A = wrench_matrix_at_pose(state[0:7].copy(), self._p_WA,
                                          *self._magnetics.kernel_arguments())
        if status != POSE_OK:
            raise RuntimeError(f"instrument_state = {state.tolist()}: out of the model's range")
        currents, _ = bounded_minimum_power_currents(A, wrench, self._resistance_ohm,
                                                     self._bound_a, TORQUE_WEIGHT_PER_M)
        discrete_state.get_mutable_vector(self._currents).SetFromVector(currents)

    def _calc_generalized_force(self, context, output):
        instrument_generalized_force(
            self._state.EvalBasicVector(context).value(),
            context.get_discrete_state(self._currents).value(), self._p_WA,
            *self._magnetics.kernel_arguments(), output.get_mutable_value())


def floor_loop_us(scenario, n_ticks: int = 2000, windows: int = 3) -> dict:
    """The one-system loop's wall time a tick (us, the best of ``windows`` runs of
    ``n_ticks``, after SETTLE_S) for ``scenario``'s device, hovering
    HOVER_ABOVE_REST_M above its rest pose; and how far it drifted from there (m), which
    says it held the instrument (a fallen one costs a contact step)."""
    if scenario.hand is not None:
        raise ValueError("scenario.hand is set: the one-system loop flies the instrument "
                         "alone; use a levitation scenario (hand: null)")
    tick_s = scenario.plant_config.time_step
    builder = DiagramBuilder()
    plant, _ = AddMultibodyPlant(scenario.plant_config, builder)
    instrument, _ = add_station_models(plant, scenario)
    plant.Finalize()
    X_WI = hover_transform(scenario)
    plant.SetDefaultFloatingBaseBodyPose(plant.GetBodyByName("instrument", instrument), X_WI)
    setpoint = np.concatenate([X_WI.translation(), [0.0, 0.0, scenario.motion.start_xy_yaw[2]],
                               np.zeros(6)])
    loop = builder.AddSystem(FloorLoop(config=scenario.device, controller=scenario.controller,
                                       setpoint=setpoint, tick_s=tick_s))
    builder.Connect(plant.get_state_output_port(instrument), loop.get_input_port())
    builder.Connect(loop.get_output_port(), plant.get_applied_generalized_force_input_port())
    simulator = Simulator(builder.Build())
    simulator.Initialize()
    simulator.AdvanceTo(SETTLE_S)
    best_s = float("inf")
    for _ in range(windows):
        start_s = simulator.get_context().get_time()
        wall_start = time.perf_counter()
        simulator.AdvanceTo(start_s + n_ticks * tick_s)
        best_s = min(best_s, time.perf_counter() - wall_start)
    plant_context = plant.GetMyContextFromRoot(simulator.get_context())
    drift_m = np.linalg.norm(plant.GetPositions(plant_context, instrument)[4:7]
                             - X_WI.translation())
    return {"us_per_tick": 1e6 * best_s / n_ticks, "drift_m": float(drift_m)}
