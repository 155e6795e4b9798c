"""The station: what real hardware replaces (docs/architecture.md).

``AddStation`` adds the scenario's station to a diagram and returns it as a
``Station`` (``diagrams/station_interface.py``: what it is, and what the rest asks
of it): simulated here (``SimulatedStation``) or, with ``station: !LcmStation``, the
LCM interface to a real or simulated device (``diagrams/lcm_station.py``). Its
Diagram, named ``station``, has the same ports either way:

- inputs ``coil_currents_commanded`` (n_coils, A) and ``coil_power`` (1: the
  amplifiers' supply, the device's enable line; 0 cuts every coil's current);
- outputs ``markers_measured`` (3 * n_markers, m in the tracker's frame T, NaN when
  hidden: the newest tracker sample), ``markers_sample_time_s`` (1: when it was published, s; over LCM
  when it was read), ``markers_sample_count`` (1: its frame number, from 1),
  ``coil_currents`` (n_coils, A, what flows), ``coil_currents_age_s`` (1: how old
  the command they follow is, s; a tick simulated, over LCM from the command's
  sequence the device reports, infinite for none), ``instrument_state`` (13, the
  true free-body state, simulation only), ``query_object`` (for visualizers).

With a hand in the scenario (the simulated user), also:

- inputs ``hand_target`` (12: pose [x, y, z, roll, pitch, yaw] of the hand in W
  and its rates, m, rad, m/s, rad/s) and ``hand_grip`` (1: > 0.5 grips);
- outputs ``handle_gripped`` (1: the handle's grip sensor), ``hand_state`` (13)
  and ``hand_wrench_on_instrument_W`` (6: [f; tau] in W about I's origin, N,
  N*m; simulation only).

A calibration flight's (``scenario.calibration``) also outputs
``coil_temperature_reported_c`` (n_coils, deg C): each coil's temperature as the
device reports it (the simulated device's own thermal model; over LCM its status).

With the stereo display in the scenario, the user's head and the glasses' tracker:

- outputs ``glasses_measured`` (9: [capture time, qw, qx, qy, qz, x, y, z, ok]
  of the glasses in W, s and m; ``systems/head_sensor.py``) and ``head_pose``
  (8: the scripted head, simulation only); without a haptic scene also
  ``rendered_world``, the query object the display renders the station's models from.
"""

from __future__ import annotations

from xml.etree import ElementTree

import numpy as np
from pydrake.geometry import SceneGraph
from pydrake.math import RigidTransform, RollPitchYaw
from pydrake.multibody.parsing import Parser
from pydrake.multibody.plant import AddMultibodyPlant, MultibodyPlant
from pydrake.systems.framework import Diagram, DiagramBuilder
from pydrake.systems.primitives import (
    Adder, AffineSystem, ConstantVectorSource, LinearSystem, MatrixGain, Multiplexer, Saturation,
    TrajectorySource)
from pydrake.systems.rendering import MultibodyPositionToGeometryPose

from maglev_haptics.diagrams.head_script import head_plan
from maglev_haptics.diagrams.lcm_station import LcmStation, LcmStationInterface, MakeLcmStation
from maglev_haptics.diagrams.scenario import Scenario, ScenarioError
from maglev_haptics.diagrams.station_interface import Station
from maglev_haptics.hardware.magnetics import load_magnetics
from maglev_haptics.hardware.thermal import coil_thermal
from maglev_haptics.systems.coil_thermal import CoilTemperatures
from maglev_haptics.plant_models import PACKAGE_XML
from maglev_haptics.systems.fault_injection import (
    CorruptSample, LatencySpike, Shove, Shoves, StuckAmplifier, StuckAmplifiers)
from maglev_haptics.systems.hand import HAND_MODEL_URL, SimulatedHand
from maglev_haptics.systems.head_sensor import HeadSensor
from maglev_haptics.systems.magnetic_actuation import MagneticActuation
from maglev_haptics.systems.marker_sensor import MarkerSensor
from maglev_haptics.systems.stereo_renderer import AddStereoRenderer

DISPLAY_MODEL_URL = "package://maglev_haptics/display.sdf"
DISPLAY_MODEL_THICKNESS_M = 0.010
DRAKE_SDF_NAMESPACE = "http://drake.mit.edu"
HAND_GRIP_PERIOD_S = 0.01
REPORTED_TEMPERATURE_PERIOD_S = 0.01  # a simulated device's coil temperatures: 100 Hz (s)  # the hand closes or opens on the handle within 10 ms (s)


def amplifier_lag_coefficient(bandwidth_hz: float, period_s: float) -> float:
    """a in i[k+1] = a i[k] + (1 - a) i_cmd[k]: exact sampling of a first-order lag."""
    return float(np.exp(-2 * np.pi * bandwidth_hz * period_s))


# Far above any current (A): the supply gate's offset (``AddAmplifiers``).
SUPPLY_GATE_OFFSET_A = 1e6


def AddAmplifiers(builder: DiagramBuilder, *, spec, n_coils: int, period_s: float):
    """Current-mode amplifiers on a supply that can be cut, then a sampled lag.

    With the supply on (``coil_power`` 1) each coil gets its command clamped at the
    current limit; cut (0) it gets nothing and its current decays with the
    amplifiers' lag, as a coil's does through its freewheel. The gate is C++ alone
    (pydrake binds no product of signals): the mean of the command clamped after
    adding and after subtracting SUPPLY_GATE_OFFSET_A * (1 - power), which is the
    clamped command at power 1 and (+limit - limit) / 2 = 0 at power 0.

    Returns the Diagram (inputs ``coil_currents_commanded`` and ``coil_power``,
    output ``coil_currents``).
    """
    sub = DiagramBuilder()
    eye, ones = np.eye(n_coils), np.ones((n_coils, 1))
    command = sub.AddNamedSystem("command", Multiplexer([n_coils, 1]))
    offset = SUPPLY_GATE_OFFSET_A
    shifted = sub.AddNamedSystem("supply_gate", AffineSystem(
        D=np.block([[eye, -offset * ones], [eye, offset * ones]]),
        y0=np.r_[np.full(n_coils, offset), np.full(n_coils, -offset)]))
    limit = np.full(2 * n_coils, spec.current_limit_a)
    clamp = sub.AddNamedSystem("current_limit", Saturation(-limit, limit))
    a = amplifier_lag_coefficient(spec.bandwidth_hz, period_s)
    lag = sub.AddNamedSystem("current_lag", LinearSystem(
        A=a * eye, B=(1 - a) / 2 * np.hstack((eye, eye)), C=eye,
        D=np.zeros((n_coils, 2 * n_coils)), time_period=period_s))
    sub.Connect(command.get_output_port(), shifted.get_input_port())
    sub.Connect(shifted.get_output_port(), clamp.get_input_port())
    sub.Connect(clamp.get_output_port(), lag.get_input_port())
    sub.ExportInput(command.get_input_port(0), "coil_currents_commanded")
    sub.ExportInput(command.get_input_port(1), "coil_power")
    sub.ExportOutput(lag.get_output_port(), "coil_currents")
    amplifiers = sub.Build()
    amplifiers.set_name("amplifiers")
    return builder.AddSystem(amplifiers)


def rest_transform(scenario: Scenario) -> RigidTransform:
    """X_WI of the instrument lying level on the glass at the script's start."""
    spec = scenario.device.instrument_spec()
    x, y, yaw = scenario.motion.start_xy_yaw
    return RigidTransform(RollPitchYaw(0.0, 0.0, yaw), [x, y, spec.rest_height_m])


def instrument_model_text(parser: Parser, device) -> str | None:
    """The instrument's SDFormat with ``device``'s mass and centre of mass, or None
    where the shipped model already has them. The rotational inertia about the centre
    of mass scales with the mass (a calibration weighs the instrument; it does not
    take it apart)."""
    spec = device.instrument_spec()
    offset = [float(v) for v in device.instrument_com_offset_m]
    path = parser.package_map().ResolveUrl(spec.model_url)
    ElementTree.register_namespace("drake", DRAKE_SDF_NAMESPACE)  # kept as written
    tree = ElementTree.parse(path)
    inertial = tree.find("model/link[@name='instrument']/inertial")
    model_mass_kg = float(inertial.find("mass").text)
    if abs(model_mass_kg - spec.mass_kg) <= 1e-9 and not any(offset):
        return None
    inertial.find("mass").text = repr(spec.mass_kg)
    for element in inertial.find("inertia"):
        element.text = repr(float(element.text) * spec.mass_kg / model_mass_kg)
    pose = inertial.find("pose")
    if pose is None:
        pose = ElementTree.SubElement(inertial, "pose")
    pose.text = " ".join(repr(v) for v in (*offset, 0.0, 0.0, 0.0))
    return ElementTree.tostring(tree.getroot(), encoding="unicode")


def add_station_models(plant, scenario: Scenario, device=None):
    """Add the instrument (of ``device``, default the scenario's), the display and
    (when the scenario has one) the user's hand to ``plant``; returns the model
    instances (instrument, hand or None)."""
    device = scenario.device if device is None else device
    parser = Parser(plant)
    parser.package_map().AddPackageXml(str(PACKAGE_XML))
    text = instrument_model_text(parser, device)
    instrument = (parser.AddModels(url=device.instrument_spec().model_url) if text is None
                  else parser.AddModelsFromString(text, "sdf"))[0]
    parser.AddModels(url=DISPLAY_MODEL_URL)
    hand = parser.AddModels(url=HAND_MODEL_URL)[0] if scenario.hand is not None else None
    return instrument, hand


def generalized_force_placement(plant, *bodies) -> np.ndarray:
    """(nv, 6 * len(bodies)) matrix that puts free bodies' generalized forces
    [tau; f], stacked in the order given, into the plant's generalized force vector."""
    placement = np.zeros((plant.num_velocities(), 6 * len(bodies)))
    for i, body in enumerate(bodies):
        start = body.floating_velocities_start_in_v()
        placement[start:start + 6, 6 * i:6 * i + 6] = np.eye(6)
    return placement


def hand_start_pose(scenario: Scenario) -> np.ndarray:
    """[x, y, z, roll, pitch, yaw] where the hand waits: the hover pose it grips at,
    the motion script's first waypoint."""
    return np.asarray(scenario.motion.waypoints[0].pose, float)


def hand_start_transform(scenario: Scenario) -> RigidTransform:
    """``hand_start_pose`` as a pose in W: X_WH of the waiting hand, and X_WI where
    it grips."""
    x, y, z, roll, pitch, yaw = hand_start_pose(scenario)
    return RigidTransform(RollPitchYaw(roll, pitch, yaw), [x, y, z])


class SimulatedStation(Station):
    """The simulated station, in the application's own diagram: its truth is there to
    read, it keeps the simulator's time, a run may end with the instrument anywhere,
    and its currents are measured in the tick that reads them."""

    simulated = True
    keeps_wall_clock = False
    lands_before_run_end = False
    shares_cores = False
    measured_currents_lag_ticks = 1


def AddStation(builder: DiagramBuilder, *, scenario: Scenario, magnetics,
               config=None) -> Station:
    """The station of ``scenario`` (or of ``config``, a SimStation or an LcmStation in
    the scenario's place), added to ``builder``."""
    station = MakeStation(scenario, magnetics=magnetics, config=config)
    builder.AddSystem(station.system)
    return station


def station_kind(scenario: Scenario, config=None) -> type:
    """The Station class of ``scenario``'s station (or of ``config`` in its place): its
    class-level answers (``keeps_wall_clock``, ...) hold before it is built."""
    return (LcmStationInterface if isinstance(config or scenario.station, LcmStation)
            else SimulatedStation)


def MakeStation(scenario: Scenario, *, magnetics, config=None) -> Station:
    """The station of ``scenario`` (or of ``config`` in its place): simulated here, or
    the LCM interface with the same ports (``diagrams/lcm_station.py``). A simulated
    station whose ``device`` differs from the scenario's (``SimStation.device``: the
    device as it is, against the model the application flies with) has its own
    electromagnetic model."""
    if station_kind(scenario, config) is LcmStationInterface:
        return MakeLcmStation(scenario)
    device = station_device(scenario, config)
    if device is not scenario.device:
        magnetics = load_magnetics(device)
    return SimulatedStation(_simulated_station(scenario, device, magnetics))


def station_device(scenario: Scenario, config=None):
    """The device a simulated station simulates: its ``SimStation.device`` (the
    scenario's overlaid, ``diagrams/scenario.py``), else the scenario's; with a
    calibration flight's payload hung on it."""
    config = config or scenario.station
    device = getattr(config, "device", None)
    device = scenario.device if device is None else device
    flight = scenario.calibration
    return device if flight is None else device.with_payload(flight.payload_kg,
                                                             flight.payload_p_I_m)


def _simulated_station(scenario: Scenario, device, magnetics) -> Diagram:
    """The simulated station's Diagram of ``device``, named ``station`` (the module
    docstring's ports)."""
    spec = device.instrument_spec()
    if abs(device.display.thickness_m - DISPLAY_MODEL_THICKNESS_M) > 1e-9:
        raise ScenarioError(
            f"device.display.thickness_m = {device.display.thickness_m}: the shipped display "
            f"model is {DISPLAY_MODEL_THICKNESS_M} m thick; other values need their own model")
    builder = DiagramBuilder()
    plant, scene_graph = AddMultibodyPlant(scenario.plant_config, builder)
    instrument, hand = add_station_models(plant, scenario, device)
    plant.Finalize()
    body = plant.GetBodyByName("instrument", instrument)
    plant.SetDefaultFloatingBaseBodyPose(body, rest_transform(scenario))
    if hand is not None:
        plant.SetDefaultFloatingBaseBodyPose(plant.GetBodyByName("hand", hand),
                                             hand_start_transform(scenario))

    control_period_s = 1.0 / scenario.control_rate_hz
    amplifiers = AddAmplifiers(builder, spec=device.amplifier, n_coils=device.n_coils,
                               period_s=control_period_s)
    actuation = builder.AddNamedSystem(
        "magnetic_actuation", MagneticActuation(magnetics=magnetics, p_WA=device.p_WA))
    faults = {kind: [f for f in scenario.faults if isinstance(f, kind)]
              for kind in (LatencySpike, CorruptSample, StuckAmplifier, Shove)}
    sensor = builder.AddNamedSystem("marker_sensor", MarkerSensor(
        instrument=spec, tracker=device.tracker, tick_s=scenario.plant_config.time_step,
        occlusions=scenario.occlusions,
        seed=scenario.random_seed, dropout_probability=scenario.marker_dropout_probability,
        latency_spikes=faults[LatencySpike], corruptions=faults[CorruptSample]))
    state_port = plant.get_state_output_port(instrument)
    builder.Connect(amplifiers.get_output_port(), actuation.GetInputPort("coil_currents"))
    builder.Connect(state_port, actuation.GetInputPort("instrument_state"))
    placement = builder.AddNamedSystem(
        "actuation_placement", MatrixGain(generalized_force_placement(plant, body)))
    builder.Connect(actuation.get_output_port(), placement.get_input_port())
    if hand is None:
        builder.Connect(placement.get_output_port(),
                        plant.get_applied_generalized_force_input_port())
    builder.Connect(state_port, sensor.GetInputPort("instrument_state"))

    if faults[StuckAmplifier]:
        stuck = builder.AddNamedSystem("stuck_amplifiers", StuckAmplifiers(
            faults[StuckAmplifier], device.n_coils, device.amplifier.current_limit_a))
        builder.Connect(stuck.get_output_port(),
                        amplifiers.GetInputPort("coil_currents_commanded"))
        builder.ExportInput(stuck.get_input_port(), "coil_currents_commanded")
    else:
        builder.ExportInput(amplifiers.GetInputPort("coil_currents_commanded"),
                            "coil_currents_commanded")
    builder.ExportInput(amplifiers.GetInputPort("coil_power"), "coil_power")
    if faults[Shove]:
        shoves = builder.AddNamedSystem("shoves", Shoves(faults[Shove], body.index(),
                                                         body.default_com()))
        builder.Connect(shoves.get_output_port(), plant.get_applied_spatial_force_input_port())
    for name in ("markers_measured", "markers_sample_time_s", "markers_sample_count"):
        builder.ExportOutput(sensor.GetOutputPort(name), name)
    builder.ExportOutput(amplifiers.get_output_port(), "coil_currents")
    # Measured in the tick that reads them, following the tick before's command (the
    # amplifiers' lag takes a tick's command at the next).
    currents_age = builder.AddNamedSystem("coil_currents_age", ConstantVectorSource(
        [1.0 / scenario.control_rate_hz]))
    builder.ExportOutput(currents_age.get_output_port(), "coil_currents_age_s")
    builder.ExportOutput(state_port, "instrument_state")
    builder.ExportOutput(scene_graph.get_query_output_port(), "query_object")
    if hand is not None:
        _add_hand(builder, scenario, plant, hand, body, actuation_force=placement.get_output_port())
    if scenario.calibration is not None:  # the device reports its coils' temperatures
        reported = builder.AddNamedSystem("coil_temperatures", CoilTemperatures(
            model=coil_thermal(device), n_coils=device.n_coils,
            period_s=REPORTED_TEMPERATURE_PERIOD_S))
        builder.Connect(amplifiers.get_output_port(), reported.get_input_port())
        builder.ExportOutput(reported.get_output_port(), "coil_temperature_reported_c")
    if scenario.stereo is not None:
        _add_head(builder, scenario)
        if scenario.haptics is None:  # with a scene, the display draws the scene's world
            builder.ExportOutput(_add_rendered_world(builder, scenario, plant),
                                 "rendered_world")
    station = builder.Build()
    station.set_name("station")
    return station


def _add_rendered_world(builder, scenario: Scenario, plant):
    """The query output of a SceneGraph of its own, with the stereo display's render
    engine, that shows the station's models at ``plant``'s state. In the plant's own
    SceneGraph the engine's poses would be updated at every step of the plant (its
    contact query asks for them: 28 us a tick in head_sweep); here only when a frame is
    rendered."""
    scene_graph = builder.AddNamedSystem("rendered_scene_graph", SceneGraph())
    twin = MultibodyPlant(scenario.plant_config.time_step)
    twin.RegisterAsSourceForSceneGraph(scene_graph)
    add_station_models(twin, scenario)
    twin.Finalize()
    # The pose system keeps the twin alive; it has the plant's state layout.
    poses = builder.AddNamedSystem(
        "rendered_poses", MultibodyPositionToGeometryPose(twin, input_multibody_state=True))
    builder.Connect(plant.get_state_output_port(), poses.get_input_port())
    builder.Connect(poses.get_output_port(),
                    scene_graph.get_source_pose_port(twin.get_source_id()))
    AddStereoRenderer(scene_graph)
    return scene_graph.get_query_output_port()


def _add_head(builder, scenario: Scenario):
    """The user's scripted head and the tracker of the glasses, and their ports."""
    head = builder.AddNamedSystem("head", TrajectorySource(head_plan(scenario.stereo.head)))
    sensor = builder.AddNamedSystem("head_sensor", HeadSensor(
        tracker=scenario.device.head_tracker, glasses=scenario.device.glasses,
        occlusions=scenario.stereo.occlusions, seed=scenario.random_seed))
    builder.Connect(head.get_output_port(), sensor.GetInputPort("head_pose"))
    builder.ExportOutput(head.get_output_port(), "head_pose")
    builder.ExportOutput(sensor.GetOutputPort("glasses_measured"), "glasses_measured")


def _add_hand(builder, scenario: Scenario, plant, hand, instrument_body, *, actuation_force):
    """The simulated user's hand: its impedance forces and grip, added to the coils'
    ``actuation_force`` (nv) on the plant, and its ports."""
    hand_body = plant.GetBodyByName("hand", hand)
    if abs(hand_body.default_mass() - scenario.hand.impedance.mass_kg) > 1e-9:
        raise ScenarioError(
            f"hand.impedance.mass_kg = {scenario.hand.impedance.mass_kg}: the hand model "
            f"{HAND_MODEL_URL} has {hand_body.default_mass()} kg; the two must agree")
    simulated_hand = builder.AddNamedSystem("hand", SimulatedHand(
        config=scenario.hand.impedance, period_s=HAND_GRIP_PERIOD_S))
    builder.Connect(plant.get_state_output_port(hand), simulated_hand.GetInputPort("hand_state"))
    builder.Connect(plant.get_state_output_port(instrument_body.model_instance()),
                    simulated_hand.GetInputPort("instrument_state"))
    placement = builder.AddNamedSystem("hand_force_placement", MatrixGain(
        generalized_force_placement(plant, hand_body, instrument_body)))
    total = builder.AddNamedSystem("generalized_force_sum", Adder(2, plant.num_velocities()))
    builder.Connect(simulated_hand.GetOutputPort("generalized_forces"),
                    placement.get_input_port())
    builder.Connect(placement.get_output_port(), total.get_input_port(0))
    builder.Connect(actuation_force, total.get_input_port(1))
    builder.Connect(total.get_output_port(), plant.get_applied_generalized_force_input_port())
    builder.ExportInput(simulated_hand.GetInputPort("hand_target"), "hand_target")
    builder.ExportInput(simulated_hand.GetInputPort("grip"), "hand_grip")
    builder.ExportOutput(simulated_hand.GetOutputPort("handle_gripped"), "handle_gripped")
    builder.ExportOutput(plant.get_state_output_port(hand), "hand_state")
    builder.ExportOutput(simulated_hand.GetOutputPort("wrench_on_instrument_W"),
                         "hand_wrench_on_instrument_W")
