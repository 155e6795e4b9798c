"""The station's ports as LCM messages (``hardware/link/lcm_messages``), both ways.

The device side (``maglev device-sim`` or a lab's drivers) turns its port values
into messages; the application side turns messages back into the same port
values, so the application cannot tell a simulated station from a real one.
Times on the wire are integer microseconds on the sender's clock.

Each receiver takes every message through its channel's ``InboundGate``
(``hardware/link/link_checks.py``: it decodes, its sizes match the scenario, its numbers
are finite and in range, its session holds the lease, its sequence is newer than
the last accepted) and never uses one it refuses; it counts them by reason. Of
what it accepted it counts ``received``, ``lost`` the
gaps in their ``sequence`` numbers (messages that never arrived), and the latency
the link added: from a message's ``sent_wall_utime`` to the tick that read it, on
the wall clock (meaningful where sender and receiver share it: one host, or
clocks kept in step by PTP), its mean, largest and percentiles (from a histogram).
What a receiver reads as the run starts (at its initialization and its first tick)
queued while the diagram was built and the run set up (up to a second with
Meshcat, measured): it is received and counted, but its latency, the start's and
not the link's, is left out of the latency figures. A receiver whose
newest message is older than ``stale_after_s`` reports it the way the hardware
would report a missing signal: markers all NaN (so the estimator loses
tracking and the controller lands blind), currents and grip held. The
silence after a sender's last message counts as a gap, as if a message read when
the counts are asked ended it: a sender that died shows in the longest gap.
"""

from __future__ import annotations

import math
import struct
import time
from dataclasses import dataclass
from typing import Callable, Optional, Sequence

import numpy as np
from pydrake.systems.framework import LeafSystem

from maglev_haptics.hardware.link.lcm_link import publish
from maglev_haptics.hardware.link.link_checks import InboundGate, log_to_stderr
from maglev_haptics.hardware.link.lcm_messages import (
    coil_currents_t, device_status_t, glasses_t, markers_t)

US_PER_S = 1_000_000
MESSAGE_QUEUE_CAPACITY = 1000  # messages a subscription holds between two reads
# Receiver state: [newest sequence read, its arrival time (s), received, lost,
# sum and largest of the latencies (s, wall clock), longest wait between two
# messages (s, diagram clock), waits long enough that a tick read the stale value,
# received as the run started (their latencies left out)]
_NEVER = np.array([-1.0, -math.inf, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
# The latencies' histogram: bins log-spaced from LATENCY_LOW_S to 10 s, each 12% wide
# (a percentile read from it is at most that much over), one below and one above.
LATENCY_LOW_S = 1e-5
LATENCY_BINS_PER_DECADE = 20
LATENCY_BINS = 6 * LATENCY_BINS_PER_DECADE + 2


def to_utime(t_s: float) -> int:
    """Seconds as LCM's integer microseconds."""
    return int(round(t_s * US_PER_S))


def markers_message(sequence: int, capture_s: float, publish_s: float,
                    markers_W: np.ndarray) -> markers_t:
    """A tracker sample: ``markers_W`` (3 n,) p_WK [m], NaN where not seen."""
    # Plain lists, not numpy: 860 of these a second, each numpy call ~5 us here.
    coordinates = markers_W.tolist()
    positions = [coordinates[i:i + 3] for i in range(0, len(coordinates), 3)]
    visible = [all(math.isfinite(c) for c in p) for p in positions]
    message = markers_t()
    message.sequence = int(sequence)
    message.capture_utime = to_utime(capture_s)
    message.publish_utime = to_utime(publish_s)
    message.num_markers = len(positions)
    message.position_m = [p if seen else [0.0, 0.0, 0.0] for p, seen in zip(positions, visible)]
    message.visible = visible
    return message


_UNSEEN = (math.nan, math.nan, math.nan)


def markers_from_message(message: markers_t, n_markers: int) -> np.ndarray:
    """(3 n,) p_WK [m] from a tracker sample, NaN where not seen; all NaN for a
    message of another instrument (a marker count that does not match)."""
    if message.num_markers != n_markers:
        return np.full(3 * n_markers, np.nan)
    # Plain lists, then one array: 860 of these a second (4 us against 13 with masks).
    coordinates = []
    for position, seen in zip(message.position_m, message.visible):
        coordinates.extend(position if seen else _UNSEEN)
    return np.array(coordinates)


def glasses_measurement_message(sequence: int, t_s: float,
                                measurement: np.ndarray) -> glasses_t:
    """The head sensor's ``glasses_measured`` (9: [capture time (s), q_WG (wxyz),
    p_WG (m), ok]) as a ``glasses_t`` published at ``t_s``."""
    message = glasses_t()
    message.sequence = int(sequence)
    seen = measurement[8] > 0.5 and math.isfinite(measurement[0])
    message.capture_utime = to_utime(measurement[0] if seen else t_s)
    message.publish_utime = to_utime(t_s)
    message.quaternion_wxyz = measurement[1:5].tolist() if seen else [1.0, 0.0, 0.0, 0.0]
    message.position_m = measurement[5:8].tolist() if seen else [0.0, 0.0, 0.0]
    message.ok = bool(seen)
    return message


def glasses_measurement_from_message(message: glasses_t, arrival_s: float) -> np.ndarray:
    """``glasses_measured`` (9) from a ``glasses_t`` that arrived at ``arrival_s`` (s,
    the receiver's clock): its capture time is the arrival less the age the sender
    stamped on it (publish - capture), since the two clocks differ."""
    if not message.ok:
        return np.array([-math.inf] + [math.nan] * 7 + [0.0])
    age_s = (message.publish_utime - message.capture_utime) / US_PER_S
    return np.array([arrival_s - age_s, *message.quaternion_wxyz, *message.position_m, 1.0])


def currents_message(sequence: int, t_s: float, currents_and_power: np.ndarray,
                     session: int = 0, command_sequence: int = 0) -> coil_currents_t:
    """``currents_and_power``: the coils' currents (A) then the supply (1 on, 0 off);
    ``session``: the commanding application's lease session (0: measured currents);
    ``command_sequence``: measured, the sequence of the newest command the amplifiers
    were given (0: none)."""
    message = coil_currents_t()
    message.sequence = int(sequence)
    message.session = int(session)
    message.command_sequence = int(command_sequence)
    message.utime = to_utime(t_s)
    message.num_coils = len(currents_and_power) - 1
    message.current_a = currents_and_power[:-1].tolist()
    message.power_enabled = bool(currents_and_power[-1] > 0.5)
    return message


def command_from_message(message: coil_currents_t) -> np.ndarray:
    """A command's [currents (A); supply (1 on, 0 off); its sequence], the first two
    ``currents_message``'s value."""
    return np.array([*message.current_a, float(message.power_enabled), float(message.sequence)])


def status_message(sequence: int, t_s: float, handle_gripped: bool, fault_bits: int,
                   coil_temperature_c: np.ndarray) -> device_status_t:
    message = device_status_t()
    message.sequence = int(sequence)
    message.utime = to_utime(t_s)
    message.fault_bits = int(fault_bits)
    message.handle_gripped = bool(handle_gripped)
    message.num_coils = len(coil_temperature_c)
    message.coil_temperature_c = coil_temperature_c.tolist()
    return message


def receiver_step(state, sequence: int, t_s: float, latency_s: float = 0.0,
                  stale_gap_s: float = math.inf, at_start: bool = False) -> list:
    """The receiver's counters after reading a message numbered ``sequence`` at ``t_s``
    (s, the receiver's diagram clock), ``latency_s`` (s) after it was sent.

    ``state`` is [newest sequence, its arrival (s), received, lost, latency sum (s),
    largest latency (s), longest gap (s), stale gaps, received at start]; a gap
    between two messages longer than ``stale_gap_s`` (s) is a stale gap. A message
    read ``at_start`` (queued before the run's first tick) counts as received, its
    latency left out. A sequence it has already read changes nothing; a lower one is
    the sender starting again, which loses nothing."""
    (newest, arrival, received, lost, latency_sum, latency_max, gap_max, stale_gaps,
     at_start_count) = state
    if received > 0 and sequence == newest:
        return list(state)
    if received > 0:
        if sequence > newest:
            lost += sequence - newest - 1
        gap_max = max(gap_max, t_s - arrival)
        stale_gaps += t_s - arrival > stale_gap_s
    if at_start:
        at_start_count += 1
    else:
        latency_sum += latency_s
        latency_max = max(latency_max, latency_s)
    return [sequence, t_s, received + 1, lost, latency_sum, latency_max, gap_max, stale_gaps,
            at_start_count]


def latency_bin(latency_s: float) -> int:
    """The histogram bin (0 to LATENCY_BINS - 1) of a latency (s): 0 up to
    LATENCY_LOW_S (a receiver's clock behind the sender's included), the last past 10 s."""
    if not latency_s > LATENCY_LOW_S:
        return 0
    return min(LATENCY_BINS - 1, math.ceil(
        LATENCY_BINS_PER_DECADE * math.log10(latency_s / LATENCY_LOW_S)))


def latency_percentile_s(histogram, percent: int, largest_s: float) -> Optional[float]:
    """The latency (s) that ``percent`` % of the counted messages did not exceed (nearest
    rank): the upper edge of its bin in ``histogram`` (``latency_bin``'s), never above
    ``largest_s``, the largest counted; None before the first."""
    counts = [int(count) for count in histogram]
    total = sum(counts)
    if total == 0:
        return None
    rank = max(1, -(-percent * total // 100))  # integers: 99 % of 100 is the 99th
    seen = 0
    for k, count in enumerate(counts):
        seen += count
        if seen >= rank:
            upper_s = (math.inf if k == LATENCY_BINS - 1
                       else LATENCY_LOW_S * 10.0 ** (k / LATENCY_BINS_PER_DECADE))
            return min(upper_s, largest_s)


def trailing_silence(state, now_s: float, stale_gap_s: float = math.inf) -> tuple:
    """(longest gap (s), stale gaps) of a receiver's ``state`` (``receiver_step``'s) with
    the silence since its newest message counted as a gap that ends at ``now_s`` (s,
    the receiver's clock), as a message read then would end it: the longest gap is at
    least that silence, and one longer than ``stale_gap_s`` is one more stale gap.
    Before the first message nothing is silent: the counts are the state's."""
    gap_max, stale_gaps = float(state[6]), int(state[7])
    if now_s is None or state[2] <= 0:
        return gap_max, stale_gaps
    silence_s = now_s - state[1]
    return max(gap_max, silence_s), stale_gaps + int(silence_s > stale_gap_s)


def receiver_counts(state, latency_histogram, now_s: Optional[float] = None,
                    stale_gap_s: float = math.inf) -> dict:
    """{"messages_received", "messages_lost", "messages_at_start", "latency_ms_mean",
    "latency_ms_p50", "latency_ms_p99", "latency_ms_max", "longest_gap_ms",
    "stale_gaps"} from a receiver's state and its latencies' histogram
    (``latency_bin``). The latencies leave out the messages received at the start
    (``messages_at_start``); None before the first counted. With ``now_s`` (s, the
    receiver's clock) the silence since the newest message counts as a gap ending
    then (``trailing_silence``): a sender that stopped leaves its silence in the
    longest gap, and in the stale gaps once it is longer than ``stale_gap_s``;
    without, gaps count once a message ends them."""
    received, at_start = int(state[2]), int(state[8])
    counted = received - at_start
    largest_s = state[5]
    gap_max_s, stale_gaps = trailing_silence(state, now_s, stale_gap_s)
    return {"messages_received": received, "messages_lost": int(state[3]),
            "messages_at_start": at_start,
            "latency_ms_mean": 1e3 * state[4] / counted if counted else None,
            **{f"latency_ms_p{percent}":
               1e3 * latency_percentile_s(latency_histogram, percent, largest_s)
               if counted else None for percent in (50, 99)},
            "latency_ms_max": 1e3 * largest_s if counted else None,
            "longest_gap_ms": 1e3 * gap_max_s, "stale_gaps": stale_gaps}


def message_sequence(data: bytes) -> tuple:
    """(``sequence``, ``sent_wall_utime``) of an encoded station message: every type
    here has them first, right after LCM's 8-byte fingerprint (big-endian int64s)."""
    return struct.unpack_from(">qq", data, 8)


@dataclass(frozen=True)
class ReceivedChannel:
    """One LCM channel a ``MessageReceiver`` reads, and the vector port it feeds.

    ``port``: the output port's name (size 0: no port, the channel only feeds
    ``on_accept``); ``decode(message, arrival_s) -> (size,)``;
    ``stale_value`` (or None: hold the newest) is output before the first message
    and once the newest is older than ``stale_after_s`` (s, on the diagram's clock,
    which a paced run keeps on the wall clock); ``initial_value`` (default the
    stale value) is held before the first message; with ``wait_s`` > 0,
    initialization waits that long (wall-clock seconds) for a first message and
    raises a TimeoutError naming the channel if none comes. ``age_port``: an output
    port of that name (1) gives the newest accepted message's age (s, on the
    diagram's clock: 0 in the tick that read it; infinite before the first), for a
    reader that must not take a stale value for a fresh one; with ``dated``, the age
    of what the message reports instead, ``dated(message)`` saying when that was (s,
    on the diagram's clock; -inf: nothing of this run). ``sample_time_port``: an
    output port of that name (1) gives when the value on ``port`` was read (s, on the
    diagram's clock): the newest accepted message's arrival, or while the value is
    stale the tick before now, so a reader that takes each reading once (the pose
    estimator) takes a new stale one every tick. ``sequence_port``: an output port of
    that name (1) gives the newest accepted message's sequence number (0 before the
    first): a tracker's frame number, whose gaps are frames missed.

    The gate (``hardware/link/link_checks.py``): ``check(message)`` raises Refused for a
    message outside what the scenario allows; ``session_of(message)`` keys the
    sequence gate by session (default: one sender); ``admit(message, t_s)`` raises
    Refused("other_session") for a message the lease does not admit;
    ``on_accept(message, t_s)`` sees every message accepted, in order."""
    port: str
    channel: str
    message_type: type
    size: int
    decode: Callable
    stale_value: Optional[np.ndarray] = None
    stale_after_s: float = math.inf
    initial_value: Optional[np.ndarray] = None
    wait_s: float = 0.0
    check: Callable = lambda message: None
    session_of: Optional[Callable] = None
    admit: Optional[Callable] = None
    on_accept: Optional[Callable] = None
    age_port: Optional[str] = None
    dated: Optional[Callable] = None
    sample_time_port: Optional[str] = None
    sequence_port: Optional[str] = None


class MessageReceiver(LeafSystem):
    """The newest message of each of several LCM channels as station vector ports.

    .. pydrake_system::

        name: MessageReceiver
        output_ports:
        - (one per channel, named by its port)

    Every ``period_s`` (s) one update reads everything that arrived on ``lcm`` (an
    ``lcm.LCM``), takes each message through its channel's gate, counts it and
    keeps each channel's newest accepted message: one Python call a tick for every
    channel, since each call is what a 1 kHz tick pays for. A gap between two
    messages in which a tick read the channel's stale value counts as a stale gap,
    and so does the silence since the newest message, when ``counts`` is asked
    (between ticks: nothing is added to a tick). ``on_tick(t_s)``, if given, is called at the end of every update
    (the lease's ends ask and answer there). What a gate refused is counted in the
    gate (I/O, as the messages are), the rest in the discrete state.
    """

    def __init__(self, *, lcm, channels: Sequence[ReceivedChannel], period_s: float,
                 on_tick: Optional[Callable[[float], None]] = None,
                 log: Callable[[str], None] = log_to_stderr):
        super().__init__()
        self._lcm = lcm
        self._on_tick = on_tick
        self._channels = {spec.port: spec for spec in channels}
        self._gates = {spec.port: InboundGate(
            spec.channel, spec.message_type, spec.check, session_of=spec.session_of,
            admit=spec.admit, log=log) for spec in channels}
        # A tick reads a channel stale once its newest message is older than
        # stale_after_s: the gap to the next message is then longer than this (s).
        self._stale_gap_s = {spec.port: (spec.stale_after_s + period_s if spec.stale_value
                                         is not None else math.inf) for spec in channels}
        self._period_s = float(period_s)
        # Raw messages that LCM handed over since the last update, (port, data) in the
        # order they came: I/O, not state. Read in that order, a command sent after
        # its session's lease request finds the lease granted, and one sent before its
        # session's release is still the holder's.
        self._arrived = []
        self._counters, self._latencies, self._held, self._dated = {}, {}, {}, {}
        for spec in channels:
            subscription = lcm.subscribe(spec.channel,
                                         lambda _, data, port=spec.port:
                                         self._arrived.append((port, data)))
            # LCM drops what queues past a subscription's capacity (30 by default): a
            # tick late by tens of ms must still read every message.
            subscription.set_queue_capacity(MESSAGE_QUEUE_CAPACITY)
            self._counters[spec.port] = self.DeclareDiscreteState(_NEVER)
            self._latencies[spec.port] = self.DeclareDiscreteState(np.zeros(LATENCY_BINS))
            if spec.dated is not None:
                self._dated[spec.port] = self.DeclareDiscreteState([-math.inf])
            if spec.age_port is not None:
                self.DeclareVectorOutputPort(
                    spec.age_port, 1,
                    lambda context, output, spec=spec: output.SetAtIndex(
                        0, context.get_time() - self._dated_s(spec, context)),
                    {self.xd_ticket(), self.time_ticket()})
            if spec.sample_time_port is not None:
                self.DeclareVectorOutputPort(
                    spec.sample_time_port, 1,
                    lambda context, output, spec=spec: output.SetAtIndex(
                        0, self._sample_time_s(spec, context)),
                    {self.xd_ticket(), self.time_ticket()})
            if spec.sequence_port is not None:
                self.DeclareVectorOutputPort(
                    spec.sequence_port, 1,
                    lambda context, output, spec=spec: output.SetAtIndex(
                        0, max(0.0, self._newest_sequence(spec, context))),
                    {self.xd_ticket()})
            if spec.size == 0:
                continue
            initial = spec.stale_value if spec.initial_value is None else spec.initial_value
            self._held[spec.port] = self.DeclareDiscreteState(np.asarray(initial, float))
            self.DeclareVectorOutputPort(
                spec.port, spec.size,
                lambda context, output, spec=spec: self._calc_value(spec, context, output),
                {self.xd_ticket(), self.time_ticket()})
        # The run's start (s, diagram clock; -inf until initialized): what is read then
        # queued before the run's first tick.
        self._started_at = self.DeclareDiscreteState([-math.inf])
        self.DeclarePeriodicDiscreteUpdateEvent(period_s, 0.0, self._update)
        self.DeclareInitializationDiscreteUpdateEvent(self._initialize)

    def _initialize(self, context, discrete_state):
        for spec in self._channels.values():
            deadline = time.monotonic() + spec.wait_s
            while spec.wait_s > 0 and not any(port == spec.port for port, _ in self._arrived):
                if time.monotonic() > deadline:
                    raise TimeoutError(
                        f"no message on LCM channel {spec.channel!r} within {spec.wait_s:g} "
                        "s: is the station running (maglev device-sim SCENARIO, or the "
                        "device's drivers) on the same LCM URL?")
                self._lcm.handle_timeout(100)
        # What queued while the diagram was built is history, some of it dropped
        # past the queue's capacity: the run counts from the newest message on.
        while self._lcm.handle_timeout(0) > 0:
            pass
        newest = {port: k for k, (port, _) in enumerate(self._arrived)}
        self._arrived[:] = [self._arrived[k] for k in sorted(newest.values())]
        discrete_state.set_value(self._started_at, [context.get_time()])
        self._read(context, discrete_state, at_start=True)

    def _update(self, context, discrete_state):
        # The first tick, at the start's time, reads what queued while the run was set up.
        self._read(context, discrete_state, at_start=context.get_time()
                   <= context.get_discrete_state(self._started_at).GetAtIndex(0))

    def _read(self, context, discrete_state, at_start: bool):
        while self._lcm.handle_timeout(0) > 0:  # one message a call: drain them all
            pass
        t_s = context.get_time()
        now_utime = time.time_ns() // 1000
        # Each port's counters, newest accepted message and latency bins this update.
        accepted = {}
        for port, data in self._arrived:
            spec = self._channels[port]
            message = self._gates[port].accept(data, t_s)
            if message is None:
                continue
            read = accepted.get(port)
            if read is None:
                read = accepted[port] = [context.get_discrete_state(
                    self._counters[port]).get_value().tolist(), None, []]
            counters = read[0]
            received = counters[2]
            latency_s = (now_utime - message.sent_wall_utime) / US_PER_S
            read[0] = counters = receiver_step(counters, message.sequence, t_s, latency_s,
                                               self._stale_gap_s[port], at_start)
            if counters[2] > received and not at_start:  # counted, and after the start
                read[2].append(latency_bin(latency_s))
            if spec.on_accept is not None:
                spec.on_accept(message, t_s)
            read[1] = message
        self._arrived.clear()
        # A port whose every message was refused is not in ``accepted``: what was held holds.
        for port, (counters, newest, latency_bins) in accepted.items():
            spec = self._channels[port]
            discrete_state.set_value(self._counters[port], counters)
            histogram = discrete_state.get_mutable_vector(self._latencies[port])
            for k in latency_bins:  # a BasicVector's element: a third of a NumPy view's cost
                histogram.SetAtIndex(k, histogram.GetAtIndex(k) + 1.0)
            if spec.size:
                discrete_state.set_value(self._held[port], spec.decode(newest, t_s))
            if spec.dated is not None:
                discrete_state.set_value(self._dated[port], [spec.dated(newest)])
        if self._on_tick is not None:
            self._on_tick(t_s)

    def _newest_sequence(self, spec, context) -> float:
        """The newest accepted message's sequence number (-1: none)."""
        return context.get_discrete_state(self._counters[spec.port]).GetAtIndex(0)

    def _arrival_s(self, spec, context) -> float:
        """When the newest accepted message of ``spec``'s channel was read (s; -inf: none)."""
        return context.get_discrete_state(self._counters[spec.port]).GetAtIndex(1)

    def _dated_s(self, spec, context) -> float:
        """When what the newest message of ``spec``'s channel reports dates from (s):
        ``spec.dated``'s, or when it was read."""
        if spec.dated is None:
            return self._arrival_s(spec, context)
        return context.get_discrete_state(self._dated[spec.port]).GetAtIndex(0)

    def _is_stale(self, spec, context) -> bool:
        return (spec.stale_value is not None
                and context.get_time() - self._arrival_s(spec, context) > spec.stale_after_s)

    def _calc_value(self, spec, context, output):
        if self._is_stale(spec, context):
            output.SetFromVector(spec.stale_value)
        else:
            output.SetFromVector(context.get_discrete_state(self._held[spec.port]).get_value())

    def _sample_time_s(self, spec, context) -> float:
        if self._is_stale(spec, context):
            return context.get_time() - self._period_s
        return self._arrival_s(spec, context)

    def ports(self) -> list:
        """The output ports' names: one a channel that feeds one, then the age, sample
        time and sequence ports."""
        return ([port for port, spec in self._channels.items() if spec.size]
                + [spec.age_port for spec in self._channels.values() if spec.age_port]
                + [spec.sample_time_port for spec in self._channels.values()
                   if spec.sample_time_port]
                + [spec.sequence_port for spec in self._channels.values() if spec.sequence_port])

    def channels(self) -> list:
        """The names its channels are counted under (``counts``), ports or not."""
        return list(self._channels)

    def newest_arrival_s(self, context, port: str) -> float:
        """When ``port``'s newest message was read (s on this diagram's clock; -inf: never)."""
        return context.get_discrete_state(self._counters[port]).GetAtIndex(1)

    def counts(self, context, port: str, until_now: bool = True) -> dict:
        """What ``receiver_counts`` says so far for ``port``'s channel, and what its gate
        refused (``messages_refused``, ``refused`` by reason, ``first_refused``).
        ``until_now``: the silence since the channel's newest message, up to the
        context's time, counts as a gap (in ``stale_gaps`` once a tick read the stale
        value in it), as if a message read now ended it: a sender that stopped is seen."""
        return {**receiver_counts(context.get_discrete_state(self._counters[port]).get_value(),
                                  context.get_discrete_state(self._latencies[port]).get_value(),
                                  context.get_time() if until_now else None,
                                  self._stale_gap_s[port]),
                **self._gates[port].counts()}


class MessageSender(LeafSystem):
    """A station vector port published on an LCM channel every ``period_s`` (s).

    .. pydrake_system::

        name: MessageSender
        input_ports:
        - value

    ``encode(sequence, t_s, value) -> message`` (None: nothing to send this tick);
    the sequence is the tick number ``round(t / period_s) + 1``, so a receiver counts a
    gap as a lost message.
    ``ready()``, if given, holds every message back while it is False (the
    application's commands, until the device's lease is granted).
    """

    def __init__(self, *, lcm, channel: str, size: int, encode, period_s: float,
                 ready: Optional[Callable[[], bool]] = None):
        super().__init__()
        self._lcm = lcm
        self._channel = channel
        self._encode = encode
        self._ready = ready
        self._period_s = float(period_s)
        self._value = self.DeclareVectorInputPort("value", size)
        self.DeclarePeriodicPublishEvent(period_s, 0.0, self._publish)

    def _publish(self, context):
        if self._ready is not None and not self._ready():
            return
        t = context.get_time()
        message = self._encode(round(t / self._period_s) + 1, t, self._value.Eval(context))
        if message is not None:
            publish(self._lcm, self._channel, message)
