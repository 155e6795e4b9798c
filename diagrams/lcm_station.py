"""The station over LCM, the application's side; and the station configs a scenario picks.

``MakeLcmStation`` is the station a real device plugs into: an
``LcmStationInterface`` (a ``Station``, ``diagrams/station_interface.py``: it keeps
the wall clock, lands before a run ends, watches for a silent device, counts the
link for the summary and holds the lease) whose Diagram, named ``station``, has the
simulated station's port names and units (``diagrams/station.py``); its values come
from LCM messages and go out as LCM messages (``hardware/link/lcm_messages``).
``SimStation`` and ``LcmStation`` are the scenario's ``station`` variants.
``diagrams/device_sim.py`` is the
other end: the simulated station alone, speaking the same messages. Channels
(``channel_prefix`` + name):

- ``MARKERS`` (markers_t, device -> application, the tracker's rate);
- ``COIL_CURRENTS_COMMANDED`` (coil_currents_t, application -> device, the control
  rate, with the coils' power: the supervisor's enable line);
- ``COIL_CURRENTS`` (coil_currents_t, device -> application: what flows);
- ``DEVICE_STATUS`` (device_status_t, device -> application: grip, faults, coil
  temperatures);
- ``GLASSES`` (glasses_t, device -> application, with the stereo display: the
  head tracker's samples);
- ``LEASE_REQUEST`` (lease_t, application -> device: asks for the one-controller
  lease, and lets it go) and ``LEASE`` (lease_t, device -> application: who holds
  it; ``hardware/link/lease.py``).

Every inbound message is checked before it is used, at both ends
(``hardware/link/link_checks.py``): one that does not decode, has the wrong sizes, a
non-finite or out-of-range number, another session's command or an old sequence
is refused, counted per channel and reason, and never used.

The device's messages go on ``url``, the commands on ``command_url``: UDP
multicast with ttl=0 by default, so they never leave this host, one port a
direction, so no process receives what it sends.

The ``lcm`` package carries the messages, not Drake's LCM systems: with Python
message types LcmSubscriberSystem and LcmPublisherSystem cost ~1 ms a tick (the
device side ran 1,450 us a tick with them against 400 without), and
``DrakeLcm.HandleSubscriptions`` handles one message a call and drops those
queued behind it (5 published, 1 handled, however often it is called), which a
1 kHz loop cannot afford. One receiver reads every inbound channel in one
update a tick, and each sender encodes its own port (``systems/station_messages.py``).

A device that goes silent (its process killed, its host gone) stops the run: once
the lease's answers have not come for ``lease_timeout_s`` (``device_silence``), the
run stops at its next check, without the landing a run's end or a signal would
fly, since the coils no longer take its commands (``StopWhenDeviceSilent``).
"""


import math
from dataclasses import dataclass
from typing import Callable, Dict, Optional

import lcm
import numpy as np
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import Multiplexer

from maglev_haptics.diagrams.hand_script import MeshcatHand
from maglev_haptics.diagrams.station_interface import Station
from maglev_haptics.hardware.config_checks import positive, require
from maglev_haptics.hardware.constants import SAME_INSTANT_S
from maglev_haptics.hardware.device import DeviceConfig
from maglev_haptics.hardware.link.lcm_messages import (
    coil_currents_t, device_status_t, glasses_t, lease_t, markers_t)
from maglev_haptics.hardware.link.lease import REPLY_PERIOD_S, LeaseClient
from maglev_haptics.hardware.link.link_checks import (
    REASONS, LinkLimits, check_glasses, check_lease_reply, check_markers,
    check_measured_currents, check_status)
from maglev_haptics.systems.station_messages import (
    US_PER_S, MessageReceiver, MessageSender, ReceivedChannel, currents_message,
    glasses_measurement_from_message, markers_from_message)

DEFAULT_LCM_URL = "udpm://239.255.76.67:7667?ttl=0"
DEFAULT_COMMAND_URL = "udpm://239.255.76.67:7668?ttl=0"
MARKERS = "MARKERS"
COIL_CURRENTS_COMMANDED = "COIL_CURRENTS_COMMANDED"
COIL_CURRENTS = "COIL_CURRENTS"
DEVICE_STATUS = "DEVICE_STATUS"
GLASSES = "GLASSES"
LEASE = "LEASE"
LEASE_REQUEST = "LEASE_REQUEST"
GLASSES_MEASUREMENT_SIZE = 9  # [capture time, q_WG (wxyz), p_WG, ok]: systems/head_sensor.py
# The station's output port each inbound channel feeds.
INBOUND_PORTS = {MARKERS: "markers_measured", COIL_CURRENTS: "coil_currents",
                 DEVICE_STATUS: "handle_gripped", GLASSES: "glasses_measured",
                 LEASE: "lease"}  # the lease's answers feed no port


# What a simulated station's ``device`` may set against the scenario's: the plant, the
# coils and the tracker, where a device differs from the model of it.
DEVICE_TRUTH_FIELDS = ("instrument_mass_kg", "instrument_com_offset_m", "magnet_strength_scales",
                       "coil_force_scales", "tracker", "amplifier", "thermal")


@dataclass
class SimStation:
    """The simulated station, in the application's own diagram (the default).

    ``device``, when set, is the device as it is (DEVICE_TRUTH_FIELDS layered on the
    scenario's ``device`` when the scenario is loaded), while the application flies
    with the scenario's: how a calibration is tried without a device.
    """

    device: Optional[DeviceConfig] = None

    def validate(self, label: str, scenario) -> None:
        """The simulated device's own range checks."""
        if self.device is not None:
            self.device.validate(f"{label}: station.device")


@dataclass
class LcmStation:
    """Whatever station answers on LCM: ``maglev device-sim`` or a lab's drivers."""

    url: str = DEFAULT_LCM_URL  # the device's messages to the application
    command_url: str = DEFAULT_COMMAND_URL  # the application's commands to the device
    channel_prefix: str = "MAGLEV_"
    # A marker message older than the tracker's period plus its latency plus this
    # is a sensor out of range: the markers read as unseen (s). Measured currents
    # older than a control period plus this are not compared with their commands.
    stale_margin_s: float = 0.002
    # At start, how long to wait for the station's first marker message (s).
    wait_for_station_s: float = 10.0
    # The device's side: commands older than this turn every coil off (s), and
    # ``maglev device-sim`` stops once none has come for ``stop_after_silence_s``.
    command_timeout_s: float = 0.010
    stop_after_silence_s: float = 1.0
    # The device's lease lapses once its holder's commands have been silent this long
    # (s); the application gives up on a device whose lease answers have been silent
    # as long (``device_silence``).
    lease_timeout_s: float = 0.5

    def validate(self, label: str, scenario) -> None:
        """Range checks, and what ``scenario`` (labelled ``label``) may hold with a station
        on LCM; a ValueError names the field, its value and what is allowed."""
        path = f"{label}: station"
        require(scenario.stereo is None or scenario.haptics is not None, f"{label}: stereo",
                "set", "needs a haptic scene with station: !LcmStation (without one the "
                "display draws the simulated station's instrument, which a real station "
                "has not)")
        require(not isinstance(scenario.hand, MeshcatHand), f"{label}: hand", "!MeshcatHand",
                "must be a !ScriptedHand or null with station: !LcmStation (the simulated "
                "hand is the device's, and device-sim has no Meshcat)")
        for name in ("url", "command_url"):
            value = getattr(self, name)
            require(value.split("://")[0] == "udpm", f"{path}.{name}", value,
                    "must be an LCM UDP multicast URL, udpm://GROUP:PORT?ttl=0")
        require(self.channel_prefix.replace("_", "").isalnum() or self.channel_prefix == "",
                f"{path}.channel_prefix", self.channel_prefix,
                "must be letters, digits and underscores")
        positive(f"{path}.stale_margin_s", self.stale_margin_s)
        for name in ("wait_for_station_s", "command_timeout_s", "stop_after_silence_s",
                     "lease_timeout_s"):
            positive(f"{path}.{name}", getattr(self, name))


def open_lcm(url: str):
    """``lcm.LCM(url)``; an OSError naming the URL where LCM cannot open it."""
    try:
        return lcm.LCM(url)
    except RuntimeError as error:
        raise OSError(f"LCM URL {url!r}: {error}") from None


def channel(station, name: str) -> str:
    return station.channel_prefix + name


def chosen_station(choice: str, scenario):
    """The station config for ``maglev run --station CHOICE``: ``sim`` the simulated
    one; ``lcm`` the scenario's LcmStation, or the defaults where it has none."""
    return SimStation() if choice == "sim" else lcm_config(scenario)


def lcm_config(scenario) -> LcmStation:
    """The scenario's LCM settings: its LcmStation, or the defaults."""
    return scenario.station if isinstance(scenario.station, LcmStation) else LcmStation()


def marker_stale_after_s(scenario, station: LcmStation) -> float:
    """How old the newest marker message may be before the markers read as unseen (s)."""
    tracker = scenario.device.tracker
    return 1.0 / tracker.rate_hz + tracker.latency_s + station.stale_margin_s


def followed_command_s(scenario) -> Callable:
    """``dated(message)`` of the measured currents: when the application sent the
    command they follow (s, on its clock; ``MessageSender`` numbers tick k's command
    k + 1), from the command's sequence the device reports; -inf for none (its
    command timeout turned the coils off). Their age, the watchdog's, is then that of
    their command however late either end ran: over LCM a stalled application read
    the currents of the device's own zero, fresh, against its commands, and latched
    healthy coils as stuck."""
    period_s = 1.0 / scenario.control_rate_hz

    def dated(message) -> float:
        if message.command_sequence <= 0:
            return -math.inf
        return (message.command_sequence - 1) * period_s
    return dated


class DeviceCoilCuts:
    """The times the device said its currents followed no command (``command_sequence``
    0 after it had followed one: its command timeout had turned the coils off), read
    from every measured-currents message the application accepts (``on_currents``):
    how many, when the application first read one (s, its clock) and how long the
    longest lasted on the device's own clock (its messages' ``utime``, so a stall of
    the application that hid the cut's start does not shorten it)."""

    def __init__(self):
        self.times = 0
        self.first_at_s = None
        self.longest_s = 0.0
        self._followed = False  # the device has followed a command
        self._since_utime = None  # the cut under way: its first message's utime (us)
        self._newest_utime = None

    def on_currents(self, message, t_s: float) -> None:
        if message.command_sequence > 0:
            if self._since_utime is not None:
                self._end(message.utime)
            self._followed = True
        elif self._followed and self._since_utime is None:
            self.times += 1
            self.first_at_s = t_s if self.first_at_s is None else self.first_at_s
            self._since_utime = message.utime
        self._newest_utime = message.utime

    def _end(self, utime: int) -> None:
        self.longest_s = max(self.longest_s, (utime - self._since_utime) / US_PER_S)
        self._since_utime = None

    def summary(self, command_timeout_s: float) -> dict:
        """``station.device_cut_coils`` in summary.json (a cut under way counts to the
        device's newest message)."""
        longest_s = self.longest_s
        if self._since_utime is not None:
            longest_s = max(longest_s, (self._newest_utime - self._since_utime) / US_PER_S)
        return {"times": self.times, "first_at_s": self.first_at_s,
                "longest_ms": 1e3 * longest_s, "command_timeout_s": command_timeout_s}


def measured_currents_lag_ticks(scenario, station: LcmStation) -> int:
    """How many control ticks' commands a measured current read over LCM may follow:
    a command reaches the device within a control period and ``stale_margin_s``, and
    the current it drives comes back as long (measured: 2 ticks behind on one host)."""
    period_s = 1.0 / scenario.control_rate_hz
    return math.ceil(round(2.0 * (period_s + station.stale_margin_s) / period_s, 9))


def station_channels(scenario, lease: LeaseClient, coil_cuts: DeviceCoilCuts) -> list:
    """The application's inbound channels for ``scenario`` (its LcmStation's names),
    each with the link's checks (``hardware/link/link_checks.py``), the lease's answers
    going to ``lease``, the measured currents to ``coil_cuts``."""
    station = scenario.station
    device = scenario.device
    n_coils = device.n_coils
    n_markers = len(device.instrument_spec().p_IK_m)
    limits = LinkLimits.from_device(device)

    def inbound(name, message_type, size, decode, check, **options):
        return ReceivedChannel(port=INBOUND_PORTS[name], channel=channel(station, name),
                               message_type=message_type, size=size, decode=decode,
                               check=lambda message: check(message, limits), **options)

    channels = [
        inbound(LEASE, lease_t, 0, None, check_lease_reply, on_accept=lease.on_reply),
        inbound(MARKERS, markers_t, 3 * n_markers,
                lambda message, _: markers_from_message(message, n_markers), check_markers,
                stale_value=np.full(3 * n_markers, np.nan),
                stale_after_s=marker_stale_after_s(scenario, station),
                wait_s=station.wait_for_station_s, sample_time_port="markers_sample_time_s",
                sequence_port="markers_sample_count"),
        inbound(COIL_CURRENTS, coil_currents_t, n_coils,
                lambda message, _: np.array(message.current_a, dtype=float),
                check_measured_currents, initial_value=np.zeros(n_coils),
                age_port="coil_currents_age_s", dated=followed_command_s(scenario),
                on_accept=coil_cuts.on_currents)]
    if scenario.hand is not None:
        channels.append(inbound(DEVICE_STATUS, device_status_t, 1,
                                lambda message, _: np.array([float(message.handle_gripped)]),
                                check_status, initial_value=np.zeros(1)))
    elif scenario.calibration is not None:  # a calibration flight's coil temperatures
        channels.append(ReceivedChannel(
            port="coil_temperature_reported_c", channel=channel(station, DEVICE_STATUS),
            message_type=device_status_t, size=n_coils,
            decode=lambda message, _: np.array(message.coil_temperature_c, dtype=float),
            check=lambda message: check_status(message, limits),
            initial_value=np.full(n_coils, np.nan)))
    if scenario.stereo is not None:
        channels.append(inbound(GLASSES, glasses_t, GLASSES_MEASUREMENT_SIZE,
                                glasses_measurement_from_message, check_glasses,
                                initial_value=glasses_measurement_from_message(glasses_t(), 0.0)))
    return channels


def MakeLcmStation(scenario) -> "LcmStationInterface":
    """The application's station for ``scenario.station`` (an LcmStation): an
    ``LcmStationInterface`` whose Diagram, named ``station``, has inputs
    ``coil_currents_commanded`` and ``coil_power``; outputs ``markers_measured``,
    ``markers_sample_time_s`` (when they were read, s), ``markers_sample_count`` (the
    tracker's frame number the message carried), ``coil_currents``,
    ``coil_currents_age_s`` (how old the newest measured currents are, s), with a hand
    in the scenario ``handle_gripped``, with the stereo display ``glasses_measured``, on a
    calibration flight ``coil_temperature_reported_c`` (the device's status).
    Its ``receiver`` checks and counts the messages it read, refused and lost on each
    channel; building it waits up to ``wait_for_station_s`` for the station's markers.
    Its first tick asks for the device's lease (``lease``, a LeaseClient), and it sends
    no command until the lease is granted: an answer naming another holder raises
    DeviceInUseError, and no grant within ``wait_for_station_s`` a TimeoutError."""
    station = scenario.station
    n_coils = scenario.device.n_coils
    period_s = 1.0 / scenario.control_rate_hz
    builder = DiagramBuilder()
    command_lcm = open_lcm(station.command_url)
    lease = LeaseClient(lcm=command_lcm, channel=channel(station, LEASE_REQUEST),
                        wait_s=station.wait_for_station_s,
                        instrument=scenario.device.instrument)
    coil_cuts = DeviceCoilCuts()
    channels = station_channels(scenario, lease, coil_cuts)
    receiver = builder.AddNamedSystem("receiver", MessageReceiver(
        lcm=open_lcm(station.url), channels=channels, period_s=period_s,
        on_tick=lease.on_tick))
    for port in receiver.ports():
        builder.ExportOutput(receiver.GetOutputPort(port), port)
    sender = builder.AddNamedSystem("coil_currents_commanded_sender", MessageSender(
        lcm=command_lcm, channel=channel(station, COIL_CURRENTS_COMMANDED),
        size=n_coils + 1, period_s=period_s, ready=lambda: lease.granted,
        encode=lambda sequence, t, value: currents_message(sequence, t, value, lease.session)))
    command = builder.AddNamedSystem("command", Multiplexer([n_coils, 1]))
    builder.Connect(command.get_output_port(), sender.GetInputPort("value"))
    builder.ExportInput(command.get_input_port(0), "coil_currents_commanded")
    builder.ExportInput(command.get_input_port(1), "coil_power")
    diagram = builder.Build()
    diagram.set_name("station")
    return LcmStationInterface(diagram, scenario=scenario, receiver=receiver, lease=lease,
                               coil_cuts=coil_cuts)


def silent_channels(newest_arrivals: Dict[str, float], now_s: float,
                    timeout_s: float) -> Dict[str, float]:
    """{channel: how long it has been silent (s)} of the channels of ``newest_arrivals``
    (channel: when its newest message was read, s; -inf: none yet) with no message for
    ``timeout_s`` (s) or more at ``now_s`` (s, the same clock), in their order. A
    channel never heard from is not among them: it did not go silent."""
    return {name: now_s - arrival_s for name, arrival_s in newest_arrivals.items()
            if math.isfinite(arrival_s) and now_s - arrival_s >= timeout_s - SAME_INSTANT_S}


def device_silence(newest_arrivals: Dict[str, float], now_s: float, timeout_s: float,
                   heartbeat: str = LEASE.lower(),
                   heartbeat_period_s: float = REPLY_PERIOD_S) -> Optional[dict]:
    """Whether the device went silent by ``now_s`` (s): None while it is heard, else
    {"at_s": its last message (s), "channels": the channels silent for ``timeout_s``
    (``silent_channels``: names as in ``newest_arrivals``), "for_s": the silence since
    its last message (s), "timeout_s"}.

    The device is its ``heartbeat`` channel, the lease's answers, which the end that
    takes the coils' commands (device-sim, a lab's coil driver) sends every
    ``heartbeat_period_s`` whoever holds the lease: silent for ``timeout_s`` past the
    answer that was due, nothing takes the commands any more. The timeout is the
    lease's (``LcmStation.lease_timeout_s``, 0.5 s): the device gives up on a silent
    application after it (the lease lapses, the coils long off), so the application
    gives up on a silent device after the same. Not the link's shorter timeouts: a
    marker older than ``stale_after_s`` (3 ms) or a command older than
    ``command_timeout_s`` (10 ms) is what a host's pause of 10-50 ms makes, which the
    loop rides out (or lands blind) while the coils still take its commands; and a
    channel silent alone is that channel's loss (markers: the landing flown blind),
    not the device's. Since the heartbeat's last answer may precede the device's last
    message by a period, every channel that stopped with it is silent for
    ``timeout_s`` by then: all are named. The clock is the diagram's, the same as the
    device's lease, so a host that pauses the application does not make the device
    silent."""
    heard_s = newest_arrivals.get(heartbeat, -math.inf)
    if not (math.isfinite(heard_s)
            and now_s - heard_s >= timeout_s + heartbeat_period_s - SAME_INSTANT_S):
        return None
    silent = silent_channels(newest_arrivals, now_s, timeout_s)
    at_s = max(newest_arrivals[name] for name in silent)
    return {"at_s": at_s, "channels": list(silent), "for_s": now_s - at_s,
            "timeout_s": timeout_s}


def silence_sentence(silence: dict, label: str, stopped_s: float) -> str:
    """One line: ``label``'s device went silent (``device_silence``'s ``silence``),
    when, on which channels, for how long, and that the application stopped at
    ``stopped_s`` (s), unable to land what it no longer commands."""
    channels = ", ".join(name.upper() for name in silence["channels"])
    return (f"{label}: the device went silent at {silence['at_s']:.3f} s ({channels}: no "
            f"message for {silence['for_s']:.2f} s, past the lease's {silence['timeout_s']:g} "
            f"s timeout): the application stopped at {stopped_s:.3f} s; it cannot land what "
            "it no longer commands")


class LcmStationInterface(Station):
    """The station on LCM (``MakeLcmStation``): a device keeps the wall clock, lands
    what flies before a run ends, shares this machine's cores where it is
    ``maglev device-sim``, measures its currents a link's round trip late, holds a
    lease, and is watched for silence (``device_silence``)."""

    simulated = False
    keeps_wall_clock = True
    lands_before_run_end = True
    shares_cores = True

    def __init__(self, system, *, scenario, receiver: MessageReceiver, lease: LeaseClient,
                 coil_cuts: DeviceCoilCuts):
        super().__init__(system)
        self.config = scenario.station
        self.receiver = receiver
        self.lease = lease
        self.coil_cuts = coil_cuts
        self.measured_currents_lag_ticks = measured_currents_lag_ticks(scenario, self.config)

    def newest_arrivals(self, context) -> Dict[str, float]:
        """{channel (lower case, as ``summary`` names them): when its newest message was
        read (s; -inf: none yet)} at the root ``context``."""
        receiver_context = self.receiver.GetMyContextFromRoot(context)
        return {name.lower(): self.receiver.newest_arrival_s(receiver_context, port)
                for name, port in INBOUND_PORTS.items() if port in self.receiver.channels()}

    def watch(self, stop):
        """``stop``, or True once the device went silent (``device_silence`` after the
        station's ``lease_timeout_s``). Asked between ticks, every PROGRESS_CHUNK_S. A
        silent device stops the run at once, even mid-landing: a landing is the coils'
        work, and nothing takes their commands any more."""
        return lambda context: self.silence(context) is not None or stop(context)

    def silence(self, context) -> Optional[dict]:
        """``device_silence`` at the root ``context``'s time: None while the device is heard."""
        return device_silence(self.newest_arrivals(context), context.get_time(),
                              self.config.lease_timeout_s)

    def summary(self, context) -> dict:
        """``station`` in summary.json: the URL; what the application read, refused (by
        reason) and lost, and the gaps in which a channel went stale, per channel and in
        all, the silence since each channel's last message counted up to the context's
        time; its lease; ``device_cut_coils`` (``DeviceCoilCuts``); and
        ``device_silent``, ``device_silence`` at the context's time
        (None: the device was heard)."""
        receiver_context = self.receiver.GetMyContextFromRoot(context)
        counts = {name.lower(): self.receiver.counts(receiver_context, port)
                  for name, port in INBOUND_PORTS.items() if port in self.receiver.channels()}
        silent = self.silence(context)
        return {"kind": "lcm", "url": self.config.url,
                "messages_received": sum(c["messages_received"] for c in counts.values()),
                "messages_lost": sum(c["messages_lost"] for c in counts.values()),
                "messages_refused": sum(c["messages_refused"] for c in counts.values()),
                "refused": {reason: sum(c["refused"][reason] for c in counts.values())
                            for reason in REASONS},
                "stale_gaps": sum(c["stale_gaps"] for c in counts.values()),
                "lease": self.lease.counts(),
                "device_cut_coils": self.coil_cuts.summary(self.config.command_timeout_s),
                "device_silent": silent,
                "channels": counts}
