"""The haptic half of the application: scene, coupling, supervisor; and the user's commands.

``AddHaptics`` puts the virtual scene (its own MultibodyPlant and SceneGraph,
so the virtual world never touches the physical instrument or the glass, and
so the scene can use hydroelastic contact while the station uses point
contact), the virtual coupling between the measured instrument and the scene's
tool, the tool's contact sensor and the mode supervisor into the diagram, and
connects them to the levitation controller. The scene plant steps at the
control period, so physics advances in lock-step with the device's control
tick. The tool always follows the instrument through the coupling; until haptics
engages (and after it is disabled) the user feels none of it, and when it
engages the user's wrench ramps in.

``AddHandCommands`` feeds the simulated hand's target and grip from its script
or from Meshcat's controls.
"""

import dataclasses
import math
from dataclasses import dataclass
from typing import List, Optional

import numpy as np
from pydrake.geometry import Meshcat
from pydrake.math import RollPitchYaw
from pydrake.systems.framework import OutputPort
from pydrake.systems.primitives import Adder, TrajectorySource
from pydrake.trajectories import PiecewisePolynomial

from maglev_haptics.diagrams.deformable_scene import AddDeformableScene, DeformableSurface
from maglev_haptics.diagrams.hand_script import MeshcatHand, hand_plan
from maglev_haptics.diagrams.motion import flight_plan
from maglev_haptics.diagrams.scenario import Scenario
from maglev_haptics.diagrams.scene import ModelScene
from maglev_haptics.diagrams.scene_builder import AddScene, SceneParts, measure_step_cost_s
from maglev_haptics.diagrams.scene_models import (
    holds_tissue, model_scene_warnings, step_cost_levers, tool_grip_inverse_mass_per_kg)
from maglev_haptics.diagrams.station import (
    hand_start_pose, hand_start_transform, rest_transform)
from maglev_haptics.diagrams.tissue_model import read_scene_tissue
from maglev_haptics.diagrams.tissue_scene import AddTissue
from maglev_haptics.hardware.limits import device_limits
from maglev_haptics.systems.haptic_coupling import (
    CouplingConfig, HapticCoupling, resolved_rotational_gains)
from maglev_haptics.systems.haptic_supervisor import HapticSupervisor
from maglev_haptics.systems.pose_estimator import velocity_lag_s
from maglev_haptics.systems.meshcat_hand import MeshcatHandInput
from maglev_haptics.systems.waiting_hand_script import WaitingHandScript


# The tool's contact wrench and flag feed only the supervisor's let-go decision
# (which remembers contact for 0.1 s) and the log, never the rendered force: 200 Hz.
CONTACT_SAMPLE_PERIOD_S = 0.005
# The mode logic's timers (50 ms debounce, 0.1 s contact memory, 0.5 s handover)
# need no finer step; its outputs are read every control tick.
SUPERVISOR_PERIOD_S = 0.005


@dataclass
class HapticParts:
    """What ``AddHaptics`` added: the scene (a plant or the lattice), the coupling, the
    haptic supervisor, and the haptics request it reads."""
    scene: SceneParts
    coupling: HapticCoupling
    supervisor: HapticSupervisor
    coupling_config: CouplingConfig  # with the device-derived limits filled in
    request: TrajectorySource  # the haptics request (1: requested)

    @property
    def setpoint(self) -> OutputPort:
        """The setpoint the controller tracks: the haptic supervisor's."""
        return self.supervisor.GetOutputPort("setpoint")

    def end_request(self) -> None:
        """Haptics no longer requested from now on, as a user switching it off: the
        coupling's force ramps out and the PD back in (the supervisor's handover)."""
        self.request.UpdateTrajectory(PiecewisePolynomial(np.zeros((1, 1))))


def loop_delay_s(scenario: Scenario) -> float:
    """From an instrument's motion to the wrench it causes acting on it (s): the
    tracker's latency, half a tracker period (the mean wait of a sample for the
    control tick), one control period (the currents computed at a tick flow from the
    next) and the amplifiers' lag 1 / (2 pi bandwidth)."""
    device = scenario.device
    tracker = device.tracker
    return (tracker.latency_s + 0.5 / tracker.rate_hz + 1.0 / scenario.control_rate_hz
            + 1.0 / (2 * math.pi * device.amplifier.bandwidth_hz))


def resolved_coupling_config(scenario: Scenario, magnetics) -> CouplingConfig:
    """The scenario's coupling config with its null values filled in: rotational
    gains from the instrument's inertia, and wrench limits from what the coils can
    add to the weight at the haptic start pose within ``device_limit``."""
    spec = scenario.device.instrument_spec()
    config = resolved_rotational_gains(scenario.haptics.coupling, spec.mass_kg,
                                       np.diag(spec.inertia_about_I()))
    if config.max_force_n is not None and config.max_torque_nm is not None:
        return config
    device = scenario.device
    pose = hand_start_pose(scenario)  # where the hand grips and haptics starts
    R_WI = RollPitchYaw(pose[3:6]).ToRotationMatrix().matrix()
    limits = device_limits(device, pose[0:3] - device.p_WA, R_WI,
                           limit=config.device_limit, magnetics=magnetics,
                           workspace=(np.zeros(3), np.zeros(3)))
    return dataclasses.replace(
        config,
        max_force_n=limits.max_force_n if config.max_force_n is None else config.max_force_n,
        max_torque_nm=(limits.max_torque_nm if config.max_torque_nm is None
                       else config.max_torque_nm))


def stepped_in_place(scenario: Scenario) -> Scenario:
    """``scenario`` with its rigid scene's plant stepped in the diagram, not in a
    worker process: the loop's linearization reads the plant's states."""
    if scenario.haptics is None:
        return scenario
    return dataclasses.replace(scenario, haptics=dataclasses.replace(
        scenario.haptics, scene_stepping="in_place"))


def haptics_request(scenario: Scenario) -> PiecewisePolynomial:
    """1 while haptics is requested, 0 otherwise (zero-order hold): from
    ``enable_at_s`` to ``disable_at_s``, or without one until the motion script's
    landing begins. The script's force ramps down after its landing: haptics left
    engaged would render the scene on an instrument the device no longer carries
    (nor brakes, let go). Ended with the handle in the hand, the supervisor hands the
    instrument back to the script, which lands it; let go, it lands it where it is."""
    haptics = scenario.haptics
    end = haptics.disable_at_s
    if end is None:
        plan = flight_plan(scenario.motion, scenario.device.instrument_spec().rest_height_m)
        end = plan.holds[-1][1] if plan.holds else np.inf
    times, values = ([0.0, haptics.enable_at_s], [0.0, 1.0]) if haptics.enable_at_s > 0 \
        else ([0.0], [1.0])
    if np.isfinite(end):
        times.append(end)
        values.append(0.0)
    times.append(times[-1] + 1.0)
    values.append(values[-1])
    return PiecewisePolynomial.ZeroOrderHold(times, np.array([values]))


def AddHaptics(builder, *, scenario: Scenario, magnetics, station, estimator, controller,
               scripted_setpoint, scripted_enable, fault_bits) -> HapticParts:
    """Scene, coupling, contact sensor and supervisor, wired to the controller; the
    device supervisor's ``scripted_setpoint``, ``scripted_enable`` and ``fault_bits``
    (a latched fault ends haptics)."""
    haptics = scenario.haptics
    period_s = 1.0 / scenario.control_rate_hz
    X_WI_start = hand_start_transform(scenario)
    if isinstance(haptics.scene, DeformableSurface):
        # The probe starts where the instrument rests, so it never sweeps through the
        # jelly on its way to the instrument; rest beside the lattice.
        scene = AddDeformableScene(builder, scene=haptics.scene, time_step_s=period_s,
                                   X_WI_start=rest_transform(scenario))
    else:
        # Unsampled ports: the scene steps in the loop's own discrete update (no
        # unrestricted update that would make the loop compute twice a tick).
        scene = AddScene(builder, scene=haptics.scene, time_step_s=period_s,
                         use_sampled_output_ports=False,
                         contact_sample_period_s=CONTACT_SAMPLE_PERIOD_S,
                         X_WI_start=X_WI_start, stepping=haptics.scene_stepping)
        if isinstance(haptics.scene, ModelScene) and holds_tissue(haptics.scene.directives):
            tissue = read_scene_tissue(haptics.scene.directives, "haptics.scene.directives")
            scene = AddTissue(builder, scene=haptics.scene, bodies=tissue.bodies, parts=scene,
                              time_step_s=period_s, X_WT_start=X_WI_start @ scene.X_IT,
                              rigid_contact=bool(tissue.rigid_directives))
    config = resolved_coupling_config(scenario, magnetics)
    coupling = builder.AddNamedSystem("haptic_coupling", HapticCoupling(
        config=config, period_s=period_s, X_IT=scene.X_IT,
        port_delay_ticks=max(1, round(
            (loop_delay_s(scenario) + velocity_lag_s(scenario.estimator)) / period_s))))
    supervisor = builder.AddNamedSystem("haptic_supervisor", HapticSupervisor(
        config=haptics.supervisor, period_s=SUPERVISOR_PERIOD_S,
        rest_height_m=scenario.device.instrument_spec().rest_height_m))
    request = builder.AddNamedSystem("haptics_request", TrajectorySource(
        haptics_request(scenario)))

    for name in ("X_WI_measured", "V_WI_measured"):
        builder.Connect(estimator.GetOutputPort(name), coupling.GetInputPort(name))
    builder.Connect(scene.X_WT_output, coupling.GetInputPort("X_WT"))
    builder.Connect(scene.V_WT_output, coupling.GetInputPort("V_WT"))
    builder.Connect(coupling.GetOutputPort("wrench_on_tool_W"), scene.wrench_on_tool_input)

    builder.Connect(scripted_setpoint, supervisor.GetInputPort("scripted_setpoint"))
    builder.Connect(scripted_enable, supervisor.GetInputPort("scripted_enable"))
    builder.Connect(fault_bits, supervisor.GetInputPort("fault_bits"))
    for name in ("X_WI_measured", "tracking_ok"):
        builder.Connect(estimator.GetOutputPort(name), supervisor.GetInputPort(name))
    builder.Connect(request.get_output_port(), supervisor.GetInputPort("haptics_request"))
    builder.Connect(station.GetOutputPort("handle_gripped"),
                    supervisor.GetInputPort("handle_gripped"))
    builder.Connect(scene.in_contact_output, supervisor.GetInputPort("tool_in_contact"))
    builder.Connect(supervisor.GetOutputPort("haptics_enable"),
                    coupling.GetInputPort("haptics_enable"))

    for name in ("setpoint", "enable", "pd_gain", "brake_gain"):
        builder.Connect(supervisor.GetOutputPort(name), controller.GetInputPort(name))
    builder.Connect(coupling.GetOutputPort("wrench_feedforward_W"),
                    controller.GetInputPort("wrench_feedforward_W"))
    return HapticParts(scene=scene, coupling=coupling, supervisor=supervisor,
                       coupling_config=config, request=request)


# A scene plant whose step costs more than this share of the tick gets a warning
# at load: with the rest of the loop (~0.3 ms a tick) it would fall behind.
STEP_COST_WARNING_FRACTION = 0.5


def scene_warnings(scenario: Scenario, label: str) -> List[str]:
    """A line for each thing about a model scene that runs but not as a user may
    expect: an OBJ declared compliant (its convex hull is used), a tool too light
    at the grip for the explicit coupling, a plant step too costly for the tick
    (measured here); none for the shipped kinds of scene."""
    if scenario.haptics is None or not isinstance(scenario.haptics.scene, ModelScene):
        return []
    scene = scenario.haptics.scene
    lines = [f"warning: {label}: haptics.scene: {line}" for line in model_scene_warnings(scene)]
    period_s = 1.0 / scenario.control_rate_hz
    # The explicit coupling holds a tool if k h^2 / m < 1 and b h / m < 2 (see
    # scene_builder), m the least mass the tool shows a force at its grip.
    inverse_mass = tool_grip_inverse_mass_per_kg(scene)
    coupling = scenario.haptics.coupling
    ratios = (max(coupling.translational_stiffness) * period_s**2 * inverse_mass,
              max(coupling.translational_damping) * period_s * inverse_mass / 2)
    if max(ratios) >= 1.0:
        lines.append(
            f"warning: {label}: haptics.scene.tool: a force at the grip meets as little as "
            f"{1e3 / inverse_mass:.2g} g (a centre of mass off the grip turns the tool), too "
            f"light for the coupling's {max(coupling.translational_stiffness):g} N/m and "
            f"{max(coupling.translational_damping):g} N s/m at {1e3 * period_s:g} ms "
            f"(k h^2 / m = {ratios[0]:.2g}, b h / m = {2 * ratios[1]:.2g}; stable needs < 1 "
            "and < 2): the tool will oscillate; bring its centre of mass nearer the grip "
            "(tool_offset_m) or raise min_inertia_kg_m2")
    cost_s = measure_step_cost_s(scene, period_s, hand_start_transform(scenario))
    if cost_s > STEP_COST_WARNING_FRACTION * period_s:
        lines.append(
            f"warning: {label}: haptics.scene: a step of its plant costs {1e6 * cost_s:.0f} us "
            f"here, more than {STEP_COST_WARNING_FRACTION:.0%} of the {1e6 * period_s:.0f} us "
            "tick, before the tool touches anything: the run will fall behind real time; "
            f"make its contact cheaper: {step_cost_levers(scene)}")
    return lines


INTERACTIVE_DURATION_S = 600.0  # an interactive run lasts this long unless told (s)


def interactive_variant(scenario: Scenario, duration_s: Optional[float]) -> Scenario:
    """``scenario`` with the hand driven from Meshcat: sliders for its target pose
    and a grip button (key G); the hover is held and haptics stays requested for
    the whole run (``duration_s``, default INTERACTIVE_DURATION_S)."""
    if scenario.haptics is None:
        raise ValueError("--interactive needs a scenario with haptics (a scene to touch)")
    duration_s = INTERACTIVE_DURATION_S if duration_s is None else duration_s
    hand = scenario.hand
    if not isinstance(hand, MeshcatHand):
        hand = MeshcatHand(impedance=hand.impedance if hand is not None
                           else MeshcatHand().impedance)
    waypoints = list(scenario.motion.waypoints)
    last = waypoints[-1]
    waypoints[-1] = dataclasses.replace(last, hold_s=last.hold_s + duration_s)
    return dataclasses.replace(
        scenario, hand=hand,
        motion=dataclasses.replace(scenario.motion, waypoints=waypoints),
        haptics=dataclasses.replace(scenario.haptics, disable_at_s=None),
        duration_s=duration_s)


def AddHandCommands(builder, *, scenario: Scenario, station, meshcat: Optional[Meshcat],
                    target_offset_input: bool = False, wait_for_start: bool = False):
    """The hand's target and grip: from its script, or from Meshcat's controls.

    ``target_offset_input``: a scripted hand's target gets an offset (12: pose and
    rates) from an exported input ``hand_target_offset``, for the analysis's input
    matrix (the user's motion as the loop's input).

    Returns the MeshcatHandInput (whose controls the caller deletes after the
    run); for a scripted hand a WaitingHandScript with ``wait_for_start``, else None.
    """
    hand = scenario.hand
    start = hand_start_pose(scenario)
    if isinstance(hand, MeshcatHand):
        if meshcat is None:
            raise ValueError("hand: !MeshcatHand is driven from Meshcat's controls, so the "
                             "diagram needs a Meshcat (run it without --no-meshcat)")
        commands = builder.AddNamedSystem("meshcat_hand", MeshcatHandInput(
            meshcat, start_pose=start, filter_time_constant_s=hand.filter_time_constant_s,
            period_s=1.0 / hand.input_rate_hz, grip_at_start=hand.grip_at_start))
        builder.Connect(commands.GetOutputPort("hand_target"), station.GetInputPort("hand_target"))
        builder.Connect(commands.GetOutputPort("grip"), station.GetInputPort("hand_grip"))
        return commands
    target, grip = hand_plan(hand, start)
    if wait_for_start:
        script = builder.AddNamedSystem("hand_script", WaitingHandScript(target=target, grip=grip))
        target_port, grip_port = script.GetOutputPort("hand_target"), script.GetOutputPort("grip")
    else:
        script = None
        target_port = builder.AddNamedSystem("hand_target", TrajectorySource(
            target, output_derivative_order=1)).get_output_port()
        grip_port = builder.AddNamedSystem("hand_grip", TrajectorySource(grip)).get_output_port()
    if target_offset_input:
        offset = builder.AddNamedSystem("hand_target_offset", Adder(2, target_port.size()))
        builder.Connect(target_port, offset.get_input_port(0))
        builder.ExportInput(offset.get_input_port(1), "hand_target_offset")
        target_port = offset.get_output_port()
    builder.Connect(target_port, station.GetInputPort("hand_target"))
    builder.Connect(grip_port, station.GetInputPort("hand_grip"))
    return script
