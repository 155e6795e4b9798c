"""The rigid scene stepped by a worker process: the same run bit for bit as in
place, a clear error when the worker dies, and no worker left behind."""

import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from pydrake.math import RigidTransform
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder

from maglev_haptics.analysis.run_results import run_scenario
from maglev_haptics.diagrams.application import BuildDiagram
from maglev_haptics.diagrams.scenario import ScenarioError, load_scenario
from maglev_haptics.diagrams.scene import PegInHole
from maglev_haptics.diagrams.scene_builder import AddScene
from maglev_haptics.systems.remote_scene import falls_on
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
@pytest.mark.parametrize("name, duration_s", [("peg_in_hole", 1.0), ("paddle_ball", 0.6)])
def test_worker_run_is_the_in_place_run_bit_for_bit(name, duration_s):
    logs = {mode: run_scenario(stepping(name, mode), label=mode, duration_s=duration_s,
                               progress=False).log for mode in ("in_place", "worker")}
    assert logs["worker"].keys() == logs["in_place"].keys()
    for key, value in logs["in_place"].items():
        assert np.array_equal(logs["worker"][key], value), key
    assert logs["worker"]["tool_in_contact"].any()


def test_a_killed_worker_is_a_clear_error():
    built = BuildDiagram(stepping("peg_in_hole", "worker"))
    pid = built.haptics.scene.worker.worker.pid
    simulator = Simulator(built.diagram)
    simulator.AdvanceTo(0.01)
    os.kill(pid, signal.SIGKILL)
    with pytest.raises(RuntimeError,
                       match=rf"scene worker \(pid {pid}\) died \(killed by signal 9\)"):
        simulator.AdvanceTo(0.1)


def X_WT(port, simulator):
    return port.Eval(port.get_system().GetMyContextFromRoot(simulator.get_context()))


def test_no_worker_outlives_its_use_and_the_next_request_starts_one():
    built = BuildDiagram(stepping("hanging_ball", "worker"))
    reference = BuildDiagram(stepping("hanging_ball", "in_place"))
    simulator, truth = Simulator(built.diagram), Simulator(reference.diagram)
    simulator.AdvanceTo(0.01)
    pid = built.haptics.scene.worker.worker.pid
    assert gone(pid, within_s=IDLE_EXIT_S + 4.0)
    simulator.AdvanceTo(0.03)
    assert built.haptics.scene.worker.worker.pid != pid
    truth.AdvanceTo(0.03)
    assert np.array_equal(X_WT(built.haptics.scene.X_WT_output, simulator),
                          X_WT(reference.haptics.scene.X_WT_output, truth))


def test_a_second_context_gets_its_own_state_not_the_first_ones_result():
    """Two simulators of one diagram, advanced in turns, each match its own run."""
    built = BuildDiagram(stepping("peg_in_hole", "worker"))
    reference = BuildDiagram(stepping("peg_in_hole", "in_place"))
    port = built.haptics.scene.X_WT_output
    reference_port = reference.haptics.scene.X_WT_output
    first, second = Simulator(built.diagram), Simulator(built.diagram)
    truth = Simulator(reference.diagram)
    for simulator in (first, second, truth):
        simulator.Initialize()
    first.AdvanceTo(0.05)
    for t in (0.02, 0.05, 0.08):
        second.AdvanceTo(t)
        first.AdvanceTo(0.05 + t)
    truth.AdvanceTo(0.08)
    assert np.array_equal(X_WT(port, second), X_WT(reference_port, truth))
    truth.AdvanceTo(0.13)
    assert np.array_equal(X_WT(port, first), X_WT(reference_port, truth))


def test_the_worker_ends_with_its_parent():
    script = (
        "import os, sys\n"
        "from pydrake.systems.analysis import Simulator\n"
        "from maglev_haptics.diagrams.application import BuildDiagram\n"
        "from maglev_haptics.diagrams.scenario import load_scenario\n"
        "built = BuildDiagram(load_scenario('hanging_ball', scenario_text="
        "'{haptics: {scene_stepping: worker}}'))\n"
        "Simulator(built.diagram).AdvanceTo(0.01)\n"
        "print(built.haptics.scene.worker.worker.pid, flush=True)\n"
        "os._exit(0)\n")  # no finalizers, no atexit: as if killed
    parent = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                            timeout=120, env={**os.environ, "MPLBACKEND": "Agg"})
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
