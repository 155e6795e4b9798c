"""The machine's own pacing floor: the slots a loop misses that does nothing but burn a
fixed compute each tick, paced by the very code that paces a diagram
(``runner.advance_paced``: the same release, spin, priority and gaps).

A paced diagram cannot miss fewer slots than this loop misses at the diagram's own
compute: what this loop misses is the machine's (a virtual machine's host taking the
core for milliseconds, the scheduler), not the diagram's. ``maglev bench`` gives it
beside every paced figure, and as a yardstick of the machine at half a slot's load.
"""

import time
from typing import Dict

from tqdm import tqdm

from maglev_haptics.diagrams.runner import PacedTicks, advance_paced, realtime_report

HALF_LOAD_S = 0.5e-3  # the yardstick's compute a tick (s): half of a 1 ms slot
YARDSTICK_DURATION_S = 10.0  # the yardstick's length (s): 10,000 slots, 0.01 % a slot


class BusyTicks:
    """What ``advance_paced`` paces, in place of a Simulator: each ``AdvanceTo`` spins
    one core for ``compute_s`` (s) and moves the clock; its context is itself."""

    def __init__(self, compute_s: float):
        self._compute_s = float(compute_s)
        self._time_s = 0.0

    def get_context(self) -> "BusyTicks":
        return self

    def get_time(self) -> float:
        return self._time_s

    def AdvanceTo(self, time_s: float) -> None:
        end = time.perf_counter() + self._compute_s
        while time.perf_counter() < end:
            pass
        self._time_s = time_s


def host_pacing(duration_s: float, compute_us: float, *, tick_s: float = 1e-3,
                progress: bool = False, label: str = "host alone") -> Dict:
    """Pace ``BusyTicks`` of ``compute_us`` (us) a tick for ``duration_s`` (s) at
    real time, as ``maglev run --realtime 1.0`` paces a diagram: the ``realtime``
    block of a run's summary (slots missed, compute percentiles, priority), with
    ``compute_us`` added."""
    if not 0.0 <= compute_us:
        raise ValueError(f"compute_us = {compute_us!r}: must be >= 0 (us)")
    n_ticks = int(round(duration_s / tick_s))
    if n_ticks < 1:
        raise ValueError(f"duration_s = {duration_s!r}: must hold at least one tick of "
                         f"{tick_s} s")
    ticks = PacedTicks(n_ticks, tick_s)
    with tqdm(total=float(duration_s), unit="s", disable=not progress, desc=label) as bar:
        advance_paced(BusyTicks(1e-6 * compute_us), duration_s, tick_s, ticks, bar)
    return {**realtime_report(ticks.times()), "compute_us": float(compute_us)}
