"""Wall-clock cost of a call, for the benchmarks."""

import time


def time_per_call_us(function, n: int, windows: int = 1) -> float:
    """Microseconds per call of ``function()`` over ``n`` calls after one warm-up call;
    the best of ``windows`` such runs, as this host's load comes and goes."""
    function()
    best = float("inf")
    for _ in range(windows):
        start = time.perf_counter()
        for _ in range(n):
            function()
        best = min(best, time.perf_counter() - start)
    return 1e6 * best / n
