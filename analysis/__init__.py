"""Offline studies of the haptic loop: `maglev analyze` (studies.py) and one module per study."""
