"""The plots a person reads after a run: pose, tracking error, coil currents, power and heat."""

from pathlib import Path
from typing import Dict

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from maglev_haptics.analysis.run_metrics import angle_between_deg, recorded_pose  # noqa: E402
from maglev_haptics.diagrams.runner import TickTimes, realtime_report  # noqa: E402
from maglev_haptics.systems.haptic_supervisor import HAPTIC  # noqa: E402

AXIS_COLORS = ("tab:red", "tab:green", "tab:blue")
MIN_TEMPERATURE_SPAN_C = 1.0  # the temperature axis spans at least this (K)


def save_figure(figure, path: Path, *, dpi: int = 110, tight: bool = True) -> Path:
    """Lay out (unless the figure does its own), write ``path`` and free the figure."""
    if tight:
        figure.tight_layout()
    figure.savefig(path, dpi=dpi)
    plt.close(figure)
    return path

def legend_outside(ax) -> None:
    """The legend beside the axes, never on what they show."""
    legend = ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.07, 1.0),
                       borderaxespad=0.0)
    for line in legend.get_lines():  # a faint or thin trace still gets a legible key
        line.set_linewidth(2.0)
        line.set_alpha(1.0)


def _round_up_125(value: float) -> float:
    """The least of 1, 2, 5 times a power of ten that is >= ``value`` (> 0)."""
    power = 10.0 ** np.floor(np.log10(value))
    return float(next(step * power for step in (1, 2, 5, 10) if step * power >= value * 0.9999))


def plot_run(log: Dict[str, np.ndarray], out_dir: Path, *, title: str,
             current_limit_a: float) -> Path:
    """Write ``levitation.png`` (five stacked panels sharing time) and return its path."""
    t = log["t"]
    # Before the first estimate the measured pose is a placeholder, not a measurement.
    measured = np.cumsum(log["tracking_ok"] > 0.5) > 0
    # With a station on LCM there is no truth: the tracker's estimate stands in for it.
    p_WI, q_WI, _, source = recorded_pose(log)
    rpy_WI = log["rpy_WI_true"] if source == "true" else log["rpy_WI_measured"]
    shown = np.ones(len(t), dtype=bool) if source == "true" else measured
    fig, axes = plt.subplots(5, 1, figsize=(12.5, 14), sharex=True)

    ax = axes[0]
    for i, axis in enumerate("xyz"):
        ax.plot(t, 1e3 * log["p_WI_desired"][:, i], color=AXIS_COLORS[i], lw=1, ls="--",
                label=f"{axis} commanded")
        ax.plot(t[shown], 1e3 * p_WI[shown, i], color=AXIS_COLORS[i], lw=1.2,
                label=f"{axis} {source}")
        if source == "true":  # the estimate over the truth
            ax.plot(t[measured], 1e3 * log["p_WI_measured"][measured, i], color="k", lw=0.5,
                    alpha=0.5, label="measured (each axis)" if i == 0 else None)
    ax.set_ylabel("position of I in W [mm]")
    legend_outside(ax)

    ax = axes[1]
    for i, axis in enumerate(("roll", "pitch", "yaw")):
        ax.plot(t, np.degrees(log["rpy_WI_desired"][:, i]), color=AXIS_COLORS[i], lw=1, ls="--",
                label=f"{axis} commanded")
        ax.plot(t, np.degrees(rpy_WI[:, i]), color=AXIS_COLORS[i], lw=1.2,
                label=f"{axis} {source}")
    ax.set_ylabel("orientation [deg]")
    legend_outside(ax)

    ax = axes[2]
    # Tracking error only while the script flies it: resting on the glass below its
    # commanded touchdown height is not an error (6.6 mm resting, 6 mm commanded), nor
    # is where the user's hand carries it in haptic mode.
    z_desired = log["p_WI_desired"][:, 2]
    flying = z_desired > z_desired.min() + 2e-3
    if "haptic_mode" in log:
        flying &= log["haptic_mode"] != HAPTIC
    error_mm = np.where(flying[:, None], 1e3 * (p_WI - log["p_WI_desired"]), np.nan)
    for i, axis in enumerate("xyz"):
        ax.plot(t, error_mm[:, i], color=AXIS_COLORS[i], lw=0.6, label=f"{axis} error")
    if "haptic_mode" in log and np.any(log["haptic_mode"] == HAPTIC):
        ax.fill_between(t, 0, 1, where=log["haptic_mode"] == HAPTIC, color="tab:purple",
                        alpha=0.1, lw=0, transform=ax.get_xaxis_transform(),
                        label="haptic mode:\nthe hand holds it")
    # Linear over the hover's errors, logarithmic beyond them (takeoff, touchdown, the
    # scripted press into the glass), so that none runs off the panel.
    span = max(np.nanpercentile(np.abs(error_mm), 99) if flying.any() else 0.0, 1e-3)
    linear = _round_up_125(1.5 * span)
    # Up to a round number, labelled: 1.2 times the largest error could fall a hair
    # under the next decade's mark, which then went undrawn.
    reach = _round_up_125(max(linear, 1.2 * np.max(np.abs(np.nan_to_num(error_mm[shown])), initial=0.0)))
    ax.set_yscale("symlog", linthresh=linear, linscale=2.0)
    ax.set_ylim(-reach, reach)
    marks = linear * 10.0 ** np.arange(0, 1 + max(0, int(np.floor(np.log10(reach / linear)
                                                                   + 1e-9))))
    if reach > marks[-1] * (1 + 1e-9):
        marks = np.append(marks, reach)
    ax.set_yticks(np.concatenate((-marks[::-1], [0.0], marks)))
    ax.set_yticklabels([f"{value:g}" for value in np.concatenate((-marks[::-1], [0.0], marks))])
    ax.set_ylabel(f"{source} - commanded [mm], flying\n(linear within +-{linear:g}, log beyond)")
    angle_deg = np.where(flying, angle_between_deg(q_WI, log["rpy_WI_desired"]), np.nan)
    angle = ax.twinx()
    angle.plot(t, angle_deg, color="k", lw=0.6)
    angle.set_ylim(0, 3 * max(np.nanpercentile(angle_deg, 98) if flying.any() else 0.0, 1e-3))
    angle.set_ylabel("angle error [deg] (black)")
    legend_outside(ax)

    ax = axes[3]
    currents = log["coil_currents"]
    busiest = int(np.argmax(np.max(np.abs(currents), axis=0)))
    ax.plot(t, currents, lw=0.6, color="0.6")
    ax.plot(t, currents[:, busiest], lw=1.0, color="tab:purple", label=f"busiest: coil {busiest}")
    for sign in (-1, 1):
        ax.axhline(sign * current_limit_a, color="k", ls=":", lw=1)
    ax.set_ylabel(f"coil currents [A]\n({currents.shape[1]} coils, limit dotted)")
    legend_outside(ax)

    ax = axes[4]
    ax.plot(t, log["coil_power_w"], color="tab:purple", lw=1, label="coil power")
    lost = measured & (log["tracking_ok"] < 0.5)
    if lost.any():
        ax.fill_between(t, 0, log["coil_power_w"].max(), where=lost, color="orange", alpha=0.3,
                        label="tracking lost")
    ax.set_ylabel("power [W]")
    hottest = ax.twinx()
    temperature_c = log["coil_temperature_c"].max(axis=1)
    hottest.plot(t, temperature_c, color="tab:red", lw=1)
    hottest.ticklabel_format(axis="y", useOffset=False)  # 25.004, not 0.004 + 2.5e1
    low, high = temperature_c.min(), temperature_c.max()
    if high - low < MIN_TEMPERATURE_SPAN_C:  # a short run: the warming shown within a kelvin
        middle = (low + high) / 2
        hottest.set_ylim(middle - MIN_TEMPERATURE_SPAN_C / 2, middle + MIN_TEMPERATURE_SPAN_C / 2)
    hottest.set_ylabel("hottest coil [deg C] (red)", color="tab:red")
    legend_outside(ax)
    ax.set_xlabel("time [s]")

    for ax in axes:
        ax.grid(alpha=0.3)
    fig.suptitle(title)
    return save_figure(fig, Path(out_dir) / "levitation.png", dpi=100)


# The least each haptics panel spans, so that a quiet axis's noise (0.003 N, a few um)
# is not stretched into what reads as a signal: the force and torque about zero.
MIN_POSITION_SPAN_MM = 2.0
MIN_FORCE_SPAN_N = 0.5
MIN_TORQUE_SPAN_NMM = 5.0


def span_at_least(ax, span: float, *, about_zero: bool = False) -> None:
    """Widen ``ax``'s y range to ``span`` where autoscale made it narrower: around its
    middle, or ``about_zero`` so zero is in view (a force that is nearly none)."""
    low, high = ax.get_ylim()
    if high - low >= span:
        return
    if about_zero:
        ax.set_ylim(min(low, -span / 2), max(high, span / 2))
    else:
        middle = (low + high) / 2
        ax.set_ylim(middle - span / 2, middle + span / 2)


def plot_haptics(log: Dict[str, np.ndarray], out_dir: Path, *, title: str) -> Path:
    """Write ``haptics.png`` in the layout of the paper's Fig. 9 and 10: x, y, z
    position of the instrument (mm, measured) and x, y, z force rendered on the
    user (N) against time, one axis a row; plus the torque on the user (N*mm)."""
    t = log["t"]
    measured = np.cumsum(log["tracking_ok"] > 0.5) > 0
    fig, axes = plt.subplots(7, 1, figsize=(10, 15), sharex=True)
    engaged = log["haptic_mode"] == HAPTIC
    # Before haptics engages the tool follows the resting instrument and may touch the
    # table, but nothing is rendered to the user: not contact in the Fig. 9 sense.
    contact = engaged & (log["tool_in_contact"] > 0.5)
    for i, axis in enumerate("xyz"):
        ax = axes[i]
        ax.plot(t[measured], 1e3 * log["p_WI_measured"][measured, i], color=AXIS_COLORS[i], lw=1)
        ax.set_ylabel(f"{axis} position [mm]")
        span_at_least(ax, MIN_POSITION_SPAN_MM)
        ax = axes[3 + i]
        ax.plot(t, log["f_user"][:, i], color=AXIS_COLORS[i], lw=0.8)
        ax.set_ylabel(f"{axis} force [N]")
        span_at_least(ax, MIN_FORCE_SPAN_N, about_zero=True)
    ax = axes[6]
    for i, axis in enumerate("xyz"):
        ax.plot(t, 1e3 * log["tau_user"][:, i], color=AXIS_COLORS[i], lw=0.8, label=f"about {axis}")
    ax.set_ylabel("torque [N mm]")
    span_at_least(ax, MIN_TORQUE_SPAN_NMM, about_zero=True)
    legend_outside(ax)
    ax.set_xlabel("time [s]")
    for ax in axes:
        ax.grid(alpha=0.3)
        # Shade where the user feels the tool touch the scene, and mark the haptic phase.
        ax.fill_between(t, 0, 1, where=contact, transform=ax.get_xaxis_transform(),
                        color="tab:orange", alpha=0.12, lw=0)
        ax.fill_between(t, 0, 0.03, where=engaged, transform=ax.get_xaxis_transform(),
                        color="tab:purple", alpha=0.5, lw=0)
    fig.suptitle(f"{title}: position and force rendered on the user\n(orange: tool in "
                 "contact while haptics is engaged; purple strip: haptics engaged)")
    return save_figure(fig, Path(out_dir) / "haptics.png", dpi=100)


def plot_tick_times(times: TickTimes, out_dir: Path, *, title: str) -> Path:
    """Write ``realtime.png``: each paced tick's compute time, and when it ended after
    its wall-clock slot began (a miss ends past the slot: a long compute, or a start
    delayed behind a late tick), and the compute times' distribution."""
    report = realtime_report(times)
    compute_us = 1e6 * times.compute_s
    slot_us = 1e6 * times.slot_s
    ended_us = slot_us + 1e6 * times.lateness_s  # after its slot's start
    missed = times.lateness_s > 0
    tick = np.arange(compute_us.size)
    fig, (trace, spread) = plt.subplots(2, 1, figsize=(11, 7.5))
    # The end behind the compute: orange shows only where a tick started late.
    trace.plot(tick, np.maximum(ended_us, compute_us), lw=0.4, color="tab:orange",
               label="ended, after its slot began\n(a late start included)")
    trace.plot(tick, compute_us, lw=0.4, color="tab:blue", label="compute of a tick")
    trace.plot(tick[missed], ended_us[missed], "o", ms=3, color="tab:red",
               label=f"missed its slot ({report['deadline_misses']}):\nended past it")
    trace.axhline(slot_us, color="k", ls="--", lw=1, label=f"slot {slot_us:.0f} us")
    trace.set_yscale("log")
    trace.set_xlabel("tick")
    trace.set_ylabel("wall time [us]")
    legend_outside(trace)
    bins = np.geomspace(max(compute_us.min(), 1.0), max(compute_us.max(), slot_us) * 1.05, 80)
    spread.hist(compute_us, bins=bins, color="tab:blue")
    spread.set_xscale("log")
    spread.set_yscale("log")
    for name, style in (("p50", ":"), ("p99", "-.")):
        value = report[f"tick_compute_us_{name}"]
        spread.axvline(value, color="tab:green", ls=style, lw=1.2, label=f"{name} {value:.0f} us")
    spread.axvline(slot_us, color="k", ls="--", lw=1, label="slot")
    spread.set_xlabel("compute of a tick [us]")
    spread.set_ylabel("ticks")
    legend_outside(spread)
    for ax in (trace, spread):
        ax.grid(alpha=0.3, which="both")
    fig.suptitle(f"{title}: {report['ticks']} paced ticks, {report['deadline_misses']} missed "
                 f"({100 * report['miss_fraction']:.2f}%), longest stall "
                 f"{report['longest_stall_ms']:.2f} ms")
    return save_figure(fig, Path(out_dir) / "realtime.png")
