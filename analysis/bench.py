"""``maglev bench``: real-time factor of each scenario and what one control tick costs.

Four kinds of numbers:
- each shipped scenario (levitation, the rigid haptic scenes and the deformable
  surface with their whole diagram: station with hand, tracker, controller,
  allocator, coupling, scene plant or lattice, logging) simulated without
  Meshcat: real-time factor and wall time per simulated 1 ms;
- the deformable lattice's kernel against its size (``lattice_bench``), with a
  plot;
- each leaf system of the diagram on its own, at a hover operating point: the
  cost of one update (discrete update plus output evaluation), with inputs fixed
  to their values in the running diagram and re-fixed every call so nothing is
  served from the cache;
- the same callbacks in the running loop (``loop_callbacks``): each Python
  callback's own time a tick in levitation and in the deformable surface, free-
  running, and the tick's time outside them (on a 2-core machine 2-8 times the
  figures above, which stay in the caches);
- the one-system loop (``loop_floor``): the station's plant closed by one Python
  system doing the floor's kernels, the least a tick of such a diagram costs;
- the electromagnetic model (a full 6 x n wrench matrix) and the allocation;
- the stereo display: view matrices per frame and a rendered frame pair;
- the offline analysis: the loop studies' wall time on the peg-in-hole scene;
- paced (``--paced``): missed slots, each beside the machine alone paced at the
  run's median compute (``host_pacing``).

Every figure's line ends with the machine's yardsticks (``machine_yardsticks``):
takeoff_hover_land's physics floor (us), the shipped lattice's masses and the
tissue's tetrahedra stepped a microsecond, and the slots the machine alone misses
paced at half a slot's compute, so that two machines' numbers can be compared.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Dict, Optional

import numpy as np
from pydrake.multibody.plant import AddMultibodyPlant
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import ConstantVectorSource
from tqdm import tqdm

from maglev_haptics.analysis.host_pacing import HALF_LOAD_S, YARDSTICK_DURATION_S, host_pacing
from maglev_haptics.analysis.lattice_bench import (
    LATTICE_SIZES, format_lattice_report, lattice_costs, lattice_scaling, plot_lattice_scaling)
from maglev_haptics.analysis.loop_callbacks import loop_callback_costs
from maglev_haptics.analysis.loop_floor import floor_loop_us, hover_transform
from maglev_haptics.analysis.stereo_bench import format_stereo_report, stereo_costs
from maglev_haptics.analysis.timing import (
    deformable_step_reports, leaf_system_costs, time_per_call_us)
from maglev_haptics.analysis.tissue_bench import tissue_costs
from maglev_haptics.diagrams.application import BuildDiagram
from maglev_haptics.diagrams.runner import simulate
from maglev_haptics.diagrams.scenario import SCENARIO_DIR, load_scenario, scenario_names
from maglev_haptics.diagrams.deformable_scene import DeformableSurface
from maglev_haptics.diagrams.scene import ModelScene, PegInHole
from maglev_haptics.diagrams.scene_builder import AddScene
from maglev_haptics.diagrams.station import (
    add_station_models, generalized_force_placement, hand_start_transform, rest_transform)
from maglev_haptics.hardware.constants import GRAVITY_M_S2
from maglev_haptics.hardware.device import DeviceConfig
from maglev_haptics.hardware.magnetics import bench_wrench_matrix, load_magnetics
from maglev_haptics.hardware.thermal import (
    coil_thermal, current_bounds_a, thermal_budget, winding_resistance_ohm)
from maglev_haptics.systems.current_allocator import (
    TORQUE_WEIGHT_PER_M, allocate_currents, bounded_minimum_power_currents)
from maglev_haptics.systems.levitation_controller import ControllerConfig

LEVITATE_FILE = SCENARIO_DIR / "levitate.yaml"
HAPTIC_FILES = [SCENARIO_DIR / f"{name}.yaml" for name in (
    "hanging_ball", "paddle_ball", "peg_in_hole", "gear_trace", "push_block", "door",
    "deformable_surface", "stereo_display")]
TISSUE_FILE = SCENARIO_DIR / "palpate_inclusion.yaml"  # every scenario of it is benched
FLOOR_LOOP_SCENARIOS = ("takeoff_hover_land", "four_magnet_tilt")  # one per instrument
HOVER_TIME_S = 1.5  # operating point for the per-system costs (s into takeoff_hover_land)
FLOOR_TOOL_PUSH_N = 1.0  # the peg is pushed down this hard onto the block (N)
# --paced: the scenarios paced at 1x (the four kinds of loop: levitation, rigid contact
# held and bouncing, the lattice on the other core), (file, name: None for the first)
PACED_SCENARIOS = (("levitate", "takeoff_hover_land"), ("peg_in_hole", None),
                   ("paddle_ball", None), ("deformable_surface", None))
QUICK_DURATION_S = 1.0  # --quick: simulated seconds a scenario
QUICK_LATTICE_SIZES = 2  # --quick: the lattice's smallest sizes only
YARDSTICK_SCENARIO = "takeoff_hover_land"  # its physics floor is the machine's yardstick
# Split callback by callback in the running loop (``loop_callbacks``): levitation alone,
# and the haptic loop over the lattice. Each runs LOOP_CALLBACKS_WARM_S, then is timed
# for LOOP_CALLBACKS_S (s).
LOOP_CALLBACK_SCENARIOS = (("levitate", "takeoff_hover_land"),
                           ("deformable_surface", "deformable_surface"))
LOOP_CALLBACKS_WARM_S, LOOP_CALLBACKS_S = 2.0, 1.0
LOOP_CALLBACKS_LISTED = 12  # the costliest callbacks a scenario's report lists


def _step_cost_us(builder, n_steps: int, period_s: float) -> float:
    """Wall microseconds per ``period_s`` of the built diagram, after 0.05 s to settle."""
    simulator = Simulator(builder.Build())
    simulator.Initialize()
    simulator.AdvanceTo(0.05)
    start = time.perf_counter()
    simulator.AdvanceTo(0.05 + n_steps * period_s)
    return 1e6 * (time.perf_counter() - start) / n_steps


def plant_step_cost_us(scenario, *, hovering: bool, n_steps: int = 1000) -> float:
    """Wall microseconds per step of the station's MultibodyPlant and SceneGraph alone.

    ``hovering``: the weights (the instrument's, and the hand's with a hand) are
    applied as constant forces, no contact; else the instrument rests on the glass
    (four point contacts).
    """
    builder = DiagramBuilder()
    plant, _ = AddMultibodyPlant(scenario.plant_config, builder)
    instrument, hand = add_station_models(plant, scenario)
    plant.Finalize()
    X_WI = hover_transform(scenario) if hovering else rest_transform(scenario)
    plant.SetDefaultFloatingBaseBodyPose(plant.GetBodyByName("instrument", instrument), X_WI)
    bodies = [plant.GetBodyByName("instrument", instrument)]
    if hand is not None:
        bodies.append(plant.GetBodyByName("hand", hand))
        plant.SetDefaultFloatingBaseBodyPose(bodies[1], hand_start_transform(scenario))
    lift = np.concatenate([[0, 0, 0, 0, 0, body.default_mass() * GRAVITY_M_S2 if hovering else 0]
                           for body in bodies])
    source = builder.AddSystem(ConstantVectorSource(
        generalized_force_placement(plant, *bodies) @ lift))
    builder.Connect(source.get_output_port(), plant.get_applied_generalized_force_input_port())
    return _step_cost_us(builder, n_steps, scenario.plant_config.time_step)


def scene_step_cost_us(scenario, n_steps: int = 1000) -> float:
    """Wall microseconds per tick of a rigid scene's plant and SceneGraph alone, held
    in the contact the scene is for: the ball bouncing on the paddle or hanging from
    the tool, the peg (or a model scene's tool) pushed down by FLOOR_TOOL_PUSH_N onto
    what lies under it."""
    builder = DiagramBuilder()
    period_s = 1.0 / scenario.control_rate_hz
    scene = AddScene(builder, scene=scenario.haptics.scene, time_step_s=period_s,
                     use_sampled_output_ports=False, X_WI_start=hand_start_transform(scenario))
    pushed = isinstance(scenario.haptics.scene, (PegInHole, ModelScene))
    push_n = FLOOR_TOOL_PUSH_N if pushed else 0.0
    push = builder.AddSystem(ConstantVectorSource([0, 0, -push_n, 0, 0, 0]))
    builder.Connect(push.get_output_port(), scene.wrench_on_tool_input)
    return _step_cost_us(builder, n_steps, period_s)


def physics_floor_us(scenario, other_core_tick_us: Optional[float]) -> Dict[str, float]:
    """What one tick of ``scenario`` costs in the plants and the compiled kernels
    alone (us): the station plant hovering, the scene plant in contact, the two
    6 x n wrench matrices (true pose, estimated pose) and one allocation. The
    lattice's or the tissue's tick runs on the other core and is listed, not added."""
    floor = {"station_plant_us": plant_step_cost_us(scenario, hovering=True)}
    if scenario.haptics is not None and not isinstance(scenario.haptics.scene, DeformableSurface):
        floor["scene_plant_us"] = scene_step_cost_us(scenario)
    config = scenario.device
    floor["wrench_matrices_us"] = 2 * bench_wrench_matrix(config)["mean_us"]
    floor["allocation_us"] = allocation_cost_us(config)[
        scenario.controller.allocation]["within_limits_us"]
    floor["total_us"] = sum(floor.values())
    if other_core_tick_us is not None:
        floor["other_core_tick_us"] = other_core_tick_us
    return floor


def floor_us(floor: Dict[str, float]) -> float:
    """The tick's floor (us): the serial physics, or the lattice's or the tissue's tick on
    the other core where that is longer."""
    return max(floor["total_us"], floor.get("other_core_tick_us", 0.0))


def allocation_cost_us(config: DeviceConfig, n: int = 2000) -> Dict[str, Dict[str, float]]:
    """Each allocator's cost a call (us) carrying the weight at a hover pose: within its
    bounds; for the thermal one also with every coil at its budget's target (the load
    spread over bounded coils) and far out of reach; for the pseudoinverse saturating."""
    magnetics = load_magnetics(config)
    spec = config.instrument_spec()
    A = magnetics.wrench_matrix_from(np.array([0.0, 0.0, 0.028]), np.eye(3))
    hover = np.array([0, 0, spec.mass_kg * GRAVITY_M_S2, 0, 0, 0])
    limit = config.amplifier.current_limit_a
    thermal = coil_thermal(config)
    budget = thermal_budget(thermal, horizon_s=ControllerConfig().thermal_horizon_s,
                            margin_c=ControllerConfig().thermal_margin_c, current_limit_a=limit)

    def thermal_call(temperature_c, wrench):
        temperatures = np.full(A.shape[1], temperature_c)
        resistance = winding_resistance_ohm(thermal, temperatures)
        bounds = current_bounds_a(budget, temperatures)
        return lambda: bounded_minimum_power_currents(A, wrench, resistance, bounds,
                                                      TORQUE_WEIGHT_PER_M)

    return {
        "thermal": {
            "within_limits_us": time_per_call_us(thermal_call(thermal.ambient_c, hover), n),
            "at_thermal_bounds_us": time_per_call_us(thermal_call(budget.target_c, 1.5 * hover), n),
            "saturating_us": time_per_call_us(thermal_call(thermal.ambient_c, 40 * hover), n // 4),
        },
        "pseudoinverse": {
            "within_limits_us": time_per_call_us(lambda: allocate_currents(A, hover, limit), n),
            "saturating_us": time_per_call_us(lambda: allocate_currents(A, 40 * hover, limit),
                                              n // 4),
        },
    }


def paced_runs(duration_s: float, progress: bool = True) -> Dict[str, Dict]:
    """Each of PACED_SCENARIOS paced at 1x for ``duration_s`` (s), Meshcat off: its
    summary's ``realtime`` block (missed slots, compute percentiles), and under
    ``host_alone`` the same block for the machine alone paced as long at that run's
    median compute (``host_pacing``): the fewest slots the run could have missed here."""
    from maglev_haptics.analysis.run_results import run_scenario

    results = {}
    for file, name in PACED_SCENARIOS:
        scenario = load_scenario(file, name)
        label = file if name is None else f"{file}:{name}"
        realtime = run_scenario(scenario, label=label, realtime_rate=1.0,
                                duration_s=duration_s, progress=progress).summary["realtime"]
        realtime["host_alone"] = host_pacing(duration_s, realtime["tick_compute_us_p50"],
                                             progress=progress, label=f"{label}, host alone")
        results[label] = realtime
    return results


def run_benchmarks(duration_s: Optional[float] = None, progress: bool = True,
                   out_dir: Optional[Path] = None, quick: bool = False, runs: int = 1,
                   paced_s: Optional[float] = None) -> Dict:
    """Everything ``maglev bench`` reports; each scenario runs its whole script by
    default, ``runs`` times (the median is reported: the host's speed drifts).
    ``quick``: QUICK_DURATION_S a scenario, no offline analysis, the lattice's
    smallest QUICK_LATTICE_SIZES. ``paced_s``: also PACED_SCENARIOS paced at 1x for
    that long. With ``out_dir``, writes bench.json and lattice_scaling.png there."""
    if quick:
        duration_s = QUICK_DURATION_S
    results: Dict = {"scenarios": {}, "systems_us": {}, "wrench_matrix_us": {}, "allocation": {},
                     "machine": {}}
    scenarios = [(LEVITATE_FILE, name) for name in scenario_names(LEVITATE_FILE)]
    scenarios += [(path, scenario_names(path)[0]) for path in HAPTIC_FILES]
    scenarios += [(TISSUE_FILE, name) for name in scenario_names(TISSUE_FILE)]
    results["tissue"] = {}
    for path, name in scenarios:
        scenario = load_scenario(str(path), name)
        built = BuildDiagram(scenario)
        simulate(built, 0.05, progress=False)  # loads the compiled kernels, off the clock
        length_s = scenario.duration_s if scenario.duration_s is not None else built.plan.end_s
        sim_s = length_s if duration_s is None else min(duration_s, length_s)
        walls_s = [simulate(built, sim_s, progress=progress, label=name)[1]
                   for _ in range(runs)]
        wall_s = float(np.median(walls_s))
        tick_us = 1e6 * wall_s * built.tick_s / sim_s
        lattice = built.haptics.scene.lattice if built.haptics is not None else None
        other_core_us = None if lattice is None else lattice_costs(
            scenario.haptics.scene)[f"symplectic_euler_{scenario.haptics.scene.substeps}_us"]
        if built.haptics is not None and built.haptics.scene.tissue:
            tissue = tissue_costs(scenario)
            results["tissue"][name] = tissue
            other_core_us = sum(body["kernel_tick_us"] for body in tissue.values())
            results["machine"]["tissue_tetrahedra_per_us"] = min(
                body["tetrahedra_per_us"] for body in tissue.values())
        floor = physics_floor_us(scenario, other_core_us)
        if lattice is not None:
            results["machine"]["lattice_masses"] = lattice.num_masses
            results["machine"]["lattice_masses_per_us"] = (
                lattice.num_masses / floor["other_core_tick_us"])
        results["scenarios"][name] = {
            "instrument": scenario.device.instrument,
            "simulated_s": sim_s,
            "runs": runs,
            "realtime_factor": sim_s / wall_s,
            "wall_us_per_1ms_tick": tick_us,
            "physics_floor": floor,
            "tick_over_floor": tick_us / floor_us(floor),
        }
        deformable = deformable_step_reports(built.diagram)
        if deformable:  # the other core's tick as these runs ran it, beside the rest
            results["scenarios"][name]["deformable_steps"] = deformable
    if YARDSTICK_SCENARIO in results["scenarios"]:
        results["machine"]["takeoff_floor_us"] = floor_us(
            results["scenarios"][YARDSTICK_SCENARIO]["physics_floor"])
    scenario = load_scenario(str(LEVITATE_FILE), "takeoff_hover_land")
    built = BuildDiagram(scenario)
    simulator, _, _ = simulate(built, HOVER_TIME_S, progress=False)
    results["systems_us"] = leaf_system_costs(built, simulator.get_context())
    results["loop_callbacks"] = {
        name: loop_callback_costs(file, name, warm_s=LOOP_CALLBACKS_WARM_S,
                                  duration_s=LOOP_CALLBACKS_S)
        for file, name in LOOP_CALLBACK_SCENARIOS}
    results["one_system_loop"] = {
        name: {**floor_loop_us(load_scenario(str(LEVITATE_FILE), name)),
               "physics_floor_us": floor_us(results["scenarios"][name]["physics_floor"])}
        for name in FLOOR_LOOP_SCENARIOS if name in results["scenarios"]}
    results["systems_us"]["plant step, hovering"] = plant_step_cost_us(scenario, hovering=True)
    results["systems_us"]["plant step, resting on the glass"] = plant_step_cost_us(
        scenario, hovering=False)
    for kind in ("two_magnet", "four_magnet"):
        config = DeviceConfig(instrument=kind)
        results["wrench_matrix_us"][kind] = bench_wrench_matrix(config)
        results["allocation"][kind] = allocation_cost_us(config)
    results["stereo"] = stereo_costs()
    results["analysis"] = {} if quick else analysis_costs()
    sizes = LATTICE_SIZES[:QUICK_LATTICE_SIZES] if quick else LATTICE_SIZES
    with tqdm(total=len(sizes), desc="lattice sizes", disable=not progress) as bar:
        results["lattice"] = lattice_scaling(sizes, progress=lambda _: bar.update(1))
    if paced_s is not None:
        results["paced"] = paced_runs(paced_s, progress=progress)
    yardstick = host_pacing(YARDSTICK_DURATION_S, 1e6 * HALF_LOAD_S, progress=progress,
                            label="host alone, half load")
    results["machine"]["host_half_load"] = yardstick
    results["report"] = format_report(results)
    if out_dir is not None:
        out_dir.mkdir(parents=True, exist_ok=True)
        (out_dir / "bench.json").write_text(json.dumps(results, indent=2))
        plot_lattice_scaling(results["lattice"], out_dir / "lattice_scaling.png")
    return results


def analysis_costs() -> Dict[str, float]:
    """Wall seconds of the loop studies on peg_in_hole (the multirate one must take
    under a minute)."""
    from maglev_haptics.analysis.loop_linearization import linearize_study, multirate_study
    from maglev_haptics.analysis.loop_studies import ZWidthSettings, zwidth_study

    scenario = load_scenario("peg_in_hole")
    costs = {}
    for name, study in (("peg_in_hole multirate", multirate_study),
                        ("peg_in_hole linearize", linearize_study),
                        ("peg_in_hole zwidth", lambda s: zwidth_study(s, ZWidthSettings.full()))):
        start = time.perf_counter()
        study(scenario)
        costs[name] = time.perf_counter() - start
    return costs


def machine_yardsticks(machine: Dict) -> str:
    """The tag every figure's line ends with: the takeoff floor (us) and the lattice's
    masses a microsecond, where measured."""
    parts = []
    if "takeoff_floor_us" in machine:
        parts.append(f"takeoff floor {machine['takeoff_floor_us']:.0f} us")
    if "lattice_masses_per_us" in machine:
        parts.append(f"lattice {machine['lattice_masses_per_us']:.1f} masses/us")
    if "tissue_tetrahedra_per_us" in machine:
        parts.append(f"tissue {machine['tissue_tetrahedra_per_us']:.1f} tetrahedra/us")
    if "host_half_load" in machine:
        parts.append(f"host alone misses {100 * machine['host_half_load']['miss_fraction']:.2f}% "
                     "at half load")
    return "  [" + ", ".join(parts) + "]" if parts else ""


def _with_yardsticks(lines, tag: str):
    """Each line that carries a figure (indented), ``tag`` appended."""
    return [line + tag if line.startswith("  ") and any(ch.isdigit() for ch in line) else line
            for line in lines]


def format_report(results: Dict) -> str:
    tag = machine_yardsticks(results.get("machine", {}))
    lines = ["Scenarios, whole diagram (Meshcat off); the physics floor is the plants, the "
             "wrench kernels and one allocation in series, or the lattice's tick on the other "
             "core where that is longer:",
             f"  {'scenario':<24}{'instrument':<13}{'sim s':>7}{'RTF':>7}{'us a tick':>11}"
             f"{'floor us':>10}{'tick/floor':>12}"]
    for name, r in results["scenarios"].items():
        lines.append(f"  {name:<24}{r['instrument']:<13}{r['simulated_s']:>7.2f}"
                     f"{r['realtime_factor']:>7.2f}{r['wall_us_per_1ms_tick']:>11.0f}"
                     f"{floor_us(r['physics_floor']):>10.0f}{r['tick_over_floor']:>12.2f}")
    in_loop = {name: r["deformable_steps"] for name, r in results["scenarios"].items()
               if "deformable_steps" in r}
    if in_loop:
        lines.append("Deformable bodies in those runs: the other core's tick as the loop ran it "
                     "(us, timed around the kernel in the worker), and the ticks stepped here:")
        for name, bodies in in_loop.items():
            for body, r in bodies.items():
                lines.append(f"  {name:<20}{body:<30}p50 {r['other_core_tick_us_p50']:>5.0f}  "
                             f"p99 {r['other_core_tick_us_p99']:>5.0f}  "
                             f"{r['ticks_on_other_core']} there, {r['ticks_stepped_here']} here")
    lines.append("One-system loop (analysis/loop_floor.py: the station's plant closed by one "
                 "Python system doing the floor's kernels, two Python calls a tick):")
    for name, r in results["one_system_loop"].items():
        lines.append(f"  {name:<24}{r['us_per_tick']:>6.0f} us a tick, "
                     f"{r['us_per_tick'] / r['physics_floor_us']:.2f} x the floor")
    lines.append("Per-system cost of one update at hover (us):")
    for name, us in sorted(results["systems_us"].items(), key=lambda kv: -kv[1]):
        lines.append(f"  {name:<52}{us:>8.1f}")
    if results.get("loop_callbacks"):
        lines.append("The loop's thread in the running loop, free-running, each Python callback's "
                     "own time (less the callbacks it evaluated; us a tick):")
        for name, r in results["loop_callbacks"].items():
            lines.append(f"  {name:<52}{r['tick_us']:>8.1f}  the tick")
            for callback, us in list(r["callbacks_us"].items())[:LOOP_CALLBACKS_LISTED]:
                lines.append(f"    {callback:<50}{us:>8.1f}  ({r['calls_per_tick'][callback]:.2f} "
                             f"calls a tick)")
            lines.append(f"    {'outside them: Drake, its plants, C++ systems':<50}"
                         f"{r['outside_callbacks_us']:>8.1f}")
    lines.append("Wrench matrix 6 x 27 (us per call):")
    for kind, r in results["wrench_matrix_us"].items():
        lines.append(f"  {kind:<14} mean {r['mean_us']:.1f}  p99 {r['p99_us']:.1f}")
    lines.append("Allocation (us per call):")
    for kind, allocators in results["allocation"].items():
        for allocator, r in allocators.items():
            lines.append(f"  {kind:<14}{allocator:<15}" + "  ".join(
                f"{case.removesuffix('_us').replace('_', ' ')} {us:.1f}"
                for case, us in r.items()))
    lines.append(format_stereo_report(results["stereo"]))
    lines.append("Offline analysis (wall s): " + (", ".join(
        f"{name} {seconds:.1f}" for name, seconds in results["analysis"].items())
        or "not run (--quick)"))
    lines.append(format_lattice_report(results["lattice"]))
    if results.get("tissue"):
        lines.append("Tissue, finite elements on the other core: the kernel's tick alone, the "
                     "system's tick (stepped on this core), one element pass's tetrahedra/us:")
        for name, bodies in results["tissue"].items():
            for body, r in bodies.items():
                lines.append(f"  {name:<20}{body:<30}{r['tetrahedra']:>6} tets "
                             f"{r['substeps']} substeps  kernel {r['kernel_tick_us']:.0f} us  "
                             f"system {r['system_tick_us']:.0f} us  "
                             f"{r['tetrahedra_per_us']:.1f} tets/us")
    if "paced" in results:
        lines.append("Paced at 1x, Meshcat off: missed slots, compute p50 / p99 / max (us):")
        for name, r in results["paced"].items():
            host = r["host_alone"]
            lines.append(f"  {name:<32}{r['deadline_misses']:>6} of {r['ticks']:<7}"
                         f"({100 * r['miss_fraction']:.3f}%)  {r['tick_compute_us_p50']:.0f} / "
                         f"{r['tick_compute_us_p99']:.0f} / {r['tick_compute_us_max']:.0f}"
                         f"  at {r['priority']}; the host alone at {host['compute_us']:.0f} us "
                         f"a tick: {host['deadline_misses']} ({100 * host['miss_fraction']:.3f}%)")
    machine = results.get("machine", {})
    if machine:
        lines.append("Machine yardsticks: " + tag.removeprefix("  ") + (
            f" ({machine['lattice_masses']} masses)" if "lattice_masses" in machine else ""))
    lines = "\n".join(lines).split("\n")  # the sections' own multi-line blocks too
    return "\n".join(_with_yardsticks(lines, tag))
