"""The scripted flight: rest, force ramp, waypoints, landing, ramp-down.

Turns a :class:`MotionScript` into C++ trajectories (no Python on the 1 kHz
path): the setpoint [x, y, z, roll, pitch, yaw] as minimum-jerk moves between
held poses, and the controller's enable gain as a ramp 0 -> 1 -> 0 (the safe
force ramp at haptics start and after touchdown).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import List, Tuple

import numpy as np
from pydrake.math import RollPitchYaw
from pydrake.trajectories import PiecewisePolynomial

from maglev_haptics.diagrams.scenario import ScenarioError
from maglev_haptics.hardware.constants import GRAVITY_M_S2
from maglev_haptics.systems.blends import (
    LANDING_PRESS_M, minimum_jerk_moves, minimum_jerk_samples)
from maglev_haptics.systems.current_allocator import allocate_currents

IDLE_AFTER_S = 0.2  # the script ends this long after the currents are ramped to zero
HOLD_MARGIN = 1.2  # a waypoint must be holdable with this multiple of the weight
MAX_TILT_DEG = 45.0  # the tilt range over which the wrench table is checked against magpylib


@dataclass
class FlightPlan:
    setpoint: PiecewisePolynomial  # 6 rows: pose of I in W (m, rad)
    enable: PiecewisePolynomial  # 1 row: controller gain 0..1
    holds: List[Tuple[float, float]]  # (start, end) of each waypoint hold (s)
    end_s: float  # the script's length: ramp-down complete plus IDLE_AFTER_S (s)


def rest_pose(start_xy_yaw, rest_height_m: float) -> np.ndarray:
    x, y, yaw = start_xy_yaw
    return np.array([x, y, rest_height_m, 0.0, 0.0, yaw])


def landing_poses(pose, rest_height_m: float) -> List[np.ndarray]:
    """The poses a landing from ``pose`` [x, y, z, roll, pitch, yaw] moves through:
    level first where tilted (so no edge of the base meets the glass first), then
    down to just below the rest height, over the same x, y and yaw."""
    pose = np.asarray(pose, dtype=float)
    poses = []
    if np.any(pose[3:5] != 0.0):
        poses.append(np.array([*pose[0:3], 0.0, 0.0, pose[5]]))
    poses.append(rest_pose([pose[0], pose[1], pose[5]], rest_height_m - LANDING_PRESS_M))
    return poses


def landing_planner(motion, rest_height_m: float):
    """``plan(pose, enable, period_s) -> commands`` of a landing from ``pose`` [x, y,
    z, roll, pitch, yaw] (m, rad) with force gain ``enable``, a row [pose (6); rates
    (6); force gain] a tick of ``period_s`` (s) from its start: ``landing_poses`` at
    ``motion``'s landing time each, its settling on the glass, then its force ramp
    down (a MotionScript's times)."""
    def plan(pose, enable: float, period_s: float):
        goals = landing_poses(pose, rest_height_m)
        down_s = len(goals) * motion.landing_s + motion.settle_s
        end_s = down_s + motion.force_ramp_s
        times_s = np.arange(math.ceil(round(end_s / period_s, 9)) + 1) * period_s
        values, rates = minimum_jerk_moves(pose, goals, motion.landing_s, times_s)
        return np.column_stack((values, rates, np.interp(
            times_s, [0.0, down_s, end_s], [enable, enable, 0.0])))
    return plan


def longest_landing_s(motion) -> float:
    """The longest a landing that ``landing_planner`` plans for ``motion`` takes, from
    a tilted pose, to the force ramped down and IDLE_AFTER_S more (s)."""
    return 2 * motion.landing_s + motion.settle_s + motion.force_ramp_s + IDLE_AFTER_S


def flight_plan(motion, rest_height_m: float) -> FlightPlan:
    """Setpoint and enable trajectories for ``motion`` (a MotionScript)."""
    times: List[float] = []
    values: List[np.ndarray] = []
    rates: List[np.ndarray] = []

    def hold(pose, t_from, t_to):
        for t in (t_from, t_to):
            if not times or t > times[-1]:
                times.append(t)
                values.append(np.asarray(pose, float))
                rates.append(np.zeros(6))

    def move(pose_from, pose_to, t_from, duration):
        for samples, new in zip((times, values, rates), minimum_jerk_samples(
                pose_from, pose_to, t_from, duration)):
            samples.extend(new)

    rest = rest_pose(motion.start_xy_yaw, rest_height_m)
    t = motion.takeoff_at_s + motion.force_ramp_s
    hold(rest, 0.0, t)
    pose = rest
    holds = []
    for waypoint in motion.waypoints:
        target = np.asarray(waypoint.pose, float)
        move(pose, target, t, waypoint.move_s)
        t += waypoint.move_s
        hold(target, t, t + waypoint.hold_s)
        holds.append((t, t + waypoint.hold_s))
        t += waypoint.hold_s
        pose = target
    for goal in landing_poses(pose, rest_height_m):
        move(pose, goal, t, motion.landing_s)
        t += motion.landing_s
        pose = goal
    t += motion.settle_s
    ramp_down_end = t + motion.force_ramp_s
    hold(pose, t, ramp_down_end)
    setpoint = PiecewisePolynomial.CubicHermite(
        np.array(times), np.array(values).T, np.array(rates).T)
    ramp_up_start = motion.takeoff_at_s
    enable = PiecewisePolynomial.FirstOrderHold(
        [0.0, ramp_up_start, ramp_up_start + motion.force_ramp_s, t, ramp_down_end,
         ramp_down_end + 1.0],
        np.array([[0.0, 0.0, 1.0, 1.0, 0.0, 0.0]]))
    return FlightPlan(setpoint=setpoint, enable=enable, holds=holds,
                      end_s=ramp_down_end + IDLE_AFTER_S)


def base_clearance_m(pose, spec) -> float:
    """Height (m) of the lowest corner of the instrument's base above the glass at ``pose``."""
    a, b, c = spec.body_size_m
    corners = np.array([[sx * a / 2, sy * b / 2, -c / 2] for sx in (-1, 1) for sy in (-1, 1)])
    R_WI = RollPitchYaw(np.asarray(pose[3:6], float)).ToRotationMatrix().matrix()
    return float(np.min(pose[2] + corners @ R_WI[2]))


def check_waypoints_reachable(motion, device, magnetics, label: str) -> None:
    """Raise ScenarioError for a waypoint inside the glass or not holdable within the
    limits (``check_pose_reachable``)."""
    for i, waypoint in enumerate(motion.waypoints):
        check_pose_reachable(waypoint.pose, device, magnetics,
                             f"{label}: motion.waypoints[{i}].pose")


def check_pose_reachable(pose_value, device, magnetics, field_name: str) -> None:
    """Raise ScenarioError naming ``field_name`` for a pose [x, y, z, roll, pitch, yaw]
    (m, rad) inside the glass, tilted beyond the model, or not holdable within the limits.

    Holdable means the coils can carry HOLD_MARGIN times the weight without any
    exceeding its limit, so control keeps some authority there.
    """
    spec = device.instrument_spec()
    limit = device.amplifier.current_limit_a
    lift = np.array([0.0, 0.0, HOLD_MARGIN * spec.mass_kg * GRAVITY_M_S2, 0.0, 0.0, 0.0])
    pose = np.asarray(pose_value, float)
    shown = pose.tolist()
    R_WI = RollPitchYaw(pose[3:6]).ToRotationMatrix().matrix()
    tilt_deg = np.degrees(np.arccos(np.clip(R_WI[2, 2], -1, 1)))
    if tilt_deg > MAX_TILT_DEG:
        raise ScenarioError(
            f"{field_name} = {shown}: tilt {tilt_deg:.1f} deg is beyond the "
            f"{MAX_TILT_DEG:.0f} deg the electromagnetic model is validated for (roll, pitch "
            "and yaw are in radians)")
    clearance = base_clearance_m(pose, spec)
    if clearance < 0:
        raise ScenarioError(
            f"{field_name} = {shown}: unreachable, the instrument's base would be "
            f"{-1e3 * clearance:.1f} mm inside the display glass (z must keep it above W's z = 0)")
    A = magnetics.wrench_matrix_from(pose[0:3] - device.p_WA, R_WI)
    if np.linalg.matrix_rank(A) < 6:
        cutoffs = magnetics.cutoffs()
        raise ScenarioError(
            f"{field_name} = {shown}: unreachable, the magnets are out of the "
            f"coils' reach there (the electromagnetic model covers magnets within "
            f"{1e3 * cutoffs['rho_max_m']:.0f} mm of a coil's axis and "
            f"{1e3 * cutoffs['z_max_m']:.0f} mm above its top)")
    _, shortfall, _ = allocate_currents(A, lift, limit)
    if np.linalg.norm(shortfall) > 1e-6 * lift[2]:
        minimum_power = np.max(np.abs(np.linalg.pinv(A) @ lift))
        raise ScenarioError(
            f"{field_name} = {shown}: unreachable, carrying {HOLD_MARGIN} x the "
            f"instrument's weight there takes {minimum_power:.3g} A in the busiest coil at "
            f"minimum power, and even spread over all coils it falls "
            f"{np.linalg.norm(shortfall):.3g} N short within the "
            f"{limit} A limit (device.amplifier.current_limit_a)")
