"""The hardware adapters: the NDI head tracker (its dummy tracker, and frames it cannot
read) and the DAQ coil output's message contract, lease and refusals; a missing extra
says which in one line."""

import json
import math
import time
import warnings

import lcm
import numpy as np
import pytest
from pydrake.math import RigidTransform, RollPitchYaw

from maglev_haptics.cli import _daq_channels, main
from maglev_haptics.hardware.link.daq_coil_output import (
    CoilOutputContract, CommandLink, coil_voltages)
from maglev_haptics.hardware.link.extras import MissingExtraError, require_extra
from maglev_haptics.hardware.link.lcm_messages import coil_currents_t, glasses_t, lease_t
from maglev_haptics.hardware.link.link_checks import Refused
from maglev_haptics.hardware.link.ndi_head_tracker import (
    NdiHeadTracker, glasses_message, parse_tool_pose)


def test_glasses_pose_goes_from_the_trackers_frame_to_w_in_metres():
    X_WN = RigidTransform(RollPitchYaw(0.1, -0.2, 2.0), [0.3, -0.4, 0.9])
    X_NG = RigidTransform(RollPitchYaw(-0.3, 0.5, 0.2), [0.12, -0.05, -1.1])
    q = X_NG.rotation().ToQuaternion()
    message = glasses_message(3, 1.0, 1.03, X_WN, [q.w(), q.x(), q.y(), q.z()],
                              1000 * X_NG.translation())
    X_WG = X_WN @ X_NG
    assert message.ok and message.sequence == 3 and message.publish_utime == 1_030_000
    np.testing.assert_allclose(message.position_m, X_WG.translation(), atol=1e-12)
    q_WG = X_WG.rotation().ToQuaternion()
    assert abs(np.dot(message.quaternion_wxyz, [q_WG.w(), q_WG.x(), q_WG.y(), q_WG.z()])) \
        == pytest.approx(1.0, abs=1e-12)
    unseen = glasses_message(4, 1.0, 1.0, X_WN, [math.nan] * 4, [math.nan] * 3)
    assert not unseen.ok


@pytest.mark.parametrize("row, reason", [
    ([1.0, 0.0, 0.0, 0.0, 0.0, 0.0], "wrong_size"),
    ("garbage", "malformed"),
    ([1.0, 0.0, 0.0, math.nan, 0.0, 0.0, 0.0], "not_finite"),
    ([1.0, 0.0, 0.0, 0.0, math.inf, 0.0, 0.0], "not_finite"),
    ([2.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0], "out_of_range"),
    ([1e200, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0], "out_of_range"),  # its square overflows
    ([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0], "out_of_range"),
])
def test_a_tool_row_that_cannot_be_read_is_refused_by_reason(row, reason):
    with pytest.raises(Refused) as refusal, warnings.catch_warnings():
        warnings.simplefilter("error")
        parse_tool_pose(row)
    assert refusal.value.reason == reason
    assert parse_tool_pose([math.nan] * 7) is None  # NaN throughout: not seen


def test_glasses_beyond_the_head_range_are_refused():
    with pytest.raises(Refused, match="out_of_range: position_m = .* within 5 m"):
        glasses_message(1, 1.0, 1.0, RigidTransform(), [1, 0, 0, 0], [1e7, 0, 0])


def test_frames_the_tracker_adapter_cannot_read_go_out_unseen_and_counted(tmp_path, capsys):
    pytest.importorskip("sksurgerynditracker", reason="the hardware extra is not installed")
    romfile = tmp_path / "glasses.rom"
    romfile.write_bytes(b"")
    tracker = NdiHeadTracker({"tracker type": "dummy", "romfiles": [str(romfile)]},
                             lcm=lcm.LCM("memq://"), channel="G", X_WN=RigidTransform())
    try:
        good = tracker.frame_message([np.array([1.0, 0, 0, 0, 10.0, 20.0, 500.0])], 2.0)
        assert good.ok and good.position_m == pytest.approx([0.01, 0.02, 0.5])
        for tracking in (None, [[1.0, 2.0]], [np.array([1.0, 0, 0, 0, np.inf, 0, 0])],
                         [np.array([1.0, 0, 0, 0, np.inf, 0, 0])], {"a": 1}):
            message = tracker.frame_message(tracking, 2.0)
            assert not message.ok and message.position_m == [0.0, 0.0, 0.0]
        assert {k: v for k, v in tracker.refused.items() if v} == {
            "malformed": 2, "wrong_size": 1, "not_finite": 2}
        assert len(capsys.readouterr().err.strip().splitlines()) == 3  # the first of each kind
    finally:
        tracker.close()


def test_dummy_ndi_tracker_publishes_unseen_glasses(tmp_path):
    pytest.importorskip("sksurgerynditracker", reason="the hardware extra is not installed")
    romfile = tmp_path / "glasses.rom"
    romfile.write_bytes(b"")
    url = "udpm://239.255.76.67:7730?ttl=0"
    listener = lcm.LCM(url)
    received = []
    listener.subscribe("TEST_GLASSES", lambda _, data: received.append(glasses_t.decode(data)))
    tracker = NdiHeadTracker({"tracker type": "dummy", "romfiles": [str(romfile)]},
                             lcm=lcm.LCM(url), channel="TEST_GLASSES", X_WN=RigidTransform())
    try:
        for _ in range(3):
            tracker.publish_frame()
    finally:
        tracker.close()
    deadline = time.monotonic() + 2.0
    while len(received) < 3 and time.monotonic() < deadline:
        listener.handle_timeout(50)
    assert [m.sequence for m in received] == [1, 2, 3]
    assert not any(m.ok for m in received)  # the dummy sees nothing


CONTRACT = CoilOutputContract(n_coils=27, current_limit_a=4.0, amps_per_volt=0.4,
                              instrument="two_magnet")


def command(currents):
    message = coil_currents_t()
    message.num_coils = len(currents)
    message.current_a = list(currents)
    message.power_enabled = True
    return message


def test_commands_within_the_contract_become_volts():
    currents = np.linspace(-4.0, 4.0, 27)
    np.testing.assert_allclose(coil_voltages(command(currents), CONTRACT), currents / 0.4)


def test_a_command_with_the_power_cut_turns_the_coils_off():
    message = command(np.full(27, 1.0))
    message.power_enabled = False
    np.testing.assert_array_equal(coil_voltages(message, CONTRACT), np.zeros(27))


@pytest.mark.parametrize("currents, reason, detail", [
    (np.zeros(26), "wrong_size", "num_coils = 26: the scenario's coil count is 27"),
    (np.r_[np.zeros(26), math.nan], "not_finite", "current_a[26] = nan: must be finite"),
    (np.r_[np.zeros(26), 4.5], "out_of_range",
     "current_a[26] = 4.5 A: must be within +-4 A (the amplifiers' limit)"),
])
def test_commands_outside_the_contract_are_refused(currents, reason, detail):
    with pytest.raises(Refused) as refusal:
        coil_voltages(command(currents), CONTRACT)
    assert (refusal.value.reason, refusal.value.detail) == (reason, detail)


def lease_request(session, sequence, action=lease_t.REQUEST):
    message = lease_t()
    message.session, message.sequence, message.action = session, sequence, action
    message.pid, message.host, message.instrument = 4242, "labpc", "two_magnet"
    return message.encode()


def test_the_coil_driver_applies_only_the_lease_holders_good_new_commands():
    """The DAQ driver's link, without a card: the lease goes to the first session that
    asks; its commands are applied, anything refused is counted by reason and never
    applied (the last good command holds); a second session is told who holds it."""
    applied, replies, lines = [], [], []
    clock = [0.0]
    link = CommandLink(CONTRACT, apply=applied.append, publish_reply=replies.append,
                       lease_timeout_s=0.5, clock=lambda: clock[0], log=lines.append)

    def send(currents, sequence, session=7):
        message = command(currents)
        message.sequence, message.session = sequence, session
        return link.on_command(message.encode())

    assert not send(np.zeros(27), 1)  # nobody holds the lease yet
    link.on_request(lease_request(7, 1))
    assert replies[-1].action == lease_t.HELD and replies[-1].session == 7
    assert send(np.full(27, 1.0), 2)
    assert not send(np.full(27, 1.0), 2)  # a replay
    assert not send(np.full(27, 1.0), 1)  # out of order
    assert not send(np.r_[np.zeros(26), math.nan], 3)
    assert not send(np.full(27, 1e6), 4)
    assert not send(np.zeros(5), 5)
    assert not send(np.zeros(27), 6, session=8)  # another session's
    assert not link.on_command(b"\x00" * 30)
    assert send(np.full(27, 2.0), 7)
    assert [m.current_a[0] for m in applied] == [1.0, 2.0]
    link.on_request(lease_request(8, 1))  # a second application asks: told who holds it
    assert replies[-1].session == 7 and replies[-1].host == "labpc"
    counts = link.counts()
    assert counts["applied"] == 2 and counts["refused"] == {
        "malformed": 1, "wrong_size": 1, "not_finite": 1, "out_of_range": 1,
        "other_session": 2, "replayed": 2, "wrong_instrument": 0}
    assert counts["lease"]["requests_refused"]["other_session"] == 1
    assert len(lines) == 7 and all("refused a message" in line for line in lines)
    clock[0] = 0.6  # the holder silent past the lease's timeout: the next asker gets it
    link.on_request(lease_request(8, 2))
    assert replies[-1].session == 8 and send(np.zeros(27), 1, session=8)


def test_missing_extra_says_which_in_one_line():
    with pytest.raises(MissingExtraError) as error:
        require_extra("no_such_driver_package", "The frobnicator")
    assert str(error.value) == (
        "The frobnicator needs the Python package 'no_such_driver_package', which is not "
        "installed: pip install 'maglev-haptics[hardware]'")


def test_daq_channel_ranges_expand_in_coil_order():
    assert _daq_channels("Dev1/ao0:26") == [f"Dev1/ao{i}" for i in range(27)]
    assert _daq_channels("Dev1/ao0:1, Dev2/ao0") == ["Dev1/ao0", "Dev1/ao1", "Dev2/ao0"]


def test_driver_commands_run_or_say_what_is_missing(tmp_path, capsys):
    pytest.importorskip("sksurgerynditracker", reason="the hardware extra is not installed")
    romfile = tmp_path / "glasses.rom"
    romfile.write_bytes(b"")
    station = "{station: !LcmStation {url: 'udpm://239.255.76.67:7732?ttl=0'}}"
    assert main(["driver", "head-tracker", "levitate", "--scenario-text", station,
                 "--tracker", "dummy", "--romfile", str(romfile), "--duration", "0.25"]) == 0
    assert json.loads(capsys.readouterr().out)["glasses_messages"] == 3  # 10 Hz for 0.25 s
    # No NI card or driver here: one line saying what is missing, not a traceback.
    assert main(["driver", "coil-daq", "levitate", "--channels", "Dev1/ao0:26",
                 "--amps-per-volt", "0.4", "--duration", "0.1"]) == 2
    error = capsys.readouterr().err.strip()
    assert len(error.splitlines()) == 1
    # nidaqmx missing (the hardware extra) or NI-DAQmx missing (the vendor driver).
    assert error.startswith("maglev driver: error: The coil current output")
