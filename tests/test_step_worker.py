"""A deformable body stepped one tick ahead on another core gives the synchronous
results, bit for bit, and falls back to stepping in the update when the context
changes: the lattice, and a second model's tick through the same system and worker."""

import numpy as np
import pytest
from pydrake.math import RigidTransform
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import ConstantVectorSource

from maglev_haptics.diagrams.deformable_scene import LATTICE_SERVER, lattice_dynamics
from maglev_haptics.hardware.kernels import (
    INDEX_VECTOR, MATRIX, SCALAR, VECTOR, declared_kernels, kernel)
from maglev_haptics.hardware.realtime_priority import (
    fifo_permitted, is_realtime, realtime_priority)
from maglev_haptics.systems import step_worker
from maglev_haptics.systems.deformable_surface import (
    DeformableBody, DeformableDynamics)
from maglev_haptics.systems.lattice_construction import build_lattice
from maglev_haptics.systems.lattice_dynamics import (
    ProbeContact, add_probe_forces, lattice_model, state_contact)

P_TP_M = np.array([0.0, 0.0, -0.030])
PERIOD_S = 1e-3

OSCILLATOR_ARGUMENTS = (MATRIX, INDEX_VECTOR, VECTOR, VECTOR, SCALAR, SCALAR, SCALAR, MATRIX)


@kernel((VECTOR, VECTOR, VECTOR, *OSCILLATOR_ARGUMENTS), nogil=True)
def oscillator_tick(masses_in, masses_out, probe, rest, surface, mass, constants, k, c, h,
                    forces):
    """A second model: every node a damped oscillator about its rest position (m), spring
    k (N/m), damper c (N*s/m), pressed by the probe; one symplectic Euler step h (s)."""
    n = masses_in.shape[0] // 6
    masses_out[:] = masses_in
    x = masses_out[:3 * n].reshape((n, 3))
    v = masses_out[3 * n:].reshape((n, 3))
    forces[:] = 0.0
    add_probe_forces(x, v, surface, probe[0:3], probe[3:6], probe[6:9], constants[0],
                     constants[1], constants[2], constants[3], constants[4], constants[5],
                     mass, h, forces)
    for i in range(n):
        for a in range(3):
            v[i, a] += h * (forces[i, a] - k * (x[i, a] - rest[i, a]) - c * v[i, a]) / mass[i]
            x[i, a] += h * v[i, a]


OSCILLATOR_SERVER = step_worker.tick_server(oscillator_tick, OSCILLATOR_ARGUMENTS)


def oscillator_body():
    """(dynamics, positions_m): 9 x 9 oscillators 2.5 mm apart at z = 0, 2 g each."""
    grid = np.linspace(-0.01, 0.01, 9)
    positions_m = np.array([[x, y, 0.0] for x in grid for y in grid])
    n = len(positions_m)
    mass_kg = np.full(n, 0.002)
    probe = ProbeContact()

    def tick_arguments():
        return (positions_m, np.arange(n), mass_kg, probe.constants(), 300.0, 0.05,
                PERIOD_S, np.zeros((n, 3)))
    def contact(state, p_TP):
        return state_contact(state, np.arange(n), p_TP, probe.constants(), mass_kg,
                             PERIOD_S)
    return DeformableDynamics(
        node_mass_kg=mass_kg, surface_nodes=np.arange(n), tick=oscillator_tick,
        tick_arguments=tick_arguments, server=OSCILLATOR_SERVER,
        state_contact=contact), positions_m


def lattice_body(integrator: str):
    """(dynamics, positions_m): a small lattice under a wavy surface around z = 0."""
    x = np.linspace(-0.01, 0.01, 9)
    y = np.linspace(-0.01, 0.01, 9)
    heights = 0.001 * np.sin(x[:, None] / 0.003) * np.cos(y[None, :] / 0.004)
    lattice = build_lattice(heights, x, y, base_z_m=-0.012, level_spacing_m=0.003)
    model = lattice_model(lattice.links, lattice.rest_lengths_m, lattice.fixed, lattice.surface,
                          node_mass_kg=0.002, link_stiffness_n_per_m=200.0,
                          link_damping_n_s_per_m=0.05)
    return (lattice_dynamics(model, probe=ProbeContact(), period_s=PERIOD_S,
                             integrator=integrator), lattice.positions_m)


def pressing_diagram(worker_thread: bool, body: str = "symplectic_euler"):
    """A body (a lattice with that integrator, or the oscillators) and a tool held with
    its probe 1.5 mm under z = 0, sliding."""
    dynamics, positions_m = oscillator_body() if body == "oscillators" else lattice_body(body)
    p_WT = np.array([0.0, 0.0, 0.030 + ProbeContact().radius_m - 0.0015])
    builder = DiagramBuilder()
    surface = builder.AddSystem(DeformableBody(
        dynamics=dynamics, positions_m=positions_m, p_TP_m=P_TP_M,
        X_WT_start=RigidTransform(p_WT), period_s=PERIOD_S, worker_thread=worker_thread))
    pose = builder.AddSystem(ConstantVectorSource(np.concatenate(([1.0, 0, 0, 0], p_WT))))
    velocity = builder.AddSystem(ConstantVectorSource([0, 0, 0, 0.01, 0, 0]))
    builder.Connect(pose.get_output_port(), surface.GetInputPort("X_WT"))
    builder.Connect(velocity.get_output_port(), surface.GetInputPort("V_WT"))
    return builder.Build(), surface


def simulate(worker_thread, body="symplectic_euler", poke_at_s=None):
    diagram, surface = pressing_diagram(worker_thread, body)
    simulator = Simulator(diagram)
    simulator.Initialize()
    wrenches = []
    for k in range(1, 301):
        if poke_at_s is not None and abs(k * PERIOD_S - poke_at_s) < 1e-9:
            # Change the state from outside: the precomputed step no longer applies.
            context = surface.GetMyMutableContextFromRoot(simulator.get_mutable_context())
            state = context.get_discrete_state(0).get_value().copy()
            state[3 * surface.num_nodes:3 * surface.num_nodes + 30] += 0.01
            context.SetDiscreteState(0, state)
        simulator.AdvanceTo(k * PERIOD_S)
        wrenches.append(surface.GetOutputPort("wrench_on_tool_W").Eval(
            surface.GetMyContextFromRoot(simulator.get_context())).copy())
    state = surface.GetMyContextFromRoot(simulator.get_context()).get_discrete_state(0)
    return state.get_value().copy(), np.array(wrenches)


@pytest.mark.parametrize("body", ["symplectic_euler", "linearly_implicit", "oscillators"])
def test_worker_gives_the_synchronous_results_bit_for_bit(body):
    """The lattice with either integrator, and a second model's tick, through the same
    system and worker."""
    ahead, ahead_wrenches = simulate(True, body)
    inline, inline_wrenches = simulate(False, body)
    assert np.abs(inline_wrenches[:, 2]).max() > 0.01  # the probe does press (N)
    np.testing.assert_array_equal(ahead, inline)
    np.testing.assert_array_equal(ahead_wrenches, inline_wrenches)


@pytest.mark.parametrize("body, server", [("symplectic_euler", LATTICE_SERVER),
                                          ("oscillators", OSCILLATOR_SERVER)])
def test_the_worker_steps_on_from_its_own_result(monkeypatch, body, server):
    """Nearly every tick takes the worker's result, and asks for the next from it with
    the two buffers swapped (nothing copied in); the state stays the synchronous one.
    The worker's loop ran as declared (nothing compiled for other argument types)."""
    taken, inputs = [], []
    result_into = step_worker.StepWorker.result_into

    def counted(self, state, out):
        taken.append(result_into(self, state, out))
        inputs.append(int(self._control[4]))
        return taken[-1]

    monkeypatch.setattr(step_worker.StepWorker, "result_into", counted)
    ahead, _ = simulate(True, body)
    assert sum(taken) >= 0.9 * len(taken) and set(inputs) == {0, 1}
    np.testing.assert_array_equal(ahead, simulate(False, body)[0])
    declared = {signature for kernel, signature in declared_kernels() if kernel is server}
    assert len(declared) == 1 and set(server.overloads) == declared


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


SLEEP_US = 3000


@kernel((VECTOR, VECTOR, VECTOR, *OSCILLATOR_ARGUMENTS), cache=False, nogil=True)
def sleepy_oscillator_tick(masses_in, masses_out, probe, rest, surface, mass, constants, k, c,
                           h, forces):
    """The oscillators' tick, then SLEEP_US (us) asleep: a step of known least length."""
    oscillator_tick(masses_in, masses_out, probe, rest, surface, mass, constants, k, c, h,
                    forces)
    step_worker._usleep(SLEEP_US)


def test_the_worker_times_each_step_around_its_tick():
    """Every tick is stepped there or here, and each step there is timed around the tick
    itself: a tick that sleeps 3 ms is timed at least that long, the request's wait not
    counted (the loop asks every 1 ms of simulated time, free-running)."""
    dynamics, positions_m = oscillator_body()
    dynamics = dynamics._replace(tick=sleepy_oscillator_tick, server=step_worker.tick_server(
        sleepy_oscillator_tick, OSCILLATOR_ARGUMENTS))
    builder = DiagramBuilder()
    body = builder.AddSystem(DeformableBody(
        dynamics=dynamics, positions_m=positions_m, p_TP_m=P_TP_M,
        X_WT_start=RigidTransform([0.0, 0.0, 0.05]), period_s=PERIOD_S))
    for port, value in (("X_WT", [1.0, 0, 0, 0, 0, 0, 0.05]), ("V_WT", np.zeros(6))):
        builder.Connect(builder.AddSystem(ConstantVectorSource(value)).get_output_port(),
                        body.GetInputPort(port))
    simulator = Simulator(builder.Build())
    simulator.AdvanceTo(0.05)
    report = body.step_report()
    assert report["ticks_on_other_core"] + report["ticks_stepped_here"] == 50
    assert report["ticks_on_other_core"] >= 40
    assert SLEEP_US <= report["other_core_tick_us_p50"] <= report["other_core_tick_us_max"]
    assert report["other_core_tick_us_p50"] < 3 * SLEEP_US


def test_the_step_times_kept_are_the_last_ones_oldest_first(monkeypatch):
    monkeypatch.setattr(step_worker, "STEP_TIMES_KEPT", 8)
    recorded = []
    result_into = step_worker.StepWorker.result_into

    def recording(self, state, out):
        taken = result_into(self, state, out)
        if taken:
            recorded.append(int(self._control[5]))
            assert self.step_us().size == min(len(recorded), 8)
        return taken

    monkeypatch.setattr(step_worker.StepWorker, "result_into", recording)
    diagram, surface = pressing_diagram(worker_thread=True, body="oscillators")
    Simulator(diagram).AdvanceTo(0.1)
    assert len(recorded) > 8 and surface._worker.steps_taken == len(recorded)
    np.testing.assert_array_equal(surface._worker.step_us(), 1e-3 * np.array(recorded[-8:]))
    assert surface.step_report()["ticks_on_other_core"] == len(recorded)
