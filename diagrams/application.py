"""The application half (DESIGN.md section 1) wired to a station: the whole diagram.

``BuildDiagram(scenario)`` adds the station, the pose estimator, the scripted
setpoint and enable ramps, the levitation controller, the current allocator,
a haptic feed-forward wrench input (zero until a scene drives it), a logger at
``log_rate_hz`` and, when given a Meshcat, the visualizers.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, Optional

import numpy as np
from pydrake.geometry import Meshcat, MeshcatVisualizer, MeshcatVisualizerParams, Role
from pydrake.systems.framework import Diagram, DiagramBuilder
from pydrake.systems.primitives import (
    ConstantVectorSource, LogVectorOutput, Multiplexer, TrajectorySource)

from maglev_haptics.diagrams.motion import FlightPlan, check_waypoints_reachable, flight_plan
from maglev_haptics.diagrams.scenario import Scenario
from maglev_haptics.diagrams.station import MakeStation
from maglev_haptics.hardware.magnetics import load_magnetics
from maglev_haptics.systems.current_allocator import CurrentAllocator
from maglev_haptics.systems.device_visualizer import DeviceVisualizer
from maglev_haptics.systems.levitation_controller import LevitationController
from maglev_haptics.systems.pose_estimator import PoseEstimator

MESHCAT_PERIOD_S = 1 / 30


@dataclass
class BuiltDiagram:
    diagram: Diagram
    plan: FlightPlan
    logger: object  # one VectorLogSink of all logged signals, stacked
    log_layout: Dict[str, slice]  # name -> its rows in the logger's data
    magnetics: object


def BuildDiagram(scenario: Scenario, *, meshcat: Optional[Meshcat] = None,
                 label: str = "scenario") -> BuiltDiagram:
    """The whole diagram for ``scenario``; ``label`` names it in error messages."""
    device = scenario.device
    spec = device.instrument_spec()
    magnetics = load_magnetics(device)
    check_waypoints_reachable(scenario.motion, device, magnetics, label)
    builder = DiagramBuilder()
    station = builder.AddSystem(MakeStation(scenario, magnetics=magnetics))

    estimator = builder.AddNamedSystem("pose_estimator", PoseEstimator(
        instrument=spec, tracker=device.tracker, config=scenario.estimator))
    plan = flight_plan(scenario.motion, spec.rest_height_m)
    setpoint = builder.AddNamedSystem(
        "setpoint", TrajectorySource(plan.setpoint, output_derivative_order=1))
    enable = builder.AddNamedSystem("enable_ramp", TrajectorySource(plan.enable))
    feedforward = builder.AddNamedSystem("haptic_feedforward", ConstantVectorSource(np.zeros(6)))
    controller = builder.AddNamedSystem("levitation_controller", LevitationController(
        config=scenario.controller, mass_kg=spec.mass_kg,
        inertia_diag=np.diag(spec.inertia_about_I()),
        period_s=1.0 / scenario.control_rate_hz))
    allocator = builder.AddNamedSystem("current_allocator", CurrentAllocator(
        magnetics=magnetics, p_WA=device.p_WA,
        current_limit_a=device.amplifier.current_limit_a))

    builder.Connect(station.GetOutputPort("markers_measured"),
                    estimator.GetInputPort("markers_measured"))
    for name in ("X_WI_measured", "V_WI_measured", "tracking_ok"):
        builder.Connect(estimator.GetOutputPort(name), controller.GetInputPort(name))
    builder.Connect(setpoint.get_output_port(), controller.GetInputPort("setpoint"))
    builder.Connect(enable.get_output_port(), controller.GetInputPort("enable"))
    builder.Connect(feedforward.get_output_port(), controller.GetInputPort("wrench_feedforward_W"))
    builder.Connect(controller.GetOutputPort("wrench_commanded_W"),
                    allocator.GetInputPort("wrench_commanded_W"))
    builder.Connect(estimator.GetOutputPort("X_WI_measured"),
                    allocator.GetInputPort("X_WI_measured"))
    builder.Connect(allocator.GetOutputPort("coil_currents_commanded"),
                    station.GetInputPort("coil_currents_commanded"))

    logged_ports = {
        "instrument_state": station.GetOutputPort("instrument_state"),
        "X_WI_measured": estimator.GetOutputPort("X_WI_measured"),
        "V_WI_measured": estimator.GetOutputPort("V_WI_measured"),
        "tracking_ok": estimator.GetOutputPort("tracking_ok"),
        "setpoint": setpoint.get_output_port(),
        "coil_currents": station.GetOutputPort("coil_currents"),
        "wrench_commanded_W": controller.GetOutputPort("wrench_commanded_W"),
        "wrench_feedforward_W": feedforward.get_output_port(),
        "allocation_shortfall_W": allocator.GetOutputPort("allocation_shortfall_W"),
    }
    # One logger of the stacked signals: a publish event a tick instead of nine.
    sizes = [port.size() for port in logged_ports.values()]
    stack = builder.AddNamedSystem("log_stack", Multiplexer(sizes))
    for i, port in enumerate(logged_ports.values()):
        builder.Connect(port, stack.get_input_port(i))
    logger = LogVectorOutput(stack.get_output_port(), builder, 1.0 / scenario.log_rate_hz)
    logger.set_name("logger")
    ends = np.cumsum(sizes)
    log_layout = {name: slice(end - size, end)
                  for name, size, end in zip(logged_ports, sizes, ends)}

    if meshcat is not None:
        MeshcatVisualizer.AddToBuilder(
            builder, station.GetOutputPort("query_object"), meshcat,
            MeshcatVisualizerParams(publish_period=MESHCAT_PERIOD_S, role=Role.kIllustration))
        visualizer = builder.AddNamedSystem("device_visualizer", DeviceVisualizer(
            meshcat=meshcat, device=device, period_s=MESHCAT_PERIOD_S))
        builder.Connect(station.GetOutputPort("coil_currents"),
                        visualizer.GetInputPort("coil_currents"))
        builder.Connect(setpoint.get_output_port(), visualizer.GetInputPort("setpoint"))
        builder.Connect(estimator.GetOutputPort("X_WI_measured"),
                        visualizer.GetInputPort("X_WI_measured"))
        builder.Connect(station.GetOutputPort("markers_measured"),
                        visualizer.GetInputPort("markers_measured"))
    diagram = builder.Build()
    diagram.set_name("maglev_haptics")
    return BuiltDiagram(diagram=diagram, plan=plan, logger=logger, log_layout=log_layout,
                        magnetics=magnetics)
