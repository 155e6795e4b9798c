"""Co-location error of the stereo display under head motion, from a run's log.

A virtual point P is drawn for each eye where the line from the eye the view was
computed for (``X_WG_predicted``, or the latest tracker sample for the
"hold" baseline) through P meets the display. The real eye, elsewhere by the
tracking error, sees that spot; the screen-space error is its distance (mm) from
where the real eye needed it. The two real eyes' lines through their spots come
closest at the perceived point; its distance from P is the perceived error (mm).
"""

from __future__ import annotations

from pathlib import Path
from typing import Dict

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from maglev_haptics.analysis.run_plots import save_figure  # noqa: E402

from maglev_haptics.systems.head_sensor import glasses_pose  # noqa: E402
from maglev_haptics.systems.rotations import rotations_of_quaternions  # noqa: E402
from maglev_haptics.systems.stereo import display_rectangle, screen_axes  # noqa: E402

MOVING_SPEED_M_S = 0.05  # the head counts as moving above this eye-midpoint speed (m/s)
# Speeds below this are round-off from differencing equal logged positions, not
# motion (a still head otherwise shows ~1e-14 m/s): 0.1 mm/s (m/s).
SPEED_RESOLUTION_M_S = 1e-4


def eyes_from_poses(poses: np.ndarray, ipd_m: float) -> np.ndarray:
    """(N, 2, 3) left and right eyes (m) of glasses pose vectors (N, 7) [q, p]."""
    seen = np.all(np.isfinite(poses[:, 0:4]), axis=1)  # NaN while the glasses are lost
    x_G = np.full((len(poses), 3), np.nan)
    if seen.any():
        x_G[seen] = rotations_of_quaternions(poses[seen, 0:4]).apply([1.0, 0.0, 0.0])
    half = x_G * ipd_m / 2
    return np.stack([poses[:, 4:7] - half, poses[:, 4:7] + half], axis=1)


def true_eyes(log, ipd_m: float) -> np.ndarray:
    """(N, 2, 3) the real eyes (m) of the logged head (``head_pose``)."""
    poses = np.array([np.concatenate(glasses_pose(h)) for h in log["head_pose"]])
    return eyes_from_poses(poses, ipd_m)


def head_speed(log) -> np.ndarray:
    """(N,) speed of the eyes' midpoint (m/s); 0 below SPEED_RESOLUTION_M_S."""
    speed = np.linalg.norm(np.gradient(log["head_pose"][:, 0:3], log["t"], axis=0), axis=1)
    return np.where(speed < SPEED_RESOLUTION_M_S, 0.0, speed)


def screen_points(screen, eyes: np.ndarray, p_W: np.ndarray) -> np.ndarray:
    """Where the lines from ``eyes`` (..., 3) through p_W (3,) meet the display (..., 3)."""
    _, _, vn = screen_axes(screen.pa, screen.pb, screen.pc)
    ray = p_W - eyes
    scale = ((screen.pa - eyes) @ vn) / (ray @ vn)
    return eyes + ray * scale[..., None]


def closest_point_of_rays(a, u, b, w) -> np.ndarray:
    """Midpoint of the shortest segment between the lines a + s u and b + t w (..., 3)."""
    r = a - b
    uu, uw, ww = (u * u).sum(-1), (u * w).sum(-1), (w * w).sum(-1)
    ur, wr = (u * r).sum(-1), (w * r).sum(-1)
    det = uu * ww - uw**2
    s = (uw * wr - ww * ur) / det
    t = (uu * wr - uw * ur) / det
    return ((a + s[..., None] * u) + (b + t[..., None] * w)) / 2


def colocation_errors(screen, eyes_true: np.ndarray, eyes_drawn: np.ndarray,
                      p_W: np.ndarray) -> Dict[str, np.ndarray]:
    """Screen-space error (N, 2) per eye and perceived 3-D error (N,) of the point p_W,
    in mm, for true and drawn eyes (N, 2, 3)."""
    p_W = np.asarray(p_W, float)
    drawn = screen_points(screen, eyes_drawn, p_W)
    needed = screen_points(screen, eyes_true, p_W)
    perceived = closest_point_of_rays(eyes_true[:, 0], drawn[:, 0] - eyes_true[:, 0],
                                      eyes_true[:, 1], drawn[:, 1] - eyes_true[:, 1])
    return {"screen_mm": 1e3 * np.linalg.norm(drawn - needed, axis=-1),
            "perceived_mm": 1e3 * np.linalg.norm(perceived - p_W, axis=-1)}


def _statistics(values: np.ndarray) -> Dict[str, float]:
    return {"mean": float(np.mean(values)), "p95": float(np.percentile(values, 95)),
            "max": float(np.max(values))}


def colocation_summary(log: Dict[str, np.ndarray], scenario) -> Dict:
    """The co-location errors of the run, with prediction and holding the latest
    sample, over the samples where both views exist and the head moves faster than
    MOVING_SPEED_M_S (over all of them if it never does); also the head's speed."""
    stereo, device = scenario.stereo, scenario.device
    screen = display_rectangle(device.display)
    ipd_m = device.glasses.ipd_m
    eyes_true = true_eyes(log, ipd_m)
    drawn = {"predicted": eyes_from_poses(log["X_WG_predicted"], ipd_m),
             "held": eyes_from_poses(log["X_WG_latest"], ipd_m)}
    valid = np.all(np.isfinite(drawn["predicted"]), axis=(1, 2)) & np.all(
        np.isfinite(drawn["held"]), axis=(1, 2))
    speed = head_speed(log)
    moving = valid & (speed > MOVING_SPEED_M_S)
    summary = {"points_m": stereo.colocation_points_m,
               "samples": int(valid.sum()),
               "head_speed_m_s": {"mean_moving": float(speed[moving].mean()) if moving.any()
                                  else 0.0, "max": float(speed.max())},
               "moving_share": float(moving.sum() / max(valid.sum(), 1))}
    if not valid.any():
        return summary
    # While the head moves, where the errors are; a still head has only tracker noise.
    used = moving if moving.any() else valid
    summary["over"] = "head moving" if moving.any() else "whole run (the head never moved)"
    for name, eyes in drawn.items():
        errors = [colocation_errors(screen, eyes_true[used], eyes[used], np.asarray(p, float))
                  for p in stereo.colocation_points_m]
        screen_mm = np.concatenate([e["screen_mm"].ravel() for e in errors])
        perceived_mm = np.concatenate([e["perceived_mm"] for e in errors])
        summary[name] = {"screen_error_mm": _statistics(screen_mm),
                         "perceived_error_mm": _statistics(perceived_mm)}
    summary["mean_screen_error_ratio"] = (summary["predicted"]["screen_error_mm"]["mean"]
                                          / max(summary["held"]["screen_error_mm"]["mean"],
                                                1e-12))
    return summary


def stereo_summary(log, scenario, parts, video_summary) -> Dict:
    """summary.json's ``stereo``: co-location errors (against the true head, so only
    with a simulated station), and the frames rendered and written."""
    summary = {"view_rate_hz": 1.0 / parts.view.view_period_s}
    if "head_pose" in log:
        summary["colocation"] = colocation_summary(log, scenario)
    renderer = parts.renderer
    if renderer is not None:
        summary["images"] = {
            "rendered_pairs": renderer.frames_rendered, "skipped_pairs": renderer.frames_skipped,
            "render_ms_per_pair": (1e3 * renderer.render_wall_s / renderer.frames_rendered
                                   if renderer.frames_rendered else None),
            "size_px": scenario.stereo.images.size_px}
    if video_summary is not None:
        summary["video"] = video_summary
    return summary


def plot_colocation(log: Dict[str, np.ndarray], scenario, out_dir: Path, title: str) -> Path:
    """stereo.png: head speed, and the first point's screen-space error (mean of the
    eyes) with prediction and holding the latest sample, against time."""
    device = scenario.device
    screen = display_rectangle(device.display)
    ipd_m = device.glasses.ipd_m
    t = log["t"]
    eyes_true = true_eyes(log, ipd_m)
    point = np.asarray(scenario.stereo.colocation_points_m[0], float)
    speed = head_speed(log)
    figure, (top, bottom) = plt.subplots(2, 1, sharex=True, figsize=(9, 6))
    top.plot(t, speed, color="0.3")
    top.axhline(MOVING_SPEED_M_S, color="0.6", linestyle="--", linewidth=0.8,
                label=f"moving: above {MOVING_SPEED_M_S} m/s (summary.json's errors)")
    # A still head's speed is 0 on a readable scale, not autoscaled noise.
    top.set_ylim(0.0, 1.1 * max(speed.max(), 2 * MOVING_SPEED_M_S))
    top.set_ylabel("head speed (m/s)")
    top.legend(loc="best")
    top.set_title(f"{title}: co-location of a virtual point at {np.round(1e3 * point).tolist()} mm")
    for key, label, color in (("X_WG_latest", "latest 10 Hz sample (no prediction)", "tab:red"),
                              ("X_WG_predicted", "predicted (Kalman, constant velocity)",
                               "tab:blue")):
        eyes = eyes_from_poses(log[key], ipd_m)
        valid = np.all(np.isfinite(eyes), axis=(1, 2))
        error = np.full(len(t), np.nan)
        error[valid] = colocation_errors(screen, eyes_true[valid], eyes[valid],
                                         point)["screen_mm"].mean(axis=1)
        bottom.plot(t, error, color=color, label=label)
    bottom.set_ylabel("screen-space error (mm)")
    bottom.set_xlabel("time (s)")
    bottom.legend(loc="upper right")
    return save_figure(figure, Path(out_dir) / "stereo.png")
