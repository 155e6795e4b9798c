"""The identification flights of ``maglev calibrate plan``: what a fit needs, flown as
ordinary scenarios against any station.

Every flight starts with the instrument resting on a mark the display draws (its
pose in W known: the registration of the tracker's frame T), takes off, and flies
holds or steps:

- ``holds_*``: still poses over the workspace (positions, heights, tilts, yaws): at
  each, the coils' wrench balances the weight, which weighs each magnet's strength,
  each coil's wrench per ampere and the centre of mass;
- ``steps``: minimum-jerk steps in each of the six degrees of freedom about the
  centre: the accelerations, against the currents, time the tracker (its latency);
- ``payload``: level holds carrying a known payload (hung by the user; a simulated
  station adds it): it separates the instrument's mass from the wrench model's scale;
- ``check``: holds at poses no other flight visits, for ``maglev calibrate check``.

The flights keep every limit the application keeps (the watchdogs, the coils' thermal
budget); each waypoint is one ``check_pose_reachable`` accepts with its margin.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Dict, List

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from pydrake.common.yaml import yaml_dump, yaml_load_typed  # noqa: E402

from maglev_haptics.diagrams.motion import check_pose_reachable, flight_plan  # noqa: E402
from maglev_haptics.diagrams.scenario import MotionScript, ScenarioError  # noqa: E402
from maglev_haptics.hardware.device import DeviceConfig  # noqa: E402
from maglev_haptics.hardware.magnetics import load_magnetics  # noqa: E402

FLIGHTS_FILE = "calibration_flights.yaml"
MARKS_IMAGE = "mark_{flight}.png"  # one a flight: its rest mark, where the display shows it
REST_BEFORE_TAKEOFF_S = 1.5  # resting on its mark before the force ramp (s): the registration
HOLD_S = 1.2  # each still pose (s): the first HOLD_SETTLE_S settle, the rest is averaged
HOLD_SETTLE_S = 0.6  # (s)
MOVE_S = 0.6  # between holds (s)
STEP_MOVE_S = 0.12  # a step's minimum-jerk move (s): accelerations of ~1.5 m/s^2 at 4 mm
STEP_HOLD_S = 0.15  # (s)
STEP_SIZES = (0.004, 0.004, 0.004, 0.08, 0.08, 0.15)  # x, y, z (m), roll, pitch, yaw (rad)
STEP_REPEATS = 4  # steps out and back in each degree of freedom
HOVER_Z_M = 0.018  # the steps' centre (m)
PAYLOAD_KG = 0.020  # a 20 g calibration weight
PAYLOAD_P_I_M = (0.0, 0.0, 0.0)  # hung centred under I's origin (m, in I)
# Where the instrument rests before each flight: [x, y, yaw] in W (m, m, rad).
MARKS = ((-0.035, -0.03, 0.0), (0.035, -0.03, 0.5), (-0.035, 0.03, 1.0),
         (0.035, 0.03, 1.5), (0.0, 0.0, 0.8), (0.0, -0.035, -0.5), (0.0, 0.035, 0.3))
TAKEOFF_CHECK_Z_M = 0.010  # a mark must be holdable this high above it (m)


def _hold_grid() -> List[List[float]]:
    """Still poses [x, y, z, roll, pitch, yaw] (m, rad) across the workspace: a
    position grid at two heights, level and tilted each way, at three yaws."""
    poses = []
    for z in (0.012, 0.022):
        for x in (-0.025, 0.0, 0.025):
            for y in (-0.02, 0.0, 0.02):
                poses.append([x, y, z, 0.0, 0.0, 0.0])
    tilts = ((0.15, 0.0), (-0.15, 0.0), (0.0, 0.15), (0.0, -0.15))
    for i, (roll, pitch) in enumerate(tilts):
        for yaw in (0.0, 0.8, 1.6):
            x = 0.015 * math.cos(1.3 * i + yaw)
            y = 0.015 * math.sin(1.3 * i + yaw)
            poses.append([x, y, 0.020, roll, pitch, yaw])
    for yaw in (0.4, 1.2, 2.0, 2.8):
        poses.append([0.01 * math.cos(yaw), -0.01 * math.sin(yaw), 0.016, 0.0, 0.0, yaw])
    return poses


def _check_poses() -> List[List[float]]:
    """Poses no other flight visits, spread over the same workspace."""
    rng = np.random.default_rng(38)
    poses = []
    while len(poses) < 8:
        x, y = rng.uniform(-0.025, 0.025, 2)
        z = rng.uniform(0.013, 0.021)
        roll, pitch = rng.uniform(-0.12, 0.12, 2)
        yaw = rng.uniform(0, 2.5)
        poses.append([round(float(v), 4) for v in (x, y, z, roll, pitch, yaw)])
    return poses


def _waypoints(poses, move_s=MOVE_S, hold_s=HOLD_S) -> List[dict]:
    return [{"pose": [round(float(v), 6) for v in pose], "move_s": move_s, "hold_s": hold_s}
            for pose in poses]


def _steps() -> List[dict]:
    """Steps out and back in each degree of freedom about the hover pose."""
    centre = np.array([0.0, 0.0, HOVER_Z_M, 0.0, 0.0, 0.0])
    waypoints = _waypoints([centre], hold_s=0.5)
    for axis, size in enumerate(STEP_SIZES):
        for repeat in range(STEP_REPEATS):
            for sign in (1.0, -1.0):
                pose = centre.copy()
                pose[axis] += sign * size * (1.0 if repeat % 2 == 0 else 0.6)
                waypoints += _waypoints([pose], STEP_MOVE_S, STEP_HOLD_S)
        waypoints += _waypoints([centre], STEP_MOVE_S, 0.3)
    return waypoints


def _flight(name: str, mark, waypoints, payload_kg: float = 0.0) -> dict:
    calibration = {"flight": name}
    if payload_kg:
        calibration |= {"payload_kg": payload_kg, "payload_p_I_m": list(PAYLOAD_P_I_M)}
    return {"calibration": calibration,
            "motion": {"start_xy_yaw": list(mark), "takeoff_at_s": REST_BEFORE_TAKEOFF_S,
                       "waypoints": waypoints}}


def calibration_flights(instrument: str) -> Dict[str, dict]:
    """The plan's flights for ``instrument``: name -> the scenario's fields."""
    device = DeviceConfig(instrument=instrument)
    device.validate()
    magnetics = load_magnetics(device)
    holds = _hold_grid()
    marks = [[x, y, TAKEOFF_CHECK_Z_M, 0.0, 0.0, yaw] for x, y, yaw in MARKS]
    for i, pose in enumerate(holds + _check_poses() + marks):
        check_pose_reachable(pose, device, magnetics, f"calibration plan: pose {i}")
    groups = np.array_split(np.arange(len(holds)), 4)
    flights = {f"holds_{k + 1}": _flight("holds", MARKS[k], _waypoints([holds[i] for i in group]))
               for k, group in enumerate(groups)}
    flights["steps"] = _flight("steps", MARKS[4], _steps())
    level = [[x, y, z, 0.0, 0.0, 0.0] for z in (0.012, 0.022) for x, y in
             ((0.0, 0.0), (-0.025, 0.0), (0.025, 0.0))]
    flights["payload"] = _flight("payload", MARKS[5], _waypoints(level), PAYLOAD_KG)
    flights["check"] = _flight("check", MARKS[6], _waypoints(_check_poses()))
    for flight in flights.values():
        flight["device"] = {"instrument": instrument}
    return flights


def flight_seconds(flight: dict) -> float:
    """A flight's length (s): its motion script's, rest to ramp-down."""
    motion = yaml_load_typed(schema=MotionScript, data=yaml_dump(flight["motion"]))
    rest_height_m = DeviceConfig(instrument=flight["device"]["instrument"]).instrument_spec() \
        .rest_height_m
    return flight_plan(motion, rest_height_m).end_s


def write_plan(out_dir: Path, instrument: str) -> Dict[str, dict]:
    """Write the flights (FLIGHTS_FILE) and each one's rest mark (MARKS_IMAGE) into
    ``out_dir``; returns the flights."""
    flights = calibration_flights(instrument)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    header = ("# maglev calibrate plan: identification flights for the "
              f"{instrument} instrument.\n# Before each flight rest the instrument on its "
              "mark (mark_<flight>.png, shown full screen on the display).\n")
    (out_dir / FLIGHTS_FILE).write_text(header + yaml_dump(flights))
    for name, flight in flights.items():
        draw_mark(out_dir / MARKS_IMAGE.format(flight=name), DeviceConfig(instrument=instrument),
                  name, flight["motion"]["start_xy_yaw"])
    return flights


def draw_mark(path: Path, device: DeviceConfig, name: str, mark: List[float]) -> None:
    """An image at the display's resolution with the outline of the instrument's base
    where it rests at ``mark`` [x, y, yaw] (m, rad) in W (the display at its nominal
    pose, W's origin at its centre, x along its long edge)."""
    display = device.display
    if any(display.pose_W):
        raise ScenarioError("device.display.pose_W: the marks are drawn for a display at "
                            "W's origin; set pose_W to zeros to draw them")
    width_px, height_px = display.resolution_px
    width_m, height_m = display.size_m
    figure = plt.figure(figsize=(width_px / 100, height_px / 100), dpi=100)
    axes = figure.add_axes([0, 0, 1, 1])
    axes.set_xlim(-width_m / 2, width_m / 2)
    axes.set_ylim(-height_m / 2, height_m / 2)
    axes.set_facecolor("black")
    axes.set_axis_off()
    a, b, _ = device.instrument_spec().body_size_m
    outline = np.array([[-a / 2, -b / 2], [a / 2, -b / 2], [a / 2, b / 2], [-a / 2, b / 2],
                        [-a / 2, -b / 2]])
    x, y, yaw = mark
    rotation = np.array([[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]])
    corners = outline @ rotation.T + [x, y]
    axes.plot(corners[:, 0], corners[:, 1], color="white", linewidth=1)
    axes.plot([x, x + 0.6 * a / 2 * math.cos(yaw)], [y, y + 0.6 * a / 2 * math.sin(yaw)],
              color="orange", linewidth=1)  # I's x axis
    axes.plot(x, y, "+", color="orange", markersize=8)
    axes.text(0.0, -height_m / 2 + 0.01, f"{name}: rest the instrument in the outline, its "
              "magnets' row along the orange line", color="white", ha="center", fontsize=12)
    figure.savefig(path, dpi=100, facecolor="black")
    plt.close(figure)
