"""What a tissue scene's finite elements cost: the kernel alone and the system's tick.

For each tissue body of a built diagram (``SceneParts.tissue``):
- the kernel alone (``tissue_fem.tick_timing``): one 1 ms tick with the scene's
  substeps on this core, and the tetrahedra one element pass steps a microsecond
  (the machine's yardstick for tissue, as masses a microsecond are the lattice's);
- the system's tick: its ``DeformableBody`` update with its inputs fixed, stepped
  synchronously on this core (what the worker thread does on the other one, plus
  the system's own overhead: state copies, the contact's wrench), in a diagram of
  the scenario built with the worker off (a worker stepping beside the timed
  update would share the cores with it).
"""

import dataclasses
from typing import Dict

from maglev_haptics.analysis.timing import leaf_system_costs
from maglev_haptics.diagrams.application import BuildDiagram
from maglev_haptics.diagrams.runner import simulate
from maglev_haptics.systems.tissue_fem import tick_timing

SYSTEM_UPDATES = 50  # the system's ticks timed (each a whole tissue tick)
SETTLE_S = 0.05  # simulated before the system is timed: the tissue sags under gravity (s)


def without_worker(scenario):
    """``scenario`` with its tissue stepped in the update itself."""
    haptics = scenario.haptics
    scene = dataclasses.replace(haptics.scene, tissue=dataclasses.replace(
        haptics.scene.tissue, worker_thread=False))
    return dataclasses.replace(scenario, haptics=dataclasses.replace(haptics, scene=scene))


def tissue_costs(scenario) -> Dict[str, Dict]:
    """Per tissue body (``model::body``) of ``scenario``: tetrahedra, nodes,
    substeps, the kernel's tick (us) and tetrahedra a microsecond, and the system's
    tick (us), SETTLE_S into the scenario."""
    built = BuildDiagram(without_worker(scenario))
    simulator, _, _ = simulate(built, SETTLE_S, progress=False)
    context = simulator.get_context()
    costs = {}
    for tissue in built.haptics.scene.tissue:
        kernel_us, tetrahedra_per_us = tick_timing(
            tissue.model, probe=tissue.probe, period_s=built.tick_s,
            substeps=tissue.substeps)
        name = tissue.system.get_name()
        system_us = leaf_system_costs(built, context, n=SYSTEM_UPDATES, only={name})[name]
        costs[f"{tissue.body.model}::{tissue.body.name}"] = {
            "tetrahedra": tissue.model.num_tetrahedra, "nodes": tissue.model.num_nodes,
            "substeps": tissue.substeps, "kernel_tick_us": kernel_us,
            "tetrahedra_per_us": tetrahedra_per_us, "system_tick_us": system_us}
    return costs
