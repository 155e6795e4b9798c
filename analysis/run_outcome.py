"""What happened to the instrument in a run that injected no fault: one line, and an
exit code.

A scenario whose ``faults`` and ``occlusions`` are empty means the instrument to
fly its script. If a fault still latched (tracking lost past the grace, the
boundary left, over-speed, over-current or over-temperature), the run says what
and when in one line ("the instrument was lost" where the sensor's fault is among
them), each fault with its time, and what it knows of why: the markers' longest silence on
an LCM station, the messages the link refused, a lease lost to another
application, the ticks the loop missed; ``maglev run`` then exits with
``EXIT_INSTRUMENT_LOST``. Runs with injected faults (and the fault campaign) are
judged by their own checks instead: ``maglev run`` says in one line which faults
latched, when, and where the instrument came down, and exits 0.

A device that went silent (``station.device_silent`` in the summary: its process
killed, its host gone) stopped the run without a landing; that is what its line
says, with or without injected faults, and ``maglev run`` exits with
``EXIT_INSTRUMENT_LOST``: the faults that latched as its messages stopped (the
markers gone, so the sensor out of range) follow from it and are not its cause.
"""

from __future__ import annotations

from typing import Dict, List, Optional, Tuple

import numpy as np

from maglev_haptics.diagrams.lcm_station import silence_sentence
from maglev_haptics.systems.device_supervisor import (
    FAULT_COIL_OVER_CURRENT, FAULT_COIL_OVER_TEMPERATURE, FAULT_OVER_SPEED,
    FAULT_SENSOR_OUT_OF_RANGE)

EXIT_DEVICE_IN_USE = 4  # maglev run: another application holds the device's lease
EXIT_INSTRUMENT_LOST = 5  # maglev run: a fault latched in a run that injected none,
# or the device went silent

FAULT_NAMES = {FAULT_SENSOR_OUT_OF_RANGE: "sensor out of range",
               FAULT_COIL_OVER_TEMPERATURE: "coil over-temperature",
               FAULT_COIL_OVER_CURRENT: "coil over-current", FAULT_OVER_SPEED: "over-speed"}


def latched_faults(log: Dict[str, np.ndarray]) -> List[Tuple[float, str]]:
    """(time it latched, s; its name) of each fault that latched in the run, in order."""
    if "fault_bits" not in log:
        return []
    bits = np.asarray(log["fault_bits"]).astype(np.int64)
    t = np.asarray(log["t"])
    return sorted((float(t[np.argmax(bits & bit)]), name) for bit, name in FAULT_NAMES.items()
                  if np.any(bits & bit))


def injected_faults_outcome(scenario, summary: Dict, log: Dict[str, np.ndarray],
                            label: str) -> Optional[str]:
    """In a run of ``scenario`` that injected faults, one line saying which latched and
    when, and where the instrument came down; None when it injected none, or none latched."""
    firsts = latched_faults(log)
    if not injects_faults(scenario) or not firsts:
        return None
    faults = ", ".join(f"{name} at {when:.3f} s" for when, name in firsts)
    touchdown = summary.get("touchdown")
    down = ("; touchdown at {time_s:.3f} s, {speed_m_s:.3f} m/s".format(**touchdown)
            if touchdown is not None and touchdown["time_s"] >= firsts[0][0] else "")
    return f"{label}: the injected faults latched {faults}{down}"


def injects_faults(scenario) -> bool:
    """Whether the scenario injects a fault (a ``faults`` entry or an occlusion)."""
    return bool(scenario.faults) or bool(scenario.occlusions)


def device_cuts_sentence(summary: Dict) -> Optional[str]:
    """How often a device on LCM turned the coils off on its command timeout (summary's
    ``station.device_cut_coils``), in words; None when it never did."""
    cuts = (summary.get("station") or {}).get("device_cut_coils") or {}
    if not cuts.get("times"):
        return None
    times = "once" if cuts["times"] == 1 else f"{cuts['times']} times"
    return (f"the device cut the coils {times} from {cuts['first_at_s']:.3f} s, "
            f"the longest {cuts['longest_ms']:.0f} ms (no command within its "
            f"{1e3 * cuts['command_timeout_s']:g} ms timeout)")


def device_silent_outcome(summary: Dict, label: str) -> Optional[str]:
    """One line saying that the device went silent, when, on which channels and for how
    long, and when the run stopped; None when it was heard to the end."""
    silent = (summary.get("station") or {}).get("device_silent")
    if not silent:
        return None
    return silence_sentence(silent, label, summary["duration_s"])


def instrument_outcome(scenario, summary: Dict, log: Dict[str, np.ndarray],
                       label: str) -> Optional[str]:
    """One line saying when and how the instrument was lost, or a fault latched, in a
    run of ``scenario`` that injected no fault; None when none latched (or the
    scenario injected one). A device that went silent is said first, injected
    faults or not (``device_silent_outcome``)."""
    silent = device_silent_outcome(summary, label)
    if silent is not None:
        return silent
    firsts = latched_faults(log)
    if injects_faults(scenario) or not firsts:
        return None
    at_s = firsts[0][0]
    what = ("the instrument was lost" if any(name == FAULT_NAMES[FAULT_SENSOR_OUT_OF_RANGE]
                                             for _, name in firsts)
            else "a fault latched")
    faults = ", ".join(name if when == at_s else f"{name} at {when:.3f} s"
                       for when, name in firsts)
    reasons = []
    station = summary.get("station")
    if station is not None:
        markers = station.get("channels", {}).get("markers", {})
        if markers.get("stale_gaps"):
            reasons.append(f"markers stale {markers['stale_gaps']} times, the longest "
                           f"silence {markers['longest_gap_ms']:.0f} ms")
        cuts = device_cuts_sentence(summary)
        if cuts is not None:
            reasons.append(cuts)
        if station.get("messages_refused"):
            refused = ", ".join(f"{count} {reason}" for reason, count in
                                station["refused"].items() if count)
            reasons.append(f"the link refused {station['messages_refused']} messages "
                           f"({refused})")
        lost_to = station.get("lease", {}).get("lost_to")
        if lost_to:
            reasons.append(f"the device's lease went to {lost_to}")
    realtime = summary.get("realtime")
    if realtime and realtime.get("deadline_misses"):
        reasons.append(f"the application missed {100 * realtime['miss_fraction']:.0f}% of "
                       f"its ticks (longest stall {realtime['longest_stall_ms']:.0f} ms)")
    touchdown = summary.get("touchdown")
    if touchdown is not None and touchdown.get("time_s", -1.0) >= at_s:
        reasons.append(f"touchdown at {touchdown['speed_m_s']:.3f} m/s")
    because = f": {'; '.join(reasons)}" if reasons else ""
    return f"{label}: {what} at {at_s:.3f} s ({faults}){because}"
