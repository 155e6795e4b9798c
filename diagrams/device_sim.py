"""``maglev device-sim``: the simulated station alone, its ports on LCM.

The device's end of ``diagrams/lcm_station.py``: the same instrument, coils,
amplifiers, tracker and (scripted) hand as the all-in-one run, publishing the
markers, the currents that flow (with the sequence of the command they follow, 0
once the command timeout turned the coils off) and the device's status, and taking
its coil currents from the application's commands. The hand's script waits for the
application's first command and then runs on the application's clock. Run paced
to the wall clock, as the real device is.

Every command is checked before it reaches the coils (``hardware/link/link_checks.py``):
one that does not decode, commands another coil count, holds a non-finite current
or one past the amplifiers' limit, comes from a session that does not hold the
lease (``hardware/link/lease.py``) or repeats an old sequence is refused, counted and
never used; like a lost command, the last good one holds until
``command_timeout_s`` turns the coils off.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Optional

import numpy as np
from pydrake.systems.framework import Diagram, DiagramBuilder
from pydrake.systems.primitives import (
    ConstantVectorSource, Demultiplexer, Multiplexer, ZeroOrderHold)

from maglev_haptics.diagrams.haptics import AddHandCommands
from maglev_haptics.diagrams.lcm_station import (
    COIL_CURRENTS, COIL_CURRENTS_COMMANDED, DEVICE_STATUS, GLASSES, LEASE, LEASE_REQUEST,
    MARKERS, SimStation, channel, lcm_config, open_lcm)
from maglev_haptics.diagrams.station import AddStation
from maglev_haptics.hardware.link.lcm_link import publish
from maglev_haptics.hardware.link.lcm_messages import coil_currents_t, device_status_t, lease_t
from maglev_haptics.hardware.link.lease import LeaseServer
from maglev_haptics.hardware.link.link_checks import LinkLimits, check_command, check_lease_request
from maglev_haptics.hardware.magnetics import load_magnetics
from maglev_haptics.hardware.thermal import coil_thermal
from maglev_haptics.systems.coil_thermal import CoilTemperatures
from maglev_haptics.systems.marker_sensor import newest_sample_before
from maglev_haptics.systems.station_messages import (
    US_PER_S, MessageReceiver, MessageSender, ReceivedChannel, command_from_message,
    currents_message, glasses_measurement_message, markers_message, status_message)

# The grip sensor, the coils' temperatures (time constant ~1 min) and the 10 Hz head
# tracker need no more than 100 Hz.
STATUS_PERIOD_S = 0.01
# The receiver's: [currents (A); power; the command's sequence], the first two the
# station's inputs.
COMMANDS_PORT = "commands"
LEASE_REQUESTS = "lease_requests"  # the receiver's channel of lease requests (no port)


@dataclass
class DeviceSim:
    diagram: Diagram
    tick_s: float  # the station's control period (s)
    command_receiver: MessageReceiver  # counts the application's commands
    stop_after_silence_s: float
    lease: LeaseServer  # who may command the coils
    frame_publishers: list = field(default_factory=list)  # none: device-sim draws nothing
    meshcat: Optional[object] = None  # nor has a Meshcat (the runner asks)

    def application_gone(self, context) -> bool:
        """Whether commands came and then stopped for ``stop_after_silence_s``."""
        last_s = self.last_command_s(context)  # -inf before the first: not gone yet
        return math.isfinite(last_s) and context.get_time() - last_s > self.stop_after_silence_s

    def last_command_s(self, context) -> float:
        """When the application's newest command was read (s; -inf: none yet)."""
        return self.command_receiver.newest_arrival_s(
            self.command_receiver.GetMyContextFromRoot(context), COMMANDS_PORT)

    def command_counts(self, context, until_now: bool = True) -> dict:
        """What the device read, refused (by reason) and lost of the application's
        commands (``MessageReceiver.counts``); ``until_now``: the silence since the
        newest command counts as a gap (left out where it is the silence device-sim
        stopped on: an application that ended)."""
        return self.command_receiver.counts(
            self.command_receiver.GetMyContextFromRoot(context), COMMANDS_PORT, until_now)

    def lease_counts(self, context) -> dict:
        """The lease requests read and refused, the holder now and the grants made."""
        counts = self.command_receiver.counts(
            self.command_receiver.GetMyContextFromRoot(context), LEASE_REQUESTS)
        return {"requests_received": counts["messages_received"],
                **{k: counts[k] for k in ("messages_refused", "refused", "first_refused")},
                **self.lease.counts()}


def MakeCommandReceiver(*, lcm, station, limits: LinkLimits, lease: LeaseServer,
                        period_s: float, log=None, on_command=None) -> MessageReceiver:
    """The device's receiver of the application's lease requests and commands on ``lcm``
    (``station``: the LcmStation's channels and timeouts): output ``commands``
    [currents (A); power; its sequence], the lease holder's newest good command, zeros
    (sequence 0: none) once it is older than ``command_timeout_s``.
    ``on_command(message, now_s)``, if given, hears of every command accepted."""
    n_coils = limits.n_coils

    def accepted(command, now_s: float) -> None:
        lease.keep_alive(now_s)  # the holder's command: its lease runs on
        if on_command is not None:
            on_command(command, now_s)

    return MessageReceiver(
        lcm=lcm, on_tick=lease.on_tick, period_s=period_s,
        **({} if log is None else {"log": log}), channels=[
            ReceivedChannel(
                port=LEASE_REQUESTS, channel=channel(station, LEASE_REQUEST),
                message_type=lease_t, size=0, decode=None, check=check_lease_request,
                session_of=lambda message: message.session, admit=lease.admit_request,
                on_accept=lease.request),
            ReceivedChannel(
                port=COMMANDS_PORT, channel=channel(station, COIL_CURRENTS_COMMANDED),
                message_type=coil_currents_t, size=n_coils + 2,
                decode=lambda message, _: command_from_message(message),
                stale_value=np.zeros(n_coils + 2), stale_after_s=station.command_timeout_s,
                check=lambda message: check_command(message, limits),
                session_of=lambda message: message.session, admit=lease.admit,
                on_accept=accepted)])


def BuildDeviceSim(scenario) -> DeviceSim:
    """The simulated station of ``scenario`` alone, its ports on LCM (the module
    docstring's channels), with the simulated hand's script when it has one.
    Commands older than ``command_timeout_s`` turn every coil off and cut the power;
    only the lease holder's commands that pass the link's checks are used."""
    station_config = lcm_config(scenario)
    device = scenario.device
    n_coils = device.n_coils
    limits = LinkLimits.from_device(device)
    period_s = 1.0 / scenario.control_rate_hz
    n_markers = len(device.instrument_spec().p_IK_m)
    builder = DiagramBuilder()
    station = AddStation(builder, scenario=scenario, magnetics=load_magnetics(device),
                         config=SimStation())
    publisher = open_lcm(station_config.url)
    hand_script = None
    if scenario.hand is not None:
        hand_script = AddHandCommands(builder, scenario=scenario, station=station, meshcat=None,
                                      wait_for_start=True)

    def on_command(command, now_s: float) -> None:
        # A command carries the application's clock when it was sent (us): the hand's
        # script runs on the application's clock, within the link's latency.
        if hand_script is not None:
            hand_script.start(now_s - command.utime / US_PER_S)

    lease = LeaseServer(timeout_s=station_config.lease_timeout_s, publish_reply=lambda message:
                        publish(publisher, channel(station_config, LEASE), message),
                        instrument=device.instrument)
    commands = builder.AddNamedSystem("commands_receiver", MakeCommandReceiver(
        lcm=open_lcm(station_config.command_url), station=station_config, limits=limits,
        lease=lease, period_s=period_s, on_command=on_command))
    command = builder.AddNamedSystem("command", Demultiplexer([n_coils, 1, 1]))
    builder.Connect(commands.GetOutputPort(COMMANDS_PORT), command.get_input_port())
    builder.Connect(command.get_output_port(0), station.GetInputPort("coil_currents_commanded"))
    builder.Connect(command.get_output_port(1), station.GetInputPort("coil_power"))

    def send(name, value_port, encode, send_period_s):
        sender = builder.AddNamedSystem(f"{name.lower()}_sender", MessageSender(
            lcm=publisher, channel=channel(station_config, name), size=value_port.size(),
            encode=encode, period_s=send_period_s))
        builder.Connect(value_port, sender.GetInputPort("value"))

    # Each tracker sample leaves at the first tick after it was published (within a
    # tick), numbered by the tracker's count so a receiver counts a gap as a loss.
    sample = builder.AddNamedSystem("marker_sample", Multiplexer([3 * n_markers, 1]))
    builder.Connect(station.GetOutputPort("markers_measured"), sample.get_input_port(0))
    builder.Connect(station.GetOutputPort("markers_sample_time_s"), sample.get_input_port(1))

    rate_hz = device.tracker.rate_hz

    def marker_message(_, t, value):
        if value[-1] == -np.inf:
            return None  # none published yet
        number = round(value[-1] * rate_hz)
        if number <= newest_sample_before(t - period_s, rate_hz):
            return None  # sent at an earlier tick
        return markers_message(number + 1, value[-1] - device.tracker.latency_s, t, value[:-1])

    send(MARKERS, sample.get_output_port(), marker_message, period_s)
    # The measured currents say which command they follow: the amplifiers' sampled lag
    # takes a tick's command at the next update, and so does this hold its sequence.
    followed = builder.AddNamedSystem("followed_command", ZeroOrderHold(period_s, 1))
    builder.Connect(command.get_output_port(2), followed.get_input_port())
    measured = builder.AddNamedSystem("measured", Multiplexer([n_coils, 1, 1]))
    builder.Connect(station.GetOutputPort("coil_currents"), measured.get_input_port(0))
    builder.Connect(command.get_output_port(1), measured.get_input_port(1))
    builder.Connect(followed.get_output_port(), measured.get_input_port(2))
    send(COIL_CURRENTS, measured.get_output_port(),
         lambda sequence, t, value: currents_message(sequence, t, value[:-1],
                                                     command_sequence=round(value[-1])),
         period_s)
    thermal = coil_thermal(device)
    temperatures = builder.AddNamedSystem("coil_temperatures", CoilTemperatures(
        model=thermal, n_coils=n_coils, period_s=STATUS_PERIOD_S))
    builder.Connect(station.GetOutputPort("coil_currents"), temperatures.get_input_port())
    status = builder.AddNamedSystem("status", Multiplexer([1, n_coils]))
    if scenario.hand is not None:
        builder.Connect(station.GetOutputPort("handle_gripped"), status.get_input_port(0))
    else:
        no_grip = builder.AddNamedSystem("no_grip_sensor", ConstantVectorSource([0.0]))
        builder.Connect(no_grip.get_output_port(), status.get_input_port(0))
    builder.Connect(temperatures.get_output_port(), status.get_input_port(1))
    send(DEVICE_STATUS, status.get_output_port(),
         lambda sequence, t, value: status_message(
             sequence, t, value[0] > 0.5,
             device_status_t.FAULT_COIL_OVER_TEMPERATURE if np.any(value[1:] > thermal.max_c)
             else 0, value[1:]),
         STATUS_PERIOD_S)
    if scenario.stereo is not None:
        # The head tracker's latency ends between its 10 Hz samples: sent at 100 Hz,
        # each sample leaves within 10 ms of its release.
        send(GLASSES, station.GetOutputPort("glasses_measured"), glasses_measurement_message,
             STATUS_PERIOD_S)
    diagram = builder.Build()
    diagram.set_name("device_sim")
    return DeviceSim(diagram=diagram, tick_s=period_s, command_receiver=commands,
                     stop_after_silence_s=station_config.stop_after_silence_s, lease=lease)
