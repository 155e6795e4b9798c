"""``maglev calibrate check``: how well a fitted device predicts a flight the fit did not
see (the plan's ``check`` flight), against the nominal model.

For each model (the flight's own, and it with the fitted ``device:`` overlay):

- co-location: where the model puts the instrument's markers while it rests on the
  flight's mark, against where the mark puts them (mm in W, and pixels on the display);
- wrench residual: at each still hold, the coils' wrench for the measured currents plus
  the weight (N, N*m): what the hand would feel wrong while the model renders;
- felt-force error: that residual force per newton rendered (the weight it carries);
- hover current: the current the model says holds each hold's pose, along the
  device's own currents, against what the device needed (%).
"""

from __future__ import annotations

from typing import Dict

import numpy as np
from pydrake.math import RotationMatrix

from maglev_haptics.analysis.calibration_fit import (
    CalibrationError, Flight, _rest_window, gravity_wrench, read_flight, settled_rest_height_m,
    still_holds)
from maglev_haptics.diagrams.scenario import layered_device
from maglev_haptics.diagrams.scenario_diagnosis import parse_mapping
from maglev_haptics.hardware.device import DeviceConfig
from maglev_haptics.hardware.magnetics import load_magnetics


def fitted_device(overlay_text: str, flight: Flight, source: str) -> DeviceConfig:
    """The flight's device with the fitted ``device:`` overlay ``overlay_text`` laid on
    it; CalibrationError for an overlay that is not one, or is another instrument's."""
    mapping = parse_mapping(overlay_text, source)
    if set(mapping) != {"device"} or not isinstance(mapping["device"], dict):
        raise CalibrationError(f"{source}: not a device overlay (a mapping with device: alone, "
                               "as maglev calibrate fit writes)")
    layer = mapping["device"]
    nominal = flight.scenario.device
    if layer.get("instrument", nominal.instrument) != nominal.instrument:
        raise CalibrationError(f"{source}: an overlay for the {layer['instrument']} instrument; "
                               f"{flight.folder} flew the {nominal.instrument}")
    device = layered_device(nominal, layer, f"{source}: device")
    try:
        device.validate(f"{source}: device")
    except ValueError as error:
        raise CalibrationError(f"{error} (an overlay for another instrument?)") from None
    return device


def colocation_error_m(flight: Flight, device: DeviceConfig, rest_height_m: float) -> float:
    """RMS distance (m) between the markers where ``device``'s registration puts them
    while the instrument rests on the flight's mark and where the mark puts them."""
    p_TI, R_TI, seen = flight.poses_T
    window = _rest_window(flight, seen)
    if window.sum() < 50:
        raise CalibrationError(f"{flight.folder}: the instrument was not tracked resting on its "
                               "mark before the takeoff")
    p_IK = device.instrument_spec().p_IK
    X_WT = device.tracker.pose_WT()
    x, y, yaw = flight.scenario.motion.start_xy_yaw
    known = p_IK @ RotationMatrix.MakeZRotation(yaw).matrix().T + [x, y, rest_height_m]
    errors = []
    for p, R in zip(p_TI[window], R_TI[window]):
        p_WK = (p_IK @ R.T + p) @ X_WT.rotation().matrix().T + X_WT.translation()
        errors.append(np.linalg.norm(p_WK - known, axis=1))
    return float(np.sqrt(np.mean(np.square(errors))))


def model_errors(flight: Flight, device: DeviceConfig, rest_height_m: float) -> Dict:
    """The check's numbers for one model of the device."""
    magnetics = load_magnetics(device)
    holds = still_holds(flight, device.tracker.pose_WT())
    if not holds:
        raise CalibrationError(f"{flight.folder}: no still hold to check the model at")
    mass_kg = device.instrument_spec().mass_kg
    force, torque, hover = [], [], []
    for hold in holds:
        coil_wrench = magnetics.wrench_matrix_from(hold.p_WI - device.p_WA, hold.R_WI) @ \
            hold.currents_a
        weight = gravity_wrench(mass_kg, device.instrument_com_offset_m, hold.R_WI,
                                hold.payload_kg, hold.payload_p_I_m)
        force.append(coil_wrench[0:3] + weight[0:3])
        torque.append(coil_wrench[3:6] + weight[3:6])
        hover.append(-coil_wrench @ weight / (coil_wrench @ coil_wrench))
    force, torque = np.array(force), np.array(torque)
    weight_n = (mass_kg + holds[0].payload_kg) * 9.81
    colocation_m = colocation_error_m(flight, device, rest_height_m)
    px_per_m = device.display.resolution_px[0] / device.display.size_m[0]
    return {
        "colocation_error_mm": 1e3 * colocation_m,
        "colocation_error_px": colocation_m * px_per_m,
        "force_residual_rms_n": float(np.sqrt(np.mean(np.sum(force**2, axis=1)))),
        "torque_residual_rms_nm": float(np.sqrt(np.mean(np.sum(torque**2, axis=1)))),
        "felt_force_error_mn_per_n": 1e3 * float(np.sqrt(np.mean(np.sum(force**2, axis=1))))
        / weight_n,
        "hover_current_error_percent": 100 * float(np.sqrt(np.mean((np.array(hover) - 1)**2))),
        "holds": len(holds),
    }


def check_calibration(folder, overlay_text: str, source: str,
                      rest_height_m: float = None) -> Dict:
    """The check of the fitted overlay against flight ``folder``, nominal beside fitted."""
    flight = read_flight(folder)
    result = {"flight": str(folder)}
    for name, device in (("nominal", flight.scenario.device),
                         ("fitted", fitted_device(overlay_text, flight, source))):
        # Where each model rests the instrument: its contact pressed by its mass.
        height_m = rest_height_m if rest_height_m is not None else settled_rest_height_m(
            flight.scenario, device.instrument_spec().mass_kg)
        result[name] = model_errors(flight, device, height_m)
    result["instrument"] = flight.scenario.device.instrument
    return result
