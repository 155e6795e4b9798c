"""Where the whole haptic loop goes unstable as the coupling stiffens: predicted from
its linearization, found by running the nonlinear simulation to the edge.

The operating point is the hand holding the instrument still in free space with
haptics on. There the tool follows the *measured* instrument, so through the
tracker's and the loop's delay tau the instrument feels a spring to where it was:
a negative damping of about K tau, which the grip's and the coupling's damping
must outlast. Both searches bisect on the coupling's translational stiffness K
(the rotational gains follow it, as the diagram builder derives them):

- linear: the spectral radius of the loop's monodromy over its hyperperiod
  (``loop_linearization``, central differences of the full diagram) crossing 1;
- nonlinear: the same scenario simulated with K, the hand held still for
  HOLD_S; unstable when the instrument's velocity, high-passed, grows by
  GROWTH_RATIO from the first to the last second of the hold (tracker noise
  excites every mode; a growing one shows within seconds, the force clamp
  then caps it).
"""

import dataclasses
import math
from dataclasses import dataclass
from typing import Callable, Dict, List, Optional

import numpy as np
import scipy.signal

from maglev_haptics.analysis.loop_linearization import loop_map, stability
from maglev_haptics.analysis.loop_studies import StudyNotApplicable
from maglev_haptics.analysis.parallel import map_jobs, report
from maglev_haptics.analysis.run_results import run_scenario
from maglev_haptics.diagrams.hand_script import ScriptedHand
from maglev_haptics.diagrams.scenario import scenario_from_yaml, scenario_yaml

HOLD_S = 3.0  # how long the hand holds still with haptics on (s)
SETTLE_S = 0.5  # after haptics is fully on, before the growth is measured (s)
GROWTH_RATIO = 2.0  # last second's RMS over the first's above this: unstable
# Or the last second's RMS this many times a stable run's (at the scenario's own
# stiffness): near the onset, a lightly damped mode amplifies the tracker noise a few
# times; a loop that blew up sits ~100x above it, at the force clamp.
SATURATED_RATIO = 20.0
HIGH_PASS_HZ = 5.0  # the oscillations of interest are above the hand's ~4 Hz (Hz)
RELATIVE_TOLERANCE = 0.02  # bisection ends when the bracket is this narrow


@dataclass
class OnsetPoint:
    label: str
    control_rate_hz: Optional[float] = None  # None: the scenario's
    damping_scale: float = 1.0  # the coupling's damping times this
    tracker_latency_s: Optional[float] = None  # None: the scenario's


# Not a larger coupling damping: the tool's own step limits it. The light tool (the
# peg) integrated explicitly under the coupling's damper diverges once B T / m_tool
# nears 2, at any stiffness: B = 10 N s/m on the peg already does (multiplier 6 over
# 50 ms, the tool's x and vx).
DEFAULT_POINTS = [OnsetPoint("as the scenario"), OnsetPoint("860 Hz loop", control_rate_hz=860.0),
                  OnsetPoint("tracker latency 4 ms", tracker_latency_s=4e-3)]


def held_still(scenario, point: OnsetPoint, stiffness: float):
    """The scenario at ``point`` with coupling stiffness K on every axis, its hand
    holding still from grip to the end (HOLD_S after haptics is fully on)."""
    if scenario.haptics is None or not isinstance(scenario.hand, ScriptedHand):
        raise StudyNotApplicable("the onset needs a scripted hand holding the instrument "
                                 "with haptics on")
    haptics = scenario.haptics
    coupling = dataclasses.replace(
        haptics.coupling, translational_stiffness=[stiffness] * 3,
        translational_damping=[b * point.damping_scale for b in haptics.coupling.translational_damping])
    engaged_s = haptics.enable_at_s + coupling.ramp_s
    duration_s = engaged_s + HOLD_S
    hand = dataclasses.replace(scenario.hand, waypoints=[], start_s=duration_s,
                               events=[e for e in scenario.hand.events if e.grip])
    changed = dataclasses.replace(
        scenario, hand=hand, duration_s=duration_s,
        haptics=dataclasses.replace(haptics, coupling=coupling, disable_at_s=None))
    if point.control_rate_hz is not None:
        changed = dataclasses.replace(changed, control_rate_hz=point.control_rate_hz)
    if point.tracker_latency_s is not None:
        tracker = dataclasses.replace(changed.device.tracker, latency_s=point.tracker_latency_s)
        changed = dataclasses.replace(changed, device=dataclasses.replace(changed.device,
                                                                          tracker=tracker))
    return changed, engaged_s


def velocity_growth(log, engaged_s: float) -> List[float]:
    """The RMS (m/s) of the instrument's high-passed velocity in the first second
    after settling (haptics fully on at ``engaged_s``, s) and in the log's last second."""
    t = log["t"]
    velocity = log["V_WI_true"][:, 3:6]
    b, a = scipy.signal.butter(2, HIGH_PASS_HZ, "highpass", fs=1.0 / np.median(np.diff(t)))
    fast = scipy.signal.filtfilt(b, a, velocity, axis=0)
    first = (t >= engaged_s + SETTLE_S) & (t < engaged_s + SETTLE_S + 1.0)
    last = t >= t[-1] - 1.0
    return [float(np.sqrt(np.mean(np.sum(fast[mask] ** 2, axis=1)))) for mask in (first, last)]


def grows(scenario, engaged_s: float, reference_rms_m_s: Optional[float] = None) -> Dict:
    """Run the scenario; the high-passed instrument velocity's RMS in the first and
    the last second after settling. Unstable when it grew by GROWTH_RATIO, or (a loop
    that blew up already while haptics faded in, and sits at the force clamp) when the
    last second is above SATURATED_RATIO times ``reference_rms_m_s``, a stable run's.
    With the passivity controller, also the work it withheld (J)."""
    result = run_scenario(scenario, label="onset", progress=False)
    rms = velocity_growth(result.log, engaged_s)
    blown_up = reference_rms_m_s is not None and rms[1] > SATURATED_RATIO * reference_rms_m_s
    return {"first_rms_m_s": rms[0], "last_rms_m_s": rms[1],
            "unstable": bool(rms[1] > GROWTH_RATIO * rms[0] or blown_up),
            "passivity_dissipated_j": result.summary.get("passivity_dissipated_j")}


def _bisect(unstable: Callable[[float], bool], low: float, high: float) -> float:
    """The stiffness where ``unstable`` turns true, between a stable ``low`` and an
    unstable ``high`` (N/m), to RELATIVE_TOLERANCE."""
    while high - low > RELATIVE_TOLERANCE * high:
        middle = math.sqrt(low * high)
        if unstable(middle):
            high = middle
        else:
            low = middle
    return 0.5 * (low + high)


def _bracket(unstable: Callable[[float], bool], start: float) -> tuple:
    """(stable, unstable) stiffnesses around the onset, doubling up from ``start``."""
    low = start
    if unstable(low):
        raise StudyNotApplicable(f"the loop is unstable already at {start:g} N/m")
    high = 2 * low
    while not unstable(high):
        low, high = high, 2 * high
        if high > 1e6:
            raise StudyNotApplicable("no onset below 1e6 N/m")
    return low, high


def onset_point(scenario, point: OnsetPoint,
                progress: Optional[Callable[[str], None]] = None) -> Dict:
    """Linear and nonlinear critical stiffness at one operating point (N/m)."""
    start = scenario.haptics.coupling.translational_stiffness[0]

    stable_point, _ = held_still(scenario, point, start)

    def linear_unstable(stiffness):
        changed, _ = held_still(scenario, point, stiffness)
        # Linearized at the equilibrium the stable loop holds (the same at any K).
        M = loop_map(changed, operating_point_from=stable_point)["M"]
        unstable = not stability(M)["stable"]
        if progress is not None:
            progress(f"{point.label}: linear {stiffness:.0f} N/m {'unstable' if unstable else 'stable'}")
        return unstable

    reference = grows(*held_still(scenario, point, start))
    if reference["unstable"]:
        raise StudyNotApplicable(f"{point.label}: the simulated loop is unstable already at the "
                                 f"scenario's {start:g} N/m")

    def nonlinear_unstable(stiffness):
        changed, engaged_s = held_still(scenario, point, stiffness)
        unstable = grows(changed, engaged_s, reference["last_rms_m_s"])["unstable"]
        if progress is not None:
            progress(f"{point.label}: simulated {stiffness:.0f} N/m "
                     f"{'unstable' if unstable else 'stable'}")
        return unstable

    linear = _bisect(linear_unstable, *_bracket(linear_unstable, start))
    # The simulation's search starts from the prediction's bracket, +-30%.
    low, high = 0.7 * linear, 1.3 * linear
    if nonlinear_unstable(low) or not nonlinear_unstable(high):
        low, high = _bracket(nonlinear_unstable, start)
    nonlinear = _bisect(nonlinear_unstable, low, high)
    return {"label": point.label, "control_rate_hz": point.control_rate_hz
            or scenario.control_rate_hz,
            "damping_n_s_m": scenario.haptics.coupling.translational_damping[0]
            * point.damping_scale,
            "linear_critical_stiffness_n_m": linear,
            "simulated_critical_stiffness_n_m": nonlinear,
            "tracker_latency_s": point.tracker_latency_s or scenario.device.tracker.latency_s,
            "relative_difference": abs(nonlinear - linear) / nonlinear}


def onset_study(scenario, points: List[OnsetPoint] = DEFAULT_POINTS, *, workers: int = 1,
                scheduler: Optional[str] = None) -> List[Dict]:
    """``onset_point`` at each point, a job each (``analysis/parallel.py``: ``workers``,
    ``scheduler``), each step of its searches reported as it ends; a point where
    there is no onset to find (unstable from the start) is reported with the reason."""
    return map_jobs(onset_job, [(scenario_yaml(scenario), point) for point in points],
                    workers=workers, scheduler=scheduler, description="onset points").results


def onset_job(job) -> Dict:
    """``onset_point`` for ``job`` = (the scenario's YAML text, point), or why there
    is none."""
    text, point = job
    scenario = scenario_from_yaml(text)
    try:
        return onset_point(scenario, point, progress=report)
    except StudyNotApplicable as reason:
        return {"label": point.label, "not_found": str(reason)}
