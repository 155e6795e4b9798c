"""maglev faults: the campaign's plan is reproducible and covers every kind, every run
of a short campaign passes the safety checks, and a check does fail when broken."""

import json

import numpy as np
import pytest

from maglev_haptics.analysis.fault_campaign import (
    FAULT_KINDS, FaultRun, outcome_row, plan_campaign)
from maglev_haptics.cli import main
from maglev_haptics.diagrams.scenario import load_scenario
from maglev_haptics.systems.device_supervisor import FAULT_SENSOR_OUT_OF_RANGE

ROW_FIELDS = ("run", "scenario", "fault", "crashed", "max_coil_current_a", "current_limit_a",
              "max_coil_temperature_c", "temperature_limit_c", "touchdown_speed_m_s",
              "lost_at_height_m")


def test_the_plan_is_reproducible_and_takes_every_kind_in_turn():
    plan = plan_campaign(20, seed=3)
    assert plan == plan_campaign(20, seed=3)
    assert [p.fault for p in plan[:len(FAULT_KINDS)]] == list(FAULT_KINDS)
    assert [p.fault_at_s for p in plan] != [p.fault_at_s for p in plan_campaign(20, seed=4)]


@pytest.mark.slow
def test_a_short_campaign_passes_every_check_and_writes_its_rows_and_plot(tmp_path, capsys):
    assert main(["faults", "--runs", str(len(FAULT_KINDS)), "--workers", "2",
                 "--out", str(tmp_path)]) == 0
    rows = json.loads((tmp_path / "faults.json").read_text())["runs"]
    assert [row["fault"] for row in rows] == list(FAULT_KINDS)
    for row in rows:
        assert all(name in row for name in ROW_FIELDS), row
        assert not row["crashed"] and row["passed"], row
        assert row["max_coil_current_a"] <= row["current_limit_a"] * (1 + 1e-6)
        assert row["max_coil_temperature_c"] <= row["temperature_limit_c"]
    lost = next(row for row in rows if row["fault"] == "tracker_lost")
    assert lost["lost_at_height_m"] > 0.005 and lost["checks"]["detected"]
    assert (tmp_path / "faults.png").stat().st_size > 10_000
    edge = next(row for row in rows if row["fault"] == "gains_near_edge")
    assert 0.0 < edge["ringing_growth"] <= 2.0
    assert next(row for row in rows if row["fault"] == "sustained_push")[
        "checks"]["heated_to_the_budget"]
    n = len(FAULT_KINDS)
    assert f"{n} of {n} runs passed every check" in capsys.readouterr().out


def test_a_broken_limit_fails_its_check():
    """outcome_row on a made-up run whose current passed the limit and whose lost
    instrument came down faster than free fall."""
    scenario = load_scenario("levitate")
    t = np.arange(0.0, 1.0, 1e-3)
    p = np.zeros((t.size, 3))
    p[:, 2] = np.where(t < 0.5, 0.02, 0.0)
    tracking = np.where(t < 0.5, 1.0, 0.0)
    log = {"t": t, "fault_bits": np.where(t < 0.52, 0, FAULT_SENSOR_OUT_OF_RANGE),
           "tracking_ok": tracking, "p_WI_true": p, "p_WI_desired": p,
           "V_WI_true": np.zeros((t.size, 6)), "coil_power": np.ones(t.size)}
    summary = {"max_coil_current_a": 4.5, "max_coil_temperature_c": 40.0,
               "touchdown": {"time_s": 0.6, "speed_m_s": 2.0, "tilt_deg": 0.0}}
    plan = FaultRun(run=0, fault="tracker_lost", scenario_file="levitate",
                    scenario_name="takeoff_hover_land", fault_at_s=0.5, parameters={})
    row = outcome_row(plan, scenario, summary, log)
    assert not row["passed"]
    assert row["checks"]["within_current_limit"] is False
    assert row["checks"]["fell_level_no_faster_than_free_fall"] is False
    assert row["checks"]["detected"] is True
    assert row["lost_at_height_m"] == pytest.approx(0.02 - scenario.device.instrument_spec()
                                                    .rest_height_m)
