"""The MLHI-style device API: blocking takeoff and landing, commands on the next tick,
the tick callback, the boundary sphere's fault, estimated coil temperatures."""

import dataclasses
import json
import os
import re
import socket
import subprocess
import sys
import threading
import time

import lcm
import numpy as np
import pytest

from maglev_haptics.diagrams.device_api import (
    FAULT_SENSOR_OUT_OF_RANGE, WATCH_PERIOD_S, DeviceFaultError, DeviceInUseError,
    DeviceSilentError, DeviceStateError, DeviceTimeoutError, MaglevDevice)
from maglev_haptics.diagrams.lcm_station import LcmStation
from maglev_haptics.diagrams.scenario import load_scenario
from maglev_haptics.hardware.link.lcm_link import publish
from maglev_haptics.hardware.link.lcm_messages import lease_t
from maglev_haptics.hardware.link.lease import LeaseClient
from maglev_haptics.systems.station_messages import currents_message, markers_message

REST_Z_M = 0.0067  # the two-magnet instrument's origin resting on the glass (about, m)


def commanded_wrench(device):
    controller = device._controller
    return controller.GetOutputPort("wrench_commanded_W").Eval(
        device._contexts[controller])


def test_fly_with_the_api():
    device = MaglevDevice("levitate")
    with pytest.raises(RuntimeError, match="not connected"):
        device.takeoff()
    device.connect()
    times = []
    device.on_tick(lambda state: times.append(state.t_s))
    device.takeoff()  # blocks until hovering at the first waypoint
    hover = np.asarray(device.scenario.motion.waypoints[0].pose)
    assert np.linalg.norm(device.state.X_WI[4:7] - hover[0:3]) < 0.5e-3
    assert len(times) == round(device.state.t_s / 1e-3)  # every tick, from the first

    # A setpoint, gains and a feed-forward wrench are what the next tick computes with.
    controller = device._controller
    controller_context = device._contexts[controller]
    device.set_desired_pose(hover + [0, 0, 1e-3, 0, 0, 0])
    setpoint = controller.GetInputPort("setpoint").Eval(controller_context)
    np.testing.assert_allclose(setpoint[0:6], hover + [0, 0, 1e-3, 0, 0, 0])
    z_error_m = setpoint[2] - controller.GetInputPort("X_WI_measured").Eval(controller_context)[6]
    kp, kd = device.gains()
    before = commanded_wrench(device)
    device.set_gains(kp=2 * kp)
    np.testing.assert_allclose(device.gains()[0], 2 * kp)
    # Translation is PD in W: doubling kp adds kp (z error) to the z force.
    assert commanded_wrench(device)[2] - before[2] == pytest.approx(kp[2] * z_error_m, rel=1e-9)
    before = commanded_wrench(device)
    device.set_feedforward_wrench([0, 0, 0.05, 0, 0, 0.001])
    np.testing.assert_allclose(commanded_wrench(device) - before, [0, 0, 0.05, 0, 0, 0.001],
                               atol=1e-12)
    device.set_feedforward_wrench(np.zeros(6))
    device.set_gains(kp=kp)
    device.run_for(1.0)
    assert device.state.X_WI[6] == pytest.approx(hover[2] + 1e-3, abs=0.1e-3)

    temperatures = device.coil_temperatures_c()
    ambient_c = device.scenario.device.thermal.ambient_temperature_c
    assert temperatures.max() > ambient_c + 0.1  # hovering heats the coils
    device.land()
    assert device.state.X_WI[6] == pytest.approx(REST_Z_M, abs=1.5e-3)
    assert device._current_enable() == 0.0 and device.faults == 0
    device.disconnect()


def test_a_takeoff_while_flying_or_landing_never_lets_the_instrument_fall():
    """The force ramps up from what it is: a second takeoff while hovering, or one
    during a landing, flies to the pose from where the setpoint is; the instrument
    never sinks towards the glass (a ramp restarted from zero dropped it 11 mm)."""
    device = MaglevDevice("levitate")
    device.connect()
    device.takeoff()
    heights = []
    device.on_tick(lambda state: heights.append(state.X_WI[6]))
    hover = np.asarray(device.scenario.motion.waypoints[0].pose)
    device.takeoff(hover + [0.005, 0, 0, 0, 0, 0])
    assert min(heights) > hover[2] - 0.5e-3
    context = device._contexts[device._supervisor]
    device._supervisor.land(context)  # a landing under way, as land() starts it
    device.run_for(0.6)
    landing_z = device.state.X_WI[6]
    assert landing_z < hover[2] - 1e-3  # on its way down
    heights.clear()
    device.takeoff()
    assert min(heights) > landing_z - 0.5e-3
    assert np.linalg.norm(device.state.X_WI[4:7] - hover[0:3]) < 0.5e-3
    device.land()
    device.disconnect()


def test_a_pose_is_refused_while_the_coils_do_not_carry_the_instrument():
    """Before takeoff and after landing the coils carry nothing: a desired pose is
    refused, saying what to do, instead of being taken and never flown."""
    device = MaglevDevice("levitate")
    device.connect()
    with pytest.raises(DeviceStateError, match=r"the coils carry nothing \(call takeoff"):
        device.set_desired_pose([0, 0, 0.02, 0, 0, 0])
    device.takeoff()
    device.set_desired_pose([0, 0, 0.02, 0, 0, 0])
    device.land()
    with pytest.raises(DeviceStateError, match="the coils carry nothing"):
        device.set_desired_pose([0, 0, 0.02, 0, 0, 0])
    device.disconnect()


def test_the_apis_arguments_are_checked_by_name():
    """Each bad argument names itself, its value and what is allowed; every call before
    connect() says to connect first."""
    with pytest.raises(ValueError, match=r"^realtime_rate = -1: must be a finite number >= 0"):
        MaglevDevice("levitate", realtime_rate=-1)
    device = MaglevDevice("levitate")
    assert device.state is None
    with pytest.raises(RuntimeError, match="not connected"):
        device.coil_temperatures_c()
    device.connect()
    for call, message in (
            (lambda: device.run_for(-1.0), r"^duration_s = -1.0: must be a finite number >= 0"),
            (lambda: device.run_for(float("nan")), r"^duration_s = nan: must be a finite"),
            (lambda: device.run_for("1"), r"^duration_s = '1': must be a finite"),
            (lambda: device.takeoff(timeout_s=-1), r"^timeout_s = -1: must be a finite number > 0"),
            (lambda: device.land(timeout_s=0), r"^timeout_s = 0: must be a finite number > 0")):
        with pytest.raises(ValueError, match=message):
            call()
    assert device.state.t_s == 0.0  # nothing ran
    device.takeoff()
    with pytest.raises(Exception, match=r"^pose = \[0.0, 0.0, -0.01, 0.0, 0.0, 0.0\]: "
                                        r"unreachable"):
        device.set_desired_pose(np.array([0.0, 0.0, -0.01, 0.0, 0.0, 0.0]))
    with pytest.raises(Exception, match=r"tilt 65.9 deg .* \(roll, pitch and yaw are in radians"):
        device.set_desired_pose([0.0, 0.0, 0.02, 0.0, 20.0, 0.0])
    device.land()
    device.disconnect()


def test_leaving_the_boundary_raises_its_fault_and_lands():
    device = MaglevDevice("levitate")
    device.connect()
    device.takeoff()
    hover = np.asarray(device.scenario.motion.waypoints[0].pose)
    raised = []
    device.on_fault(raised.append)
    device.set_boundary(hover[0:3], 0.005)
    device.set_desired_pose(hover + [0.01, 0, 0, 0, 0, 0])  # out of the sphere
    device.run_for(4.0)
    assert raised and raised[0] & FAULT_SENSOR_OUT_OF_RANGE
    assert device.faults & FAULT_SENSOR_OUT_OF_RANGE  # latched
    assert device.state.X_WI[6] == pytest.approx(REST_Z_M, abs=1.5e-3)  # landed
    assert device._current_enable() == 0.0
    with pytest.raises(DeviceFaultError, match="takeoff refused: fault 0x1 is latched"):
        device.takeoff()
    device.reset_faults()
    assert device.faults == 0


def test_a_takeoff_that_cannot_finish_times_out_and_lands():
    device = MaglevDevice("levitate")
    device.connect()
    with pytest.raises(DeviceTimeoutError, match="takeoff not done within 0.3 s"):
        device.takeoff(timeout_s=0.3)  # the force ramp alone takes longer
    assert device._current_enable() == 0.0  # landed and ramped down
    device.takeoff()
    with pytest.raises(DeviceTimeoutError, match="land not done within 0.01 s"):
        device.land(timeout_s=0.01)
    device.run_for(0.005)
    assert device._current_enable() == 0.0  # the coils stay off: no landing ramp resumes
    with pytest.raises(ValueError, match=r"pose = \[0.0, 0.0, 0.02\]: must be 6 finite"):
        device.set_desired_pose([0.0, 0.0, 0.02])
    with pytest.raises(ValueError, match="pose = .*inside the display glass"):
        device.set_desired_pose([0.0, 0.0, 0.001, 0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="pose = .*out of the coils' reach"):
        device.set_desired_pose([0.0, 0.0, 0.2, 0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="kp = .*must be 6 finite gains >= 0"):
        device.set_gains(kp=[-1.0] * 6)


def test_after_tracking_is_lost_and_back_a_reset_lets_it_fly_again():
    """Tracking lost past the grace: the controller cuts the coils and the instrument
    falls onto the glass, the fault latches; once tracking is back, reset_faults
    clears the latched loss and a takeoff flies."""
    scenario = load_scenario(
        "levitate", scenario_text="{occlusions: [{marker: null, start_s: 4.0, end_s: 4.3}]}")
    device = MaglevDevice(scenario)
    device.connect()
    device.takeoff()
    assert device.state.t_s < 4.0
    device.run_for(4.5 - device.state.t_s)
    assert device.faults == FAULT_SENSOR_OUT_OF_RANGE
    assert device.state.X_WI[6] == pytest.approx(REST_Z_M, abs=1.5e-3)  # fell onto the glass
    assert not commanded_wrench(device).any()  # every coil off
    device.reset_faults()
    device.takeoff()
    hover = np.asarray(device.scenario.motion.waypoints[0].pose)
    assert np.linalg.norm(device.state.X_WI[4:7] - hover[0:3]) < 0.5e-3
    device.land()
    device.disconnect()


@pytest.mark.slow
def test_connect_is_refused_while_another_application_holds_the_device():
    """With a station on LCM, connect takes the device's lease first: while another
    application holds it (this test, commanding coils off), connect raises
    DeviceInUseError naming the holder, and its diagram commanded nothing."""
    port = 8400 + 2 * (os.getpid() % 50)
    url, command_url = (f"udpm://239.255.76.67:{port}?ttl=0",
                        f"udpm://239.255.76.67:{port + 1}?ttl=0")
    station = f"{{station: !LcmStation {{url: '{url}', command_url: '{command_url}'}}}}"
    device = subprocess.Popen(
        [sys.executable, "-m", "maglev_haptics.cli", "device-sim", "levitate",
         "--scenario-text", station, "--duration", "120"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    listener, commands = lcm.LCM(url), lcm.LCM(command_url)
    replies = []
    listener.subscribe("MAGLEV_LEASE", lambda _, data: replies.append(lease_t.decode(data)))
    holder = LeaseClient(lcm=commands, channel="MAGLEV_LEASE_REQUEST", wait_s=180.0,
                         instrument="two_magnet")
    stop = threading.Event()

    def keep_alive():  # the holder commands the coils off at 100 Hz
        sequence = 0
        while not stop.wait(0.01):
            sequence += 1
            publish(commands, "MAGLEV_COIL_CURRENTS_COMMANDED",
                    currents_message(sequence, 0.0, np.zeros(28), holder.session))

    thread = threading.Thread(target=keep_alive)
    try:
        start = time.monotonic()
        while not holder.granted:
            assert device.poll() is None, device.communicate()[1][-2000:]
            holder.on_tick(time.monotonic() - start)
            listener.handle_timeout(20)
            for reply in replies:
                holder.on_reply(reply, 0.0)
            replies.clear()
        thread.start()
        api = MaglevDevice(load_scenario("levitate", scenario_text=station))
        with pytest.raises(DeviceInUseError, match=re.escape(
                f"in use by another application (session {holder.session:#x}, process "
                f"{os.getpid()} on {socket.gethostname()})")):
            api.connect()
        with pytest.raises(RuntimeError, match="not connected"):
            api.takeoff()
        stop.set()
        thread.join()
        out, err = device.communicate(timeout=60)  # stops once the holder is silent
    finally:
        stop.set()
        device.kill()
    assert device.returncode == 0, err[-2000:]
    report = json.loads(out)
    # Only the holder's commands came: the refused connect sent none.
    assert report["commands"]["messages_received"] > 0
    assert report["commands"]["messages_refused"] == 0, report["commands"]["first_refused"]
    assert report["lease"]["grants"] == 1


def test_a_device_that_goes_silent_ends_the_call_and_every_later_one_but_disconnect():
    """Over LCM (an in-memory bus, on which a thread of this test answers as a device
    would: markers and currents every millisecond, the lease held, answered every
    0.1 s), the device stops. The run_for that is ticking raises DeviceSilentError once
    its lease answer is the lease's timeout late, saying when it went silent; every
    later call raises it again but disconnect, which releases the diagram."""
    scenario = dataclasses.replace(load_scenario("levitate"), station=LcmStation(
        url="memq://", command_url="memq://", channel_prefix="SILENT_"))
    device = MaglevDevice(scenario)
    answering = threading.Event()
    answering.set()
    markers = np.array([0.01, 0.0, 0.0067, -0.01, 0.0, 0.0067, 0.0, 0.01, 0.0067])

    def answer():  # as device-sim would, on the application's own in-memory bus
        k = 0
        while answering.is_set():
            time.sleep(1e-3)
            station = getattr(getattr(device, "_built", None), "station", None)
            if station is None:
                continue
            k += 1
            bus, t_s = station.receiver._lcm, 1e-3 * k
            publish(bus, "SILENT_MARKERS", markers_message(k, t_s, t_s, markers))
            publish(bus, "SILENT_COIL_CURRENTS", currents_message(k, t_s, np.r_[
                np.zeros(27), 1.0]))
            if k % 100 == 1:
                reply = lease_t()
                reply.sequence, reply.action = k // 100 + 1, lease_t.HELD
                reply.session, reply.instrument = station.lease.session, "two_magnet"
                publish(bus, "SILENT_LEASE", reply)

    device_thread = threading.Thread(target=answer, daemon=True)
    device_thread.start()
    try:
        device.connect()
        device.run_for(0.3)
    finally:
        answering.clear()
        device_thread.join()
    stopped_s = device.state.t_s
    with pytest.raises(DeviceSilentError, match=(
            r"^MaglevDevice: the device went silent at \d\.\d{3} s \(MARKERS, COIL_CURRENTS, "
            r"LEASE: no message for 0\.\d\d s, past the lease's 0\.5 s timeout\): the "
            r"application stopped at \d\.\d{3} s; it cannot land what it no longer commands$")):
        device.run_for(5.0)
    # Seen within a watch period of the lease's answer being a timeout late.
    assert stopped_s + 0.5 <= device.state.t_s <= stopped_s + 0.6 + WATCH_PERIOD_S + 0.01
    for call in (device.land, lambda: device.run_for(0.1),
                 lambda: device.set_feedforward_wrench(np.zeros(6))):
        with pytest.raises(DeviceSilentError, match="call disconnect"):
            call()
    device.disconnect()
    with pytest.raises(RuntimeError, match="not connected"):
        device.run_for(0.1)
