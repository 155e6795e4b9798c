"""A device that goes silent (its process killed, its host gone): the application
notices it within the lease's timeout, stops at once without a landing, says so in
one line and exits 5; the silence is counted in ``summary.json``'s ``station``.
And device-sim's own stop by a signal: 128 + N, with a line."""

import dataclasses
import json
import math
import os
import re
import signal
import subprocess
import sys
import time

import lcm
import numpy as np
import pytest
from pydrake.systems.framework import DiagramBuilder

from maglev_haptics.analysis.run_outcome import device_silent_outcome, instrument_outcome
from maglev_haptics.diagrams.lcm_station import (
    LcmStation, MakeLcmStation, device_silence, silent_channels)
from maglev_haptics.diagrams.scenario import load_scenario
from maglev_haptics.hardware.link.lcm_link import publish
from maglev_haptics.hardware.link.lcm_messages import lease_t
from maglev_haptics.hardware.link.lease import REPLY_PERIOD_S
from maglev_haptics.systems.station_messages import (
    LATENCY_BINS, currents_message, markers_message, receiver_counts, receiver_step,
    trailing_silence)

LABEL = "levitate:takeoff_hover_land"
NEVER = [-1.0, -math.inf, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]


def test_silent_channels_are_those_quiet_for_the_timeout():
    arrivals = {"markers": 3.549, "coil_currents": 3.549, "lease": 3.45, "glasses": -math.inf}
    assert silent_channels(arrivals, 3.9, 0.5) == {}
    assert silent_channels(arrivals, 3.95, 0.5) == {"lease": pytest.approx(0.5)}
    # Exactly the timeout, in floats that miss it by an ulp, is silent; never heard is not.
    assert list(silent_channels(arrivals, 3.549 + 0.5, 0.5)) == [
        "markers", "coil_currents", "lease"]


def test_the_device_is_silent_once_its_lease_answers_stop_for_the_timeout():
    """The lease's answers (every REPLY_PERIOD_S) are the device's heartbeat: silent for
    the timeout past the answer that was due, the device is silent, and every channel
    that stopped with it is named, since when and for how long."""
    arrivals = {"markers": 3.549, "coil_currents": 3.549, "lease": 3.45}
    assert device_silence(arrivals, 3.45 + 0.5, 0.5) is None  # its next answer was due at 3.55
    assert device_silence(arrivals, 4.0, 0.5) is None
    silence = device_silence(arrivals, 4.05, 0.5)
    assert silence == {"at_s": 3.549, "channels": ["markers", "coil_currents", "lease"],
                       "for_s": pytest.approx(0.501), "timeout_s": 0.5}
    # The lease alone silent (a coil driver gone, the tracker still sending): the
    # device that takes the commands is gone; the markers still came, so are not named.
    alone = device_silence({"markers": 9.999, "lease": 9.0}, 10.0, 0.5)
    assert alone == {"at_s": 9.0, "channels": ["lease"], "for_s": pytest.approx(1.0),
                     "timeout_s": 0.5}
    # Markers silent alone: their own loss (the landing flown blind), not the device's.
    assert device_silence({"markers": 1.0, "lease": 9.95}, 10.0, 0.5) is None
    # No answer yet: the lease's own wait (wait_for_station_s) judges that.
    assert device_silence({"markers": 1.0, "lease": -math.inf}, 10.0, 0.5) is None
    assert REPLY_PERIOD_S == 0.1  # the period the heartbeat's allowance assumes


def test_the_silence_after_the_last_message_counts_as_a_gap():
    state = NEVER
    for sequence, t_s in ((1, 0.000), (2, 0.001), (3, 0.009)):
        state = receiver_step(state, sequence, t_s, 0.0, stale_gap_s=0.005)
    histogram = np.zeros(LATENCY_BINS)
    histogram[0] = 3  # the three latencies, 0 s
    assert trailing_silence(state, None) == (pytest.approx(0.008), 1)
    assert trailing_silence(state, 0.010, stale_gap_s=0.005) == (pytest.approx(0.008), 1)
    assert trailing_silence(state, 0.5, stale_gap_s=0.005) == (pytest.approx(0.491), 2)
    assert trailing_silence(state, 0.5) == (pytest.approx(0.491), 1)  # no stale value
    assert trailing_silence(NEVER, 0.5, 0.005) == (0.0, 0)  # nothing heard: nothing silent
    counts = receiver_counts(state, histogram, now_s=0.5, stale_gap_s=0.005)
    assert counts["longest_gap_ms"] == pytest.approx(491.0) and counts["stale_gaps"] == 2
    counts = receiver_counts(state, histogram)  # gaps that a message ended only
    assert counts["longest_gap_ms"] == pytest.approx(8.0) and counts["stale_gaps"] == 1


def silent_summary(**station):
    return {"duration_s": 4.25, "station": {"device_silent": {
        "at_s": 3.549, "channels": ["markers", "coil_currents", "lease"], "for_s": 0.701,
        "timeout_s": 0.5}, **station}}


def test_a_silent_device_is_the_line_printed_not_a_lost_instrument():
    """The markers stopped with the device, so tracking was lost too: the line says
    the device went silent (and is said with injected faults as well)."""
    line = (f"{LABEL}: the device went silent at 3.549 s (MARKERS, COIL_CURRENTS, LEASE: no "
            "message for 0.70 s, past the lease's 0.5 s timeout): the application stopped "
            "at 4.250 s; it cannot land what it no longer commands")
    t = np.arange(0.0, 4.25, 0.001)
    log = {"t": t, "fault_bits": np.where(t >= 3.551, 1, 0)}
    summary = silent_summary(channels={"markers": {"stale_gaps": 1, "longest_gap_ms": 701.0}},
                             messages_refused=0, lease={"lost_to": None})
    assert device_silent_outcome(summary, LABEL) == line
    assert instrument_outcome(load_scenario("levitate"), summary, log, LABEL) == line
    injected = load_scenario("levitate", scenario_text=(
        "{occlusions: [{marker: null, start_s: 1.0, end_s: 1.3}]}"))
    assert instrument_outcome(injected, summary, log, LABEL) == line
    summary["station"]["device_silent"] = None
    assert device_silent_outcome(summary, LABEL) is None
    assert " the instrument was lost at 3.551 s" in instrument_outcome(
        load_scenario("levitate"), summary, log, LABEL)


def lcm_station_on_memory(name: str = "levitate"):
    """(scenario, the LCM station, a diagram holding it, that diagram's context, the
    station's LCM bus): the application's station on an in-memory LCM (``memq://``),
    whose messages a test publishes on the receiver's own bus."""
    scenario = load_scenario(name)
    scenario = dataclasses.replace(scenario, station=LcmStation(
        url="memq://", command_url="memq://", channel_prefix="T_"))
    builder = DiagramBuilder()
    station = MakeLcmStation(scenario)
    builder.AddSystem(station.system)
    diagram = builder.Build()
    return scenario, station, diagram, diagram.CreateDefaultContext(), station.receiver._lcm


def test_a_device_that_stops_sending_is_seen_silent_and_its_silence_counted():
    """The application's station reads markers and currents every tick and the lease's
    answers every 0.1 s; then the device stops (at 0.35 s, its last answer at 0.3 s).
    Its silence is seen once the answer due at 0.4 s is 0.5 s late, the run's stop
    says stop (without asking the run's own, which would land), and the counts hold
    the silence: the longest gap, and a stale gap for the markers."""
    scenario, station, diagram, context, bus = lcm_station_on_memory()
    receiver = station.receiver
    receiver_context = receiver.GetMyMutableContextFromRoot(context)
    lease = station.lease
    markers = np.array([0.01, 0.0, 0.02, -0.01, 0.0, 0.02, 0.0, 0.01, 0.02])
    currents = np.r_[np.zeros(27), 1.0]
    asked = []
    stop = station.watch(lambda context: asked.append(context.get_time()))

    def tick(t_s):
        context.SetTime(t_s)
        receiver_context.SetDiscreteState(receiver.EvalUniquePeriodicDiscreteUpdate(
            receiver_context))

    answer = 0
    for k in range(1, 351):
        t_s = k * 0.001
        publish(bus, "T_MARKERS", markers_message(k, t_s, t_s, markers))
        publish(bus, "T_COIL_CURRENTS", currents_message(k, t_s, currents))
        if k % 100 == 0:
            answer += 1
            reply = lease_t()
            reply.sequence, reply.action, reply.session = answer, lease_t.HELD, lease.session
            reply.instrument = scenario.device.instrument
            publish(bus, "T_LEASE", reply)
        tick(t_s + 0.001)
    assert lease.granted
    assert station.newest_arrivals(context) == {
        "markers": pytest.approx(0.351), "coil_currents": pytest.approx(0.351),
        "lease": pytest.approx(0.301)}
    for t_s in (0.5, 0.75, 0.9):  # the lease's answer due at 0.401 is not yet 0.5 s late
        tick(t_s)
        assert not stop(context) and station.silence(context) is None
    assert asked == [0.5, 0.75, 0.9]
    tick(0.901)
    assert stop(context) and asked == [0.5, 0.75, 0.9]  # the run's own stop not asked
    silence = station.silence(context)
    assert silence == {"at_s": pytest.approx(0.351), "timeout_s": 0.5,
                       "channels": ["markers", "coil_currents", "lease"],
                       "for_s": pytest.approx(0.55)}
    counts = station.summary(context)
    assert counts["device_silent"] == silence and counts["kind"] == "lcm"
    channels = counts["channels"]
    assert channels["markers"]["longest_gap_ms"] == pytest.approx(550.0)
    assert channels["markers"]["stale_gaps"] == 1  # the markers read as unseen in it
    assert channels["coil_currents"]["longest_gap_ms"] == pytest.approx(550.0)
    assert channels["coil_currents"]["stale_gaps"] == 0  # held, never stale
    assert channels["lease"]["longest_gap_ms"] == pytest.approx(600.0)
    assert counts["stale_gaps"] == 1 and counts["messages_lost"] == 0


def test_device_sim_stopped_by_a_signal_says_so_and_exits_128_plus_n(monkeypatch, capsys):
    """SIGTERM while device-sim runs: its report (rounded: 394.75 s, not
    394.75000016864215), then one line, exit 143."""
    from maglev_haptics.diagrams import device_sim, runner
    from maglev_haptics.cli import main

    class FakeDeviceSim:
        stop_after_silence_s = 1.0

        def application_gone(self, context):
            return False

        def last_command_s(self, context):
            return 394.0

        def command_counts(self, context, until_now=True):
            return {"messages_received": 3, "until_now": until_now}

        def lease_counts(self, context):
            return {"grants": 1}

    class Context:
        def get_time(self):
            return 394.75000016864215

    class Simulator:
        def get_context(self):
            return Context()

    def simulate(built, duration_s, *, stop, **_):
        signal.raise_signal(signal.SIGTERM)  # StopOnSignal's handler takes it
        assert stop(Context())
        return Simulator(), 394.7500003, runner.TickTimes(
            slot_s=0.001, compute_s=np.full(3, 3e-4), lateness_s=np.full(3, -1e-4))

    monkeypatch.setattr(device_sim, "BuildDeviceSim", lambda scenario: FakeDeviceSim())
    monkeypatch.setattr(runner, "simulate", simulate)
    assert main(["device-sim", "levitate"]) == 128 + signal.SIGTERM
    out, err = capsys.readouterr()
    report = json.loads(out)
    assert report["duration_s"] == 394.75 and report["wall_time_s"] == 394.75
    assert report["commands"]["until_now"] is True
    assert err.strip().splitlines()[-1] == f"device-sim {LABEL}: stopped by SIGTERM at 394.750 s"


SILENT_LINE = re.compile(
    rf"^{LABEL}: the device went silent at (\d+\.\d{{3}}) s \(MARKERS, COIL_CURRENTS, LEASE: "
    r"no message for (\d\.\d\d) s, past the lease's 0\.5 s timeout\): the application "
    r"stopped at (\d+\.\d{3}) s; it cannot land what it no longer commands$")


@pytest.mark.slow
@pytest.mark.parametrize("kill", ["SIGKILL", "SIGTERM"])
def test_an_application_whose_device_dies_stops_within_the_lease_timeout(tmp_path, kill):
    """`maglev device-sim levitate` killed 2 s into `maglev run levitate --station lcm
    --duration 15`, both paced at 1x: the application stops within the lease's
    timeout and a check (0.5-0.85 s of silence), without a landing, says which
    channels went silent, since when and for how long, and exits 5 once its files are
    written; summary.json's station holds the silence. device-sim itself,
    stopped by SIGTERM, says so and exits 143."""
    port = 8500 + 2 * (os.getpid() % 50)
    station = (f"{{station: !LcmStation {{url: 'udpm://239.255.76.67:{port}?ttl=0', "
               f"command_url: 'udpm://239.255.76.67:{port + 1}?ttl=0'}}}}")
    maglev = [sys.executable, "-m", "maglev_haptics.cli"]
    paced = ["--scenario-text", station, "--realtime", "1"]
    listener = lcm.LCM(f"udpm://239.255.76.67:{port}?ttl=0")
    holders = []
    listener.subscribe("MAGLEV_LEASE", lambda _, data: holders.append(lease_t.decode(data)))
    device = subprocess.Popen(maglev + ["device-sim", "levitate", *paced, "--duration", "120"],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    application = None
    try:
        application = subprocess.Popen(
            maglev + ["run", "levitate", *paced, "--no-meshcat", "--duration", "15",
                      "--out", str(tmp_path / "run")],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        deadline = time.monotonic() + 180
        while not any(h.action == lease_t.HELD for h in holders):
            assert application.poll() is None and time.monotonic() < deadline
            listener.handle_timeout(50)
        time.sleep(2.0)  # flying: take-off ends at ~1 s
        assert application.poll() is None
        device.send_signal(getattr(signal, kill))
        killed = time.monotonic()
        while application.poll() is None and time.monotonic() < killed + 60:
            time.sleep(0.01)
        exit_s = time.monotonic() - killed
        out, err = application.communicate(timeout=60)
        device_out, device_err = device.communicate(timeout=60)
    finally:
        for process in (application, device):
            if process is not None:
                process.kill()
    print(f"{kill}: the application exited {exit_s:.2f} s after it")
    assert application.returncode == 5, err[-2000:]
    line = err.strip().splitlines()[-1]
    match = SILENT_LINE.match(line)
    assert match, line
    at_s, for_s, stopped_s = (float(group) for group in match.groups())
    assert 0.5 <= for_s <= 0.5 + REPLY_PERIOD_S + 0.25 + 0.01  # timeout, answer, check
    assert stopped_s < 15.0 and "landed first" not in err  # no landing flown
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    silent = summary["station"]["device_silent"]
    assert silent["channels"] == ["markers", "coil_currents", "lease"]
    assert silent["at_s"] == pytest.approx(at_s, abs=1e-3)
    assert silent["for_s"] == pytest.approx(for_s, abs=0.006)
    assert summary["duration_s"] == pytest.approx(stopped_s, abs=1e-3)
    assert "landed_before_stopping" not in summary
    channels = summary["station"]["channels"]
    assert channels["markers"]["longest_gap_ms"] >= 1e3 * silent["for_s"] - 1.0
    assert channels["markers"]["stale_gaps"] >= 1
    assert channels["lease"]["longest_gap_ms"] >= 1e3 * (silent["timeout_s"] + REPLY_PERIOD_S)
    # The loop stopped within the timeout, an answer's period and a check of the kill
    # (above); the process then writes the run's files (two plots, 1.5-3 s on a 2-core
    # host) and exits: 2.8-3.9 s after the kill measured on a quiet one, 6-8 s on one
    # loaded by other test runs.
    assert exit_s < 15.0, f"{exit_s:.2f} s from the kill to the application's exit"
    if kill == "SIGTERM":
        assert device.returncode == 128 + signal.SIGTERM, device_err[-2000:]
        assert re.fullmatch(r"device-sim levitate:takeoff_hover_land: stopped by SIGTERM at "
                            r"\d+\.\d{3} s", device_err.strip().splitlines()[-1])
        report = json.loads(device_out)
        assert len(repr(report["duration_s"]).replace(".", "").lstrip("0")) <= 6
    else:
        assert device.returncode == -signal.SIGKILL
