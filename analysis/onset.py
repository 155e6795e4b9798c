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

import collections
import dataclasses
import functools
import math
from dataclasses import dataclass
from typing import Callable, Dict, List, Optional

import numpy as np
import scipy.signal

from maglev_haptics.analysis.loop_linearization import loop_map, stability
from maglev_haptics.analysis.loop_studies import StudyNotApplicable
from maglev_haptics.analysis.parallel import report, run_searches
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
MAX_STIFFNESS_N_M = 1e6  # no onset below this: the search gives up


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


def _check_applies(scenario) -> None:
    if scenario.haptics is None or not isinstance(scenario.hand, ScriptedHand):
        raise StudyNotApplicable("the onset needs a scripted hand holding the instrument "
                                 "with haptics on")


def held_still(scenario, point: OnsetPoint, stiffness: float):
    """The scenario at ``point`` with coupling stiffness K on every axis, its hand
    holding still from grip to the end (HOLD_S after haptics is fully on)."""
    _check_applies(scenario)
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


def grew(rms_m_s: List[float], reference_rms_m_s: Optional[float] = None) -> bool:
    """Unstable: the high-passed velocity's RMS (m/s, first and last second) grew by
    GROWTH_RATIO, or (a loop that blew up already while haptics faded in, and sits at
    the force clamp) its last second is above SATURATED_RATIO times
    ``reference_rms_m_s``, a stable run's."""
    first, last = rms_m_s
    return bool(last > GROWTH_RATIO * first
                or (reference_rms_m_s is not None and last > SATURATED_RATIO * reference_rms_m_s))


def grows(scenario, engaged_s: float, reference_rms_m_s: Optional[float] = None) -> Dict:
    """Run the scenario; the high-passed instrument velocity's RMS in the first and
    the last second after settling, and whether it ``grew``. With the passivity
    controller, also the work it withheld (J)."""
    result = run_scenario(scenario, label="onset", progress=False)
    rms = velocity_growth(result.log, engaged_s)
    return {"first_rms_m_s": rms[0], "last_rms_m_s": rms[1],
            "unstable": grew(rms, reference_rms_m_s),
            "passivity_dissipated_j": result.summary.get("passivity_dissipated_j")}


# The searches below are generators for ``parallel.run_searches``: ``unstable`` is a
# generator function that, given stiffnesses (N/m), yields their jobs as a round and
# returns whether each is unstable (a list of bools). Each round speculates as wide as
# ``width()`` allows; the stiffness found is the serial search's, however wide.

def bracket_onset(unstable, start: float, width: Callable[[], int]):
    """(stable, unstable) stiffnesses around the onset (N/m), doubling up from ``start``
    (stable, or there is nothing to find); ``width()`` doublings a round."""
    stiffnesses = [start]
    low = None
    while True:
        while len(stiffnesses) < width() and 2 * stiffnesses[-1] <= MAX_STIFFNESS_N_M:
            stiffnesses.append(2 * stiffnesses[-1])
        for stiffness, is_unstable in zip(stiffnesses, (yield from unstable(stiffnesses))):
            if is_unstable:
                if low is None:
                    raise StudyNotApplicable(f"the loop is unstable already at {start:g} N/m")
                return low, stiffness
            low = stiffness
        if 2 * low > MAX_STIFFNESS_N_M:
            raise StudyNotApplicable(f"no onset below {MAX_STIFFNESS_N_M:g} N/m")
        stiffnesses = [2 * low]


def bisect_onset(unstable, low: float, high: float, width: Callable[[], int]):
    """The stiffness where ``unstable`` turns true between a stable ``low`` and an
    unstable ``high`` (N/m), to RELATIVE_TOLERANCE, bisecting geometrically. A round
    evaluates the first ``width()`` midpoints of the bisection's tree from here: 2^d - 1
    of them decide d steps; one more than a level's decides the next step on one side."""
    known = {}
    while high - low > RELATIVE_TOLERANCE * high:
        middle = math.sqrt(low * high)
        if middle not in known:
            nodes = _bisection_tree(low, high, width())
            known.update(zip(nodes, (yield from unstable(nodes))))
        if known[middle]:
            high = middle
        else:
            low = middle
    return 0.5 * (low + high)


def _bisection_tree(low: float, high: float, count: int) -> List[float]:
    """The first ``count`` midpoints, level by level, that bisection may visit from
    (low, high) (N/m): the next step's, then both of the step after's, ..."""
    nodes: List[float] = []
    intervals = collections.deque([(low, high)])
    while intervals and len(nodes) < count:
        low, high = intervals.popleft()
        if high - low > RELATIVE_TOLERANCE * high:
            middle = math.sqrt(low * high)
            nodes.append(middle)
            intervals.extend([(low, middle), (middle, high)])
    return nodes


def onset_search(text: str, point: OnsetPoint, width: Callable[[], int]):
    """Linear and nonlinear critical stiffness (N/m) at one operating point of the
    scenario (its YAML ``text``), or why there is none: a search whose jobs are
    ``onset_evaluation``'s, each round's steps reported as the round ends."""
    scenario = scenario_from_yaml(text)

    def evaluated(kind: str, stiffnesses: List[float]):
        return (yield [(text, point, kind, stiffness) for stiffness in stiffnesses])

    def reported(kind: str, stiffnesses: List[float], outcomes: List[bool]) -> List[bool]:
        for stiffness, unstable in zip(stiffnesses, outcomes):
            report(f"{point.label}: {kind} {stiffness:.0f} N/m "
                   f"{'unstable' if unstable else 'stable'}")
        return outcomes

    def linear_unstable(stiffnesses: List[float]):
        return reported("linear", stiffnesses,
                        (yield from evaluated("linear", stiffnesses)))

    reference_rms_m_s = None

    def nonlinear_unstable(stiffnesses: List[float]):
        rms = yield from evaluated("simulated", stiffnesses)
        return reported("simulated", stiffnesses, [grew(r, reference_rms_m_s) for r in rms])

    try:
        _check_applies(scenario)
        start = scenario.haptics.coupling.translational_stiffness[0]
        # The stable run the simulated ones are judged against, at the scenario's own
        # stiffness: first, as a loop unstable there has no onset to find.
        (reference,) = yield from evaluated("simulated", [start])
        if grew(reference):
            raise StudyNotApplicable(f"{point.label}: the simulated loop is unstable already "
                                     f"at the scenario's {start:g} N/m")
        reference_rms_m_s = reference[1]
        low, high = yield from bracket_onset(linear_unstable, start, width)
        linear = yield from bisect_onset(linear_unstable, low, high, width)
        # The simulation's search starts from the prediction's bracket, +-30% (one round:
        # both ends are needed unless the lower is unstable).
        low, high = 0.7 * linear, 1.3 * linear
        low_unstable, high_unstable = yield from nonlinear_unstable([low, high])
        if low_unstable or not high_unstable:
            low, high = yield from bracket_onset(nonlinear_unstable, start, width)
        nonlinear = yield from bisect_onset(nonlinear_unstable, low, high, width)
    except StudyNotApplicable as reason:
        return {"label": point.label, "not_found": str(reason)}
    return {"label": point.label, "control_rate_hz": point.control_rate_hz
            or scenario.control_rate_hz,
            "damping_n_s_m": scenario.haptics.coupling.translational_damping[0]
            * point.damping_scale,
            "linear_critical_stiffness_n_m": linear,
            "simulated_critical_stiffness_n_m": nonlinear,
            "tracker_latency_s": point.tracker_latency_s or scenario.device.tracker.latency_s,
            "relative_difference": abs(nonlinear - linear) / nonlinear}


def onset_evaluation(job):
    """One step of ``onset_search`` on a worker: ``job`` = (the scenario's YAML text,
    point, "linear" or "simulated", stiffness N/m). Linear: whether the loop's
    monodromy, linearized at the equilibrium the stable loop holds (the same at any
    stiffness), is unstable. Simulated: the high-passed velocity's RMS (m/s) in the
    first and the last second of the hold."""
    text, point, kind, stiffness = job
    scenario = scenario_from_yaml(text)
    changed, engaged_s = held_still(scenario, point, stiffness)
    if kind == "linear":
        stable_point, _ = held_still(
            scenario, point, scenario.haptics.coupling.translational_stiffness[0])
        return not stability(loop_map(changed, operating_point_from=stable_point)["M"])["stable"]
    result = grows(changed, engaged_s)
    return [result["first_rms_m_s"], result["last_rms_m_s"]]


def onset_study(scenario, points: List[OnsetPoint] = DEFAULT_POINTS, *, workers: int = 1,
                scheduler: Optional[str] = None) -> List[Dict]:
    """``onset_search`` at each point, its evaluations jobs on ``workers`` local
    processes or a Dask ``scheduler``'s workers (``analysis/parallel.py``); with more
    workers than points, each bisection evaluates several levels a round. A point
    where there is no onset to find is reported with the reason."""
    text = scenario_yaml(scenario)
    return run_searches(onset_evaluation,
                        [functools.partial(onset_search, text, point) for point in points],
                        workers=workers, scheduler=scheduler, description="onset points").results
