"""The rigid scene stepped by a worker process: the same run bit for bit as in
place, a clear error when the worker dies, and no worker left behind."""

import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from pydrake.common.eigen_geometry import Quaternion
from pydrake.math import RigidTransform
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder

from maglev_haptics.analysis.run_results import run_scenario
from maglev_haptics.diagrams.scenario import ScenarioError, load_scenario
from maglev_haptics.diagrams.scene import PegInHole
from maglev_haptics.diagrams.scene_builder import AddScene
from maglev_haptics.systems.remote_scene import falls_on
from maglev_haptics.hardware.realtime_priority import (
    fifo_permitted, is_realtime, realtime_priority)
from maglev_haptics.systems.scene_worker import IDLE_EXIT_S


def stepping(name: str, mode: str):
    return load_scenario(name, scenario_text=f"{{haptics: {{scene_stepping: {mode}}}}}")


def gone(pid: int, within_s: float = 5.0) -> bool:
    """Whether process ``pid`` has ended (a zombie not yet reaped counts) within
    ``within_s``."""
    end = time.monotonic() + within_s
    while time.monotonic() < end:
        try:
            with open(f"/proc/{pid}/stat") as stat:
                if stat.read().rsplit(")", 1)[1].split()[0] == "Z":
                    return True
        except FileNotFoundError:
            return True
        time.sleep(0.02)
    return False


# The peg rests on the table from 0.03 s; the paddle's ball lands on it at ~0.2 s.
@pytest.mark.parametrize("name, duration_s", [("peg_in_hole", 0.5), ("paddle_ball", 0.6)])
def test_worker_run_is_the_in_place_run_bit_for_bit(name, duration_s):
    logs = {mode: run_scenario(stepping(name, mode), label=mode, duration_s=duration_s,
                               progress=False).log for mode in ("in_place", "worker")}
    assert logs["worker"].keys() == logs["in_place"].keys()
    for key, value in logs["in_place"].items():
        assert np.array_equal(logs["worker"][key], value), key
    assert logs["worker"]["tool_in_contact"].any()


PUSH_W = [0.0, 0.0, -0.5, 1e-5, 0.0, 0.0]  # on the peg: into the hole, barely tilting it (N, N*m)


class Scene:
    """The peg scene alone, pushed by PUSH_W: stepped in place or by a worker."""

    def __init__(self, mode: str):
        builder = DiagramBuilder()
        self.parts = AddScene(builder, scene=PegInHole(), time_step_s=0.001,
                              X_WI_start=RigidTransform([0.0, 0.0, 0.05]),
                              use_sampled_output_ports=False, contact_sample_period_s=0.005,
                              stepping=mode)
        self.diagram = builder.Build()

    def simulator(self) -> Simulator:
        simulator = Simulator(self.diagram)
        port = self.parts.wrench_on_tool_input
        port.FixValue(
            port.get_system().GetMyMutableContextFromRoot(simulator.get_mutable_context()), PUSH_W)
        simulator.Initialize()
        return simulator

    def outputs(self, simulator) -> np.ndarray:
        """[X_WT, V_WT, contact wrench, in contact] now."""
        return np.concatenate([
            port.Eval(port.get_system().GetMyContextFromRoot(simulator.get_context()))
            for port in (self.parts.X_WT_output, self.parts.V_WT_output,
                         self.parts.contact_wrench_output, self.parts.in_contact_output)])

    @property
    def pid(self) -> int:
        return self.parts.worker.worker.pid


def test_a_second_context_gets_its_own_state_not_the_first_ones_result():
    """Two simulators of one diagram, advanced in turns, each match the plant
    stepped in place; the peg reaches the hole's floor."""
    scene, reference = Scene("worker"), Scene("in_place")
    first, second, truth = scene.simulator(), scene.simulator(), reference.simulator()
    first.AdvanceTo(0.05)
    for t in (0.02, 0.05, 0.08):
        second.AdvanceTo(t)
        first.AdvanceTo(0.05 + t)
    truth.AdvanceTo(0.08)
    assert np.array_equal(scene.outputs(second), reference.outputs(truth))
    truth.AdvanceTo(0.13)
    assert np.array_equal(scene.outputs(first), reference.outputs(truth))
    assert scene.outputs(first)[-1] == 1.0


@pytest.mark.skipif(not fifo_permitted(), reason="this process may not use SCHED_FIFO")
def test_the_worker_runs_at_its_parents_priority():
    """As a paced loop enters real-time priority the worker takes it up, and steps
    (sleeping between requests); back to normal after. Still bit for bit."""
    scene, reference = Scene("worker"), Scene("in_place")
    simulator, truth = scene.simulator(), reference.simulator()
    tick = 0

    def ticks(n: int) -> None:
        """``n`` ticks, each with a pause for the worker to step (as a paced loop's
        wait gives it)."""
        nonlocal tick
        for _ in range(n):
            tick += 1
            simulator.AdvanceTo(tick * 0.001)
            time.sleep(0.0005)

    with realtime_priority():
        assert is_realtime(scene.pid)
        ticks(100)
        assert is_realtime(scene.pid)
    assert not is_realtime(scene.pid)
    ticks(50)
    truth.AdvanceTo(tick * 0.001)
    assert np.array_equal(scene.outputs(simulator), reference.outputs(truth))


def test_a_killed_worker_is_a_clear_error():
    scene = Scene("worker")
    simulator = scene.simulator()
    simulator.AdvanceTo(0.01)
    pid = scene.pid
    os.kill(pid, signal.SIGKILL)
    # Until the kill is seen (its threads take tens of ms to end) the plant steps here.
    with pytest.raises(RuntimeError,
                       match=rf"scene worker \(pid {pid}\) died \(killed by signal 9\)"):
        simulator.AdvanceTo(2.0)


def test_no_worker_outlives_its_use_and_the_next_request_starts_one():
    scene, reference = Scene("worker"), Scene("in_place")
    simulator, truth = scene.simulator(), reference.simulator()
    simulator.AdvanceTo(0.01)
    pid = scene.pid
    assert gone(pid, within_s=IDLE_EXIT_S + 4.0)
    simulator.AdvanceTo(0.03)
    assert scene.pid != pid
    truth.AdvanceTo(0.03)
    assert np.array_equal(scene.outputs(simulator), reference.outputs(truth))


def test_the_worker_ends_with_its_parent():
    script = (
        "import os\n"
        "from pydrake.math import RigidTransform\n"
        "from pydrake.systems.framework import DiagramBuilder\n"
        "from maglev_haptics.diagrams.scene import PegInHole\n"
        "from maglev_haptics.diagrams.scene_builder import AddScene\n"
        "parts = AddScene(DiagramBuilder(), scene=PegInHole(), time_step_s=0.001,\n"
        "                 X_WI_start=RigidTransform([0, 0, 0.05]), contact_sample_period_s=0.005,\n"
        "                 stepping='worker')\n"
        "parts.worker.worker.wait_ready()\n"
        "print(parts.worker.worker.pid, flush=True)\n"
        "os._exit(0)\n")  # no finalizers, no atexit: as if killed
    parent = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                            timeout=120)
    assert parent.returncode == 0, parent.stderr
    assert gone(int(parent.stdout.split()[-1]))


def test_contact_samples_fall_on_the_ticks_they_share_a_time_with():
    assert all(falls_on(k * 0.001, 0.005) == (k % 5 == 0) for k in range(20000))
    assert not falls_on(1 / 860, 0.005)


def test_stepping_is_checked():
    builder = DiagramBuilder()
    with pytest.raises(ValueError, match=r"stepping = 'elsewhere': one of worker, in_place"):
        AddScene(builder, scene=PegInHole(), time_step_s=0.001,
                 X_WI_start=RigidTransform([0, 0, 0.05]), stepping="elsewhere")
    with pytest.raises(ValueError, match=r"give contact_sample_period_s"):
        AddScene(builder, scene=PegInHole(), time_step_s=0.001,
                 X_WI_start=RigidTransform([0, 0, 0.05]), stepping="worker")
    with pytest.raises(ScenarioError, match=r"haptics.scene_stepping = 'thread': one of worker"):
        stepping("peg_in_hole", "thread")


def test_the_scene_graph_draws_the_worker_stepped_tool_where_it_is():
    scene = Scene("worker")
    simulator = scene.simulator()
    simulator.AdvanceTo(0.1)
    parts = scene.parts
    query = parts.scene_graph.get_query_output_port().Eval(
        parts.scene_graph.GetMyContextFromRoot(simulator.get_context()))
    X_WT = RigidTransform(Quaternion(scene.outputs(simulator)[0:4]), scene.outputs(simulator)[4:7])
    X_WT_drawn = query.GetPoseInWorld(parts.plant.GetBodyFrameIdOrThrow(parts.tool_body.index()))
    assert X_WT_drawn.IsNearlyEqualTo(X_WT, 1e-12)
    assert X_WT.translation()[2] < 0.03  # it has moved: the peg rests on the hole's floor
