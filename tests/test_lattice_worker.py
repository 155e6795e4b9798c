"""The lattice stepped one tick ahead on another core gives the synchronous results,
bit for bit, and falls back to stepping in the update when the context changes."""

import numpy as np
import pytest
from pydrake.math import RigidTransform
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import ConstantVectorSource

from maglev_haptics.hardware.realtime_priority import (
    fifo_permitted, is_realtime, realtime_priority)
from maglev_haptics.systems import lattice_worker
from maglev_haptics.systems.deformable_surface import DeformableSurface
from maglev_haptics.systems.lattice_construction import build_lattice
from maglev_haptics.systems.lattice_dynamics import ProbeContact, lattice_model

P_TP_M = np.array([0.0, 0.0, -0.030])


def pressing_diagram(worker_thread: bool, integrator: str = "symplectic_euler"):
    """A small lattice and a tool held with its probe 1.5 mm into the surface, sliding."""
    x = np.linspace(-0.01, 0.01, 9)
    y = np.linspace(-0.01, 0.01, 9)
    heights = 0.001 * np.sin(x[:, None] / 0.003) * np.cos(y[None, :] / 0.004)
    lattice = build_lattice(heights, x, y, base_z_m=-0.012, level_spacing_m=0.003)
    model = lattice_model(lattice.links, lattice.rest_lengths_m, lattice.fixed, lattice.surface,
                          node_mass_kg=0.002, link_stiffness_n_per_m=200.0,
                          link_damping_n_s_per_m=0.05)
    probe = ProbeContact()
    p_WT = np.array([0.0, 0.0, 0.030 + probe.radius_m - 0.0015])
    builder = DiagramBuilder()
    surface = builder.AddSystem(DeformableSurface(
        model=model, positions_m=lattice.positions_m, probe=probe, p_TP_m=P_TP_M,
        X_WT_start=RigidTransform(p_WT), period_s=1e-3, integrator=integrator,
        worker_thread=worker_thread))
    pose = builder.AddSystem(ConstantVectorSource(np.concatenate(([1.0, 0, 0, 0], p_WT))))
    velocity = builder.AddSystem(ConstantVectorSource([0, 0, 0, 0.01, 0, 0]))
    builder.Connect(pose.get_output_port(), surface.GetInputPort("X_WT"))
    builder.Connect(velocity.get_output_port(), surface.GetInputPort("V_WT"))
    return builder.Build(), surface


def simulate(worker_thread, integrator="symplectic_euler", poke_at_s=None):
    diagram, surface = pressing_diagram(worker_thread, integrator)
    simulator = Simulator(diagram)
    simulator.Initialize()
    wrenches = []
    for k in range(1, 301):
        if poke_at_s is not None and abs(k * 1e-3 - poke_at_s) < 1e-9:
            # Change the state from outside: the precomputed step no longer applies.
            context = surface.GetMyMutableContextFromRoot(simulator.get_mutable_context())
            state = context.get_discrete_state(0).get_value().copy()
            state[3 * surface.num_masses:3 * surface.num_masses + 30] += 0.01
            context.SetDiscreteState(0, state)
        simulator.AdvanceTo(k * 1e-3)
        wrenches.append(surface.GetOutputPort("wrench_on_tool_W").Eval(
            surface.GetMyContextFromRoot(simulator.get_context())).copy())
    state = surface.GetMyContextFromRoot(simulator.get_context()).get_discrete_state(0)
    return state.get_value().copy(), np.array(wrenches)


@pytest.mark.parametrize("integrator", ["symplectic_euler", "linearly_implicit"])
def test_worker_gives_the_synchronous_results_bit_for_bit(integrator):
    ahead, ahead_wrenches = simulate(True, integrator)
    inline, inline_wrenches = simulate(False, integrator)
    assert np.abs(inline_wrenches[:, 2]).max() > 0.01  # the probe does press (N)
    np.testing.assert_array_equal(ahead, inline)
    np.testing.assert_array_equal(ahead_wrenches, inline_wrenches)


def test_the_worker_steps_on_from_its_own_result(monkeypatch):
    """Nearly every tick takes the worker's result, and asks for the next from it with
    the two buffers swapped (nothing copied in); the state stays the synchronous one."""
    taken, inputs = [], []
    result_into = lattice_worker.LatticeWorker.result_into

    def counted(self, state, out):
        taken.append(result_into(self, state, out))
        inputs.append(int(self._control[4]))
        return taken[-1]

    monkeypatch.setattr(lattice_worker.LatticeWorker, "result_into", counted)
    ahead, _ = simulate(True)
    assert sum(taken) >= 0.9 * len(taken) and set(inputs) == {0, 1}
    np.testing.assert_array_equal(ahead, simulate(False)[0])


def test_a_state_changed_from_outside_is_stepped_in_the_update():
    ahead, _ = simulate(True, poke_at_s=0.150)
    inline, _ = simulate(False, poke_at_s=0.150)
    np.testing.assert_array_equal(ahead, inline)


@pytest.mark.skipif(not fifo_permitted(), reason="this process may not use SCHED_FIFO")
def test_the_worker_thread_takes_up_the_loops_real_time_priority():
    """Told as the loop enters real-time priority, the worker thread runs at it and
    polls by sleeping; back to normal after. Still bit for bit."""
    diagram, surface = pressing_diagram(worker_thread=True)
    simulator = Simulator(diagram)
    simulator.Initialize()
    simulator.AdvanceTo(0.01)
    worker = surface._worker
    thread_id = worker._thread.native_id
    assert not is_realtime(thread_id)
    with realtime_priority():
        assert is_realtime(thread_id) and worker._control[3] == 1
        simulator.AdvanceTo(0.3)
    assert not is_realtime(thread_id) and worker._control[3] == 0
    state = surface.GetMyContextFromRoot(simulator.get_context()).get_discrete_state(0)
    assert np.array_equal(state.get_value(), simulate(worker_thread=False)[0])
