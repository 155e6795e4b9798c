"""What ``maglev calibrate fit`` tells its user: each parameter nominal, fitted and its
95 % interval, the residuals before and after, what the flights cannot separate, and a
plot of it (``calibration.png``)."""

from __future__ import annotations

from pathlib import Path
from typing import Dict

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from maglev_haptics.analysis.calibration_fit import TORQUE_LEVER_M, Calibration  # noqa: E402

REPORT_FILE = "calibration_report.json"
PLOT_FILE = "calibration.png"
GAUGE_NOTE = ("magnet_strength_scales and coil_force_scales act as products: the flights "
              "weigh each coil's wrench per ampere, not how it splits between the magnets' "
              "common strength and the coils' common scale (the coils' geometric mean is "
              "held at 1); a gaussmeter reading of one magnet would split them")


def _rms(values, axis=0):
    return np.sqrt(np.mean(np.square(values), axis=axis))


def calibration_report(calibration: Calibration) -> Dict:
    """The report's numbers (JSON-ready): parameters, residuals, what is not identified."""
    nominal, device, wrench = calibration.nominal, calibration.device, calibration.wrench
    registration, latency = calibration.registration, calibration.latency
    n_magnets = len(wrench.magnet_scales)
    parameters = {
        "instrument_mass_kg": {"nominal": nominal.instrument_spec().mass_kg,
                               "fitted": wrench.mass_kg,
                               "interval_95": float(wrench.intervals["mass_kg"])},
        "instrument_com_offset_m": {"nominal": [0.0, 0.0, 0.0],
                                    "fitted": wrench.com_I_m.tolist(),
                                    "interval_95": wrench.intervals["com_I_m"].tolist()},
        "magnet_strength_scales": {"nominal": [1.0] * n_magnets,
                                   "fitted": wrench.magnet_scales.tolist(),
                                   "interval_95": wrench.intervals["magnet_scales"].tolist()},
        "coil_force_scales": {"nominal": [1.0] * len(wrench.coil_scales),
                              "fitted": wrench.coil_scales.tolist(),
                              "interval_95": wrench.intervals["coil_scales"].tolist()},
        "tracker.latency_s": {"nominal": nominal.tracker.latency_s,
                              "fitted": device.tracker.latency_s,
                              "logged_latency_s": latency["logged_latency_s"]},
        "tracker.X_WT": {"nominal": {"translation_m": [0.0] * 3, "rpy_deg": [0.0] * 3},
                         "fitted": {"translation_m": registration["translation_m"].tolist(),
                                    "rpy_deg": registration["rpy_deg"].tolist()},
                         "interval_95": {"translation_m": registration["translation_95_m"].tolist(),
                                         "rpy_deg": registration["rotation_95_deg"].tolist()}},
    }
    thermal = calibration.thermal
    if thermal is not None:
        parameters["thermal.thermal_resistances_k_per_w"] = {
            "nominal": nominal.thermal.thermal_resistance_k_per_w,
            "fitted": thermal["resistances_k_per_w"].tolist(),
            "interval_95": thermal["resistance_95"].tolist()}
        parameters["thermal.heat_capacities_j_per_k"] = {
            "fitted": thermal["capacities_j_per_k"].tolist(),
            "interval_95": thermal["capacity_95"].tolist()}
    before, after = wrench.residuals_before, wrench.residuals_after
    return {
        "instrument": calibration.instrument,
        "flights": calibration.flights,
        "holds": calibration.holds,
        "rest_height_m": calibration.rest_height_m,
        "parameters": parameters,
        "residuals": {
            "force_rms_n": {"nominal": _rms(before[:, 0:3]).tolist(),
                            "fitted": _rms(after[:, 0:3]).tolist()},
            "torque_rms_nm": {"nominal": _rms(before[:, 3:6]).tolist(),
                              "fitted": _rms(after[:, 3:6]).tolist()},
            "registration_rms_m": registration["residual_rms_m"],
            "latency_velocity_rms_m_s": latency["rms_velocity_m_s"],
        },
        "not_identified": wrench.not_identified + (
            ["device.thermal: the flights logged no coil temperatures from the device"]
            if thermal is None else thermal["not_identified"]),
        "not_separable": [GAUGE_NOTE],
        "left_out": [
            "the instrument's inertia (the holds are still; the steps' rotations would "
            "weigh it against the fitted torque model)"],
    }


def format_summary(report: Dict) -> str:
    """A few lines for the terminal: what was fitted, how well."""
    p, r = report["parameters"], report["residuals"]
    mass = p["instrument_mass_kg"]
    com = np.array(p["instrument_com_offset_m"]["fitted"]) * 1e3
    reg = p["tracker.X_WT"]
    lines = [
        f"mass {mass['fitted'] * 1e3:.2f} g (nominal {mass['nominal'] * 1e3:.2f}, "
        f"+-{mass['interval_95'] * 1e3:.2f}); centre of mass "
        f"[{', '.join(f'{v:.3f}' for v in com)}] mm",
        "magnet strengths " + ", ".join(f"{v:.4f}" for v in p["magnet_strength_scales"]["fitted"])
        + "; coil scales " + f"{min(p['coil_force_scales']['fitted']):.4f}"
        + f"..{max(p['coil_force_scales']['fitted']):.4f}",
        f"tracker latency {p['tracker.latency_s']['fitted'] * 1e3:.2f} ms (nominal "
        f"{p['tracker.latency_s']['nominal'] * 1e3:.2f}); registration X_WT "
        f"[{', '.join(f'{1e3 * v:.3f}' for v in reg['fitted']['translation_m'])}] mm, "
        f"rpy [{', '.join(f'{v:.3f}' for v in reg['fitted']['rpy_deg'])}] deg",
        f"hold residuals over {report['holds']} holds: force "
        f"{np.linalg.norm(r['force_rms_n']['nominal']) * 1e3:.1f} -> "
        f"{np.linalg.norm(r['force_rms_n']['fitted']) * 1e3:.2f} mN, torque "
        f"{np.linalg.norm(r['torque_rms_nm']['nominal']) * 1e3:.3f} -> "
        f"{np.linalg.norm(r['torque_rms_nm']['fitted']) * 1e3:.4f} mN m (RMS)",
    ]
    if "thermal.thermal_resistances_k_per_w" in p:
        fitted = [v for v, half in zip(p["thermal.thermal_resistances_k_per_w"]["fitted"],
                                       p["thermal.thermal_resistances_k_per_w"]["interval_95"])
                  if half is not None and np.isfinite(half)]
        if fitted:
            lines.append(f"coil thermal resistances {min(fitted):.3g}..{max(fitted):.3g} K/W "
                         f"({len(fitted)} coils warmed enough to weigh)")
    lines += [f"not identified: {line}" for line in report["not_identified"]]
    return "\n".join(lines)


def plot_calibration(calibration: Calibration, path: Path) -> None:
    """Residuals per hold before and after, each coil's fitted scale with its interval,
    and the latency scan."""
    wrench, latency = calibration.wrench, calibration.latency
    figure, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    holds = np.arange(len(wrench.residuals_before))
    for residuals, label in ((wrench.residuals_before, "nominal model"),
                             (wrench.residuals_after, "fitted")):
        size = np.linalg.norm(np.hstack((residuals[:, 0:3], residuals[:, 3:6] / TORQUE_LEVER_M)),
                              axis=1)
        axes[0].semilogy(holds, 1e3 * np.maximum(size, 1e-6), "o", label=label, markersize=4)
    axes[0].set(xlabel="hold", ylabel=f"wrench residual (mN; torque / {TORQUE_LEVER_M * 1e3:g} mm)",
                title="Coils' wrench + weight at each still hold")
    axes[0].legend()
    coils = np.arange(len(wrench.coil_scales))
    axes[1].errorbar(coils, wrench.coil_scales, yerr=wrench.intervals["coil_scales"] *
                     wrench.coil_scales, fmt="o", markersize=4, capsize=2)
    axes[1].axhline(1.0, color="grey", linewidth=0.8)
    axes[1].set(xlabel="coil", ylabel="force scale (95 % interval)",
                title="Each coil's wrench per ampere against the model")
    axes[2].plot(1e3 * latency["scan_s"], latency["scan_error"] * 1e6)
    axes[2].axvline(1e3 * latency["logged_latency_s"], color="C3", linestyle="--",
                    label=f"best: {1e3 * latency['logged_latency_s']:.2f} ms as logged")
    axes[2].set(xlabel="delay tried (ms)", ylabel="velocity mismatch (mm/s)^2",
                title="Tracker latency: samples against the currents' motion")
    axes[2].legend()
    figure.suptitle(f"Calibration of the {calibration.instrument} instrument's device")
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)
