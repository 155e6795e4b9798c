"""The plots a person reads after a run: pose, orientation, coil currents, power and heat."""

from __future__ import annotations

from pathlib import Path
from typing import Dict

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


def plot_run(log: Dict[str, np.ndarray], out_dir: Path, *, title: str,
             current_limit_a: float) -> Path:
    """Write ``levitation.png`` (four stacked panels sharing time) and return its path."""
    t = log["t"]
    fig, axes = plt.subplots(4, 1, figsize=(11, 12), sharex=True)
    colors = ("tab:red", "tab:green", "tab:blue")
    ax = axes[0]
    for i, axis in enumerate("xyz"):
        ax.plot(t, 1e3 * log["p_WI_desired"][:, i], color=colors[i], lw=1, ls="--",
                label=f"{axis} commanded")
        ax.plot(t, 1e3 * log["p_WI_true"][:, i], color=colors[i], lw=1.2, label=f"{axis} true")
        ax.plot(t, 1e3 * log["p_WI_measured"][:, i], color="k", lw=0.5, alpha=0.5,
                label="measured" if i == 0 else None)
    ax.set_ylabel("position of I in W [mm]")
    ax.legend(ncol=4, fontsize=8, loc="upper left")
    ax = axes[1]
    for i, axis in enumerate(("roll", "pitch", "yaw")):
        ax.plot(t, np.degrees(log["rpy_WI_desired"][:, i]), color=colors[i], lw=1, ls="--",
                label=f"{axis} commanded")
        ax.plot(t, np.degrees(log["rpy_WI_true"][:, i]), color=colors[i], lw=1.2,
                label=f"{axis} true")
    ax.set_ylabel("orientation [deg]")
    ax.legend(ncol=3, fontsize=8, loc="upper left")
    ax = axes[2]
    currents = log["coil_currents"]
    ax.plot(t, currents, lw=0.7)
    for sign in (-1, 1):
        ax.axhline(sign * current_limit_a, color="k", ls=":", lw=1)
    ax.set_ylabel(f"coil currents [A]\n({currents.shape[1]} coils, limit dotted)")
    ax = axes[3]
    ax.plot(t, log["coil_power_w"], color="tab:purple", lw=1, label="coil power")
    ax.set_ylabel("power [W]")
    lost = log["tracking_ok"] < 0.5
    if lost.any():
        ax.fill_between(t, 0, log["coil_power_w"].max(), where=lost, color="orange", alpha=0.3,
                        label="tracking lost")
    ax.legend(fontsize=8, loc="upper left")
    hottest = ax.twinx()
    hottest.plot(t, log["coil_temperature_c"].max(axis=1), color="tab:red", lw=1)
    hottest.set_ylabel("hottest coil [deg C]", color="tab:red")
    ax.set_xlabel("time [s]")
    for ax in axes:
        ax.grid(alpha=0.3)
    fig.suptitle(title)
    fig.tight_layout()
    path = Path(out_dir) / "levitation.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
