"""Summary numbers of a haptic run, from its log: free-motion transparency,
contact stiffness and friction, let-go behaviour, and per-scene checks."""

from typing import Dict, List, Optional

import numpy as np

from scipy.ndimage import binary_dilation
from scipy.signal import butter, sosfiltfilt

from maglev_haptics.analysis.run_metrics import recorded_pose
from maglev_haptics.diagrams.deformable_scene import DeformableSurface
from maglev_haptics.diagrams.scene import HangingBall, PaddleBall, PegInHole
from maglev_haptics.systems.haptic_supervisor import HAPTIC, LANDING
from maglev_haptics.systems.rotations import rotation_matrix, rotations_of_quaternions

CONTACT_GUARD_S = 0.05  # free motion excludes samples this close to any contact (s)
RELEASE_WINDOW_S = 5.0  # how long a let-go is watched (s)
DEPTH_MIN_M = 2e-4  # pressing shallower than this is not used for the stiffness fit (m)
SLIDING_SPEED_M_S = 2e-3  # the tool slides when faster than this along the floor (m/s)
STRIKE_MAX_S = 0.6  # a contact shorter than this is a strike, longer a press or a slide (s)
CONTACT_GAP_S = 0.15  # contacts closer than this are one touch: the probe skips on bumps (s)
# The palpation and roughness metrics split the rendered force at this frequency
# (Hz): below it, the hand's pressing and the texture met at sweep speed (a 4 mm
# bump at 15 mm/s is ~4 Hz); above it, ringing, stick-slip and the tracker noise.
SMOOTH_BELOW_HZ = 20.0
TEXTURE_ABOVE_HZ = 1.0  # slower z-force changes while sliding are the hand's, not the texture's
MIN_FILTERED_SAMPLES = 100  # zero-phase filtering needs this many log samples


def _band(signal: np.ndarray, t: np.ndarray, corner_hz: float, kind: str) -> np.ndarray:
    """Zero-phase 2nd-order Butterworth low- or high-pass of ``signal`` (along axis 0)."""
    rate_hz = 1.0 / float(np.median(np.diff(t)))
    return sosfiltfilt(butter(2, corner_hz, btype=kind, fs=rate_hz, output="sos"), signal, axis=0)


def force_roughness(log, ramp_s: float) -> Optional[Dict]:
    """How jagged the rendered force is in contact: its RMS above SMOOTH_BELOW_HZ (N)
    in contact and in free motion (the tracker noise's floor), and what contact adds
    to that floor, in quadrature. None for runs too short to filter or without both."""
    contact = (log["tool_in_contact"] > 0.5) & engaged_mask(log, ramp_s)
    free = free_mask(log, ramp_s)
    if contact.sum() < 10 or free.sum() < 10 or len(log["t"]) < MIN_FILTERED_SAMPLES:
        return None
    force = log["f_user"]
    rough = force - _band(force, log["t"], SMOOTH_BELOW_HZ, "lowpass")
    in_contact, in_free = (float(np.sqrt(np.mean(np.sum(rough[mask] ** 2, axis=1))))
                           for mask in (contact, free))
    return {"in_contact_n": in_contact, "free_motion_n": in_free,
            "added_by_contact_n": float(np.sqrt(max(in_contact**2 - in_free**2, 0.0)))}


def palpation_metrics(log, ramp_s: float) -> Dict:
    """Strikes (short contacts: their peak upward force), the slide (long contacts
    while the tool moves sideways: the z-force variation the texture gives), and
    the roughness of the force in contact."""
    t = log["t"]
    engaged = engaged_mask(log, ramp_s)
    contact = (log["tool_in_contact"] > 0.5) & engaged
    strikes, sliding = [], np.zeros_like(contact)
    speed = np.linalg.norm(recorded_pose(log)[2][:, 3:5], axis=1)
    for touch in _runs(_near(contact, t, CONTACT_GAP_S / 2) & engaged):
        touching = np.flatnonzero(contact[touch]) + touch.start
        if t[touching[-1]] - t[touching[0]] < STRIKE_MAX_S:
            strikes.append({"time_s": float(t[touching[0]]),
                            "peak_force_z_n": float(log["f_user"][touch, 2].max())})
        else:
            sliding[touch] = speed[touch] > 5 * SLIDING_SPEED_M_S
    variation = None
    if sliding.any() and len(t) >= MIN_FILTERED_SAMPLES:
        texture = _band(log["f_user"][:, 2], t, TEXTURE_ABOVE_HZ, "highpass")
        smooth_texture = _band(texture, t, SMOOTH_BELOW_HZ, "lowpass")
        variation = float(np.sqrt(np.mean(smooth_texture[sliding] ** 2)))
    return {
        "strikes": strikes,
        "sliding_s": float(sliding.sum() * np.median(np.diff(t))),
        # z-force variation while sliding, between TEXTURE_ABOVE_HZ and SMOOTH_BELOW_HZ (N)
        "sliding_force_z_variation_n": variation,
        "sliding_mean_force_z_n": (float(log["f_user"][sliding, 2].mean())
                                   if sliding.any() else None),
    }


def _runs(mask: np.ndarray) -> List[slice]:
    """Slices of the consecutive True runs in ``mask``."""
    edges = np.diff(np.concatenate(([0], mask.astype(int), [0])))
    return [slice(a, b) for a, b in zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1))]


def _near(mask: np.ndarray, t: np.ndarray, guard_s: float) -> np.ndarray:
    """``mask`` widened by ``guard_s`` (s) on both sides."""
    dt = float(np.median(np.diff(t))) if len(t) > 1 else 1.0
    n = int(np.ceil(guard_s / dt))
    return binary_dilation(mask, structure=np.ones(2 * n + 1, dtype=bool))


def engaged_mask(log: Dict[str, np.ndarray], ramp_s: float) -> np.ndarray:
    """Samples in haptic mode after the coupling's force ramp has completed."""
    haptic = log["haptic_mode"] == HAPTIC
    mask = np.zeros_like(haptic)
    t = log["t"]
    for run in _runs(haptic):
        mask[run] = t[run] >= t[run.start] + ramp_s
    return mask


def clamped_in_haptics_s(log: Dict[str, np.ndarray]) -> float:
    """How long (s) the coupling's wrench was clamped at its limits while in haptic mode:
    out of it the coupling still runs, but nobody feels it."""
    clamped = (log["coupling_clamped"] > 0.5) & (log["haptic_mode"] == HAPTIC)
    return float(np.sum(clamped) * np.median(np.diff(log["t"])))


def free_mask(log, ramp_s: float) -> np.ndarray:
    """Samples engaged, held and at least CONTACT_GUARD_S from any contact."""
    return (engaged_mask(log, ramp_s) & (log["handle_gripped"] > 0.5)
            & ~_near(log["tool_in_contact"] > 0.5, log["t"], CONTACT_GUARD_S))


def free_motion(log, ramp_s: float) -> Optional[Dict]:
    """Rendered wrench while engaged, held and far from any contact: should be ~0."""
    t = log["t"]
    free = free_mask(log, ramp_s)
    if not free.any():
        return None
    force = np.linalg.norm(log["f_user"][free], axis=1)
    torque = np.linalg.norm(log["tau_user"][free], axis=1)
    speed = np.linalg.norm(recorded_pose(log)[2][free, 3:6], axis=1)
    return {"duration_s": float(np.sum(free) * np.median(np.diff(t))),
            "max_force_n": float(force.max()), "rms_force_n": float(np.sqrt(np.mean(force**2))),
            "max_torque_nmm": float(1e3 * torque.max()),
            "max_speed_mm_s": float(1e3 * speed.max())}


def releases(log, rest_height_m: float, debounce_s: float) -> List[Dict]:
    """What followed each let-go of the handle while haptics was engaged."""
    t = log["t"]
    gripped = log["handle_gripped"] > 0.5
    events = []
    for k in np.flatnonzero(gripped[:-1] & ~gripped[1:]) + 1:
        if log["haptic_mode"][k] != HAPTIC:
            continue
        window = (t >= t[k]) & (t <= t[k] + RELEASE_WINDOW_S) & ~gripped
        after = (t > t[k] + debounce_s + 0.01) & (t <= t[k] + RELEASE_WINDOW_S)
        modes = log["haptic_mode"][after]
        if np.any(modes == LANDING):
            outcome = "landed"
        elif np.any(gripped[after]):
            outcome = "gripped again"
        elif np.any(modes != HAPTIC):
            outcome = "haptics disabled"
        else:
            outcome = "held by the scene"
        p_WI, _, V_WI, _ = recorded_pose(log)
        deviation = np.linalg.norm(p_WI[window] - p_WI[k], axis=1)
        last = window & (t >= t[k] + RELEASE_WINDOW_S - 2.0)
        events.append({
            "time_s": float(t[k]),
            "outcome": outcome,
            "watched_s": float(t[window][-1] - t[k]) if window.any() else 0.0,
            "max_deviation_mm": float(1e3 * deviation.max()) if window.any() else None,
            # The last 2 s of the window: a settled hold has no motion left.
            "final_speed_rms_mm_s": (float(1e3 * np.sqrt(np.mean(np.sum(
                V_WI[last, 3:6] ** 2, axis=1)))) if last.any() else None),
            "final_height_above_rest_mm": float(1e3 * (p_WI[window][-1, 2]
                                                       - rest_height_m)) if window.any() else None,
            "max_coil_current_a": float(np.max(np.abs(log["coil_currents"][window])))
            if window.any() else None,
        })
    return events


def peg_centers(log, scene: PegInHole) -> np.ndarray:
    """(N, 3) centre of the simulated peg in W (m): ``tool_offset_m`` in the tool's frame."""
    offset = np.asarray(scene.tool_offset_m, float)
    return log["p_WT"] + rotations_of_quaternions(log["q_WT"]).apply(offset)


def peg_metrics(log, scene: PegInHole, ramp_s: float) -> Dict:
    """Stiffness of pressing on the hole's floor, sliding friction, x travel in the hole."""
    t = log["t"]
    engaged = engaged_mask(log, ramp_s)
    # Where the peg's bottom would be if it moved rigidly with the instrument (level).
    z_bottom_D = (log["p_WI_measured"][:, 2] + scene.tool_offset_m[2]
                  - scene.peg_size_m[2] / 2)
    p_WPeg = peg_centers(log, scene)
    floor_z = scene.hole_center_m[2] - scene.hole_size_m[2]
    depth = floor_z - z_bottom_D
    f_z = log["f_user"][:, 2]
    pressing = engaged & (log["tool_in_contact"] > 0.5) & (depth > DEPTH_MIN_M)
    result: Dict = {"floor_z_mm": 1e3 * floor_z}
    if np.sum(pressing) > 10:
        # Least squares through the origin: force = stiffness * depth.
        d, f = depth[pressing], f_z[pressing]
        stiffness = float(d @ f / (d @ d))
        residual = f - stiffness * d
        result["effective_stiffness_n_per_mm"] = 1e-3 * stiffness
        result["stiffness_fit_r2"] = float(1 - residual @ residual / np.sum((f - f.mean())**2))
        result["max_depth_mm"] = float(1e3 * d.max())
        result["max_normal_force_n"] = float(f.max())
    v_T = np.gradient(p_WPeg[:, 0:2], t, axis=0)
    sliding = pressing & (np.linalg.norm(v_T, axis=1) > SLIDING_SPEED_M_S) & (f_z > 0.1)
    if np.sum(sliding) > 10:
        tangential = np.linalg.norm(log["tool_contact_wrench_W"][sliding, 0:2], axis=1)
        normal = log["tool_contact_wrench_W"][sliding, 2]
        result["sliding_friction_ratio"] = float(np.median(tangential / normal))
        result["sliding_duration_s"] = float(np.sum(sliding) * np.median(np.diff(t)))
    top_z = scene.hole_center_m[2]
    inside = engaged & (p_WPeg[:, 2] - scene.peg_size_m[2] / 2 < top_z - 1e-3)
    if inside.any():
        x = p_WPeg[inside, 0] - scene.hole_center_m[0]
        result["x_range_in_hole_mm"] = float(1e3 * (x.max() - x.min()))
        result["x_clearance_mm"] = float(1e3 * (scene.hole_size_m[0] - scene.peg_size_m[0]))
        result["z_instrument_range_in_hole_mm"] = [
            float(1e3 * log["p_WI_measured"][inside, 2].min()),
            float(1e3 * log["p_WI_measured"][inside, 2].max())]
    return result


def contact_hits(log, ramp_s: float, tool_offset_m) -> List[Dict]:
    """Each contact episode of the tool while engaged: where it hit (in the tool's
    x, from the contact wrench's moment) and the torque the user felt."""
    t = log["t"]
    engaged = engaged_mask(log, ramp_s)
    hits = []
    for run in _runs((log["tool_in_contact"] > 0.5) & engaged):
        wrench = log["tool_contact_wrench_W"][run]
        k = int(np.argmax(np.abs(wrench[:, 2])))
        R_WT = rotation_matrix(log["q_WT"][run][k]).matrix()
        # The contact moment about the paddle's centre (tool_offset_m in T), in T.
        f_T = R_WT.T @ wrench[k, 0:3]
        tau_T = R_WT.T @ wrench[k, 3:6] - np.cross(np.asarray(tool_offset_m, float), f_T)
        if abs(f_T[2]) < 1e-3:
            continue
        # A mainly normal force f_z at x on the paddle's face: tau_y = -x f_z.
        x_hit = -tau_T[1] / f_T[2]
        window = slice(run.start, min(run.stop + int(0.05 / np.median(np.diff(t))), len(t)))
        tau_user_y = log["tau_user"][window]
        tau_user_I_y = rotations_of_quaternions(recorded_pose(log)[1][window]).inv().apply(
            tau_user_y)[:, 1]
        peak = float(tau_user_I_y[np.argmax(np.abs(tau_user_I_y))])
        hits.append({"time_s": float(t[run.start]), "duration_s": float(t[run.stop - 1] - t[run.start]),
                     "peak_normal_force_n": float(abs(f_T[2])), "x_hit_mm": float(1e3 * x_hit),
                     "peak_user_torque_about_y_nmm": 1e3 * peak})
    return hits


def haptic_summary(log, scenario, *, rest_height_m: float) -> Dict:
    """The haptic part of summary.json (empty without haptics)."""
    if scenario.haptics is None:
        return {}
    haptics = scenario.haptics
    ramp_s = max(haptics.coupling.ramp_s, haptics.supervisor.handover_s)
    engaged = engaged_mask(log, ramp_s)
    summary: Dict = {
        "haptics_engaged_s": float(np.sum(log["haptic_mode"] == HAPTIC) * np.median(np.diff(log["t"]))),
        # The hanging ball's spring always pulls on the tool: it never moves freely.
        "free_motion": (None if isinstance(haptics.scene, HangingBall)
                        else free_motion(log, ramp_s)),
        "releases": releases(log, rest_height_m, haptics.supervisor.release_debounce_s),
        "coupling_clamped_s": clamped_in_haptics_s(log),
        # What the passivity controller dissipated (J); null when it is off.
        "passivity_dissipated_j": (float(log["passivity_dissipated_j"][-1])
                                   if haptics.coupling.passivity_controller else None),
    }
    if engaged.any():
        summary["max_user_force_n"] = float(np.max(np.linalg.norm(log["f_user"][engaged], axis=1)))
        summary["max_user_torque_nmm"] = float(
            1e3 * np.max(np.linalg.norm(log["tau_user"][engaged], axis=1)))
    scene = haptics.scene
    if isinstance(scene, PegInHole):
        summary["peg_in_hole"] = peg_metrics(log, scene, ramp_s)
    elif isinstance(scene, DeformableSurface):
        summary["palpation"] = palpation_metrics(log, ramp_s)
    if isinstance(scene, (PegInHole, DeformableSurface)):
        summary["force_roughness"] = force_roughness(log, ramp_s)
    elif isinstance(scene, PaddleBall):
        summary["paddle_hits"] = contact_hits(log, ramp_s, scene.tool_offset_m)
    elif isinstance(scene, HangingBall) and engaged.any():
        force = log["f_user"][engaged]
        summary["hanging_ball"] = {
            "user_force_range_n": [float(v) for v in np.ptp(force, axis=0)],
            "mean_user_force_n": [float(v) for v in force.mean(axis=0)]}
    return summary
