"""What reads a diagram or a run's log rather than flying one: a run's log on disk
(``load_run_log``), its summary and plots (``run_results.py``), the offline studies of
the haptic loop (``maglev analyze``: studies.py, one module per study), benchmarks, the
fault campaign and sweeps, and where their jobs run."""

from maglev_haptics.analysis.run_log import load_run_log  # noqa: F401  (DESIGN.md section 8)
