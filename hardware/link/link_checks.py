"""What the LCM link refuses: every inbound station message is checked before it is used.

Any process on the host (or, past ttl=0, on the network) can publish on the
station's channels, and LCM has no authentication; so each end that reads a
message (device-sim, the drivers, the application's receiver) takes it through
an ``InboundGate`` first. In order, a message is refused, counted by reason and
never used when it:

- ``malformed``: does not decode as its type (random bytes, another type's
  fingerprint, truncated), or has bytes past its end (oversized);
- ``wrong_size``: its size fields do not match the scenario (coils, markers);
- ``not_finite``: holds a NaN or an infinity where a number is read (the
  positions of markers flagged unseen are not read);
- ``out_of_range``: a number outside the message's physical range: currents
  past the amplifiers' limit, markers outside the tracker's volume, the glasses
  farther than ``HEAD_RANGE_M``, a sample older than ``MAX_SAMPLE_AGE_S`` or
  younger than zero, temperatures outside ``TEMPERATURE_RANGE_C``, unknown fault
  bits or lease actions;
- ``other_session``: a command (or lease request) of a session that does not
  hold the device's lease (``hardware/link/lease.py``);
- ``replayed``: a sequence number not newer than the last one accepted from the
  same sender and session (a replay, a duplicate or an out-of-order message);
- ``wrong_instrument``: a lease request for another instrument than the device's.

A refused message is a lost message: the receiver keeps what it had (the device's
coils their last good command until ``command_timeout_s`` turns them off; the
application's markers their last sample until they read as unseen). The first
refusal of each kind on a channel is logged in one line.
"""

from __future__ import annotations

import math
import sys
from collections import OrderedDict
from dataclasses import dataclass
from io import BytesIO
from typing import Callable, Dict, Optional

from tqdm import tqdm

from maglev_haptics.hardware.link.lcm_messages import device_status_t, lease_t

REASONS = ("malformed", "wrong_size", "not_finite", "out_of_range", "other_session", "replayed",
           "wrong_instrument")
# The instrument tracker's measuring volume, as a distance from W's origin (m): an
# Optotrak's reaches ~1-6 m from its cameras; a marker beyond 2 m of the display is
# nowhere the instrument can be.
MARKER_RANGE_M = 2.0
HEAD_RANGE_M = 5.0  # the glasses farther than this from W's origin: not a head at the display
MAX_SAMPLE_AGE_S = 1.0  # capture to publish longer than this: no live tracker sample
TEMPERATURE_RANGE_C = (-50.0, 400.0)  # a winding's temperature (C): past these, a broken sensor
# A measured current may read past the amplifiers' limit by its sensor's error (share).
MEASURED_CURRENT_MARGIN = 0.05
UNIT_QUATERNION_TOLERANCE = 1e-3
KNOWN_FAULT_BITS = (device_status_t.FAULT_SENSOR_OUT_OF_RANGE
                    | device_status_t.FAULT_COIL_OVER_TEMPERATURE
                    | device_status_t.FAULT_COIL_OVER_CURRENT | device_status_t.FAULT_OVER_SPEED)
SESSIONS_REMEMBERED = 64  # sessions whose newest sequence a gate keeps


class Refused(ValueError):
    """A message the link does not use: ``reason`` (one of REASONS) and ``detail``, a
    line naming the field, its value and what is allowed."""

    def __init__(self, reason: str, detail: str):
        super().__init__(f"{reason}: {detail}")
        self.reason = reason
        self.detail = detail


@dataclass(frozen=True)
class LinkLimits:
    """What the scenario's device allows on the wire."""

    n_coils: int
    n_markers: int
    current_limit_a: float  # the amplifiers' limit (A)

    @classmethod
    def from_device(cls, device) -> "LinkLimits":
        """From a ``DeviceConfig``."""
        return cls(n_coils=device.n_coils, n_markers=len(device.instrument_spec().p_IK_m),
                   current_limit_a=float(device.amplifier.current_limit_a))


def decode_exact(message_type, data: bytes):
    """``message_type.decode(data)``; Refused("malformed") where it does not decode or
    leaves bytes over."""
    buffer = BytesIO(data)
    try:
        message = message_type.decode(buffer)
    except Exception as error:  # noqa: BLE001 (LCM's decoders raise what struct does)
        raise Refused("malformed", f"{len(data)} bytes: not a {message_type.__name__} "
                      f"({type(error).__name__}: {error})") from None
    if buffer.tell() != len(data):
        raise Refused("malformed", f"{len(data)} bytes: {len(data) - buffer.tell()} past the "
                      f"end of a {message_type.__name__}")
    # LCM's Python decoder reads a string short without a word: one cut inside a
    # string decodes. Its encoding again must be what came (strings are rare and small).
    if "string" in message_type.__typenames__ and message.encode() != data:
        raise Refused("malformed", f"{len(data)} bytes: a {message_type.__name__} cut short "
                      "or padded inside a string")
    return message


def _size(name: str, value: int, expected: int, what: str) -> None:
    if value != expected:
        raise Refused("wrong_size", f"{name} = {value}: the scenario's {what} is {expected}")


def _finite(name: str, values) -> None:
    if not all(map(math.isfinite, values)):
        index = next(i for i, v in enumerate(values) if not math.isfinite(v))
        raise Refused("not_finite", f"{name}[{index}] = {values[index]}: must be finite")


def _within(name: str, values, limit: float, unit: str, why: str) -> None:
    if values and max(map(abs, values)) > limit:
        index = max(range(len(values)), key=lambda i: abs(values[i]))
        raise Refused("out_of_range", f"{name}[{index}] = {values[index]:.6g} {unit}: must be "
                      f"within +-{limit:g} {unit} ({why})")


def _age(capture_utime: int, publish_utime: int) -> None:
    age_s = (publish_utime - capture_utime) * 1e-6
    if not 0.0 <= age_s <= MAX_SAMPLE_AGE_S:
        raise Refused("out_of_range", f"publish_utime - capture_utime = {age_s:.6g} s: a "
                      f"sample's age must be within 0-{MAX_SAMPLE_AGE_S:g} s")


def check_command(message, limits: LinkLimits) -> None:
    """A commanded ``coil_currents_t``: the scenario's coils, finite, within the limit."""
    _size("num_coils", message.num_coils, limits.n_coils, "coil count")
    _finite("current_a", message.current_a)
    # A hair over from rounding is the limit; more is a broken command.
    _within("current_a", message.current_a, limits.current_limit_a * (1 + 1e-9), "A",
            "the amplifiers' limit")


def check_measured_currents(message, limits: LinkLimits) -> None:
    """A measured ``coil_currents_t``: as a command, within the sensor's margin."""
    _size("num_coils", message.num_coils, limits.n_coils, "coil count")
    _finite("current_a", message.current_a)
    _within("current_a", message.current_a,
            limits.current_limit_a * (1 + MEASURED_CURRENT_MARGIN), "A",
            "the amplifiers' limit and the sensor's margin")


def check_markers(message, limits: LinkLimits) -> None:
    """A ``markers_t``: the instrument's marker count; seen markers finite and in the
    tracker's volume; a sane age."""
    _size("num_markers", message.num_markers, limits.n_markers, "instrument's marker count")
    _size("len(visible)", len(message.visible), limits.n_markers, "instrument's marker count")
    _age(message.capture_utime, message.publish_utime)
    for k, (position, seen) in enumerate(zip(message.position_m, message.visible)):
        if seen:
            _finite(f"position_m[{k}]", position)
            if math.hypot(*position) > MARKER_RANGE_M:
                raise Refused("out_of_range", f"position_m[{k}] = {list(position)} m: must be "
                              f"within {MARKER_RANGE_M:g} m of the display's centre (the "
                              "tracker's volume)")


def check_status(message, limits: LinkLimits) -> None:
    """A ``device_status_t``: the scenario's coils, known fault bits, sane temperatures."""
    _size("num_coils", message.num_coils, limits.n_coils, "coil count")
    _finite("coil_temperature_c", message.coil_temperature_c)
    low, high = TEMPERATURE_RANGE_C
    for i, value in enumerate(message.coil_temperature_c):
        if not low <= value <= high:
            raise Refused("out_of_range", f"coil_temperature_c[{i}] = {value:.6g} C: must be "
                          f"within {low:g}-{high:g} C")
    if message.fault_bits & ~KNOWN_FAULT_BITS or message.fault_bits < 0:
        raise Refused("out_of_range", f"fault_bits = {message.fault_bits:#x}: only "
                      f"{KNOWN_FAULT_BITS:#x} are defined")


def check_glasses(message, limits: LinkLimits = None) -> None:
    """A ``glasses_t``: where seen, a finite unit quaternion and a position within
    ``HEAD_RANGE_M``; a sane age."""
    if not message.ok:
        return  # not seen: its pose is not read
    _finite("quaternion_wxyz", message.quaternion_wxyz)
    _finite("position_m", message.position_m)
    norm = math.sqrt(sum(q * q for q in message.quaternion_wxyz))
    if abs(norm - 1.0) > UNIT_QUATERNION_TOLERANCE:
        raise Refused("out_of_range", f"quaternion_wxyz = {list(message.quaternion_wxyz)}: "
                      f"must have norm 1 (+-{UNIT_QUATERNION_TOLERANCE:g}), not {norm:.6g}")
    if math.hypot(*message.position_m) > HEAD_RANGE_M:
        raise Refused("out_of_range", f"position_m = {list(message.position_m)} m: must be "
                      f"within {HEAD_RANGE_M:g} m of the display's centre")
    _age(message.capture_utime, message.publish_utime)


def check_lease_request(message, limits: LinkLimits = None) -> None:
    """A ``lease_t`` from an application: REQUEST or RELEASE, of a non-zero session."""
    if message.action not in (lease_t.REQUEST, lease_t.RELEASE):
        raise Refused("out_of_range", f"action = {message.action}: an application sends "
                      f"REQUEST ({lease_t.REQUEST}) or RELEASE ({lease_t.RELEASE})")
    if message.session == 0:
        raise Refused("out_of_range", "session = 0: must be the application's non-zero id")


def check_lease_reply(message, limits: LinkLimits = None) -> None:
    """A ``lease_t`` from the device: HELD (by a non-zero session) or FREE."""
    if message.action not in (lease_t.HELD, lease_t.FREE):
        raise Refused("out_of_range", f"action = {message.action}: the device answers HELD "
                      f"({lease_t.HELD}) or FREE ({lease_t.FREE})")
    if message.action == lease_t.HELD and message.session == 0:
        raise Refused("out_of_range", "session = 0: a held lease names its holder")


def log_to_stderr(line: str) -> None:
    """One line on stderr, on a line of its own beside a progress bar."""
    tqdm.write(line, file=sys.stderr)


class InboundGate:
    """Takes one channel's raw messages through ``decode_exact``, ``check(message)``,
    ``admit(message, now_s)`` (optional: the lease; raises Refused) and the sequence
    gate, and counts what it refused by reason. ``session_of(message)`` (optional)
    keys the sequence gate: each session's sequence must rise; without it the
    channel is one sender's."""

    def __init__(self, channel: str, message_type, check: Callable, *,
                 session_of: Optional[Callable] = None, admit: Optional[Callable] = None,
                 log: Callable[[str], None] = log_to_stderr):
        self.channel = channel
        self._type = message_type
        self._check = check
        self._session_of = session_of
        self._admit = admit
        self._log = log
        self._newest: "OrderedDict[int, int]" = OrderedDict()  # session -> newest sequence
        self.refused: Dict[str, int] = dict.fromkeys(REASONS, 0)
        self.first_refused: Dict[str, str] = {}

    def accept(self, data: bytes, now_s: float = 0.0):
        """The decoded message if it passes every check (its sequence then becomes the
        newest of its session); else None, counted."""
        try:
            message = decode_exact(self._type, data)
            self._check(message)
            session = self._session_of(message) if self._session_of is not None else 0
            if self._admit is not None:
                self._admit(message, now_s)
            newest = self._newest.get(session)
            if newest is not None and message.sequence <= newest:
                raise Refused("replayed", f"sequence = {message.sequence}: not newer than "
                              f"{newest}, the last accepted from this sender")
        except Refused as refusal:
            self.refuse(refusal)
            return None
        self._newest[session] = message.sequence
        self._newest.move_to_end(session)
        if len(self._newest) > SESSIONS_REMEMBERED:
            self._newest.popitem(last=False)
        return message

    def refuse(self, refusal: Refused) -> None:
        """Count ``refusal``; the first of its kind is logged in one line."""
        self.refused[refusal.reason] += 1
        if refusal.reason not in self.first_refused:
            self.first_refused[refusal.reason] = refusal.detail
            self._log(f"{self.channel}: refused a message ({refusal.reason}): {refusal.detail}; "
                      "more of this kind are counted, not logged")

    def counts(self) -> dict:
        """{"messages_refused", "refused": {reason: count}, "first_refused": {reason: line}}."""
        return {"messages_refused": sum(self.refused.values()), "refused": dict(self.refused),
                "first_refused": dict(self.first_refused)}
