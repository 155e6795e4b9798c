"""From the logger to ``log.npz`` arrays, and from those to the run's summary numbers."""

from __future__ import annotations

import math
from typing import Dict, Optional

import numpy as np
from scipy.spatial.transform import Rotation

from maglev_haptics.diagrams.motion import FlightPlan
from maglev_haptics.hardware.thermal import (
    coil_thermal, steady_state_temperature_c, weakest_coil_current_limit_a, winding_resistance_ohm)
from maglev_haptics.systems.haptic_supervisor import HAPTIC
from maglev_haptics.systems.rotations import rotation_matrix, rotations_of_quaternions

HOVER_SETTLE_S = 0.5  # skipped at the start of each hold before hover errors count (s)
HOLD_POSE_TOLERANCE = 1e-6  # the commanded pose is the hold's within this (m, rad)
HOLD_CUT_SHORT_S = 0.002  # a hold flown to within this of its end was flown whole (s)


def rpy_from_quaternions(q: np.ndarray) -> np.ndarray:
    """(N, 3) roll-pitch-yaw (rad, each unwrapped over time) from (N, 4) [w, x, y, z]."""
    rpy = rotations_of_quaternions(q).as_euler("xyz")  # extrinsic: Drake's roll-pitch-yaw
    return np.unwrap(rpy, axis=0)


def log_arrays(logger, log_layout, context, device) -> Dict[str, np.ndarray]:
    """The run's log as named arrays; the public contract's keys first (docs/haptic_loop.md, "What a run writes")."""
    log = logger.FindLog(context)
    return log_arrays_from(log.sample_times(), log.data(), log_layout, coil_thermal(device))


def log_arrays_from(times: np.ndarray, samples: np.ndarray, log_layout,
                    thermal) -> Dict[str, np.ndarray]:
    """``log_arrays`` from the logger's sample times (N,) [s] and samples (rows, N),
    ``log_layout`` (name -> its rows) and the coils' ``thermal`` model."""
    data = {name: samples[rows].T for name, rows in log_layout.items()}
    if len(times) < 2:
        raise ValueError(f"the run logged {len(times)} sample(s) in {times[-1] if len(times) else 0} "
                         "s: simulate at least two log periods")
    t = times
    measured = data["X_WI_measured"]
    rendered = data["wrench_rendered_W"]
    engaged = (data["haptic_mode"][:, 0] == HAPTIC if "haptic_mode" in data
               else np.zeros(len(t), dtype=bool))
    user_wrench = rendered * engaged[:, None]
    currents = data["coil_currents"]
    temperatures = data["coil_temperature_c"]  # the loop's thermal model's
    return {
        "t": t,
        "p_WI_measured": measured[:, 4:7],
        "rpy_WI_measured": rpy_from_quaternions(measured[:, 0:4]),
        **_truth(data),
        # What the device renders on the hand beyond carrying the weight while
        # haptics is engaged; zero otherwise (levitation has no user's wrench).
        "f_user": user_wrench[:, 0:3],
        "tau_user": user_wrench[:, 3:6],
        "coil_currents": currents,
        "coil_power_w": np.sum(winding_resistance_ohm(thermal, temperatures) * currents**2, axis=1),
        "coil_temperature_c": temperatures,
        "p_WI_desired": data["setpoint"][:, 0:3],
        "rpy_WI_desired": data["setpoint"][:, 3:6],
        "q_WI_measured": measured[:, 0:4],
        "V_WI_measured": data["V_WI_measured"],
        "tracking_ok": data["tracking_ok"][:, 0],
        "fault_bits": data["fault_bits"][:, 0].astype(np.int64),
        "coil_power": data["coil_power"][:, 0],  # the coils' supply: 1 on, 0 cut
        "wrench_commanded_W": data["wrench_commanded_W"],
        "wrench_rendered_W": rendered,
        "allocation_shortfall_W": data["allocation_shortfall_W"],
        **_optional_arrays(data),
    }


def _truth(data) -> Dict[str, np.ndarray]:
    """p, rpy, q and V of I in W from the true state, which only a simulated station
    has; NaN with a station on LCM (log.npz keeps the contract's keys)."""
    if "instrument_state" not in data:
        n = len(data["X_WI_measured"])
        return {f"{name}_WI_true": np.full((n, size), np.nan)
                for name, size in (("p", 3), ("rpy", 3), ("q", 4), ("V", 6))}
    state = data["instrument_state"]
    return {"p_WI_true": state[:, 4:7], "rpy_WI_true": rpy_from_quaternions(state[:, 0:4]),
            "q_WI_true": state[:, 0:4], "V_WI_true": state[:, 7:13]}


def recorded_pose(log: Dict[str, np.ndarray]):
    """(p_WI, q_WI, V_WI, source) that the metrics read: the true pose where the
    station is simulated, the tracker's estimate ("measured") where it is not."""
    if not np.all(np.isnan(log["p_WI_true"])):
        return log["p_WI_true"], log["q_WI_true"], log["V_WI_true"], "true"
    return log["p_WI_measured"], log["q_WI_measured"], log["V_WI_measured"], "measured"


def _optional_arrays(data) -> Dict[str, np.ndarray]:
    """The hand's, the scene's and the stereo display's logs, where the scenario has them."""
    arrays = {}
    if "markers_sample_time_s" in data:  # a calibration flight's
        arrays["markers_measured"] = data["markers_measured"]
        arrays["markers_sample_time_s"] = data["markers_sample_time_s"][:, 0]
        arrays["coil_temperature_reported_c"] = data["coil_temperature_reported_c"]
    if "handle_gripped" in data:
        arrays["handle_gripped"] = data["handle_gripped"][:, 0]
    if "hand_state" in data:
        arrays["p_WH_true"] = data["hand_state"][:, 4:7]
        arrays["hand_wrench_on_instrument_W"] = data["hand_wrench_on_instrument_W"]
    if "X_WT" in data:
        arrays["p_WT"] = data["X_WT"][:, 4:7]
        arrays["q_WT"] = data["X_WT"][:, 0:4]
        arrays["tool_contact_wrench_W"] = data["tool_contact_wrench_W"]
        arrays["tool_in_contact"] = data["tool_in_contact"][:, 0]
        arrays["haptic_mode"] = data["haptic_mode"][:, 0]
        arrays["coupling_clamped"] = data["coupling_clamped"][:, 0]
        arrays["passivity_dissipated_j"] = data["passivity_dissipated_j"][:, 0]
    if "head_pose" in data:
        arrays["head_pose"] = data["head_pose"]
    if "glasses_measured" in data:
        arrays["glasses_measured"] = data["glasses_measured"]
        arrays["X_WG_predicted"] = data["X_WG_predicted"]
        arrays["X_WG_latest"] = data["X_WG_latest"]
        arrays["eye_positions_W"] = data["eye_positions_W"]
        arrays["view_ok"] = data["view_ok"][:, 0]
    return arrays


def angle_between_deg(q_WI: np.ndarray, rpy_WD: np.ndarray) -> np.ndarray:
    """Rotation angle (deg) between each measured/true orientation and the setpoint."""
    R_DI = Rotation.from_euler("xyz", rpy_WD).inv() * rotations_of_quaternions(q_WI)
    return np.degrees(R_DI.magnitude())


AIRBORNE_M = 1e-3  # above the rest height by this much counts as flying (m)


def first_touchdown(log: Dict[str, np.ndarray], rest_height_m: float):
    """Time, speed and tilt when the instrument first comes back down onto the glass.

    Any return counts, scripted or not: a lost instrument's drop is reported the
    same way as a landing. None if it never flew or never came back.
    """
    p_WI, q_WI, V_WI, _ = recorded_pose(log)
    z = p_WI[:, 2]
    airborne = z > rest_height_m + AIRBORNE_M
    if not airborne.any():
        return None
    down = (np.arange(len(z)) > np.argmax(airborne)) & (z <= rest_height_m)
    if not down.any():
        return None
    k = int(np.argmax(down))
    R_WI = rotation_matrix(q_WI[k]).matrix()
    return {"time_s": float(log["t"][k]),
            "speed_m_s": float(np.linalg.norm(V_WI[k, 3:6])),
            "tilt_deg": float(np.degrees(np.arccos(np.clip(R_WI[2, 2], -1.0, 1.0))))}


COILS_OFF_A = 1e-3  # every coil within this of zero counts as off (A)


def final_state(log: Dict[str, np.ndarray], rest_height_m: float) -> Dict:
    """Where the run left the instrument, as its last logged sample shows: its height
    ``z_m`` (m, the recorded pose's), the busiest coil's current (A), and whether it
    ``rests`` on the glass with every coil off (what a landing must end in)."""
    p_WI, _, _, _ = recorded_pose(log)
    z_m = float(p_WI[-1, 2])
    busiest_a = float(np.max(np.abs(log["coil_currents"][-1])))
    return {"z_m": z_m, "busiest_coil_current_a": busiest_a,
            "rests": bool(z_m <= rest_height_m + AIRBORNE_M and busiest_a < COILS_OFF_A)}


def for_people(value, digits: int = 6):
    """``value`` (a number, or dicts and lists of them) with each float rounded to
    ``digits`` significant digits: 6.6, not 6.6000000000000005."""
    if isinstance(value, float):
        return float(f"{value:.{digits}g}") if math.isfinite(value) else value
    if isinstance(value, dict):
        return {key: for_people(item, digits) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [for_people(item, digits) for item in value]
    return value


def hold_window(log: Dict[str, np.ndarray], plan: FlightPlan, start: float, end: float,
                rest_height_m: float) -> np.ndarray:
    """The samples of the hold from ``start`` to ``end`` (s) that count as hovering:
    after HOVER_SETTLE_S (or half a short hold), with the instrument in the air and
    the hold's pose still commanded (not a run stopped before takeoff, not a landing
    after a fault)."""
    t = log["t"]
    p_WI, _, _, _ = recorded_pose(log)
    pose = plan.setpoint.value(start).ravel()
    commanded = np.hstack((log["p_WI_desired"], log["rpy_WI_desired"]))
    return ((t >= start + min(HOVER_SETTLE_S, (end - start) / 2)) & (t <= end)
            & (p_WI[:, 2] > rest_height_m + AIRBORNE_M)
            & np.all(np.abs(commanded - pose) < HOLD_POSE_TOLERANCE, axis=1))


def _finite_or_none(value):
    """JSON has no infinity: a float, or None where ``value`` is not finite."""
    return float(value) if np.isfinite(value) else None


def summarize(log: Dict[str, np.ndarray], plan: FlightPlan, *, rest_height_m: float,
              thermal, holds_before_s: Optional[float] = None) -> Dict:
    """Hover accuracy per hold, hover currents, power and heating, touchdown speed, limits.

    Holds count up to ``holds_before_s`` (s; when haptics starts, the hand moves
    the instrument and hover accuracy no longer means anything).
    """
    t = log["t"]
    p_WI, q_WI, _, source = recorded_pose(log)
    holds = []
    for start, end in plan.holds:
        if holds_before_s is not None:
            end = min(end, holds_before_s)
            if end <= start:
                continue
        window = hold_window(log, plan, start, end, rest_height_m)
        if not window.any():
            continue
        position_error = p_WI[window] - log["p_WI_desired"][window]
        angle_error = angle_between_deg(q_WI[window], log["rpy_WI_desired"][window])
        estimate_error = log["p_WI_measured"][window] - p_WI[window]
        # A hold the run ended, or a fault's landing cut short, ends where it was last
        # flown (s).
        flown_end_s = min(float(end), float(t[window][-1]))
        holds.append({
            "start_s": float(start), "end_s": flown_end_s,
            "cut_short": bool(flown_end_s < end - HOLD_CUT_SHORT_S),
            "pose_desired": [*map(float, log["p_WI_desired"][window][0]),
                             *map(float, log["rpy_WI_desired"][window][0])],
            "position_error_rms_mm": float(1e3 * np.sqrt(np.mean(np.sum(position_error**2, 1)))),
            "angle_error_rms_deg": float(np.sqrt(np.mean(angle_error**2))),
            "estimate_error_rms_mm": (float(1e3 * np.sqrt(np.mean(np.sum(estimate_error**2, 1))))
                                      if source == "true" else None),
            "max_coil_current_a": float(np.max(np.abs(log["coil_currents"][window]))),
            "mean_power_w": float(np.mean(log["coil_power_w"][window])),
            # Where the busiest coil would settle if the hold lasted at these currents (the
            # time constant is ~1 min): a what-if, not a forecast, since the thermal
            # allocation spreads the load as a coil nears its limit; None where it never
            # settles (thermal runaway: I^2 dR/dT beats cooling).
            "busiest_coil_steady_temperature_at_hold_currents_c": _finite_or_none(np.max(steady_state_temperature_c(
                thermal, np.sqrt(np.mean(log["coil_currents"][window] ** 2, axis=0))))),
        })
    touchdown = first_touchdown(log, rest_height_m)
    shortfall = np.linalg.norm(log["allocation_shortfall_W"], axis=1)
    tracked_before = np.cumsum(log["tracking_ok"] > 0.5) > 0
    dt = np.diff(t, prepend=t[0])
    return for_people({
        # "measured" with a station on LCM: no truth, so errors are the tracker's view.
        "pose_source": source,
        "max_coil_current_a": float(np.max(np.abs(log["coil_currents"]))),
        "max_power_w": float(np.max(log["coil_power_w"])),
        "max_coil_temperature_c": float(np.max(log["coil_temperature_c"])),
        "continuous_current_limit_a": weakest_coil_current_limit_a(thermal),
        "holds": holds,
        "hover_position_error_rms_mm": max((h["position_error_rms_mm"] for h in holds), default=None),
        "hover_angle_error_rms_deg": max((h["angle_error_rms_deg"] for h in holds), default=None),
        "hover_max_coil_current_a": holds[0]["max_coil_current_a"] if holds else None,
        "hover_mean_power_w": holds[0]["mean_power_w"] if holds else None,
        "hover_busiest_coil_steady_temperature_at_hold_currents_c":
            holds[0]["busiest_coil_steady_temperature_at_hold_currents_c"] if holds else None,
        "touchdown": touchdown,
        "final_state": final_state(log, rest_height_m),
        # Counted from the first estimate on: the log's t = 0 sample precedes it.
        "tracking_lost_s": float(np.sum(dt[tracked_before & (log["tracking_ok"] < 0.5)])),
        "allocation_saturated_s": float(np.sum(dt[shortfall > 1e-6])),
    })
