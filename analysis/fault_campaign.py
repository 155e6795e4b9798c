"""The fault-injection campaign (``maglev faults``): randomized runs of the shipped
scenarios, one injected fault each, checked against the safety policy.

Each fault kind, where it is injected and what is expected of the device:

| kind | scenario | injected | expected |
|---|---|---|---|
| marker_dropout | levitate hover | one marker hidden 5-50 ms | ridden through within the 20 ms grace (three markers: two cannot be fitted), else as tracker_lost |
| tracker_lost | levitate hover | every marker hidden 0.1-0.3 s | coils off past the 20 ms grace: falls level, no faster than free fall; sensor fault within 29.7 ms |
| latency_spike | levitate hover | the tracker stalls 10-40 ms | ridden through, or a controlled landing |
| nan_sample | levitate hover | one coordinate of one sample NaN | ridden through |
| amplifier_stuck_zero | levitate hover | one coil stuck at 0 A | ridden through: a coil commanded under 1 A is not missed (one commanded more is, as below) |
| amplifier_stuck_limit | levitate hover | one coil stuck at +-4 A | over-current fault within 17 ms; the coil allocated nothing, its current taken as given; controlled landing, the power cut on the glass; where the other coils cannot carry it against the stuck one, the power cut at once: falls level, no faster than free fall |
| hand_lets_go | peg_release_outside | the hand lets go at a random time | the device lands it |
| shove | levitate hover | 10 N for 10 ms, horizontal, random direction | over-speed fault within 23 ms, controlled landing |
| haptic_shove | peg_release_outside, the hand holding the peg with haptics on | as shove | ridden through (the hand holds it), or over-speed: haptics ends and the device lands it |
| gains_near_edge | peg held still | coupling at 80-95% of the analysed critical stiffness, the hand holding still (the onset study's test) | no fault; its high-passed velocity's RMS in the last second at most GROWTH_RATIO times the first's |
| sustained_push | peg_in_hole, the hand pushing the peg against a wall | coils cooled poorly that heat in seconds | the coils reach the thermal budget's target and no further: the push is carried, spread over the others |
| overload_hold | a high hold with coils that heat in seconds | the hold outlasts the thermal budget | over-temperature fault, controlled landing |

Every run is checked: no crash; no coil past its current or temperature limit; a
fault that must be detected is, within its stated time; a controlled landing touches
down under LANDING_SPEED_LIMIT_M_S; a lost instrument touches down level and no
faster than free fall from the height and speed it was lost at (tracking lost, or the
power cut in flight: ``lost_at_height_m``); the instrument stays within
BOUNDARY_MARGIN_M of where it was asked to be.
"""

import dataclasses
import json
import math
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.ticker import MaxNLocator  # noqa: E402
import numpy as np  # noqa: E402

from maglev_haptics.analysis.haptic_loop import critical_stiffness  # noqa: E402
from maglev_haptics.analysis.loop_studies import loop_parameters  # noqa: E402
from maglev_haptics.analysis.parallel import map_jobs  # noqa: E402
from maglev_haptics.analysis.onset import (  # noqa: E402
    GROWTH_RATIO, OnsetPoint, held_still, velocity_growth)
from maglev_haptics.analysis.run_plots import legend_outside, save_figure  # noqa: E402
from maglev_haptics.diagrams.application import WATCHDOG_PERIOD_S  # noqa: E402
from maglev_haptics.diagrams.hand_script import GripEvent  # noqa: E402
from maglev_haptics.diagrams.scenario import load_scenario  # noqa: E402
from maglev_haptics.hardware.constants import GRAVITY_M_S2  # noqa: E402
from maglev_haptics.hardware.thermal import coil_thermal  # noqa: E402
from maglev_haptics.systems.device_supervisor import (  # noqa: E402
    FAULT_COIL_OVER_CURRENT, FAULT_COIL_OVER_TEMPERATURE, FAULT_OVER_SPEED,
    FAULT_SENSOR_OUT_OF_RANGE, STUCK_PERSIST_S)
from maglev_haptics.systems.fault_injection import (  # noqa: E402
    CorruptSample, LatencySpike, Shove, StuckAmplifier)
from maglev_haptics.systems.marker_sensor import Occlusion  # noqa: E402
from maglev_haptics.systems.pose_estimator import velocity_lag_s  # noqa: E402

FAULT_KINDS = ("marker_dropout", "tracker_lost", "latency_spike", "nan_sample",
               "amplifier_stuck_zero", "amplifier_stuck_limit", "hand_lets_go", "shove",
               "haptic_shove", "gains_near_edge", "sustained_push", "overload_hold")
LANDING_SPEED_LIMIT_M_S = 0.1  # a controlled landing touches down slower (m/s)
BOUNDARY_MARGIN_M = 0.03  # the instrument stays this close to its setpoint (m)
LEVEL_TILT_DEG = 5.0  # a lost instrument touches down tilted less (deg)
EXPECTED_BIT = {"tracker_lost": FAULT_SENSOR_OUT_OF_RANGE, "shove": FAULT_OVER_SPEED,
                "overload_hold": FAULT_COIL_OVER_TEMPERATURE,
                "amplifier_stuck_limit": FAULT_COIL_OVER_CURRENT}
EDGE_POINT = OnsetPoint("the fault campaign's gains near the edge")
HOVER = ("levitate", "takeoff_hover_land")  # hovers 1.4-4.4 s
# The hand pushes the peg against the hole's +x wall and holds it there, on coils
# cooled poorly (6 K/W against 2.5: a failed fan) that heat in seconds (2 J/K: a 12 s
# time constant) with a 1 s budget: the busiest coils reach the budget's target and
# the allocation spreads the push over the others (measured: sustained, 95 C).
SUSTAINED_PUSH = ("peg_in_hole", "peg_in_hole")
PRESS = ("{duration_s: 16.0, device: {thermal: {heat_capacity_j_per_k: 2.0, "
         "thermal_resistance_k_per_w: 6.0}}, "
         "controller: {thermal_horizon_s: 1.0}, hand: !ScriptedHand {start_s: 3.0, "
         "events: [{at_s: 1.8, grip: true}], waypoints: ["
         "{pose: [0.0, 0.0, 0.0175, 0.0, 0.0, 0.0], move_s: 1.5, hold_s: 0.5}, "
         "{pose: [0.021, 0.0, 0.017, 0.0, 0.0, 0.0], move_s: 1.5, hold_s: 20.0}]}}")
PRESS_AT_S = 6.0  # pressed in from here (s)
# Heats in seconds (2 J/K: a 5 s time constant), and a hold 46 mm up that the coils
# cannot keep for ever: the thermal budget ends it after ~4.5 s.
HIGH_HOLD = ("{motion: {waypoints: [{pose: [0.0, 0.0, 0.036, 0.0, 0.0, 0.0], move_s: 1.0, "
             "hold_s: 8.0}]}, device: {thermal: {heat_capacity_j_per_k: 2.0}}, "
             "controller: {thermal_horizon_s: 1.0}}")


@dataclass
class FaultRun:
    """One run of the campaign: which scenario, which fault, when."""

    run: int
    fault: str
    scenario_file: str
    scenario_name: str
    fault_at_s: float  # when the fault starts (s)
    parameters: Dict  # the fault's own numbers
    scenario_text: str = "{}"  # layered over the named scenario


def plan_campaign(runs: int, seed: int) -> List[FaultRun]:
    """``runs`` runs, the kinds in turn (every kind within the first ten), each with
    its random draws from numpy's generator seeded with (seed, run)."""
    plans = []
    for run in range(runs):
        rng = np.random.default_rng([seed, run])
        fault = FAULT_KINDS[run % len(FAULT_KINDS)]
        file, name, text = (*HOVER, "{}")
        at_s = float(rng.uniform(1.8, 3.6))  # hovering
        if fault == "marker_dropout":
            parameters = {"marker": int(rng.integers(3)),
                          "duration_s": float(rng.uniform(0.005, 0.05))}
        elif fault == "tracker_lost":
            parameters = {"duration_s": float(rng.uniform(0.1, 0.3))}
        elif fault == "latency_spike":
            parameters = {"duration_s": float(rng.uniform(0.01, 0.04))}
        elif fault == "nan_sample":
            parameters = {"marker": int(rng.integers(3)), "coordinate": int(rng.integers(3))}
        elif fault.startswith("amplifier_stuck"):
            parameters = {"coil": int(rng.integers(27)),
                          "stuck_at": "zero" if fault.endswith("zero") else
                          str(rng.choice(["positive_limit", "negative_limit"]))}
        elif fault == "hand_lets_go":
            file, name = "peg_in_hole", "peg_release_outside"
            at_s = float(rng.uniform(3.0, 4.5))  # haptics on, the peg held above the block
            parameters = {}
        elif fault in ("shove", "haptic_shove"):
            angle = float(rng.uniform(0.0, 2 * math.pi))
            parameters = {"force_n": [10 * math.cos(angle), 10 * math.sin(angle), 0.0],
                          "duration_s": 0.01}
            if fault == "haptic_shove":  # the hand holds the peg above the block
                file, name = "peg_in_hole", "peg_release_outside"
                at_s = float(rng.uniform(3.0, 4.3))
        elif fault == "gains_near_edge":
            file, name = "peg_in_hole", "peg_release_outside"
            at_s = 2.0  # haptics engages
            parameters = {"fraction_of_critical": float(rng.uniform(0.8, 0.95))}
        elif fault == "sustained_push":
            (file, name), at_s, parameters, text = SUSTAINED_PUSH, PRESS_AT_S, {}, PRESS
        else:  # overload_hold
            at_s, parameters, text = 1.4, {}, HIGH_HOLD
        plans.append(FaultRun(run=run, fault=fault, scenario_file=file, scenario_name=name,
                              fault_at_s=at_s, parameters=parameters, scenario_text=text))
    return plans


def faulted_scenario(plan: FaultRun):
    """The scenario of ``plan`` with its fault injected."""
    scenario = load_scenario(plan.scenario_file, plan.scenario_name, plan.scenario_text)
    p, at_s = plan.parameters, plan.fault_at_s
    if plan.fault == "marker_dropout":
        return dataclasses.replace(scenario, occlusions=[
            Occlusion(marker=p["marker"], start_s=at_s, end_s=at_s + p["duration_s"])])
    if plan.fault == "tracker_lost":
        return dataclasses.replace(scenario, occlusions=[
            Occlusion(marker=None, start_s=at_s, end_s=at_s + p["duration_s"])])
    if plan.fault == "latency_spike":
        return dataclasses.replace(scenario, faults=[LatencySpike(at_s, at_s + p["duration_s"])])
    if plan.fault == "nan_sample":
        return dataclasses.replace(scenario, faults=[CorruptSample(at_s, p["marker"],
                                                                   p["coordinate"])])
    if plan.fault.startswith("amplifier_stuck"):
        return dataclasses.replace(scenario, faults=[StuckAmplifier(p["coil"], at_s,
                                                                    p["stuck_at"])])
    if plan.fault == "hand_lets_go":
        hand = scenario.hand
        events = [e for e in hand.events if e.grip] + [GripEvent(at_s=at_s, grip=False)]
        return dataclasses.replace(scenario, hand=dataclasses.replace(hand, events=events))
    if plan.fault in ("shove", "haptic_shove"):
        return dataclasses.replace(scenario, faults=[Shove(at_s, p["duration_s"], p["force_n"])])
    if plan.fault == "gains_near_edge":  # the hand holds it still: the onset study's test
        stiffness = p["fraction_of_critical"] * critical_stiffness(loop_parameters(scenario))
        return held_still(scenario, EDGE_POINT, stiffness)[0]
    return scenario  # sustained_push, overload_hold: the scenario text is the fault


def detection_limit_s(plan: FaultRun, scenario) -> Optional[float]:
    """How long after the fault starts (s) its bit must be raised, as the README's
    fault table states it; None where the time is the thermal budget's."""
    tracker = scenario.device.tracker
    seen_s = tracker.latency_s + 1.0 / tracker.rate_hz  # a sample shows it
    check_s = WATCHDOG_PERIOD_S + 1.0 / scenario.control_rate_hz  # the next check, a tick late
    if plan.fault == "tracker_lost":  # the count passes the grace a tick after reaching it
        return seen_s + scenario.controller.lost_grace_s + 1.0 / scenario.control_rate_hz + check_s
    if plan.fault == "amplifier_stuck_limit":  # the mismatch lasts two checks
        return STUCK_PERSIST_S + check_s + 1.0 / scenario.control_rate_hz
    if plan.fault == "shove":  # the estimate's speed crosses the limit
        return (plan.parameters["duration_s"] + seen_s + velocity_lag_s(scenario.estimator)
                + check_s)
    return None


def outcome_row(plan: FaultRun, scenario, summary: Dict, log: Dict[str, np.ndarray]) -> Dict:
    """The campaign's row for a finished run: what happened and each check."""
    t = log["t"]
    device = scenario.device
    current_limit_a = device.amplifier.current_limit_a
    temperature_limit_c = coil_thermal(device).max_c
    bits = log["fault_bits"].astype(int)
    after = t >= plan.fault_at_s
    raised = int(np.bitwise_or.reduce(bits[after])) if after.any() else 0
    expected_bit = EXPECTED_BIT.get(plan.fault)
    detected_s = None
    if expected_bit is not None and ((bits & expected_bit) != 0).any():
        detected_s = float(t[np.argmax((bits & expected_bit) != 0)] - plan.fault_at_s)
    touchdown = summary.get("touchdown")
    touchdown_speed = touchdown["speed_m_s"] if touchdown else None
    # Lost to the coils: the sensor fault raised after tracking was lost (past the
    # grace the coils are cut; tracking may be back by the check that raises it), or
    # the supervisor cut the coils' power while they carried it. It falls from there.
    rest_m = device.instrument_spec().rest_height_m
    lost_at = None  # the log's index
    unseen = after & (log["tracking_ok"] < 0.5)
    cut = after & (log["coil_power"] < 0.5)
    if raised & FAULT_SENSOR_OUT_OF_RANGE and unseen.any():
        lost_at = max(int(np.argmax(unseen)) - 1, 0)  # the last good sample
    elif cut.any() and (touchdown is None or t[np.argmax(cut)] < touchdown["time_s"]):
        lost_at = int(np.argmax(cut))
    lost_at_height = None if lost_at is None else float(log["p_WI_true"][lost_at, 2] - rest_m)
    power_cut_s = float(t[np.argmax(cut)]) if cut.any() else None
    # Off the setpoint while it flies (on the glass it is at rest, wherever it is).
    flying = after & (t < touchdown["time_s"]) if touchdown else after
    excursion = float(np.max(np.linalg.norm(
        log["p_WI_true"][flying] - log["p_WI_desired"][flying], axis=1))) if flying.any() else 0.0
    checks = {
        "within_current_limit": summary["max_coil_current_a"] <= current_limit_a * (1 + 1e-6),
        "within_temperature_limit": summary["max_coil_temperature_c"] <= temperature_limit_c,
        "within_boundary": excursion <= BOUNDARY_MARGIN_M or lost_at_height is not None,
    }
    if expected_bit is not None:
        limit = detection_limit_s(plan, scenario)
        checks["detected"] = detected_s is not None and (limit is None or detected_s <= limit)
    if lost_at_height is not None:  # from its speed down then, under gravity alone
        sinking_m_s = max(-float(log["V_WI_true"][lost_at, 5]), 0.0)
        free_fall = math.sqrt(sinking_m_s**2 + 2 * GRAVITY_M_S2 * max(lost_at_height, 0.0))
        checks["fell_level_no_faster_than_free_fall"] = (
            touchdown is not None and touchdown["tilt_deg"] < LEVEL_TILT_DEG
            and touchdown_speed <= 1.05 * free_fall + 0.01)
    elif touchdown is not None:
        checks["landing_under_speed_limit"] = touchdown_speed < LANDING_SPEED_LIMIT_M_S
    if plan.fault == "sustained_push":  # it heated them to the budget, not past
        target_c = temperature_limit_c - scenario.controller.thermal_margin_c
        checks["heated_to_the_budget"] = summary["max_coil_temperature_c"] >= target_c - 1.0
    ringing = None
    if plan.fault == "gains_near_edge":  # held still: its shaking must not grow
        haptics = scenario.haptics
        first_rms, last_rms = velocity_growth(log, haptics.enable_at_s + haptics.coupling.ramp_s)
        ringing = last_rms / first_rms
        checks["not_ringing"] = ringing <= GROWTH_RATIO
    return {
        "run": plan.run, "scenario": f"{plan.scenario_file}:{plan.scenario_name}",
        "fault": plan.fault, "fault_at_s": plan.fault_at_s, "parameters": plan.parameters,
        "crashed": False, "error": None,
        "max_coil_current_a": summary["max_coil_current_a"], "current_limit_a": current_limit_a,
        "max_coil_temperature_c": summary["max_coil_temperature_c"],
        "temperature_limit_c": temperature_limit_c,
        "touchdown_speed_m_s": touchdown_speed, "lost_at_height_m": lost_at_height,
        "power_cut_at_s": power_cut_s, "ringing_growth": ringing,
        "fault_bits_raised": raised, "detected_after_s": detected_s,
        "max_excursion_m": excursion, "checks": checks, "passed": all(checks.values()),
    }


def run_fault(plan: FaultRun) -> Dict:
    """Run one plan; a run that raises is a row with ``crashed`` true and the error."""
    from maglev_haptics.analysis.run_results import run_scenario
    try:
        scenario = faulted_scenario(plan)
        result = run_scenario(scenario, label=f"faults run {plan.run}", progress=False)
        return outcome_row(plan, scenario, result.summary, result.log)
    except Exception as error:  # the campaign records it; a crash is what it looks for
        return {"run": plan.run, "scenario": f"{plan.scenario_file}:{plan.scenario_name}",
                "fault": plan.fault, "fault_at_s": plan.fault_at_s,
                "parameters": plan.parameters, "crashed": True,
                "error": "".join(traceback.format_exception_only(error)).strip(),
                "max_coil_current_a": None, "current_limit_a": None,
                "max_coil_temperature_c": None, "temperature_limit_c": None,
                "touchdown_speed_m_s": None, "lost_at_height_m": None,
                "power_cut_at_s": None, "ringing_growth": None, "checks": {},
                "passed": False}


def run_campaign(runs: int, seed: int, out_dir: Path, workers: int = 1,
                 scheduler: Optional[str] = None, progress: bool = True) -> Dict:
    """Run the campaign here, on ``workers`` local processes or on the Dask
    ``scheduler``'s workers (``analysis/parallel.py``); write ``faults.json`` and
    ``faults.png`` to ``out_dir``; returns {"runs": rows, "table": ..., "report": str,
    "jobs": what ran them}."""
    plans = plan_campaign(runs, seed)
    jobs = map_jobs(run_fault, plans, workers=workers, scheduler=scheduler,
                    description="fault campaign", progress=progress)
    rows = jobs.results
    table = summary_table(rows)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    ran = {"where": jobs.where, "workers": jobs.workers, "reran": jobs.reran}
    (out_dir / "faults.json").write_text(json.dumps(
        {"seed": seed, "runs": rows, "table": table, "jobs": ran}, indent=1))
    plot_outcomes(rows, out_dir / "faults.png")
    return {"runs": rows, "table": table, "report": format_table(table), "jobs": ran}


def outcome(row: Dict) -> str:
    """How the run ended: crashed, failed a check, landed, fell, or ridden through."""
    if row["crashed"]:
        return "crashed"
    if not row["passed"]:
        return "failed a check"
    if row["lost_at_height_m"] is not None:
        return "fell level"
    if row["fault_bits_raised"]:
        return "landed on a fault"
    return "ridden through"


OUTCOMES = ("ridden through", "landed on a fault", "fell level", "failed a check", "crashed")


def summary_table(rows: List[Dict]) -> List[Dict]:
    """One row per fault kind: runs, outcomes and the worst of each measure."""
    table = []
    for fault in FAULT_KINDS:
        mine = [r for r in rows if r["fault"] == fault]
        if not mine:
            continue
        done = [r for r in mine if not r["crashed"]]
        speeds = [r["touchdown_speed_m_s"] for r in done if r["touchdown_speed_m_s"] is not None]
        detected = [r["detected_after_s"] for r in done if r.get("detected_after_s") is not None]
        table.append({
            "fault": fault, "runs": len(mine),
            **{name: sum(outcome(r) == name for r in mine) for name in OUTCOMES},
            "max_coil_current_a": max((r["max_coil_current_a"] for r in done), default=None),
            "max_coil_temperature_c": max((r["max_coil_temperature_c"] for r in done),
                                          default=None),
            "max_touchdown_speed_m_s": max(speeds, default=None),
            "max_detected_after_s": max(detected, default=None),
            "max_excursion_mm": max((1e3 * r["max_excursion_m"] for r in done), default=None),
        })
    return table


def _cell(value, digits: int) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def format_table(table: List[Dict]) -> str:
    lines = [f"{'fault':<22}{'runs':>5}{'ridden':>8}{'landed':>8}{'fell':>6}{'failed':>8}"
             f"{'crash':>7}{'max A':>7}{'max C':>7}{'touch m/s':>10}{'seen s':>8}{'dev mm':>8}"]
    for r in table:
        lines.append(
            f"{r['fault']:<22}{r['runs']:>5}{r['ridden through']:>8}{r['landed on a fault']:>8}"
            f"{r['fell level']:>6}{r['failed a check']:>8}{r['crashed']:>7}"
            f"{_cell(r['max_coil_current_a'], 2):>7}{_cell(r['max_coil_temperature_c'], 0):>7}"
            f"{_cell(r['max_touchdown_speed_m_s'], 3):>10}{_cell(r['max_detected_after_s'], 3):>8}"
            f"{_cell(r['max_excursion_mm'], 1):>8}")
    return "\n".join(lines)


def plot_outcomes(rows: List[Dict], path: Path) -> Path:
    """Stacked bars of the outcomes by fault kind."""
    kinds = [k for k in FAULT_KINDS if any(r["fault"] == k for r in rows)]
    figure, axes = plt.subplots(figsize=(10, 4.8))
    bottom = np.zeros(len(kinds))
    colors = ("tab:green", "tab:blue", "tab:cyan", "tab:orange", "tab:red")
    for name, color in zip(OUTCOMES, colors):
        counts = np.array([sum(r["fault"] == k and outcome(r) == name for r in rows)
                           for k in kinds])
        axes.bar(kinds, counts, bottom=bottom, color=color, label=name)
        bottom += counts
    axes.set_ylabel("runs")
    axes.yaxis.set_major_locator(MaxNLocator(integer=True))
    axes.set_title(f"fault campaign: {len(rows)} runs, outcome by fault kind")
    legend_outside(axes)
    plt.setp(axes.get_xticklabels(), rotation=30, ha="right")
    return save_figure(figure, path)
