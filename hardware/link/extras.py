"""Optional packages behind ``pip install 'maglev-haptics[hardware]'``."""

from __future__ import annotations

import importlib

HARDWARE_EXTRA = "pip install 'maglev-haptics[hardware]'"


class MissingExtraError(ImportError):
    """An optional package a driver needs is not installed: says which and how."""


def require_extra(module: str, purpose: str):
    """``import module``, or a MissingExtraError of one line naming the extra."""
    try:
        return importlib.import_module(module)
    except ImportError:
        raise MissingExtraError(
            f"{purpose} needs the Python package {module!r}, which is not installed: "
            f"{HARDWARE_EXTRA}") from None


class MissingDriverError(OSError):
    """A vendor's driver (not a Python package) is missing on this machine."""
