"""The haptic loop's passivity, Z-width and stability map for a scenario, from the
exactly discretized loop along one axis (``haptic_loop.py``).

The scenario gives the loop's numbers: the instrument's mass, the hand's grip and
arm impedances and its mass (the instrument hangs on the grip, the hand on the
arm), the coupling's stiffness, damping and velocity filter, the control period,
and the delay from a sample to the force it causes:

    tracker latency + half a tracker period (the mean wait of an 860 Hz sample
    for the 1 kHz tick) + one control period (the currents computed at a tick
    flow from the next) + the amplifiers' lag 1 / (2 pi bandwidth).

The estimator's own filtering (its 50 Hz alpha-beta filter) is left out: the
coupling's 30 Hz filter dominates it.

A tissue scene (a ``ModelScene`` whose models declare deformable bodies) renders
the coupling in series with the tissue: the coupling's spring K and damper B pull
the virtual tool, which presses the tissue with the contact stiffness k_t it meets
(``tissue_press``: the sphere pressed TISSUE_PRESS_DEPTH_M into the top centre of
each body, linearized there; the stiffest body counts). The tool's mass between
them (grams, against a coupling of hundreds of N/m: its mode is far above the
loop's) is taken as zero, so the tool is in balance between the two and the hand
feels the series combination, in z: H k_t / (H + k_t) with H the coupling's
impedance, then the loop's delay. Its passivity is that impedance's; the
closed-loop stability (a Z-width point stable but not passive) is the loop's with
the series combination's low-frequency stiffness and damping,
K k_t / (K + k_t) and B (k_t / (K + k_t))^2.
"""

import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable, Dict, List, Optional

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import scipy.signal  # noqa: E402

from maglev_haptics.analysis.parallel import map_jobs  # noqa: E402
from maglev_haptics.analysis.run_plots import save_figure  # noqa: E402

from maglev_haptics.analysis.haptic_loop import (  # noqa: E402
    LoopParameters, critical_stiffness, environment_impedance, is_stable)
from maglev_haptics.analysis import tissue_press  # noqa: E402
from maglev_haptics.analysis.passivity import passivity_bound, passivity_margin  # noqa: E402
from maglev_haptics.diagrams.haptics import loop_delay_s  # noqa: E402


class StudyNotApplicable(ValueError):
    """The study does not apply to this scenario; the message says why."""


def loop_parameters(scenario, axis: int = 0) -> LoopParameters:
    """The 1-DOF loop along W's ``axis`` (0 x, 1 y, 2 z) of a haptic scenario."""
    if scenario.haptics is None:
        raise StudyNotApplicable(
            "it has no haptic coupling (haptics: null): there is no rendered environment "
            "whose loop to analyse; the levitation loop's own analyses are `linearize` and "
            "`multirate`")
    device = scenario.device
    coupling = scenario.haptics.coupling
    hand = scenario.hand.impedance
    period_s = 1.0 / scenario.control_rate_hz
    delay_s = loop_delay_s(scenario)
    return LoopParameters(
        mass_kg=device.instrument_spec().mass_kg, device_damping=0.0,
        hand_damping=hand.arm_translational_damping[axis],
        hand_stiffness=hand.arm_translational_stiffness[axis],
        grip_stiffness=hand.grip_translational_stiffness[axis],
        grip_damping=hand.grip_translational_damping[axis], hand_mass_kg=hand.mass_kg,
        stiffness=coupling.translational_stiffness[axis],
        damping=coupling.translational_damping[axis], period_s=period_s, delay_s=delay_s,
        velocity_filter_hz=coupling.velocity_filter_hz)


def stability_warnings(scenario, label: str) -> List[str]:
    """A line for each axis along which the loop analysis (``haptic_loop.is_stable``
    on ``loop_parameters``, ~10 ms an axis) predicts the scenario's coupling gains
    unstable at its control rate and delays; none for a scenario without a coupling
    or a hand to hold it."""
    if scenario.haptics is None or scenario.hand is None:
        return []
    lines = []
    for axis, name in enumerate("xyz"):
        p = loop_parameters(scenario, axis)
        if is_stable(p):
            continue
        lines.append(
            f"warning: {label}: the loop analysis predicts the haptic coupling unstable "
            f"along {name}: haptics.coupling.translational_stiffness[{axis}] = "
            f"{p.stiffness:g} N/m is past the {critical_stiffness(p):.0f} N/m this loop "
            f"holds ({scenario.control_rate_hz:g} Hz, {1e3 * p.delay_s:.2f} ms delay, damping "
            f"{p.damping:g} N s/m); " + (
                "the passivity controller is on" if scenario.haptics.coupling.passivity_controller
                else "lower it, or set haptics.coupling.passivity_controller: true"))
    return lines


def _parameters_dict(p: LoopParameters) -> Dict:
    return {name: getattr(p, name) for name in p.__dataclass_fields__}


# --- tissue --------------------------------------------------------------------------

TISSUE_PRESS_DEPTH_M = 3e-3  # the depth at which the tissue's contact is linearized (m)


def tissue_contact(scenario) -> Optional[Dict]:
    """None unless the scenario's scene holds tissue; else the contact stiffness
    (N/m) the tool meets pressed TISSUE_PRESS_DEPTH_M into each body's top centre
    (the middle of its nodes' x-y extent, where the shipped slab's lump lies: the
    stiffest spot, the conservative one for the loop), the stiffest body's for the
    loop. About 3 s a body."""
    from maglev_haptics.diagrams.tissue_model import read_scene_tissue
    from maglev_haptics.diagrams.tissue_scene import kernel_model

    scene = scenario.haptics.scene if scenario.haptics is not None else None
    if not hasattr(scene, "directives"):
        return None
    bodies = read_scene_tissue(scene.directives, "haptics.scene.directives").bodies
    if not bodies:
        return None
    probe = tissue_press.scene_probe(scene)
    rows = []
    for body in bodies:
        lower, upper = body.positions_m.min(axis=0), body.positions_m.max(axis=0)
        p_xy = 0.5 * (lower[:2] + upper[:2])
        model = kernel_model(body, scene.tissue)
        rows.append({
            "body": f"{body.model}::{body.name}", "press_point_xy_W_m": p_xy.tolist(),
            "surface_z_m": tissue_press.surface_top_m(body.positions_m, body.tetrahedra, p_xy),
            "contact_stiffness_n_m": tissue_press.contact_stiffness(
                model, probe, p_xy, TISSUE_PRESS_DEPTH_M)})
    return {"bodies": rows, "press_depth_m": TISSUE_PRESS_DEPTH_M,
            "probe_radius_m": probe.radius_m,
            "probe_stiffness_n_per_m3": probe.stiffness_n_per_m3,
            "contact_stiffness_n_m": max(row["contact_stiffness_n_m"] for row in rows)}


def felt_loop(p: LoopParameters, tissue_stiffness_n_m: Optional[float]) -> LoopParameters:
    """``p`` with the coupling's K and B replaced by their series combination with
    the tissue's contact stiffness k_t (N/m), at low frequency: K k_t / (K + k_t)
    and B (k_t / (K + k_t))^2; ``p`` itself where there is no tissue."""
    if tissue_stiffness_n_m is None:
        return p
    share = tissue_stiffness_n_m / (p.stiffness + tissue_stiffness_n_m)
    return replace(p, stiffness=p.stiffness * share, damping=p.damping * share ** 2)


def felt_impedance(p: LoopParameters, tissue_stiffness_n_m: Optional[float]):
    """The rendered environment the hand feels, a ``scipy.signal.dlti`` (force over
    displacement): ``environment_impedance`` in series with the tissue's contact
    stiffness k_t (N/m) where there is one, the massless tool between them, the
    loop's delay after both: k_t N / (k_t D + N) z^-d for the coupling's N / D."""
    delayed = environment_impedance(p)
    if tissue_stiffness_n_m is None:
        return delayed
    coupling = environment_impedance(replace(p, delay_s=0.0))
    numerator, denominator = coupling.num, coupling.den
    delay = [1.0] + [0.0] * (len(delayed.den) - len(denominator))  # z^d
    return scipy.signal.dlti(
        tissue_stiffness_n_m * numerator,
        np.polymul(np.polyadd(tissue_stiffness_n_m * denominator, numerator), delay),
        dt=p.period_s)


def _tissue_fields(tissue: Optional[Dict], p: LoopParameters) -> Dict:
    """The study's tissue fields: the contact and the felt stiffness and damping."""
    if tissue is None:
        return {}
    felt = felt_loop(p, tissue["contact_stiffness_n_m"])
    return {"tissue": tissue, "felt_stiffness_n_m": felt.stiffness,
            "felt_damping_n_s_m": felt.damping}


# --- passivity -------------------------------------------------------------------

def passivity_study(scenario) -> Dict:
    """The coupling's passivity margin with the device's own damping (zero for a
    maglev device), the damping it needs over frequency, and whether the hand's
    damping covers it. In a tissue scene, the coupling in series with the tissue's
    contact stiffness (module docstring): the environment the hand feels pressing it."""
    p = loop_parameters(scenario)
    tissue = tissue_contact(scenario)
    k_t = None if tissue is None else tissue["contact_stiffness_n_m"]
    H = felt_impedance(p, k_t)
    needed = -passivity_margin(H, 0.0)
    frequencies_hz = np.linspace(1.0, 0.5 / p.period_s, 400)
    bound = passivity_bound(H, 2 * np.pi * frequencies_hz * p.period_s)
    wall = felt_impedance(replace(p, delay_s=0.0, velocity_filter_hz=math.inf), k_t)
    felt = felt_loop(p, k_t)
    return {
        "parameters": _parameters_dict(p), **_tissue_fields(tissue, p),
        "margin_device_only_n_s_m": passivity_margin(H, p.device_damping),
        "damping_needed_n_s_m": needed,
        "margin_with_hand_n_s_m": passivity_margin(H, p.device_damping + p.hand_damping),
        "ideal_wall_damping_needed_n_s_m": -passivity_margin(wall, 0.0),
        # K T / 2 + |B| holds for a spring and damper only, not through the tissue.
        "closed_form_ideal_wall_n_s_m": (p.stiffness * p.period_s / 2 + abs(p.damping)
                                         if tissue is None else None),
        "frequencies_hz": frequencies_hz.tolist(),
        "damping_needed_by_frequency_n_s_m": bound.tolist(),
        "meaning": (
            f"A maglev device has no damping of its own, so the rendered coupling "
            f"(K {p.stiffness:g} N/m, B {p.damping:g} N s/m, velocity filtered at "
            f"{p.velocity_filter_hz:g} Hz, {1e3 * p.delay_s:.2f} ms delay rounded up to whole "
            f"{1e3 * p.period_s:g} ms periods) is passive only if the hand or the controller "
            f"supplies {needed:.2f} N s/m of damping; the simulated hand's arm gives "
            f"{p.hand_damping:g} N s/m." + ("" if tissue is None else
            f" The tool presses tissue {TISSUE_PRESS_DEPTH_M * 1e3:g} mm deep at its top "
            f"centre, meeting {k_t:.1f} N/m: in series with the coupling the hand feels "
            f"{felt.stiffness:.1f} N/m and {felt.damping:.3g} N s/m.")),
    }


def plot_passivity(results: Dict, out_dir: Path, title: str) -> Path:
    p = results["parameters"]
    figure, axes = plt.subplots(figsize=(8, 4.5))
    axes.plot(results["frequencies_hz"], results["damping_needed_by_frequency_n_s_m"],
              label="damping the environment needs at each frequency")
    axes.axhline(p["device_damping"] + p["hand_damping"], color="tab:green", ls="--",
                 label="device + hand damping")
    axes.axhline(p["device_damping"], color="tab:red", ls=":", label="device damping (maglev)")
    axes.set_xlabel("frequency (Hz)")
    axes.set_ylabel("damping (N s/m)")
    pressing = ("" if "tissue" not in results else
                f"\npressing tissue (k_t {results['tissue']['contact_stiffness_n_m']:.1f} N/m "
                f"at {1e3 * results['tissue']['press_depth_m']:g} mm) through the coupling: "
                f"felt {results['felt_stiffness_n_m']:.1f} N/m")
    axes.set_title(f"{title}: passivity (Colgate and Schenkel), needs "
                   f"{results['damping_needed_n_s_m']:.2f} N s/m{pressing}", fontsize=10)
    axes.legend()
    return save_figure(figure, Path(out_dir) / "passivity.png")


# --- Z-width ----------------------------------------------------------------------

@dataclass
class ZWidthSettings:
    stiffness_n_m: List[float]  # K grid (N/m)
    damping_n_s_m: List[float]  # B grid (N s/m)

    @classmethod
    def full(cls):
        return cls(np.geomspace(10, 2e4, 60).tolist(), np.linspace(-5, 40, 46).tolist())

    @classmethod
    def quick(cls):
        return cls(np.geomspace(10, 2e4, 12).tolist(), np.linspace(-5, 40, 10).tolist())


def zwidth_study(scenario, settings: ZWidthSettings,
                 progress: Optional[Callable[[int, int], None]] = None) -> Dict:
    """Colgate and Brown's Z-width: over a grid of the rendered stiffness K and
    damping B, each point is passive with the device's damping alone, passive with the
    hand's as well, stable in closed loop with the hand (but not passive), or unstable.
    Region codes: 3 passive (device), 2 passive with the hand, 1 stable, 0 unstable.
    In a tissue scene each (K, B) is the coupling's, in series with the tissue's
    contact stiffness (module docstring)."""
    p = loop_parameters(scenario)
    tissue = tissue_contact(scenario)
    k_t = None if tissue is None else tissue["contact_stiffness_n_m"]
    K, B = np.asarray(settings.stiffness_n_m), np.asarray(settings.damping_n_s_m)
    region = np.zeros((len(B), len(K)), dtype=int)
    for i, damping in enumerate(B):
        for j, stiffness in enumerate(K):
            region[i, j] = zwidth_region(replace(p, stiffness=float(stiffness),
                                                 damping=float(damping)), k_t)
        if progress is not None:
            progress(i + 1, len(B))
    stable_K = [float(K[row >= 1].max()) if (row >= 1).any() else None for row in region]
    return {"parameters": _parameters_dict(p), **_tissue_fields(tissue, p),
            "stiffness_n_m": K.tolist(),
            "damping_n_s_m": B.tolist(), "region": region.tolist(),
            "region_codes": {str(code): name for code, name in enumerate(ZWIDTH_REGIONS)},
            "largest_stable_stiffness_by_damping_n_m": stable_K,
            "scenario_point": {"stiffness_n_m": p.stiffness, "damping_n_s_m": p.damping,
                               "region": ZWIDTH_REGIONS[zwidth_region(p, k_t)]}}


# The Z-width's regions, by their code.
ZWIDTH_REGIONS = ("unstable", "stable with the hand, not passive",
                  "passive with the hand's damping", "passive with the device's damping alone")


def zwidth_region(p, tissue_stiffness_n_m: Optional[float] = None) -> int:
    """The Z-width region code (an index of ZWIDTH_REGIONS) of the loop ``p``, its
    coupling in series with the tissue's contact stiffness (N/m) if one is given."""
    H = felt_impedance(p, tissue_stiffness_n_m)
    # A negative damper in series with the tissue is an unstable environment: never
    # passive (passivity_margin takes stable ones only).
    if np.all(np.abs(H.poles) < 1.0):
        if passivity_margin(H, p.device_damping) > 0:
            return 3
        if passivity_margin(H, p.device_damping + p.hand_damping) > 0:
            return 2
    return 1 if is_stable(felt_loop(p, tissue_stiffness_n_m)) else 0


def plot_zwidth(results: Dict, out_dir: Path, title: str) -> Path:
    K, B = np.array(results["stiffness_n_m"]), np.array(results["damping_n_s_m"])
    region = np.array(results["region"])
    colors = matplotlib.colors.ListedColormap(["#d9534f", "#f0ad4e", "#5bc0de", "#5cb85c"])
    figure, axes = plt.subplots(figsize=(8, 5.5))
    mesh = axes.pcolormesh(K, B, region, cmap=colors, vmin=-0.5, vmax=3.5, shading="nearest")
    bar = figure.colorbar(mesh, ticks=[0, 1, 2, 3])
    bar.ax.set_yticklabels(["unstable", "stable (hand)", "passive (hand)", "passive (device)"])
    point = results["scenario_point"]
    axes.plot(point["stiffness_n_m"], point["damping_n_s_m"], "k*", ms=14,
              label="the scenario's coupling")
    axes.set_xscale("log")
    axes.set_xlabel("rendered stiffness K (N/m)")
    axes.set_ylabel("rendered damping B (N s/m)")
    if "tissue" in results:
        # The felt stiffness can never pass the tissue's: the coupling is in series.
        axes.axvline(results["tissue"]["contact_stiffness_n_m"], color="k", ls=":",
                     label="tissue contact stiffness k_t (3 mm pressed)")
        axes.set_xlabel("coupling stiffness K (N/m), in series with the tissue's k_t")
    axes.set_title(f"{title}: Z-width")
    axes.legend(loc="upper left")
    return save_figure(figure, Path(out_dir) / "zwidth.png")


# --- stability map ----------------------------------------------------------------

@dataclass
class StabilityMapSettings:
    rates_hz: List[float]  # control rates swept (Hz)
    delays_s: List[float]  # delays swept (s)
    damping_n_s_m: List[float]  # B axis (N s/m)

    @classmethod
    def full(cls):
        return cls([500.0, 860.0, 1000.0, 2000.0], [0.0, 1e-3, 2.5e-3, 5e-3],
                   np.linspace(0.0, 30.0, 31).tolist())

    @classmethod
    def quick(cls):
        return cls([860.0, 1000.0], [0.0, 2.5e-3], [0.0, 5.0, 10.0])


def stability_map_study(scenario, settings: StabilityMapSettings,
                        progress: Optional[Callable[[int, int], None]] = None, *,
                        workers: int = 1, scheduler: Optional[str] = None) -> Dict:
    """The largest stable coupling stiffness against damping, for each control rate
    and delay, from the linear model of the instrument against a wall with the
    scenario's hand; with the closed form 2 (b + B) / (T + 2 tau) it must reproduce in
    its limit (a heavy, damped mass with no hand stiffness and no filter, b the hand's
    damping) beside each curve. ``maglev analyze stability-map`` adds the whole loop's
    onset in free space, linearized and simulated (``onset.py``). Each (rate, delay)
    curve is a job (``analysis/parallel.py``: ``workers``, ``scheduler``)."""
    p = loop_parameters(scenario)
    jobs = [(replace(p, period_s=1.0 / rate, delay_s=delay), rate, list(settings.damping_n_s_m))
            for rate in settings.rates_hz for delay in settings.delays_s]
    curves = map_jobs(stability_curve, jobs, workers=workers, scheduler=scheduler,
                      description="stability curves", progress=False, on_result=progress)
    return {"parameters": _parameters_dict(p), "damping_n_s_m": settings.damping_n_s_m,
            "curves": curves.results,
            "scenario_critical_stiffness_n_m": critical_stiffness(p)}


def stability_curve(job) -> Dict:
    """One curve of the stability map: ``job`` is (the loop's parameters at a rate
    and delay, that rate in Hz, the dampings N s/m)."""
    q, rate_hz, dampings = job
    limit = replace(q, mass_kg=50.0, hand_stiffness=0.0, grip_stiffness=None,
                    velocity_filter_hz=math.inf)
    return {"rate_hz": rate_hz, "delay_s": q.delay_s,
            "critical_stiffness_n_m": [critical_stiffness(replace(q, damping=float(b)))
                                       for b in dampings],
            "limit_model_critical_stiffness_n_m": [
                critical_stiffness(replace(limit, damping=float(b))) for b in dampings],
            "closed_form_limit_n_m": [2 * (q.hand_damping + b) / (q.period_s + 2 * q.delay_s)
                                      for b in dampings]}


def plot_stability_map(results: Dict, out_dir: Path, title: str) -> Path:
    B = results["damping_n_s_m"]
    curves = results["curves"]
    rates = sorted({c["rate_hz"] for c in curves})
    figure, panels = plt.subplots(1, len(rates), figsize=(4.2 * len(rates), 4.5), sharey=True,
                                  squeeze=False)
    for panel, rate in zip(panels[0], rates):
        for index, curve in enumerate(c for c in curves if c["rate_hz"] == rate):
            color = f"C{index}"
            label = f"delay {1e3 * curve['delay_s']:g} ms"
            panel.plot(B, curve["critical_stiffness_n_m"], color=color, label=label)
            panel.plot(B, curve["closed_form_limit_n_m"], color=color, ls=":", lw=1)
            panel.plot(B, curve["limit_model_critical_stiffness_n_m"], color=color, ls="none",
                       marker=".", ms=4)
        for point in results.get("onset", []):
            if point.get("control_rate_hz") != rate:
                continue
            for key, marker, name in (("linear_critical_stiffness_n_m", "*", "linearized"),
                                      ("simulated_critical_stiffness_n_m", "X", "simulated")):
                panel.plot(point["damping_n_s_m"], point[key], marker, color="k", ms=10,
                           mfc="none" if marker == "X" else "k",
                           label=f"whole loop, {name}: {point['label']}")
        panel.set_title(f"{rate:g} Hz")
        panel.set_xlabel("coupling damping B (N s/m)")
        panel.set_yscale("log")
    panels[0][0].set_ylabel("largest stable stiffness K (N/m)")
    panels[0][0].legend(title="solid: against a wall, with the hand; dots: heavy-mass\n"
                        "limit; dotted: 2(b+B)/(T+2 tau)", fontsize=7, title_fontsize=7)
    for panel in panels[0][1:]:
        handles, labels = panel.get_legend_handles_labels()
        onset = [(h, label) for h, label in zip(handles, labels) if label.startswith("whole loop")]
        if onset:
            panel.legend(*zip(*onset), fontsize=7, loc="upper right")
    figure.suptitle(f"{title}: stability map")
    return save_figure(figure, Path(out_dir) / "stability_map.png")
