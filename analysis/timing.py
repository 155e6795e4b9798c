"""Wall-clock cost of a call and of a leaf system's update, for the benchmarks; and
where a run's deformable bodies were stepped, and how long the other core took."""

import time
from typing import Dict

from pydrake.multibody.plant import MultibodyPlant
from pydrake.systems.primitives import VectorLogSink

from maglev_haptics.analysis.linearization import leaf_systems
from maglev_haptics.systems.deformable_surface import DeformableBody

WINDOWS = 5  # a leaf system's cost is the best of this many runs: one run drifts 2x here


def time_per_call_us(function, n: int, windows: int = 1) -> float:
    """Microseconds per call of ``function()`` over ``n`` calls after one warm-up call;
    the best of ``windows`` such runs, as the machine's load comes and goes."""
    function()
    best = float("inf")
    for _ in range(windows):
        start = time.perf_counter()
        for _ in range(n):
            function()
        best = min(best, time.perf_counter() - start)
    return 1e6 * best / n


def leaf_system_costs(built, context, n: int = 300, only=None) -> Dict[str, float]:
    """Microseconds for one update of each leaf system with vector inputs (or of
    those named in ``only``), the best of WINDOWS runs of ``n``.

    One update = its outputs evaluated and its periodic discrete update computed,
    with the inputs re-fixed first so nothing comes from the cache (the time to
    re-fix them, and to read each output from Python, are measured apart and
    subtracted: a C++ system with many outputs costs the loop little, but each
    Python ``Eval`` is a call and a copy). Loggers and the plant
    (abstract geometry input) are left out; see plant_step_cost_us.
    """
    costs = {}
    for system in leaf_systems(built.diagram):
        # Named by path below the root ("levitation_controller::law"): several stacked
        # systems have a leaf named "law".
        name = system.GetSystemPathname().split("::", 2)[-1]
        if isinstance(system, (VectorLogSink, MultibodyPlant)) or (
                only is not None and name not in only):
            continue
        sub = system.GetMyContextFromRoot(context)
        own = system.CreateDefaultContext()
        own.SetTimeStateAndParametersFrom(sub)
        inputs = []
        for i in range(system.num_input_ports()):
            port = system.get_input_port(i)
            if port.get_data_type().name != "kVectorValued":
                break
            inputs.append((port, port.Eval(sub).copy()))
        else:
            periodic = own.num_discrete_state_groups() > 0

            def fix_inputs(inputs=inputs, own=own):
                for port, value in inputs:
                    port.FixValue(own, value)

            def one_update(system=system, own=own, periodic=periodic, fix_inputs=fix_inputs):
                fix_inputs()
                for j in range(system.num_output_ports()):
                    system.get_output_port(j).Eval(own)
                if periodic:
                    system.EvalUniquePeriodicDiscreteUpdate(own)

            def read_outputs(system=system, own=own):
                for j in range(system.num_output_ports()):
                    system.get_output_port(j).Eval(own)
            # Re-fixing the inputs and reading the outputs from Python (a call and a
            # copy each: what an output costs read again from the cache) are the
            # harness's cost, not the system's.
            costs[name] = max(
                0.0, time_per_call_us(one_update, n, WINDOWS)
                - time_per_call_us(fix_inputs, n, WINDOWS)
                - time_per_call_us(read_outputs, n, WINDOWS))
    return costs


def deformable_step_reports(diagram) -> Dict[str, Dict]:
    """Each deformable body's ``step_report`` (its ticks on the other core, how long
    they took there, and those stepped on the loop's thread), by system name."""
    return {system.get_name(): system.step_report() for system in leaf_systems(diagram)
            if isinstance(system, DeformableBody)}
