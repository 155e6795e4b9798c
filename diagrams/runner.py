"""Advance a built diagram: a simulator, optionally paced to the wall clock, with progress."""

from __future__ import annotations

import gc
import time

import numpy as np
from pydrake.systems.analysis import Simulator
from tqdm import tqdm

PROGRESS_CHUNK_S = 0.25  # simulated seconds between progress-bar updates


def simulate(built, duration_s: float, *, realtime_rate: float = 0.0,
             progress: bool = True, label: str = "", interruptible: bool = False):
    """Advance the diagram to ``duration_s``; returns (simulator, wall seconds).
    ``interruptible``: Ctrl-C ends the run early instead of raising."""
    # The diagram lives as long as the run: keep the collector from scanning it every tick.
    gc.collect()
    gc.freeze()
    simulator = Simulator(built.diagram)
    simulator.set_target_realtime_rate(realtime_rate)
    simulator.Initialize()
    chunks = np.append(np.arange(PROGRESS_CHUNK_S, duration_s, PROGRESS_CHUNK_S), duration_s)
    start = time.perf_counter()
    try:
        with tqdm(total=float(duration_s), unit="sim s", disable=not progress, desc=label,
                  bar_format="{l_bar}{bar}| {n:.2f}/{total:.2f} sim s [{elapsed}]") as bar:
            for t in chunks:
                simulator.AdvanceTo(float(t))
                bar.update(float(t) - bar.n)
    except KeyboardInterrupt:
        if not interruptible:
            raise
        # Ctrl-C ends an interactive run early; what was simulated is kept.
    finally:
        gc.unfreeze()  # later runs in this process must be able to collect this one
    return simulator, time.perf_counter() - start


