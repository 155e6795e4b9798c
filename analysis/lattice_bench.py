"""The deformable lattice's cost against its size, and what each integrator allows.

For lattices of about LATTICE_SIZES masses, built like the shipped scene (same
column and level spacing, depth and heightmap, a larger footprint), one 1 ms
tick of each integrator is timed with the kernel alone (no Drake): symplectic
Euler with 1 and 4 substeps, and the linearly implicit step at ten times the
1-substep stability limit, its conjugate gradients started from a jiggling
lattice. The largest stable link stiffness at 1 ms is computed for each
symplectic Euler substep count (the implicit step has no such limit).
"""

import dataclasses
from pathlib import Path
from typing import Dict, Sequence

import matplotlib
import numpy as np

from maglev_haptics.analysis.run_plots import save_figure
from maglev_haptics.analysis.timing import time_per_call_us
from maglev_haptics.diagrams.deformable_scene import DeformableSurface, build_scene_lattice
from maglev_haptics.systems.lattice_dynamics import (
    ProbeContact, implicit_workspace, lattice_model, linearly_implicit_tick,
    max_stable_link_stiffness, symplectic_euler_tick)

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

LATTICE_SIZES = (1000, 5000, 10000, 20000)  # masses, about
SUBSTEP_COUNTS = (1, 2, 4)
TICK_S = 1e-3
BUDGET_US = 1000.0  # one haptic tick (us)
WINDOWS = 7  # timing windows, the best kept


def scene_with_masses(target_masses: int, base: DeformableSurface = None) -> DeformableSurface:
    """``base`` (the shipped defaults) with its footprint grown or shrunk, 4:3, to
    about ``target_masses`` masses."""
    base = base or DeformableSurface()
    per_column = build_scene_lattice(base).num_masses / np.prod(
        [round(s / base.column_spacing_m) + 1 for s in base.size_m])
    columns = target_masses / per_column
    nx = max(3, int(round(np.sqrt(columns * 4 / 3))))
    ny = max(3, int(round(columns / nx)))
    return dataclasses.replace(base, size_m=[(nx - 1) * base.column_spacing_m,
                                             (ny - 1) * base.column_spacing_m])


def lattice_costs(scene: DeformableSurface) -> Dict:
    """Per-tick costs (us) of the integrators on ``scene``'s lattice, and the
    stiffness limits (N/m) of symplectic Euler."""
    lattice = build_scene_lattice(scene)
    limits = {str(n): max_stable_link_stiffness(
        lattice.positions_m, lattice.links, lattice.fixed, node_mass_kg=scene.node_mass_kg,
        link_damping_n_s_per_m=scene.link_damping_n_s_per_m, time_step_s=TICK_S, substeps=n)
        for n in SUBSTEP_COUNTS}
    rng = np.random.default_rng(0)
    probe = ProbeContact()
    far = np.array([0.0, 0.0, 10.0])

    def arguments(stiffness):
        model = lattice_model(lattice.links, lattice.rest_lengths_m, lattice.fixed,
                              lattice.surface, node_mass_kg=scene.node_mass_kg,
                              link_stiffness_n_per_m=stiffness,
                              link_damping_n_s_per_m=scene.link_damping_n_s_per_m)
        x = lattice.positions_m.copy()
        v = np.where(lattice.fixed[:, None], 0.0, 1e-3 * rng.standard_normal(x.shape))
        return (x, v, *model.topology, model.rest_lengths_m, model.stiffness_n_per_m,
                model.damping_n_s_per_m, model.mass_kg, model.inv_mass_per_kg,
                model.gravity_m_s2, model.surface, np.zeros_like(x), far, np.zeros(3),
                np.zeros(3), probe.radius_m, probe.stiffness_n_per_m, probe.onset_depth_m,
                probe.dissipation_s_per_m,
                probe.friction, probe.slip_speed_m_s, TICK_S)

    repeats = max(3, int(2e5 / lattice.num_links))
    forces = np.zeros((lattice.num_masses, 3))
    explicit = arguments(scene.link_stiffness_n_per_m)
    costs = {f"symplectic_euler_{n}_us": time_per_call_us(
        lambda n=n: symplectic_euler_tick(*explicit, n, forces), repeats, WINDOWS)
        for n in (1, 4)}
    stiff = 10.0 * limits["1"]
    implicit = arguments(stiff)
    workspace = implicit_workspace(lattice.num_masses, lattice.num_links)
    iterations = linearly_implicit_tick(*implicit, scene.cg_tolerance, scene.cg_max_iterations,
                                        *workspace)[2]
    costs["linearly_implicit_us"] = time_per_call_us(lambda: linearly_implicit_tick(
        *implicit, scene.cg_tolerance, scene.cg_max_iterations, *workspace),
        max(2, repeats // 8), WINDOWS)
    return {"masses": lattice.num_masses, "links": lattice.num_links, **costs,
            "linearly_implicit_link_stiffness_n_per_m": stiff,
            "linearly_implicit_cg_iterations": int(iterations),
            "symplectic_euler_max_link_stiffness_n_per_m": limits}


def lattice_scaling(sizes: Sequence[int] = LATTICE_SIZES, progress=None) -> Dict:
    """``lattice_costs`` for about each of ``sizes`` masses."""
    rows = []
    for target in sizes:
        rows.append(lattice_costs(scene_with_masses(target)))
        if progress is not None:
            progress(rows[-1])
    return {"tick_s": TICK_S, "node_mass_kg": DeformableSurface().node_mass_kg,
            "link_damping_n_s_per_m": DeformableSurface().link_damping_n_s_per_m,
            "link_stiffness_n_per_m": DeformableSurface().link_stiffness_n_per_m, "sizes": rows}


def plot_lattice_scaling(scaling: Dict, path: Path) -> None:
    """Cost per tick against masses, one line per integrator, the 1 ms budget drawn."""
    rows = scaling["sizes"]
    masses = [r["masses"] for r in rows]
    figure, axes = plt.subplots(figsize=(7, 4.5))
    for key, label in (("symplectic_euler_1_us", "symplectic Euler, 1 substep"),
                       ("symplectic_euler_4_us", "symplectic Euler, 4 substeps"),
                       ("linearly_implicit_us", "linearly implicit (CG), 10x stiffer links")):
        axes.plot(masses, [1e-3 * r[key] for r in rows], "o-", label=label)
    axes.axhline(1e-3 * BUDGET_US, color="k", linestyle="--", linewidth=1,
                 label="one 1 kHz tick")
    axes.set_xscale("log")
    axes.set_yscale("log")
    axes.set_xlabel("masses in the lattice")
    axes.set_ylabel("kernel time per 1 ms tick [ms]")
    axes.set_title("Deformable lattice: one haptic tick, kernel alone (numba, 1 core)")
    axes.grid(True, which="both", alpha=0.3)
    axes.legend(fontsize=8)
    save_figure(figure, path)


def format_lattice_report(scaling: Dict) -> str:
    lines = ["Deformable lattice, kernel per 1 ms tick (us); symplectic Euler's largest stable "
             "link stiffness (N/m) at "
             f"{1e3 * scaling['node_mass_kg']:.0f} g nodes, "
             f"{scaling['link_damping_n_s_per_m']} N s/m links:",
             f"  {'masses':>7}{'links':>8}{'SE x1':>8}{'SE x4':>8}{'implicit':>10}"
             f"{'CG it':>7}{'k max x1':>10}{'x2':>8}{'x4':>8}{'masses/us x1':>14}"]
    for r in scaling["sizes"]:
        k = r["symplectic_euler_max_link_stiffness_n_per_m"]
        lines.append(f"  {r['masses']:>7}{r['links']:>8}{r['symplectic_euler_1_us']:>8.0f}"
                     f"{r['symplectic_euler_4_us']:>8.0f}{r['linearly_implicit_us']:>10.0f}"
                     f"{r['linearly_implicit_cg_iterations']:>7}{k['1']:>10.0f}{k['2']:>8.0f}"
                     f"{k['4']:>8.0f}{r['masses'] / r['symplectic_euler_1_us']:>14.1f}")
    lines.append("  (implicit: links 10x the 1-substep limit; it is stable at any stiffness)")
    return "\n".join(lines)
