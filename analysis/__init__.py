"""Offline studies of the haptic loop (`maglev analyze`: studies.py, one module per study),
the run's metrics and plots, and its log on disk (``load_run_log``)."""

from maglev_haptics.analysis.run_log import load_run_log  # noqa: F401  (DESIGN.md section 8)
