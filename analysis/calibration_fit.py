"""``maglev calibrate fit``: the device's own numbers from its identification flights.

From the run folders of ``maglev calibrate plan``'s flights (each its ``log.npz`` and
``scenario.yaml``) it fits, in turn:

1. the registration X_WT of the tracker's frame T in W: the instrument rests on a
   mark of known pose before each flight; its markers as the tracker reports them
   against where the mark puts them (a rigid fit over every flight's three markers);
2. the wrench model, the instrument's mass and its centre of mass: at each still hold
   the coils' wrench balances the weight, W(pose) i = -G(pose); W's columns are each
   coil's wrench per ampere, each magnet's share scaled by its strength and each
   coil's by its force scale; the payload flight's known mass separates the weight
   from the model's scale (scipy's least squares, 95 % intervals from its Jacobian);
3. the tracker's latency: the accelerations the tracker's poses show during the
   steps against those the currents make through the fitted model, over a scan of
   delays.

A parameter the flights cannot separate is said to be so, with the flight that
would separate it, and written at its nominal value; the magnets' common strength
and the coils' common scale are one product (the coils' geometric mean is held at 1).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Dict, List, Sequence

import numpy as np
import scipy.optimize
import scipy.sparse
from scipy.integrate import cumulative_trapezoid
from pydrake.common.schema import Transform
from pydrake.math import RigidTransform, RollPitchYaw, RotationMatrix
from scipy.ndimage import uniform_filter1d
from scipy.signal import savgol_filter
from scipy.spatial.transform import Rotation

from maglev_haptics.analysis.calibration_plan import HOLD_SETTLE_S
from maglev_haptics.analysis.run_log import load_run_log
from maglev_haptics.analysis.run_results import SCENARIO_FILE
from maglev_haptics.diagrams.motion import flight_plan
from maglev_haptics.diagrams.scenario import Scenario, scenario_from_yaml
from maglev_haptics.hardware.constants import GRAVITY_M_S2
from maglev_haptics.hardware.device import MAX_COM_OFFSET_M, MODEL_SCALE_RANGE, DeviceConfig
from maglev_haptics.hardware.magnetics import MagneticsModel, load_magnetics
from maglev_haptics.hardware.thermal import (
    coil_thermal, step_temperatures_c, winding_resistance_ohm)
from maglev_haptics.systems.pose_estimator import MarkerModel, fit_pose
from maglev_haptics.systems.rotations import rotation_from_quaternion

REST_FROM_S = 0.3  # the rest window starts here, the instrument settled on its mark (s)
REST_ENDS_BEFORE_TAKEOFF_S = 0.05  # and ends this long before the force ramp (s)
HOLD_STILL_M = 2e-4  # a hold whose position wanders more than this (std, m) is not still
HOLD_NEAR_M = 0.005  # a hold counts within this of its commanded position (m)
TORQUE_LEVER_M = 0.02  # torque residuals divided by this count as forces (N)
GAUGE_WEIGHT = 100.0  # the row holding the coils' geometric mean at 1
MIN_HOLDS = 12  # still holds a fit needs, of which MIN_PAYLOAD_HOLDS with the payload
MIN_PAYLOAD_HOLDS = 2
MIN_REST_MARKS = 2  # flights rested on a mark, for the registration
USED_CURRENT_A = 0.02  # a coil that never carries this much in a hold is not weighed (A)
# A parameter whose 95 % interval is wider than this is not identified.
NOT_IDENTIFIED = {"scale": 0.02, "mass_kg": 0.01, "com_m": 1e-3}
VELOCITY_WINDOW = 15  # tracker samples in the Savitzky-Golay window (~17 ms at 860 Hz)
VELOCITY_HIGH_PASS_S = 0.35  # the moving mean taken off both velocities (s)
LATENCY_SCAN_S = np.arange(-0.002, 0.008, 5e-5)  # delays tried (s)
REPORT_STEP_S = 0.01  # the thermal fit's step: a device's report period (s)
WARMED_K = 1.0  # a coil that warmed less than this in every flight is not weighed (K)


class CalibrationError(ValueError):
    """A refusal of ``maglev calibrate``: one line naming what is wrong and what to do."""


@dataclass
class Flight:
    """One identification flight as its run folder holds it."""

    name: str
    folder: Path
    scenario: Scenario
    log: Dict[str, np.ndarray]

    @cached_property
    def poses_T(self) -> tuple:
        """``tracker_poses`` of this flight."""
        return tracker_poses(self)


def read_flight(folder) -> Flight:
    """The flight in run folder ``folder``; CalibrationError if it is not one."""
    folder = Path(folder)
    if not (folder / SCENARIO_FILE).exists():
        raise CalibrationError(f"{folder}: not a run folder ({SCENARIO_FILE} missing): give "
                               "the --out folders of the plan's flights")
    try:
        scenario = scenario_from_yaml((folder / SCENARIO_FILE).read_text())
    except (RuntimeError, ValueError) as error:
        raise CalibrationError(f"{folder / SCENARIO_FILE}: not readable ({error})") from None
    if scenario.calibration is None:
        raise CalibrationError(f"{folder}: not a calibration flight (its scenario has no "
                               "calibration block): fly the flights of maglev calibrate plan")
    try:
        log = load_run_log(folder)
    except FileNotFoundError as error:
        raise CalibrationError(str(error)) from None
    if "markers_measured" not in log:
        raise CalibrationError(f"{folder}: its log has no tracker samples (markers_measured): "
                               "fly it again with this version's plan")
    latched = np.flatnonzero(log["fault_bits"] != 0)
    if len(latched):
        raise CalibrationError(
            f"{folder}: the flight latched a fault at {log['t'][latched[0]]:.3f} s (its "
            "summary.json says which): fly it again (over LCM on a host that stalls, at "
            "--realtime 0.5 on both sides)")
    return Flight(scenario.calibration.flight, folder, scenario, log)


def check_same_instrument(flights: Sequence[Flight]) -> str:
    kinds = sorted({flight.scenario.device.instrument for flight in flights})
    if len(kinds) != 1:
        raise CalibrationError(
            "the flights are of different instruments (" + ", ".join(
                f"{f.folder}: {f.scenario.device.instrument}" for f in flights) + "): fit one "
            "instrument's flights at a time")
    return kinds[0]


def tracker_poses(flight: Flight) -> tuple:
    """(p_TI (N, 3) [m], R_TI (N, 3, 3), seen (N,) bool): a rigid fit of the model's
    markers to each logged tracker sample, in the tracker's frame T."""
    model = MarkerModel(flight.scenario.device.instrument_spec().p_IK)
    markers = flight.log["markers_measured"]
    n = len(markers)
    p, R, seen = np.zeros((n, 3)), np.tile(np.eye(3), (n, 1, 1)), np.zeros(n, dtype=bool)
    for k in range(n):
        if np.all(np.isfinite(markers[k])):
            q_TI, rms_m = fit_pose(model, markers[k].reshape(-1, 3))
            if np.isfinite(rms_m):
                p[k], R[k], seen[k] = q_TI[4:7], rotation_from_quaternion(q_TI[0:4]), True
    return p, R, seen


def settled_rest_height_m(scenario: Scenario, mass_kg: float = None) -> float:
    """The height (m) of I above the glass where the station's model lets the
    instrument (of ``mass_kg``, default its kind's) settle, coils off: below
    ``rest_height_m`` by what its point contact presses (a device's hard pads press
    microns: ``--rest-height-m``)."""
    from pydrake.systems.analysis import Simulator
    from pydrake.systems.framework import DiagramBuilder

    from maglev_haptics.diagrams.station import MakeStation

    rest = Scenario(device=DeviceConfig(instrument=scenario.device.instrument,
                                        instrument_mass_kg=mass_kg))
    station = MakeStation(rest, magnetics=load_magnetics(rest.device))
    builder = DiagramBuilder()
    builder.AddSystem(station.system)
    diagram = builder.Build()
    simulator = Simulator(diagram)
    context = station.system.GetMyContextFromRoot(simulator.get_mutable_context())
    station.GetInputPort("coil_currents_commanded").FixValue(context, np.zeros(rest.device.n_coils))
    station.GetInputPort("coil_power").FixValue(context, [0.0])
    simulator.AdvanceTo(1.0)
    return float(station.GetOutputPort("instrument_state").Eval(context)[6])


def _rest_window(flight: Flight, seen: np.ndarray) -> np.ndarray:
    t = flight.log["t"]
    end_s = flight.scenario.motion.takeoff_at_s - REST_ENDS_BEFORE_TAKEOFF_S
    return (t >= REST_FROM_S) & (t <= end_s) & seen


def _mean_rotation(R: np.ndarray) -> np.ndarray:
    return Rotation.from_matrix(R).mean().as_matrix()


def fit_registration(flights: Sequence[Flight], rest_height_m: float) -> Dict:
    """X_WT from each flight's rest on its mark: the markers where the tracker saw them
    (T) against where the mark puts them (W), a rigid fit by least squares."""
    p_IK = flights[0].scenario.device.instrument_spec().p_IK
    seen, known = [], []
    for flight in flights:
        p_TI, R_TI, tracked = flight.poses_T
        window = _rest_window(flight, tracked)
        if window.sum() < 50:
            continue
        R_mean, p_mean = _mean_rotation(R_TI[window]), p_TI[window].mean(axis=0)
        x, y, yaw = flight.scenario.motion.start_xy_yaw
        R_WI = RotationMatrix.MakeZRotation(yaw).matrix()
        seen.append(p_IK @ R_mean.T + p_mean)
        known.append(p_IK @ R_WI.T + [x, y, rest_height_m])
    if len(seen) < MIN_REST_MARKS:
        raise CalibrationError(
            f"{len(seen)} flight(s) rest on a mark long enough (tracked from {REST_FROM_S} s to "
            f"the takeoff): the registration needs {MIN_REST_MARKS}; fly the plan's holds_* "
            "flights, each resting on its mark first")
    seen, known = np.concatenate(seen), np.concatenate(known)

    def residuals(x):
        R = Rotation.from_rotvec(x[0:3]).as_matrix()
        return (seen @ R.T + x[3:6] - known).ravel()

    result = scipy.optimize.least_squares(residuals, np.zeros(6), method="lm")
    covariance = _covariance(result)
    X_WT = RigidTransform(RotationMatrix(Rotation.from_rotvec(result.x[0:3]).as_matrix()),
                          result.x[3:6])
    rpy_deg = np.degrees(RollPitchYaw(X_WT.rotation()).vector())
    return {"X_WT": X_WT, "translation_m": X_WT.translation(), "rpy_deg": rpy_deg,
            "translation_95_m": 1.96 * np.sqrt(np.diag(covariance)[3:6]),
            "rotation_95_deg": np.degrees(1.96 * np.sqrt(np.diag(covariance)[0:3])),
            "residual_rms_m": float(np.sqrt(np.mean(result.fun**2))), "marks": len(known) // 3}


def _covariance(result) -> np.ndarray:
    J = result.jac
    dof = max(1, J.shape[0] - J.shape[1])
    sigma2 = 2 * result.cost / dof
    return sigma2 * np.linalg.pinv(J.T @ J)


def poses_in_W(flight: Flight, X_WT: RigidTransform) -> tuple:
    """(p_WI (N, 3), R_WI (N, 3, 3), seen (N,)) of every log row's tracker sample
    through the registration X_WT."""
    p_TI, R_TI, seen = flight.poses_T
    R_WT, p_WT = X_WT.rotation().matrix(), X_WT.translation()
    return p_TI @ R_WT.T + p_WT, np.einsum("ij,njk->nik", R_WT, R_TI), seen


@dataclass
class Hold:
    """A still pose of a flight: its mean pose in W, mean currents and payload."""

    flight: str
    p_WI: np.ndarray  # (3,) m
    R_WI: np.ndarray  # (3, 3)
    currents_a: np.ndarray  # (n_coils,) A
    payload_kg: float
    payload_p_I_m: np.ndarray  # (3,) m


def still_holds(flight: Flight, X_WT: RigidTransform) -> List[Hold]:
    """The flight's holds: each one's settled part, where the instrument stays still."""
    scenario = flight.scenario
    spec = scenario.device.instrument_spec()
    plan = flight_plan(scenario.motion, spec.rest_height_m)
    t, log = flight.log["t"], flight.log
    p_WI, R_WI, seen = poses_in_W(flight, X_WT)
    holds = []
    # Flying, where the flight holds it: the coils powered, near the commanded pose.
    flying = (log["coil_power"] > 0.5) & (np.linalg.norm(
        log["p_WI_measured"] - log["p_WI_desired"], axis=1) < HOLD_NEAR_M)
    for start_s, end_s in plan.holds:
        rows = (t >= start_s + HOLD_SETTLE_S) & (t <= end_s) & seen & flying
        if rows.sum() < 100 or np.max(np.std(p_WI[rows], axis=0)) > HOLD_STILL_M:
            continue
        holds.append(Hold(flight.name, p_WI[rows].mean(axis=0), _mean_rotation(R_WI[rows]),
                          log["coil_currents"][rows].mean(axis=0),
                          scenario.calibration.payload_kg,
                          np.asarray(scenario.calibration.payload_p_I_m, float)))
    return holds


def gravity_wrench(mass_kg, com_I, R_WI, payload_kg, payload_p_I) -> np.ndarray:
    """[f; tau] (N, N*m about I's origin, W axes) of the weight of the instrument
    (``mass_kg`` at ``com_I``, m in I) and its payload."""
    total = mass_kg + payload_kg
    com = (mass_kg * np.asarray(com_I) + payload_kg * np.asarray(payload_p_I)) / total
    force = np.array([0.0, 0.0, -total * GRAVITY_M_S2])
    return np.concatenate((force, np.cross(R_WI @ com, force)))


@dataclass
class WrenchFit:
    magnet_scales: np.ndarray
    coil_scales: np.ndarray
    mass_kg: float
    com_I_m: np.ndarray
    intervals: Dict[str, np.ndarray]  # each parameter's 95 % half-width
    residuals_before: np.ndarray  # (holds, 6): nominal model, N and N*m
    residuals_after: np.ndarray
    not_identified: List[str]


def fit_wrench_model(holds: Sequence[Hold], magnetics: MagneticsModel,
                     device: DeviceConfig) -> WrenchFit:
    """Magnet strengths, coil scales, mass and centre of mass from the holds.

    A coil no hold drives (USED_CURRENT_A) is left out of the fit at 1.0 and said so;
    the others' geometric mean is held at 1 (the gauge)."""
    n_payload = sum(hold.payload_kg > 0 for hold in holds)
    if len(holds) < MIN_HOLDS or n_payload < MIN_PAYLOAD_HOLDS:
        raise CalibrationError(
            f"{len(holds)} still holds ({n_payload} with a payload): the fit needs at least "
            f"{MIN_HOLDS}, {MIN_PAYLOAD_HOLDS} of them carrying the payload: fly the plan's "
            "holds_* flights and its payload flight")
    if not all(np.all(np.isfinite(h.currents_a)) and np.all(np.isfinite(h.p_WI)) for h in holds):
        raise CalibrationError("a hold's currents or pose are not finite numbers: the logs "
                               "are damaged; fly those flights again")
    n_m, n_c = len(magnetics.p_IM), magnetics.n_coils
    shares = np.array([magnetics.magnet_wrench_matrices(h.p_WI - device.p_WA, h.R_WI)
                       for h in holds])  # (holds, magnets, 6, coils)
    currents = np.array([h.currents_a for h in holds])
    used = np.flatnonzero(np.abs(currents).max(axis=0) >= USED_CURRENT_A)
    n_u = len(used)
    nominal_mass = device.instrument_spec().mass_kg
    scale = np.array([1, 1, 1, 1 / TORQUE_LEVER_M, 1 / TORQUE_LEVER_M, 1 / TORQUE_LEVER_M])

    def unpacked(x):
        """(magnet scales, all coil scales, mass, com) of the parameters x."""
        coils = np.ones(n_c)
        coils[used] = np.exp(x[n_m:n_m + n_u])
        return np.exp(x[0:n_m]), coils, x[n_m + n_u], x[n_m + n_u + 1:]

    def wrench_errors(x):
        s, c, mass, com = unpacked(x)
        coil_wrench = np.einsum("m,hmkj,j,hj->hk", s, shares, c, currents)
        gravity = np.array([gravity_wrench(mass, com, h.R_WI, h.payload_kg, h.payload_p_I_m)
                            for h in holds])
        return coil_wrench + gravity

    def residuals(x):
        gauge = GAUGE_WEIGHT * np.mean(x[n_m:n_m + n_u])
        return np.concatenate(((wrench_errors(x) * scale).ravel(), [gauge]))

    x0 = np.concatenate((np.zeros(n_m + n_u), [nominal_mass], np.zeros(3)))
    log_range = np.log(MODEL_SCALE_RANGE)  # bounded where the schema is
    lower = np.concatenate((np.full(n_m + n_u, log_range[0]), [0.5 * nominal_mass],
                            np.full(3, -MAX_COM_OFFSET_M)))
    upper = np.concatenate((np.full(n_m + n_u, log_range[1]), [2.0 * nominal_mass],
                            np.full(3, MAX_COM_OFFSET_M)))
    result = scipy.optimize.least_squares(residuals, x0, bounds=(lower, upper), x_scale="jac")
    if not result.success or not np.all(np.isfinite(result.x)):
        raise CalibrationError(f"the wrench fit did not converge ({result.message}): check "
                               "that the flights flew their holds (summary.json)")
    half = 1.96 * np.sqrt(np.abs(np.diag(_covariance(result))))
    x = result.x.copy()
    coil_half = np.full(n_c, np.inf)
    coil_half[used] = half[n_m:n_m + n_u]
    not_identified = []
    coil_positions = magnetics.p_ACj + device.p_WA
    for j in range(n_c):
        if coil_half[j] > NOT_IDENTIFIED["scale"]:
            x_j, y_j, _ = coil_positions[j]
            not_identified.append(
                f"coil_force_scales[{j}] (+-{100 * coil_half[j]:.1f} %): the holds barely use "
                f"coil {j}; a hold above it, pose [{x_j:.3f}, {y_j:.3f}, 0.014, 0, 0, 0], "
                "would identify it; written as 1.0")
            if j in used:
                x[n_m + int(np.flatnonzero(used == j)[0])] = 0.0
    if half[n_m + n_u] > NOT_IDENTIFIED["mass_kg"] * nominal_mass:
        not_identified.append(f"instrument_mass_kg (+-{half[n_m + n_u]:.4f} kg): fly the "
                              "payload flight with a heavier payload; written as the nominal")
        x[n_m + n_u] = nominal_mass
    for k, axis in enumerate("xyz"):
        if half[n_m + n_u + 1 + k] > NOT_IDENTIFIED["com_m"]:
            not_identified.append(
                f"instrument_com_offset_m[{k}] (+-{1e3 * half[n_m + n_u + 1 + k]:.2f} mm): "
                f"the holds tilt too little to weigh it along {axis}; written as 0")
            x[n_m + n_u + 1 + k] = 0.0
    magnet_scales, coil_scales, mass_kg, com = unpacked(x)
    return WrenchFit(
        magnet_scales=magnet_scales, coil_scales=coil_scales, mass_kg=float(mass_kg),
        com_I_m=np.array(com),
        intervals={"magnet_scales": half[0:n_m], "coil_scales": coil_half,
                   "mass_kg": half[n_m + n_u], "com_I_m": half[n_m + n_u + 1:]},
        residuals_before=wrench_errors(x0), residuals_after=wrench_errors(x),
        not_identified=not_identified)


def tracker_samples(flight: Flight, X_WT: RigidTransform) -> tuple:
    """(publish times (S,) [s], p_WI (S, 3) [m], R_WI (S, 3, 3)): each tracker sample
    once."""
    times = flight.log["markers_sample_time_s"]
    p_WI, R_WI, seen = poses_in_W(flight, X_WT)
    published = np.isfinite(times) & seen
    rows = np.flatnonzero(published)
    rows = rows[np.diff(times[rows], prepend=-np.inf) > 0]
    return times[rows], p_WI[rows], R_WI[rows]


def fit_latency(flights: Sequence[Flight], X_WT: RigidTransform, magnetics: MagneticsModel,
                device: DeviceConfig, mass_kg: float) -> Dict:
    """The delay (s) between the instrument's motion and the tracker's samples of it, from
    the steps flight: the velocity the samples show (Savitzky-Golay) against the one the
    currents make through the model (integrated), both high-passed, over a scan of delays.

    A log's row of currents is the acceleration at its time (the plant's step is
    centred on it): a sample's currents are interpolated to its capture time.

    Returns ``logged_latency_s``, the delay as the log's times show it, and
    ``latency_s``, the twin's ``tracker.latency_s`` that reproduces it: the simulated
    tracker reads the plant's state held over the tick after its sample's time, on
    average half a tick (h / 2) later, so the twin's latency is the logged one + h / 2."""
    steps = [flight for flight in flights if flight.name == "steps"]
    if not steps:
        raise CalibrationError("no steps flight among the run folders: the latency needs the "
                               "plan's steps flight")
    flight = steps[0]
    t_s, p_WI, R_WI = tracker_samples(flight, X_WT)
    period_s = float(np.median(np.diff(t_s)))
    plan = flight_plan(flight.scenario.motion, device.instrument_spec().rest_height_m)
    inside = (t_s > plan.holds[0][0]) & (t_s < plan.holds[-1][1])
    high_pass = max(3, int(round(VELOCITY_HIGH_PASS_S / period_s)))
    measured = _high_passed(savgol_filter(p_WI, VELOCITY_WINDOW, 2, deriv=1, delta=period_s,
                                          axis=0), high_pass)
    model = np.array([magnetics.wrench_matrix_from(p - device.p_WA, R)[0:3]
                      for p, R in zip(p_WI, R_WI)])
    tick_t, currents = flight.log["t"], flight.log["coil_currents"]
    tick_s = float(np.median(np.diff(tick_t)))
    weight = np.array([0.0, 0.0, -GRAVITY_M_S2])

    def error(latency_s):
        rows = np.clip((t_s - latency_s - tick_t[0]) / tick_s, 0, len(tick_t) - 2)
        before = rows.astype(int)
        after = (rows - before)[:, None]
        held = currents[before] * (1 - after) + currents[before + 1] * after
        acceleration = np.einsum("skj,sj->sk", model, held)
        velocity = cumulative_trapezoid(acceleration / mass_kg + weight, dx=period_s, axis=0,
                                        initial=0.0)
        predicted = _high_passed(savgol_filter(velocity, VELOCITY_WINDOW, 2, axis=0), high_pass)
        return float(np.mean((measured[inside] - predicted[inside]) ** 2))

    errors = np.array([error(latency) for latency in LATENCY_SCAN_S])
    best = int(np.argmin(errors))
    if best in (0, len(errors) - 1):
        raise CalibrationError(
            f"the tracker's latency is at the end of the scan ({1e3 * LATENCY_SCAN_S[best]:.2f} "
            "ms): the steps flight did not move the instrument as commanded")
    e0, e1, e2 = errors[best - 1:best + 2]
    step = LATENCY_SCAN_S[1] - LATENCY_SCAN_S[0]
    latency = LATENCY_SCAN_S[best] + step * 0.5 * (e0 - e2) / (e0 - 2 * e1 + e2)
    return {"logged_latency_s": float(latency), "latency_s": float(latency + tick_s / 2),
            "scan_s": LATENCY_SCAN_S, "scan_error": errors,
            "rms_velocity_m_s": math.sqrt(errors[best])}


def _high_passed(values: np.ndarray, samples: int) -> np.ndarray:
    """``values`` less their moving mean over ``samples``: an integration's drift gone."""
    return values - uniform_filter1d(values, samples, axis=0)


@dataclass
class Calibration:
    """What ``fit_device`` found: the fitted device and how it was found."""

    instrument: str
    nominal: DeviceConfig  # the model the flights flew with
    device: DeviceConfig  # the nominal with the fitted numbers
    registration: Dict
    wrench: WrenchFit
    latency: Dict
    thermal: Dict  # fit_thermal's, or None where the device reported no temperatures
    rest_height_m: float
    holds: int
    flights: List[str]


def fit_device(folders: Sequence, rest_height_m: float = None, progress=print) -> Calibration:
    """Fit the device of the flights in run ``folders`` (``maglev calibrate plan``'s);
    CalibrationError for folders that do not make a calibration. ``rest_height_m``: the
    height of I resting on the glass (m); default the model's settled one."""
    if not folders:
        raise CalibrationError("no run folder given: give the --out folders of the plan's flights")
    flights = [read_flight(folder) for folder in folders]
    instrument = check_same_instrument(flights)
    if any(flight.name == "check" for flight in flights):
        raise CalibrationError(
            "the check flight is among the folders: keep it out of the fit, for maglev "
            "calibrate check to test the fit on poses it did not see")
    nominal = flights[0].scenario.device
    given = rest_height_m is not None
    if not given:
        rest_height_m = settled_rest_height_m(flights[0].scenario)
    registration, holds, wrench = _registration_and_wrench(flights, nominal, rest_height_m,
                                                           progress)
    if not given:  # the model's contact presses with the weight: again at the fitted mass
        rest_height_m = settled_rest_height_m(flights[0].scenario, wrench.mass_kg)
        registration, holds, wrench = _registration_and_wrench(flights, nominal,
                                                               rest_height_m, progress)
    fitted = dataclasses.replace(
        nominal, magnet_strength_scales=[float(v) for v in wrench.magnet_scales],
        coil_force_scales=[float(v) for v in wrench.coil_scales],
        instrument_mass_kg=wrench.mass_kg,
        instrument_com_offset_m=[float(v) for v in wrench.com_I_m])
    progress("tracker latency from the steps")
    latency = fit_latency(flights, registration["X_WT"], load_magnetics(fitted), fitted,
                          wrench.mass_kg)
    tracker = dataclasses.replace(nominal.tracker, latency_s=latency["latency_s"],
                                  X_WT=drake_transform(registration["X_WT"]))
    fitted = dataclasses.replace(fitted, tracker=tracker)
    progress("each coil's thermal resistance and capacity from its reported temperatures")
    thermal = fit_thermal(flights, nominal)
    if thermal is not None:
        fitted = dataclasses.replace(fitted, thermal=dataclasses.replace(
            nominal.thermal,
            thermal_resistances_k_per_w=[float(v) for v in thermal["resistances_k_per_w"]],
            heat_capacities_j_per_k=[float(v) for v in thermal["capacities_j_per_k"]]))
    return Calibration(instrument=instrument, nominal=nominal, device=fitted,
                       registration=registration, wrench=wrench, latency=latency,
                       thermal=thermal, rest_height_m=rest_height_m, holds=len(holds),
                       flights=[str(flight.folder) for flight in flights])


def _registration_and_wrench(flights, nominal: DeviceConfig, rest_height_m: float,
                             progress) -> tuple:
    """(registration, holds, WrenchFit) of the flights, resting at ``rest_height_m``."""
    progress(f"registration from {len(flights)} rest marks")
    registration = fit_registration(flights, rest_height_m)
    holds = [hold for flight in flights for hold in still_holds(flight, registration["X_WT"])]
    progress(f"wrench model, mass and centre of mass from {len(holds)} still holds")
    return registration, holds, fit_wrench_model(holds, load_magnetics(nominal), nominal)


def drake_transform(X: RigidTransform) -> Transform:
    """``X`` in Drake's schema (translation, roll-pitch-yaw in degrees)."""
    value = Transform()
    value.translation = X.translation()
    value.set_rotation_rpy_deg(np.degrees(RollPitchYaw(X.rotation()).vector()))
    return value


def overlay_text(device: DeviceConfig) -> str:
    """The fitted numbers as a ``device:`` overlay (``maglev run --scenario-text``, a
    scenario file's ``device``, ``station: !SimStation {device: ...}``)."""
    X_WT = device.tracker.pose_WT()
    rpy_deg = np.degrees(RollPitchYaw(X_WT.rotation()).vector())

    def numbers(values, digits=6):
        return "[" + ", ".join(f"{float(v):.{digits}g}" for v in values) + "]"

    thermal = device.thermal
    thermal_lines = [] if thermal.thermal_resistances_k_per_w is None else [
        "  thermal:",
        f"    thermal_resistances_k_per_w: {numbers(thermal.thermal_resistances_k_per_w, 5)}",
        f"    heat_capacities_j_per_k: {numbers(thermal.heat_capacities_j_per_k, 5)}"]
    return "\n".join([
        "device:",
        f"  instrument_mass_kg: {device.instrument_mass_kg:.6g}",
        f"  instrument_com_offset_m: {numbers(device.instrument_com_offset_m, 4)}",
        f"  magnet_strength_scales: {numbers(device.magnet_strength_scales)}",
        f"  coil_force_scales: {numbers(device.coil_force_scales)}",
        "  tracker:",
        f"    latency_s: {device.tracker.latency_s:.6g}",
        f"    X_WT: {{translation: {numbers(X_WT.translation(), 5)}, "
        f"rotation: !Rpy {{deg: {numbers(rpy_deg, 5)}}}}}",
        *thermal_lines,
        ""])


def fit_thermal(flights: Sequence[Flight], nominal: DeviceConfig) -> Dict:
    """Each coil's thermal resistance R_th [K/W] and heat capacity C [J/K] from the
    temperatures the device reported against the currents that flowed: the thermal
    model's exact RC step (``hardware/thermal.py``) every REPORT_STEP_S from each
    flight's first report, the current held over each step, fitted per coil (scipy's
    least squares; the coils are independent, so the Jacobian is two diagonals).

    A coil that warmed by less than WARMED_K in every flight is not identified and
    keeps the nominal values. Returns resistances, capacities, their 95 % intervals
    and the not-identified lines; None where no flight logged reported temperatures."""
    model = coil_thermal(nominal)
    n = nominal.n_coils
    series = []
    for flight in flights:
        reported = flight.log["coil_temperature_reported_c"]
        t = flight.log["t"]
        rows = np.flatnonzero(np.all(np.isfinite(reported), axis=1))
        if len(rows) < 2:
            continue
        tick_s = float(np.median(np.diff(t)))
        every = max(1, int(round(REPORT_STEP_S / tick_s)))
        rows = rows[::every]
        series.append((flight.log["coil_currents"][rows[:-1]], reported[rows],
                       float(np.median(np.diff(t[rows])))))
    if not series:
        return None
    warmed = np.max([np.max(temps - temps[0], axis=0) for _, temps, _ in series], axis=0)
    fitted = np.flatnonzero(warmed >= WARMED_K)
    C0, R0 = model.per_coil(n)

    def simulated(x):
        capacity, resistance = C0.copy(), R0.copy()
        capacity[fitted], resistance[fitted] = np.exp(x[:len(fitted)]), np.exp(x[len(fitted):])
        out = []
        for currents, temps, step_s in series:
            temperature = temps[0].copy()
            path = [temperature.copy()]
            for current in currents:
                step_temperatures_c(temperature, np.ascontiguousarray(current), step_s,
                                    model.ambient_c, capacity, resistance,
                                    model.resistance_ref_ohm, model.alpha_per_k,
                                    float(winding_resistance_ohm(model, model.ambient_c)))
                path.append(temperature.copy())
            out.append(np.array(path)[:, fitted] - temps[:, fitted])
        return np.concatenate(out)

    result = {"resistances_k_per_w": R0.copy(), "capacities_j_per_k": C0.copy(),
              "resistance_95": np.full(n, np.inf), "capacity_95": np.full(n, np.inf),
              "warmed_k": warmed, "not_identified": []}
    if len(fitted):
        rows = sum(len(temps) for _, temps, _ in series)
        block = scipy.sparse.kron(scipy.sparse.coo_array(np.ones((rows, 1))),
                                  scipy.sparse.eye_array(len(fitted)))
        sparsity = scipy.sparse.hstack([block, block])
        x0 = np.log(np.concatenate((C0[fitted], R0[fitted])))
        fit = scipy.optimize.least_squares(lambda x: simulated(x).ravel(), x0,
                                           jac_sparsity=sparsity, x_scale="jac")
        half = 1.96 * np.sqrt(np.abs(np.diag(_covariance(_dense(fit)))))
        result["capacities_j_per_k"][fitted] = np.exp(fit.x[:len(fitted)])
        result["resistances_k_per_w"][fitted] = np.exp(fit.x[len(fitted):])
        result["capacity_95"][fitted] = half[:len(fitted)]
        result["resistance_95"][fitted] = half[len(fitted):]
    cold = np.flatnonzero(warmed < WARMED_K)
    if len(cold):
        result["not_identified"].append(
            f"device.thermal of coils {', '.join(str(j) for j in cold)}: each warmed by "
            f"{warmed[cold].max():.2f} K at most (under {WARMED_K} K); longer holds above "
            "them would identify them; written as the nominal")
    return result


def _dense(result):
    """``result`` with its Jacobian as a dense array (``_covariance`` takes one)."""
    if scipy.sparse.issparse(result.jac):
        result.jac = result.jac.toarray()
    return result
