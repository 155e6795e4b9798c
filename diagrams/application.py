"""The application half (docs/architecture.md) wired to a station: the whole diagram.

``BuildDiagram(scenario, mode=...)`` is a recipe, read top to bottom: ``AddStation``;
``AddApplication`` (the pose estimator, the coils' thermal model, the device
supervisor, which flies the motion script and lands on a fault, and the levitation
controller, which allocates the currents and commands the station); the commands
the controller tracks, ``AddLevitationCommands`` or, with haptics, ``AddHaptics`` (the
scene, coupling and supervisor, ``diagrams/haptics.py``); with a simulated hand
``AddHandCommands``; with the stereo display ``AddStereo``; ``AddLogging``; and,
given a Meshcat, ``AddVisualization``. Every choice comes from the scenario, the
station (what it is: ``diagrams/station_interface.py``) and one ``RunMode``.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field
from typing import Dict, List, Optional

import numpy as np
from pydrake.geometry import Meshcat, MeshcatVisualizer, MeshcatVisualizerParams, Rgba, Role
from pydrake.multibody.meshcat import ContactVisualizer, ContactVisualizerParams
from pydrake.systems.framework import Diagram, DiagramBuilder, LeafSystem, OutputPort
from pydrake.systems.primitives import (
    ConstantVectorSource, LogVectorOutput, Multiplexer, VectorLogSink)

from maglev_haptics.diagrams.haptics import AddHandCommands, AddHaptics, HapticParts
from maglev_haptics.diagrams.motion import (
    FlightPlan, check_waypoints_reachable, flight_plan, landing_planner)
from maglev_haptics.diagrams.scenario import Scenario
from maglev_haptics.diagrams.station import AddStation
from maglev_haptics.diagrams.station_interface import Station
from maglev_haptics.diagrams.stereo_display import AddStereoDisplay, StereoParts
from maglev_haptics.hardware.constants import GRAVITY_M_S2
from maglev_haptics.hardware.magnetics import MagneticsModel, load_magnetics
from maglev_haptics.hardware.thermal import coil_thermal
from maglev_haptics.systems.coil_thermal import CoilTemperatures
from maglev_haptics.systems.device_supervisor import (
    DeviceSupervisor, WatchLimits, hold_motion, make_motion)
from maglev_haptics.systems.device_visualizer import DeviceVisualizer
from maglev_haptics.systems.surface_visualizer import (
    JELLY_RGBA, SurfaceVisualizer, surface_faces, wire_rgba_of)
from maglev_haptics.systems.meshcat_hand import MeshcatHandInput
from maglev_haptics.systems.levitation_controller import LevitationController
from maglev_haptics.systems.pose_estimator import PoseEstimator
from maglev_haptics.systems.stereo_renderer import AddStereoRenderer, SurfaceLayer

MESHCAT_PERIOD_S = 1 / 30
# A paced run draws its frames between ticks (``diagrams/runner.py``), not in them:
# the visualizers' own periodic events then have a period no run reaches (s).
FRAMES_BETWEEN_TICKS_PERIOD_S = 1e6
# The coils' thermal model runs at 100 Hz: its time constant is ~1 min (s).
THERMAL_PERIOD_S = 0.01
# The device supervisor's watchdogs check at 200 Hz (s; its docstring says why).
WATCHDOG_PERIOD_S = 0.005


def watch_limits(scenario: Scenario) -> WatchLimits:
    """The supervisor's limits: the scenario's watchdog and the device's own."""
    watchdog = scenario.watchdog
    return WatchLimits(
        current_limit_a=scenario.device.amplifier.current_limit_a,
        temperature_limit_c=coil_thermal(scenario.device).max_c,
        max_speed_m_s=watchdog.max_speed_m_s,
        boundary_center_m=tuple(watchdog.boundary_center_m),
        boundary_radius_m=watchdog.boundary_radius_m)


class RunMode(enum.Enum):
    """How the diagram will be run: the one choice ``BuildDiagram`` takes besides the
    scenario."""
    SIMULATE = "simulate"  # as fast as it goes, or stepped: visualizers publish themselves
    # Paced to the wall clock: Meshcat's frames are the runner's, between ticks, and the
    # stereo display may skip a frame rather than make a tick late.
    PACED = "paced"
    # The device API commands: the supervisor rests on the glass, coils off, until told,
    # and the feed-forward wrench is a source it sets.
    DEVICE_API = "device_api"
    # The loop's offline analysis: a scripted hand's target takes an exported offset,
    # ``hand_target_offset`` (the user's motion as the loop's input), which the caller fixes.
    LINEARIZE = "linearize"


@dataclass
class ApplicationParts:
    """The application's systems on the device's loop, and the scripted command."""
    estimator: PoseEstimator
    temperatures: CoilTemperatures
    supervisor: DeviceSupervisor
    controller: LevitationController
    scripted_setpoint: object  # the device supervisor's setpoint output port
    scripted_enable: object  # and its force-ramp output port


def AddApplication(builder: DiagramBuilder, *, scenario: Scenario, station: Station, magnetics,
                   plan: FlightPlan, device_api: bool, label: str) -> ApplicationParts:
    """The pose estimator, the coils' thermal model, the device supervisor (which flies
    ``plan``, or with ``device_api`` rests on the glass, coils off, until the API
    commands) and the levitation controller, wired to ``station`` and each other; the
    controller commands the station's coils."""
    device = scenario.device
    spec = device.instrument_spec()
    tick_s = 1.0 / scenario.control_rate_hz
    estimator = builder.AddNamedSystem("pose_estimator", PoseEstimator(
        instrument=spec, tracker=device.tracker, tick_s=tick_s, config=scenario.estimator))
    if device_api:  # resting on the glass, coils off, until the API commands
        if scenario.haptics is not None:
            raise ValueError(f"{label}: the device API flies levitation scenarios only "
                             "(haptics: null)")
        initial_motion = hold_motion(np.concatenate((plan.setpoint.value(0.0).ravel(),
                                                     np.zeros(6))), 0.0, 0.0, tick_s)
    else:
        initial_motion = make_motion(plan.setpoint, plan.enable, 0.0, tick_s)
    temperatures = builder.AddNamedSystem("coil_temperatures", CoilTemperatures(
        model=coil_thermal(device), n_coils=device.n_coils, period_s=THERMAL_PERIOD_S))
    builder.Connect(station.GetOutputPort("coil_currents"), temperatures.get_input_port())
    supervisor = builder.AddNamedSystem("device_supervisor", DeviceSupervisor(
        initial_motion=initial_motion, limits=watch_limits(scenario),
        lost_grace_s=scenario.controller.lost_grace_s,
        plan_landing=landing_planner(scenario.motion, spec.rest_height_m),
        n_coils=device.n_coils, watchdog_period_s=WATCHDOG_PERIOD_S,
        weight_n=spec.mass_kg * GRAVITY_M_S2,
        measured_lag_ticks=station.measured_currents_lag_ticks))
    for name in ("X_WI_measured", "V_WI_measured", "tracking_ok"):
        builder.Connect(estimator.GetOutputPort(name), supervisor.GetInputPort(name))
    for name in ("coil_currents", "coil_currents_age_s"):
        builder.Connect(station.GetOutputPort(name), supervisor.GetInputPort(name))
    builder.Connect(temperatures.get_output_port(), supervisor.GetInputPort("coil_temperature_c"))
    controller = builder.AddNamedSystem("levitation_controller", LevitationController(
        config=scenario.controller, mass_kg=spec.mass_kg,
        inertia_diag=np.diag(spec.inertia_about_I()),
        magnetics=magnetics, p_WA=device.p_WA,
        current_limit_a=device.amplifier.current_limit_a, thermal=coil_thermal(device)))
    builder.Connect(temperatures.get_output_port(), controller.GetInputPort("coil_temperature_c"))
    for name in ("thermally_limited", "coil_currents_commanded", "allocation_shortfall_W"):
        builder.Connect(controller.GetOutputPort(name), supervisor.GetInputPort(name))
    builder.Connect(supervisor.GetOutputPort("coils_stuck"), controller.GetInputPort("coils_stuck"))
    builder.Connect(supervisor.GetOutputPort("coil_power"), station.GetInputPort("coil_power"))
    builder.Connect(station.GetOutputPort("coil_currents"),
                    controller.GetInputPort("coil_currents"))
    for name in ("markers_measured", "markers_sample_time_s", "markers_sample_count"):
        builder.Connect(station.GetOutputPort(name), estimator.GetInputPort(name))
    for name in ("X_WI_measured", "V_WI_measured", "tracking_ok"):
        builder.Connect(estimator.GetOutputPort(name), controller.GetInputPort(name))
    builder.Connect(supervisor.GetOutputPort("tracking_lost_s"),
                    controller.GetInputPort("tracking_lost_s"))
    builder.Connect(controller.GetOutputPort("coil_currents_commanded"),
                    station.GetInputPort("coil_currents_commanded"))
    return ApplicationParts(
        estimator=estimator, temperatures=temperatures, supervisor=supervisor,
        controller=controller, scripted_setpoint=supervisor.GetOutputPort("setpoint"),
        scripted_enable=supervisor.GetOutputPort("enable"))


@dataclass
class LevitationCommands:
    """What the controller tracks without haptics: the script's setpoint, and the
    feed-forward wrench's source (the device API sets it)."""
    setpoint: OutputPort
    feedforward: ConstantVectorSource  # 6: [f; tau] in W (N, N*m), zero unless set


def AddLevitationCommands(builder: DiagramBuilder, *, app: ApplicationParts) -> LevitationCommands:
    """Without haptics the controller flies the script at full PD, no brake, and a
    feed-forward wrench (``haptic_feedforward``) that stays zero unless the device API
    sets it."""
    controller = app.controller
    builder.Connect(app.scripted_setpoint, controller.GetInputPort("setpoint"))
    builder.Connect(app.scripted_enable, controller.GetInputPort("enable"))
    sources = {}
    for name, port, value in (("pd_gain", "pd_gain", [1.0]),
                              ("brake_gain", "brake_gain", [0.0]),
                              ("haptic_feedforward", "wrench_feedforward_W", np.zeros(6))):
        sources[name] = builder.AddNamedSystem(name, ConstantVectorSource(value))
        builder.Connect(sources[name].get_output_port(), controller.GetInputPort(port))
    return LevitationCommands(setpoint=app.scripted_setpoint,
                              feedforward=sources["haptic_feedforward"])


def AddStereo(builder: DiagramBuilder, *, scenario: Scenario, station: Station, haptics,
              meshcat: Optional[Meshcat], frame_period_s: float, frame_sink,
              realtime: bool):
    """The stereo display (``diagrams/stereo_display.py``) of the virtual world: the
    scene's, with the lattice's surface over it, or without a scene the instrument
    where it is tracked (it should sit exactly on the real one)."""
    surface = None
    if haptics is not None:
        AddStereoRenderer(haptics.scene.scene_graph)
        virtual_world = haptics.scene.scene_graph.get_query_output_port()
        if haptics.scene.surface is not None:
            lattice = haptics.scene.lattice
            surface = (SurfaceLayer(
                surface_faces(lattice.surface, lattice.surface_triangles).T,
                (JELLY_RGBA.r(), JELLY_RGBA.g(), JELLY_RGBA.b(), JELLY_RGBA.a())),
                haptics.scene.surface.GetOutputPort("surface_positions_m"))
        elif haptics.scene.tissue:
            # The stereo renderer lays one deformable surface over the scene: the first.
            tissue = haptics.scene.tissue[0]
            surface = (SurfaceLayer(tissue.faces.T, tuple(tissue.body.rgba)),
                       tissue.system.GetOutputPort("surface_positions_m"))
    else:
        virtual_world = station.GetOutputPort("rendered_world")
    return AddStereoDisplay(builder, scenario=scenario, station=station,
                            query_object_port=virtual_world, meshcat=meshcat,
                            frame_period_s=frame_period_s, frame_sink=frame_sink,
                            realtime=realtime, surface=surface)


def AddLogging(builder: DiagramBuilder, *, scenario: Scenario, station: Station,
               app: ApplicationParts, setpoint, haptics, stereo):
    """(logger, layout): one logger of every logged signal stacked, sampled at
    ``log_rate_hz``; ``layout`` maps each name to its rows."""
    estimator, controller, supervisor = app.estimator, app.controller, app.supervisor
    simulated = station.simulated
    # What only a simulation knows (the true state, the hand's) is logged only there.
    logged_ports = {"instrument_state": station.GetOutputPort("instrument_state")} \
        if simulated else {}
    logged_ports |= {
        "X_WI_measured": estimator.GetOutputPort("X_WI_measured"),
        "V_WI_measured": estimator.GetOutputPort("V_WI_measured"),
        "tracking_ok": estimator.GetOutputPort("tracking_ok"),
        "setpoint": setpoint,
        "coil_currents": station.GetOutputPort("coil_currents"),
        "wrench_commanded_W": controller.GetOutputPort("wrench_commanded_W"),
        "wrench_rendered_W": controller.GetOutputPort("wrench_rendered_W"),
        "allocation_shortfall_W": controller.GetOutputPort("allocation_shortfall_W"),
        "coil_temperature_c": app.temperatures.get_output_port(),
        "fault_bits": supervisor.GetOutputPort("fault_bits"),
        "coil_power": supervisor.GetOutputPort("coil_power"),
    }
    if scenario.calibration is not None:  # what a calibration fits the device to
        for name in ("markers_measured", "markers_sample_time_s", "coil_temperature_reported_c"):
            logged_ports[name] = station.GetOutputPort(name)
    if scenario.hand is not None:
        logged_ports["handle_gripped"] = station.GetOutputPort("handle_gripped")
    if scenario.hand is not None and simulated:
        logged_ports["hand_state"] = station.GetOutputPort("hand_state")
        logged_ports["hand_wrench_on_instrument_W"] = station.GetOutputPort(
            "hand_wrench_on_instrument_W")
    if stereo is not None:
        if simulated:  # the true head
            logged_ports["head_pose"] = station.GetOutputPort("head_pose")
        logged_ports["glasses_measured"] = station.GetOutputPort("glasses_measured")
        for name in ("X_WG_predicted", "X_WG_latest"):
            logged_ports[name] = stereo.predictor.GetOutputPort(name)
        for name in ("eye_positions_W", "view_ok"):
            logged_ports[name] = stereo.view.GetOutputPort(name)
    if haptics is not None:
        logged_ports["X_WT"] = haptics.scene.X_WT_output
        logged_ports["tool_contact_wrench_W"] = haptics.scene.contact_wrench_output
        logged_ports["tool_in_contact"] = haptics.scene.in_contact_output
        logged_ports["haptic_mode"] = haptics.supervisor.GetOutputPort("mode")
        logged_ports["coupling_clamped"] = haptics.coupling.GetOutputPort("coupling_clamped")
        logged_ports["passivity_dissipated_j"] = haptics.coupling.GetOutputPort(
            "passivity_dissipated_j")
    # One logger of the stacked signals: a publish event a tick instead of nine.
    sizes = [port.size() for port in logged_ports.values()]
    stack = builder.AddNamedSystem("log_stack", Multiplexer(sizes))
    for i, port in enumerate(logged_ports.values()):
        builder.Connect(port, stack.get_input_port(i))
    # Read in the logger's publish at the end of each step: from the state the next
    # tick's update reads, whose values it computes and caches for that update (one
    # Simulator step a tick), so the log adds no Python call.
    log_period_s = 1.0 / scenario.log_rate_hz
    logger = LogVectorOutput(stack.get_output_port(), builder, log_period_s)
    logger.set_name("logger")
    ends = np.cumsum(sizes)
    return logger, {name: slice(end - size, end)
                    for name, size, end in zip(logged_ports, sizes, ends)}


def AddVisualization(builder: DiagramBuilder, *, scenario: Scenario, meshcat: Meshcat,
                     station: Station, app: ApplicationParts, setpoint, haptics,
                     frame_period_s: float) -> List[LeafSystem]:
    """Meshcat's layers: the true instrument and the glass (a simulated station's), the
    device's overlay (coils, measured markers and pose, setpoint, rendered wrench), the
    scene, its contact forces and the lattice's surface. Returns the visualizers, each
    publishing every ``frame_period_s`` (s)."""
    frame_publishers = []
    if station.simulated:  # the true instrument and the glass; the measured one is drawn below
        frame_publishers.append(MeshcatVisualizer.AddToBuilder(
            builder, station.GetOutputPort("query_object"), meshcat,
            MeshcatVisualizerParams(publish_period=frame_period_s, role=Role.kIllustration)))
    visualizer = builder.AddNamedSystem("device_visualizer", DeviceVisualizer(
        meshcat=meshcat, device=scenario.device, period_s=frame_period_s,
        close_view=scenario.haptics is not None))
    frame_publishers.append(visualizer)
    builder.Connect(station.GetOutputPort("coil_currents"),
                    visualizer.GetInputPort("coil_currents"))
    builder.Connect(setpoint, visualizer.GetInputPort("setpoint"))
    builder.Connect(app.estimator.GetOutputPort("X_WI_measured"),
                    visualizer.GetInputPort("X_WI_measured"))
    builder.Connect(station.GetOutputPort("markers_measured"),
                    visualizer.GetInputPort("markers_measured"))
    builder.Connect(app.controller.GetOutputPort("wrench_rendered_W"),
                    visualizer.GetInputPort("wrench_rendered_W"))
    if haptics is None:
        return frame_publishers
    frame_publishers.append(MeshcatVisualizer.AddToBuilder(
        builder, haptics.scene.scene_graph.get_query_output_port(), meshcat,
        MeshcatVisualizerParams(publish_period=frame_period_s, role=Role.kIllustration,
                                prefix="scene")))
    scene = haptics.scene
    # A scene stepped by a worker process has its contact results there: no
    # contact forces drawn (the device's overlay draws the rendered wrench).
    if scene.surface is None and scene.worker is None:
        frame_publishers.append(ContactVisualizer.AddToBuilder(
            builder, scene.plant, meshcat,
            ContactVisualizerParams(publish_period=frame_period_s, prefix="contact",
                                    newtons_per_meter=10.0, newton_meters_per_meter=1.0)))
    elif scene.surface is not None:
        # The lattice is no geometry of the scene plant: it draws itself.
        config = scenario.haptics.scene
        lattice = scene.lattice
        top = lattice.positions_m[lattice.surface.ravel()]
        surface_visualizer = builder.AddNamedSystem("lattice_visualizer", SurfaceVisualizer(
            meshcat=meshcat, faces=surface_faces(lattice.surface, lattice.surface_triangles),
            num_vertices=lattice.surface.size, p_TP_m=config.tool_offset_m,
            probe_radius_m=config.probe.radius_m,
            camera_target_m=[np.mean(lattice.x_m), np.mean(lattice.y_m), np.mean(top[:, 2])],
            period_s=frame_period_s))
        frame_publishers.append(surface_visualizer)
        for name in ("surface_positions_m", "wrench_on_tool_W"):
            builder.Connect(scene.surface.GetOutputPort(name),
                            surface_visualizer.GetInputPort(name))
        builder.Connect(scene.X_WT_output, surface_visualizer.GetInputPort("X_WT"))
    config = scenario.haptics.scene
    for i, tissue in enumerate(scene.tissue):
        # Tissue is no geometry of the scene plant either: each body draws itself.
        p_TP, radius_m = config.tissue.sphere(config.tool, "haptics.scene.tissue")
        rgba = Rgba(*tissue.body.rgba)
        nodes = tissue.body.positions_m
        top = [*nodes[:, 0:2].mean(axis=0), nodes[:, 2].max()]  # the first body's, looked at
        visualizer = builder.AddNamedSystem(f"{tissue.system.get_name()}_visualizer",
                                            SurfaceVisualizer(
            meshcat=meshcat, faces=tissue.faces, num_vertices=len(tissue.model.surface),
            p_TP_m=p_TP, probe_radius_m=radius_m, rgba=rgba, wire_rgba=wire_rgba_of(rgba),
            path=f"/tissue/{tissue.body.model}", camera_target_m=top if i == 0 else None,
            period_s=frame_period_s))
        frame_publishers.append(visualizer)
        for name in ("surface_positions_m", "wrench_on_tool_W"):
            builder.Connect(tissue.system.GetOutputPort(name), visualizer.GetInputPort(name))
        builder.Connect(scene.X_WT_output, visualizer.GetInputPort("X_WT"))
    return frame_publishers


@dataclass
class BuiltDiagram:
    """The whole diagram and its typed parts (``BuildDiagram``)."""
    diagram: Diagram
    plan: FlightPlan
    station: Station
    app: ApplicationParts
    logger: VectorLogSink  # one logger of all logged signals, stacked
    log_layout: Dict[str, slice]  # name -> its rows in the logger's data
    magnetics: MagneticsModel
    tick_s: float  # the control period: the real-time loop's tick (s)
    levitation: Optional[LevitationCommands] = None  # without haptics
    haptics: Optional[HapticParts] = None  # with haptics
    meshcat_hand: Optional[MeshcatHandInput] = None  # whose controls to delete after a run
    stereo: Optional[StereoParts] = None
    # Paced runs: the visualizers the runner publishes every MESHCAT_PERIOD_S between ticks.
    frame_publishers: List[LeafSystem] = field(default_factory=list)
    meshcat: Optional[Meshcat] = None  # the one given, if any


def BuildDiagram(scenario: Scenario, *, mode: RunMode = RunMode.SIMULATE,
                 meshcat: Optional[Meshcat] = None, label: str = "scenario",
                 frame_sink=None) -> BuiltDiagram:
    """The whole diagram for ``scenario``, built for ``mode``; ``label`` names it in
    error messages. With the stereo display, ``frame_sink(t, left, right)`` receives
    the rendered eye images (none rendered without it)."""
    device = scenario.device
    magnetics = load_magnetics(device)
    check_waypoints_reachable(scenario.motion, device, magnetics, label)
    plan = flight_plan(scenario.motion, device.instrument_spec().rest_height_m)
    paced = mode is RunMode.PACED
    builder = DiagramBuilder()
    station = AddStation(builder, scenario=scenario, magnetics=magnetics)
    app = AddApplication(builder, scenario=scenario, station=station, magnetics=magnetics,
                         plan=plan, device_api=mode is RunMode.DEVICE_API, label=label)
    levitation = haptics = None
    if scenario.haptics is None:
        commands = levitation = AddLevitationCommands(builder, app=app)
    else:
        commands = haptics = AddHaptics(
            builder, scenario=scenario, magnetics=magnetics, station=station,
            estimator=app.estimator, controller=app.controller,
            scripted_setpoint=app.scripted_setpoint, scripted_enable=app.scripted_enable,
            fault_bits=app.supervisor.GetOutputPort("fault_bits"))
    meshcat_hand = None
    if scenario.hand is not None and station.simulated:  # else the device moves the hand
        meshcat_hand = AddHandCommands(builder, scenario=scenario, station=station,
                                       meshcat=meshcat,
                                       target_offset_input=mode is RunMode.LINEARIZE)
    frame_period_s = FRAMES_BETWEEN_TICKS_PERIOD_S if paced else MESHCAT_PERIOD_S
    stereo = None
    if scenario.stereo is not None:
        stereo = AddStereo(builder, scenario=scenario, station=station, haptics=haptics,
                           meshcat=meshcat, frame_period_s=frame_period_s,
                           frame_sink=frame_sink, realtime=paced)
    logger, log_layout = AddLogging(builder, scenario=scenario, station=station, app=app,
                                    setpoint=commands.setpoint, haptics=haptics, stereo=stereo)
    frame_publishers = [stereo.visualizer] if stereo is not None and stereo.visualizer else []
    if meshcat is not None:
        frame_publishers += AddVisualization(
            builder, scenario=scenario, meshcat=meshcat, station=station, app=app,
            setpoint=commands.setpoint, haptics=haptics, frame_period_s=frame_period_s)
    diagram = builder.Build()
    diagram.set_name("maglev_haptics")
    return BuiltDiagram(diagram=diagram, plan=plan, station=station, app=app, logger=logger,
                        log_layout=log_layout, magnetics=magnetics,
                        tick_s=1.0 / scenario.control_rate_hz, levitation=levitation,
                        haptics=haptics, meshcat_hand=meshcat_hand, stereo=stereo,
                        frame_publishers=frame_publishers if paced else [], meshcat=meshcat)
