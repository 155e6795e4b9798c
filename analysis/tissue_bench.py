"""What a tissue scene's finite elements cost: the kernel alone and the system's tick.

For each tissue body of a built diagram (``SceneParts.tissue``):
- the kernel alone (``tissue_fem.tick_timing``): one 1 ms tick with the scene's
  substeps on this core, and the tetrahedra one element pass steps a microsecond
  (the machine's yardstick for tissue, as masses a microsecond are the lattice's);
- the system's tick: its ``DeformableBody`` update with its inputs fixed, stepped
  synchronously on this core (what the worker thread does on the other one, plus
  the system's own overhead: state copies, the contact's wrench).
"""

from typing import Dict

from maglev_haptics.analysis.timing import leaf_system_costs
from maglev_haptics.systems.tissue_fem import tick_timing

SYSTEM_UPDATES = 50  # the system's ticks timed (each a whole tissue tick)


def tissue_costs(built, context) -> Dict[str, Dict]:
    """Per tissue body (``model::body``): tetrahedra, nodes, substeps, the kernel's
    tick (us) and tetrahedra a microsecond, and the system's tick (us) in the state
    of ``context`` (the root context of ``built.diagram``)."""
    costs = {}
    for tissue in built.haptics.scene.tissue:
        kernel_us, tetrahedra_per_us = tick_timing(
            tissue.model, tissue.body.positions_m, probe=tissue.probe, period_s=built.tick_s,
            substeps=tissue.substeps)
        name = tissue.system.get_name()
        system_us = leaf_system_costs(built, context, n=SYSTEM_UPDATES, only={name})[name]
        costs[f"{tissue.body.model}::{tissue.body.name}"] = {
            "tetrahedra": tissue.model.num_tetrahedra, "nodes": tissue.model.num_nodes,
            "substeps": tissue.substeps, "kernel_tick_us": kernel_us,
            "tetrahedra_per_us": tetrahedra_per_us, "system_tick_us": system_us}
    return costs
