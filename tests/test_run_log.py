"""The run's log goes to disk as the run goes: the chunks add up to the in-memory log,
and a run killed with SIGKILL leaves a log that load_run_log reads to within a
second of the kill; SIGTERM or Ctrl-C ends a run with its results written."""

import json
import os
import re
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from maglev_haptics.analysis import load_run_log
from maglev_haptics.analysis import run_log
from maglev_haptics.analysis.run_results import run_scenario
from maglev_haptics.diagrams import runner, scenario_run
from maglev_haptics.diagrams.application import BuildDiagram
from maglev_haptics.diagrams.scenario import load_scenario
from maglev_haptics.hardware.realtime_priority import (
    BACKGROUND_PRIORITY, LOOP_PRIORITY, fifo_permitted, is_realtime, realtime_priority)
from maglev_haptics.hardware.thermal import coil_thermal


def test_chunked_log_is_the_in_memory_log(tmp_path, monkeypatch):
    monkeypatch.setattr(run_log, "CHUNK_WALL_S", 0.0)  # a chunk every progress step
    scenario = load_scenario("levitate")
    in_memory = run_scenario(scenario, label="levitate", duration_s=1.3, progress=False).log
    written = run_scenario(scenario, label="levitate", duration_s=1.3, progress=False,
                           out_dir=tmp_path).log
    assert not (tmp_path / run_log.CHUNK_DIR).exists()  # the finished run keeps log.npz only
    loaded = load_run_log(tmp_path)
    assert set(loaded) == set(in_memory) == set(written)
    for name, array in in_memory.items():
        np.testing.assert_array_equal(loaded[name], array, err_msg=name)
        np.testing.assert_array_equal(written[name], array, err_msg=name)
    assert len(loaded["t"]) == 1301  # 0 to 1.3 s at 1 kHz, the run's last state included


def test_a_run_into_an_earlier_runs_folder_writes_its_own_results(tmp_path):
    """Not the earlier run's log.npz or summary.json, whatever their scenario."""
    run_scenario(load_scenario("levitate"), label="first", duration_s=0.6, progress=False,
                 out_dir=tmp_path)
    second = run_scenario(load_scenario("peg_in_hole"), label="second", duration_s=0.3,
                          progress=False, out_dir=tmp_path)
    assert len(second.log["t"]) == 301 and "haptic_mode" in second.log
    assert len(load_run_log(tmp_path)["t"]) == 301
    assert json.loads((tmp_path / "summary.json").read_text())["scenario"] == "second"


def test_a_folder_without_a_log_is_named(tmp_path):
    with pytest.raises(FileNotFoundError, match=re.escape(str(tmp_path))):
        load_run_log(tmp_path)


@pytest.mark.slow  # a paced run in its own process, killed mid-flight
def test_a_killed_run_leaves_its_log_to_within_a_second(tmp_path):
    """A paced run killed with SIGKILL mid-flight: no log.npz, but the chunks hold the
    flight up to less than a second before the kill."""
    process = subprocess.Popen(
        [sys.executable, "-m", "maglev_haptics.cli", "run", "levitate", "--no-meshcat",
         "--realtime", "1.0", "--duration", "60", "--out", str(tmp_path)],
        stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    shown = []  # the simulated times its progress bar shows (s)

    def read_progress():
        text = ""
        while chunk := process.stderr.read(1):
            text = "" if chunk in "\r\n" else text + chunk
            if (match := re.search(r"([\d.]+)/[\d.]+ sim s", text)):
                shown.append(float(match.group(1)))

    threading.Thread(target=read_progress, daemon=True).start()
    try:
        deadline = time.monotonic() + 240.0  # building, and on a fresh install compiling
        while not shown or shown[-1] < 3.0:
            assert process.poll() is None and time.monotonic() < deadline, "the run never flew"
            time.sleep(0.05)
        process.send_signal(signal.SIGKILL)
        killed_at_s = shown[-1]  # at least this far when killed
        assert process.wait(timeout=10) == -signal.SIGKILL
    finally:
        if process.poll() is None:
            process.kill()
    assert not (tmp_path / "log.npz").exists()
    log = load_run_log(tmp_path)
    assert log["t"][-1] > killed_at_s - 1.0
    assert np.all(np.diff(log["t"]) > 0) and log["t"][0] == 0.0
    assert log["coil_currents"].shape == (len(log["t"]), 27)
    # It took off (resting at 7 mm, 18 mm up by 3 s).
    assert np.max(log["p_WI_true"][:, 2]) > 0.015 and np.all(np.isfinite(log["p_WI_measured"]))
    assert os.listdir(tmp_path / run_log.CHUNK_DIR)


@pytest.mark.slow  # a paced run in its own process, stopped mid-flight
@pytest.mark.parametrize("stop_signal", [signal.SIGTERM, signal.SIGINT])
def test_a_stopped_run_writes_its_results_and_says_so_in_one_line(tmp_path, stop_signal):
    """SIGTERM or Ctrl-C on a scripted run: the flying instrument lands, the run ends
    between ticks, writes the log, the summary and the plots of what it ran, and says
    so in one line (no traceback). The hover is held 40 s, so the signal finds the
    instrument flying however late a loaded host lets this test send it."""
    process = subprocess.Popen(
        [sys.executable, "-m", "maglev_haptics.cli", "run", "levitate", "--no-meshcat",
         "--realtime", "1.0", "--duration", "60", "--out", str(tmp_path), "--scenario-text",
         "{motion: {waypoints: [{pose: [0, 0, 0.018, 0, 0, 0], hold_s: 40}]}}"],
        stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 240.0
    while not list((tmp_path / run_log.CHUNK_DIR).glob("chunk_000003.npy")):  # ~2 s flown
        assert process.poll() is None and time.monotonic() < deadline, "the run never flew"
        time.sleep(0.05)
    process.send_signal(stop_signal)
    _, stderr = process.communicate(timeout=60)
    assert process.returncode == 128 + stop_signal.value
    last_line = stderr.strip().splitlines()[-1]
    assert f"stopped by {stop_signal.name}" in last_line and "after landing" in last_line
    assert "Traceback" not in stderr
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["stopped_by"] == stop_signal.name and 1.5 < summary["duration_s"] < 30.0
    # Down softly and level, the coils ramped off, before the run ended.
    assert summary["landed_before_stopping"]
    assert summary["touchdown"]["speed_m_s"] < 0.05 and summary["touchdown"]["tilt_deg"] < 1.0
    log = load_run_log(tmp_path)
    assert (tmp_path / "log.npz").exists() and not (tmp_path / run_log.CHUNK_DIR).exists()
    assert log["t"][-1] == pytest.approx(summary["duration_s"], abs=0.002)
    assert (tmp_path / "levitation.png").exists()
    assert np.all(log["wrench_commanded_W"][-10:] == 0.0)
    assert np.all(np.abs(log["coil_currents"][-10:]) < 1e-9)


class ScriptedSignals(runner.StopOnSignal):
    """SIGINT arriving at the given simulated times (s), as Ctrl-C pressed then."""

    def __init__(self, at_s):
        super().__init__()
        self._at_s = list(at_s)

    def __enter__(self):
        return self

    def __call__(self, context) -> bool:
        self.count = sum(context.get_time() >= at_s for at_s in self._at_s)
        self.received = "SIGINT" if self.count else None
        return self.received is not None


HOVER_40_S = "{motion: {waypoints: [{pose: [0, 0, 0.018, 0, 0, 0], hold_s: 40}]}}"


@pytest.mark.parametrize("signals_at_s, lands", [([3.0], True), ([3.0, 3.3], False)])
def test_a_stopped_runs_report_says_what_its_log_shows(monkeypatch, signals_at_s, lands):
    """One Ctrl-C lands the hovering instrument before the run stops; a second one 0.3 s
    later stops it at once, mid-landing: the summary then says it did not land, and
    where its last sample left the instrument."""
    scenario = load_scenario("levitate", scenario_text=HOVER_40_S)
    monkeypatch.setattr(scenario_run, "StopOnSignal", lambda: ScriptedSignals(signals_at_s))
    result = run_scenario(scenario, label="levitate", duration_s=20.0, progress=False)
    summary, log = result.summary, result.log
    assert summary["stopped_by"] == "SIGINT"
    assert summary["signals_received"] == len(signals_at_s)
    assert summary["landed_before_stopping"] is lands
    final = summary["final_state"]
    assert final["rests"] is lands
    assert final["z_m"] == pytest.approx(log["p_WI_true"][-1, 2], abs=1e-6)
    assert final["busiest_coil_current_a"] == pytest.approx(
        np.max(np.abs(log["coil_currents"][-1])), abs=1e-5)
    if lands:
        assert np.max(np.abs(log["coil_currents"][-1])) < 1e-3
    else:  # still flying, the coils carrying it
        assert log["p_WI_true"][-1, 2] > 0.010 and final["busiest_coil_current_a"] > 0.5
        assert summary["duration_s"] < 4.0


@pytest.mark.slow  # a paced run in its own process, Ctrl-C twice
def test_ctrl_c_twice_says_the_instrument_was_left_flying(tmp_path):
    """Ctrl-C twice 0.3 s apart on a haptic run: the second ends the landing the first
    began, and the last line says where the instrument was left, as the log shows."""
    process = subprocess.Popen(
        [sys.executable, "-m", "maglev_haptics.cli", "run", "peg_in_hole",
         "--no-meshcat", "--realtime", "1.0", "--out", str(tmp_path)],
        stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 240.0
    while not list((tmp_path / run_log.CHUNK_DIR).glob("chunk_000004.npy")):  # ~4 s flown
        assert process.poll() is None and time.monotonic() < deadline, "the run never flew"
        time.sleep(0.05)
    process.send_signal(signal.SIGINT)
    time.sleep(0.3)
    process.send_signal(signal.SIGINT)
    _, stderr = process.communicate(timeout=60)
    assert process.returncode == 128 + signal.SIGINT.value
    last_line = stderr.strip().splitlines()[-1]
    summary = json.loads((tmp_path / "summary.json").read_text())
    log = load_run_log(tmp_path)
    assert not summary["landed_before_stopping"] and "after landing" not in last_line
    assert re.search(r"stopped by SIGINT at [\d.]+ s \(signal 2 ended its landing\): the "
                     r"instrument was left at z = [\d.]+ mm with [\d.]+ A in the busiest coil",
                     last_line), last_line
    z_mm = float(re.search(r"z = ([\d.]+) mm", last_line).group(1))
    assert z_mm == pytest.approx(1e3 * log["p_WI_true"][-1, 2], abs=0.06)


@pytest.mark.skipif(not fifo_permitted(), reason="this process may not use SCHED_FIFO")
def test_the_writer_thread_runs_just_below_the_loops_real_time_priority(tmp_path):
    """Above normal threads (one preempting it between writes would hold the GIL, and
    the loop); below the loop's helpers, which must take the other core from it at once."""
    built = BuildDiagram(load_scenario("levitate"))
    writer = run_log.RunLogWriter(tmp_path, built.logger, built.log_layout,
                                  coil_thermal(load_scenario("levitate").device))
    thread_id = writer._writer.native_id
    with realtime_priority():
        assert is_realtime(thread_id)
        assert os.sched_getparam(thread_id).sched_priority == BACKGROUND_PRIORITY
        assert BACKGROUND_PRIORITY < LOOP_PRIORITY
    assert not is_realtime(thread_id)
