"""The fuzz of the LCM link (slow): bad messages on every channel in each direction, beside
valid traffic, at up to 10 kHz; device-sim and the application keep running, no coil
current leaves its limit, no NaN or infinity from a payload reaches the coils, a plant
or a log, and what each end refused matches what was sent, reason by reason. And the
same checks and the NDI adapter's frame parsing under hypothesis."""

import collections
import json
import math
import os
import subprocess
import sys
import time

import lcm
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from maglev_haptics.hardware.link.lcm_messages import (
    coil_currents_t, device_status_t, glasses_t, lease_t, markers_t)
from maglev_haptics.hardware.link.lease import LeaseClient
from maglev_haptics.hardware.link.link_checks import (
    HEAD_RANGE_M, MARKER_RANGE_M, REASONS, InboundGate, LinkLimits, Refused, check_command,
    check_glasses, check_lease_reply, check_lease_request, check_markers,
    check_measured_currents, check_status)
from maglev_haptics.hardware.link.ndi_head_tracker import glasses_message, parse_tool_pose
from maglev_haptics.systems.station_messages import currents_message, markers_message

pytestmark = pytest.mark.slow

LIMITS = LinkLimits(n_coils=27, n_markers=3, current_limit_a=4.0)
CHECKS = {coil_currents_t: [check_command, check_measured_currents],
          markers_t: [check_markers], device_status_t: [check_status], glasses_t: [check_glasses],
          lease_t: [check_lease_request, check_lease_reply]}
MAGLEV = [sys.executable, "-m", "maglev_haptics.cli"]
# Bad messages a process fuzz sends, at up to 10 kHz (10 s at most: a loaded host's
# test process keeps 4-10 kHz beside its own checks).
FUZZ_MESSAGES = 30_000

numbers = st.one_of(st.floats(allow_nan=True, allow_infinity=True),
                    st.sampled_from([math.nan, math.inf, -math.inf, 1e6, 4.0, 4.5, -1e308]))


def valid_message(message_type, sequence=1):
    if message_type is coil_currents_t:
        return currents_message(sequence, 0.0, np.r_[np.full(27, 0.5), 1.0], 7)
    if message_type is markers_t:
        return markers_message(sequence, 0.0, 0.001, np.full(9, 0.01))
    if message_type is device_status_t:
        message = device_status_t()
        message.num_coils, message.coil_temperature_c = 27, [30.0] * 27
    elif message_type is glasses_t:
        message = glasses_t()
        message.quaternion_wxyz, message.position_m, message.ok = [1.0, 0, 0, 0], [0, 0, 0.5], True
    else:
        message = lease_t()
        message.session, message.action, message.instrument = 7, lease_t.REQUEST, "two_magnet"
    message.sequence = sequence
    return message


def read_numbers(message) -> list:
    """Every number a receiver reads from an accepted message."""
    if isinstance(message, coil_currents_t):
        return list(message.current_a)
    if isinstance(message, markers_t):
        return [c for p, seen in zip(message.position_m, message.visible) if seen for c in p]
    if isinstance(message, device_status_t):
        return list(message.coil_temperature_c)
    if isinstance(message, glasses_t):
        return [*message.quaternion_wxyz, *message.position_m] if message.ok else []
    return []


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(message_type=st.sampled_from(list(CHECKS)), data=st.data())
def test_whatever_arrives_is_refused_or_finite_and_in_range(message_type, data):
    """Random bytes, valid messages truncated, extended or with a byte changed, and
    valid messages with fields set to random values: each is refused with one of the
    reasons, or accepted with every number it gives finite and in range."""
    encoded = valid_message(message_type).encode()
    kind = data.draw(st.sampled_from(["bytes", "truncated", "extended", "flipped", "fields"]))
    if kind == "bytes":
        payload = data.draw(st.binary(max_size=400))
    elif kind == "truncated":
        payload = encoded[:data.draw(st.integers(0, len(encoded) - 1))]
    elif kind == "extended":
        payload = encoded + data.draw(st.binary(min_size=1, max_size=50))
    elif kind == "flipped":
        i = data.draw(st.integers(0, len(encoded) - 1))
        payload = encoded[:i] + bytes([data.draw(st.integers(0, 255))]) + encoded[i + 1:]
    else:
        message = valid_message(message_type)
        for name in data.draw(st.lists(st.sampled_from(message.__slots__), max_size=3)):
            value = getattr(message, name)
            if isinstance(value, (list, tuple)) and value and isinstance(value[0], (list, tuple)):
                value = [[data.draw(numbers) for _ in row] for row in value]
            elif isinstance(value, (list, tuple)):
                value = [data.draw(numbers) for _ in value]
            elif isinstance(value, bool):
                value = data.draw(st.booleans())
            elif isinstance(value, int) and name.startswith("num_"):
                value = data.draw(st.integers(-5, 40))
            elif isinstance(value, int):
                value = data.draw(st.integers(-2**31, 2**31 - 1))
            elif isinstance(value, str):
                value = data.draw(st.text(max_size=20))
            setattr(message, name, value)
        try:
            payload = message.encode()
        except Exception:  # noqa: BLE001 (a value its type cannot carry: nothing to send)
            return
    for check in CHECKS[message_type]:
        gate = InboundGate("C", message_type, lambda m, check=check: check(m, LIMITS),
                           log=lambda line: None)
        accepted = gate.accept(payload)
        refusals = gate.counts()["refused"]
        if accepted is None:
            assert sum(refusals.values()) == 1
            continue
        values = read_numbers(accepted)
        assert all(math.isfinite(v) for v in values)
        if message_type is coil_currents_t:
            assert max(map(abs, values)) <= 4.0 * 1.05
        elif message_type is markers_t:
            assert all(abs(v) <= MARKER_RANGE_M for v in values)
        elif message_type is glasses_t and accepted.ok:
            assert math.hypot(*accepted.position_m) <= HEAD_RANGE_M


@settings(max_examples=300, deadline=None)
@given(row=st.one_of(
    st.lists(numbers, min_size=0, max_size=10),
    st.lists(st.floats(-2.0, 2.0), min_size=7, max_size=7),
    st.text(max_size=10)))
def test_the_ndi_adapter_publishes_a_finite_pose_or_none(row):
    """Any tool row the tracker might give: refused by reason, unseen, or a glasses_t
    whose pose is finite, unit and within the head's range."""
    from pydrake.math import RigidTransform

    try:
        parse_tool_pose(row)
        message = glasses_message(1, 1.0, 1.0, RigidTransform([0.0, 0.4, 0.6]),
                                  *(np.asarray(row, float)[0:4], np.asarray(row, float)[4:7]))
    except Refused as refusal:
        assert refusal.reason in REASONS
        return
    if message.ok:
        check_glasses(message)  # what the application would accept
        assert all(map(math.isfinite, [*message.quaternion_wxyz, *message.position_m]))


class Fuzzer:
    """Bad messages of every kind for a channel, each with the reason it must get."""

    def __init__(self, seed: int):
        self.rng = np.random.default_rng(seed)
        self.sent = {}  # channel -> {reason: count}
        self.total = 0

    def count(self, channel, reason):
        self.sent.setdefault(channel, dict.fromkeys(REASONS, 0))[reason] += 1
        self.total += 1

    def garbage(self, valid: bytes):
        kind = self.rng.integers(3)
        if kind == 0:
            return self.rng.bytes(int(self.rng.integers(0, 300)))
        if kind == 1:
            return valid[:int(self.rng.integers(0, len(valid)))]  # truncated
        return valid + self.rng.bytes(int(self.rng.integers(1, 100)))  # oversized

    def command(self, valid: coil_currents_t, replay: coil_currents_t):
        """(bytes, reason) of a bad command beside ``valid``, the holder's newest."""
        kind = self.rng.integers(7)
        message = coil_currents_t.decode(valid.encode())
        if kind == 0:
            return self.garbage(valid.encode()), "malformed"
        if kind == 1:
            n = int(self.rng.choice([0, 5, 26, 28]))
            message.num_coils, message.current_a = n, [0.0] * n
            return message.encode(), "wrong_size"
        if kind == 2:
            message.current_a = list(message.current_a)
            message.current_a[int(self.rng.integers(27))] = float(
                self.rng.choice([math.nan, math.inf, -math.inf]))
            return message.encode(), "not_finite"
        if kind == 3:
            message.current_a = [float(self.rng.choice([4.5, 1e6, -1e300]))] * 27
            return message.encode(), "out_of_range"
        if kind == 4:
            message.session = int(self.rng.integers(1, 2**62))
            return message.encode(), "other_session"
        return replay.encode(), "replayed"  # an old one: a replay or out of order


class Delivered:
    """What of this test's own messages came back to it: multicast brings each back to
    the test's own socket in the same pass as to the others', so where all came back
    the kernel dropped none on the way (its loopback backlog holds 1000 packets).
    ``counts``: channel -> {reason: delivered}."""

    def __init__(self, lcm_instance, channels):
        self._pending = {}  # bytes -> deque of (channel, reason or None: a valid one)
        self.counts = {}
        self._lcm = lcm_instance
        for channel in channels:
            lcm_instance.subscribe(channel, self.on_message).set_queue_capacity(1_000_000)

    def publish(self, channel, data, reason=None):
        self._pending.setdefault(data, collections.deque()).append((channel, reason))
        self._lcm.publish(channel, data)

    def on_message(self, channel, data) -> bool:
        """Whether ``data`` was this test's (then counted)."""
        pending = self._pending.get(data)
        if not pending:
            return False
        sent_on, reason = pending.popleft()
        if reason is not None:
            self.counts.setdefault(sent_on, dict.fromkeys(REASONS, 0))[reason] += 1
        return True

    def drain(self):
        quiet_since = time.monotonic()
        while time.monotonic() - quiet_since < 0.3:
            if self._lcm.handle_timeout(50) > 0:
                quiet_since = time.monotonic()


def assert_counted(refused: dict, sent: dict, delivered: dict, lost: int) -> None:
    """What an end refused is what was sent, reason by reason, where the host dropped
    none of it: this test's own socket got back every message it sent (``delivered``)
    and the end lost none of its valid traffic (``lost``). Where a stall made the
    kernel drop messages, what arrived of each kind is counted as that kind: at most
    what was sent, and each kind's share within 0.05 of the whole's (a stall drops
    kinds alike; a kind taken for another would not)."""
    if lost == 0 and delivered == sent:
        assert refused == sent
        return
    arrived = sum(refused.values()) / sum(sent.values())
    if arrived <= 0.3:  # too few to judge each kind's share by: the host, not the link
        pytest.skip(f"this machine dropped {100 * (1 - arrived):.0f}% of the fuzzed messages "
                    f"({lost} of the device's own lost): its stalls overflowed the socket")
    for reason in REASONS:
        assert refused[reason] <= sent[reason], (reason, refused, sent)
        if sent[reason] >= 500:
            assert abs(refused[reason] / sent[reason] - arrived) < 0.05, (reason, refused, sent)


def device_sim_process(name, port, duration_s, rate, extra=""):
    station = (f"{{station: !LcmStation {{url: 'udpm://239.255.76.67:{port}?ttl=0', "
               f"command_url: 'udpm://239.255.76.67:{port + 1}?ttl=0'}}{extra}}}")
    return station, subprocess.Popen(
        MAGLEV + ["device-sim", name, "--scenario-text", station, "--realtime", str(rate),
                  "--duration", str(duration_s)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def test_device_sim_under_fuzz_keeps_its_coils_and_counts_what_it_refused():
    """This test is the application: it takes the lease and commands device-sim at
    1 kHz, and publishes FUZZ_MESSAGES bad commands and lease requests beside them at
    up to 10 kHz. Device-sim keeps running, the currents it reports stay finite and
    within the limit, it applies every good command, and it counts the bad ones that
    the host delivered by reason."""
    port = 8100 + 2 * (os.getpid() % 50)
    _, device = device_sim_process("levitate", port, 60, 1.0)
    url, command_url = (f"udpm://239.255.76.67:{port}?ttl=0",
                        f"udpm://239.255.76.67:{port + 1}?ttl=0")
    listener, bus = lcm.LCM(url), lcm.LCM(command_url)
    measured, replies = [], []
    listener.subscribe("MAGLEV_COIL_CURRENTS",
                       lambda _, data: measured.append(coil_currents_t.decode(data).current_a))
    listener.subscribe("MAGLEV_LEASE", lambda _, data: replies.append(lease_t.decode(data)))
    lease = LeaseClient(lcm=bus, channel="MAGLEV_LEASE_REQUEST", wait_s=60.0,
                        instrument="two_magnet")
    delivered = Delivered(bus, ["MAGLEV_COIL_CURRENTS_COMMANDED", "MAGLEV_LEASE_REQUEST"])
    fuzzer = Fuzzer(26)
    sent_valid = 0
    try:
        start = time.monotonic()
        while not lease.granted:  # device-sim builds (~10 s), then answers
            assert device.poll() is None, device.communicate()[1][-2000:]
            lease.on_tick(time.monotonic() - start)
            listener.handle_timeout(10)
            for reply in replies:
                lease.on_reply(reply, 0.0)
            replies.clear()
            assert time.monotonic() - start < 120
        history = []
        period_s, fuzz_period_s = 1e-3, 1e-4
        t0 = time.monotonic()
        next_valid, next_fuzz = t0, t0 + 0.2  # the holder's commands first
        fuzz_end = t0 + 10.0  # or once FUZZ_MESSAGES are out
        while time.monotonic() < fuzz_end + 0.2:
            now = time.monotonic()
            if now >= next_valid:
                sent_valid += 1
                # Small currents, a slow wave: the instrument stays on the glass.
                value = np.r_[0.3 * np.sin(np.arange(27) + now), 1.0]
                message = currents_message(sent_valid, now - t0, value, lease.session)
                message.sent_wall_utime = time.time_ns() // 1000
                delivered.publish("MAGLEV_COIL_CURRENTS_COMMANDED", message.encode())
                history.append(message)
                next_valid += period_s
            elif now >= next_fuzz and now < fuzz_end:
                if fuzzer.rng.random() < 0.9:
                    data, reason = fuzzer.command(history[-1], history[max(0, len(history) - 30)])
                    channel = "MAGLEV_COIL_CURRENTS_COMMANDED"
                else:
                    other = lease_t()
                    other.session, other.action, other.sequence = 99, lease_t.REQUEST, 1
                    other.instrument = "two_magnet"
                    data, reason = (other.encode(), "other_session") if fuzzer.rng.random() < 0.5 \
                        else (fuzzer.rng.bytes(int(fuzzer.rng.integers(0, 60))), "malformed")
                    channel = "MAGLEV_LEASE_REQUEST"
                delivered.publish(channel, data, reason)
                fuzzer.count(channel, reason)
                # At most 2 ms behind: a burst would overflow the kernel's backlog.
                next_fuzz = max(next_fuzz + fuzz_period_s, now - 0.002)
                if fuzzer.total >= FUZZ_MESSAGES:
                    fuzz_end = now
            listener.handle_timeout(0)
            bus.handle_timeout(0)
        delivered.drain()
        out, err = device.communicate(timeout=60)  # stops 1 s after the last command
    finally:
        device.kill()
    assert device.returncode == 0, err[-2000:]
    report = json.loads(out)
    commands = report["commands"]
    sent = fuzzer.sent["MAGLEV_COIL_CURRENTS_COMMANDED"]
    print(json.dumps({"sent": fuzzer.sent, "delivered": delivered.counts,
                      "sent_valid": sent_valid, "device": commands, "lease": report["lease"]}))
    assert sum(sent.values()) > 10_000  # the fuzz had volume (FUZZ_MESSAGES, up to 10 kHz)
    # Every good command applied or counted lost; every bad one counted as what it was.
    assert commands["messages_received"] + commands["messages_lost"] == sent_valid
    for channel, refused in (("MAGLEV_COIL_CURRENTS_COMMANDED", commands["refused"]),
                             ("MAGLEV_LEASE_REQUEST", report["lease"]["refused"])):
        assert_counted(refused, fuzzer.sent[channel], delivered.counts.get(channel),
                       commands["messages_lost"])
    # The first of each kind in one line each.
    refusal_lines = [line for line in err.splitlines() if "refused a message" in line]
    assert len(refusal_lines) == sum(1 for v in {**sent}.values() if v) + sum(
        1 for v in fuzzer.sent["MAGLEV_LEASE_REQUEST"].values() if v)
    currents = np.array(measured)
    assert currents.size and np.all(np.isfinite(currents)) and np.abs(currents).max() <= 4.0


# The application's inbound channels and what summary.json calls them.
APPLICATION_CHANNELS = {"MAGLEV_MARKERS": "markers", "MAGLEV_COIL_CURRENTS": "coil_currents",
                        "MAGLEV_LEASE": "lease", "MAGLEV_DEVICE_STATUS": "device_status",
                        "MAGLEV_GLASSES": "glasses"}


def bad_station_message(fuzzer, channel, newest: bytes, older: bytes):
    """(bytes, reason) of a bad message on one of the application's channels, from the
    device's newest and an older message there."""
    kind = fuzzer.rng.integers(4)
    if kind == 0:
        return fuzzer.garbage(newest), "malformed"
    if kind == 1:
        return older, "replayed"
    message_type = {"MAGLEV_MARKERS": markers_t, "MAGLEV_COIL_CURRENTS": coil_currents_t,
                    "MAGLEV_LEASE": lease_t, "MAGLEV_DEVICE_STATUS": device_status_t,
                    "MAGLEV_GLASSES": glasses_t}[channel]
    message = message_type.decode(newest)
    message.sequence += 100_000  # would be the newest: must be refused for its content
    bad = float(fuzzer.rng.choice([np.nan, np.inf, -np.inf]))
    if channel == "MAGLEV_MARKERS":
        if kind == 2:
            message.position_m, message.visible = [[bad, 0.0, 0.0]] * 3, [True] * 3
            reason = "not_finite"
        elif fuzzer.rng.random() < 0.5:
            message.position_m, message.visible = [[0.0, 0.0, 0.01]] * 4, [True] * 4
            message.num_markers, reason = 4, "wrong_size"
        else:  # beyond the tracker's volume
            message.position_m, message.visible = [[3.0, 0.0, 0.01]] * 3, [True] * 3
            reason = "out_of_range"
    elif channel == "MAGLEV_COIL_CURRENTS":
        message.current_a, reason = (([1e6] * 27, "out_of_range") if kind == 2
                                     else ([bad] * 27, "not_finite"))
    elif channel == "MAGLEV_DEVICE_STATUS":
        if kind == 2:
            message.coil_temperature_c, reason = [bad] * 27, "not_finite"
        else:
            message.fault_bits, reason = 0x100, "out_of_range"
    elif channel == "MAGLEV_GLASSES":
        message.ok, message.quaternion_wxyz = True, [1.0, 0.0, 0.0, 0.0]
        message.position_m = [0.0, 0.3, 0.5]
        if kind == 2:
            message.position_m, reason = [bad, 0.3, 0.5], "not_finite"
        else:
            message.quaternion_wxyz, reason = [2.0, 0.0, 0.0, 0.0], "out_of_range"
    else:
        message.action = 9 if kind == 2 else lease_t.HELD
        if kind == 3:
            message.session = 0  # held by nobody
        reason = "out_of_range"
    return message.encode(), reason


@pytest.mark.parametrize("name, extra", [
    ("levitate", ""), ("peg_in_hole", ", stereo: {images: {rate_hz: 0}}")],
    ids=["levitate", "peg_in_hole with the glasses"])
def test_the_application_under_fuzz_flies_and_counts_what_it_refused(tmp_path, name, extra):
    """Device-sim and `maglev run --station lcm` as their own processes at half speed;
    this test publishes bad messages on every channel the application reads (markers,
    currents, lease answers; with the hand and the glasses, the device's status and
    the glasses' samples): garbage, truncated, oversized, other sizes, NaN,
    infinities, out of range, replays of the device's own messages, FUZZ_MESSAGES at up to
    10 kHz.
    The application runs to its end, counts what it refused per channel and reason as
    sent, and logs no NaN or infinity in the currents or the glasses it used. (How
    well it flew is the two-process test's; a host that stalls it past the link's
    timeouts makes it lose the instrument, which it then says.)"""
    port = 8200 + 4 * (os.getpid() % 50) + 2 * (name == "peg_in_hole")
    rate = 0.5
    station, device = device_sim_process(name, port, 120, rate, extra)
    url = f"udpm://239.255.76.67:{port}?ttl=0"
    bus = lcm.LCM(url)
    channels = ["MAGLEV_MARKERS", "MAGLEV_COIL_CURRENTS", "MAGLEV_LEASE"] + (
        ["MAGLEV_DEVICE_STATUS", "MAGLEV_GLASSES"] if extra else [])
    seen = {channel: [] for channel in channels}
    delivered = Delivered(bus, [])
    for channel, store in seen.items():  # the device's messages, and this test's counted
        bus.subscribe(channel, lambda name, data, store=store: delivered.on_message(name, data)
                      or store.append(data)).set_queue_capacity(1_000_000)
    application = subprocess.Popen(
        MAGLEV + ["run", name, "--scenario-text", station, "--realtime", str(rate),
                  "--no-meshcat", "--duration", "7", "--out", str(tmp_path / "run")],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    fuzzer = Fuzzer(27)
    try:
        start = time.monotonic()
        while not seen["MAGLEV_LEASE"] or lease_t.decode(
                seen["MAGLEV_LEASE"][-1]).action != lease_t.HELD or not all(seen.values()):
            assert application.poll() is None, application.communicate()[1][-2000:]
            bus.handle_timeout(10)
            assert time.monotonic() - start < 180
        t0 = time.monotonic()
        next_fuzz = t0 + 0.5
        while time.monotonic() - t0 < 10.5 and fuzzer.total < FUZZ_MESSAGES:
            bus.handle_timeout(0)
            now = time.monotonic()
            if now < next_fuzz:
                continue
            next_fuzz = max(next_fuzz + 1.0 / 10_000, now - 0.002)  # no bursts
            channel = str(fuzzer.rng.choice(channels))
            data, reason = bad_station_message(fuzzer, channel, seen[channel][-1],
                                               seen[channel][max(0, len(seen[channel]) - 20)])
            delivered.publish(channel, data, reason)
            fuzzer.count(channel, reason)
        delivered.drain()
        out, err = application.communicate(timeout=300)
        device.communicate(timeout=60)
    finally:
        application.kill()
        device.kill()
    assert application.returncode in (0, 5), err[-2000:]  # 5: says it lost the instrument
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    print(json.dumps({"sent": fuzzer.sent, "delivered": delivered.counts,
                      "station": summary["station"]}))
    lost = summary["station"]["messages_lost"]
    for channel, sent in fuzzer.sent.items():
        assert_counted(summary["station"]["channels"][APPLICATION_CHANNELS[channel]]["refused"],
                       sent, delivered.counts.get(channel), lost)
    assert sum(sum(s.values()) for s in fuzzer.sent.values()) > 10_000  # it had volume
    log = np.load(tmp_path / "run" / "log.npz")
    assert np.all(np.isfinite(log["coil_currents"])) and np.abs(log["coil_currents"]).max() <= 4.0
    if extra:  # the glasses' samples the application used: finite where seen
        glasses = log["glasses_measured"]
        assert np.all(np.isfinite(glasses[glasses[:, 8] > 0.5, 1:8]))
    if application.returncode == 5:  # the host stalled it past the link's timeouts: said
        last = err.strip().splitlines()[-1]
        assert " the instrument was lost at " in last or " a fault latched at " in last
