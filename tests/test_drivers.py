"""The hardware adapters: the NDI head tracker (its dummy tracker) and the DAQ coil output's
message contract; a missing extra says which in one line."""

import json
import math
import time

import lcm
import numpy as np
import pytest
from pydrake.math import RigidTransform, RollPitchYaw

from maglev_haptics.diagrams.cli import _daq_channels, main
from maglev_haptics.hardware.daq_coil_output import CoilOutputContract, coil_voltages
from maglev_haptics.hardware.extras import MissingExtraError, require_extra
from maglev_haptics.hardware.lcm_messages import coil_currents_t, glasses_t
from maglev_haptics.hardware.ndi_head_tracker import NdiHeadTracker, glasses_message


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


CONTRACT = CoilOutputContract(n_coils=27, current_limit_a=4.0, amps_per_volt=0.4)


def command(currents):
    message = coil_currents_t()
    message.num_coils = len(currents)
    message.current_a = list(currents)
    message.power_enabled = True
    return message


def test_commands_within_the_contract_become_volts():
    currents = np.linspace(-4.0, 4.0, 27)
    volts, why = coil_voltages(command(currents), CONTRACT)
    assert why is None
    np.testing.assert_allclose(volts, currents / 0.4)


def test_a_command_with_the_power_cut_turns_the_coils_off():
    message = command(np.full(27, 1.0))
    message.power_enabled = False
    volts, why = coil_voltages(message, CONTRACT)
    np.testing.assert_array_equal(volts, np.zeros(27))
    assert why == "the application cut the coils' power"


@pytest.mark.parametrize("currents, reason", [
    (np.zeros(26), "command for 26 coils: the card drives 27"),
    (np.r_[np.zeros(26), math.nan], "non-finite"),
    (np.r_[np.zeros(26), 4.5], "command of 4.500 A exceeds the 4.0 A current limit"),
])
def test_commands_outside_the_contract_turn_the_coils_off(currents, reason):
    volts, why = coil_voltages(command(currents), CONTRACT)
    assert reason in why
    assert np.all(volts == 0.0) and volts.shape == (27,)


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
