"""Range checks for configuration values: each failure is a ValueError that names
the field's path, its value and what is allowed (``path = value: allowed``)."""

import math

import numpy as np


def require(ok: bool, path: str, value, allowed: str) -> None:
    if not ok:
        raise ValueError(f"{path} = {value!r}: {allowed}")


def finite(value) -> bool:
    """A finite real number (a Python or numpy int or float, not a bool)."""
    return (isinstance(value, (int, float, np.integer, np.floating))
            and not isinstance(value, bool) and math.isfinite(value))


def positive(path: str, value) -> None:
    require(finite(value) and value > 0, path, value, "must be a finite number > 0")


def nonnegative(path: str, value) -> None:
    require(finite(value) and value >= 0, path, value, "must be a finite number >= 0")


def vector(path: str, value, length: int = 3, positive: bool = False, meaning: str = "") -> None:
    """A list of ``length`` finite numbers, all > 0 when ``positive``; ``meaning`` is
    appended to the message."""
    require(isinstance(value, (list, tuple)) and len(value) == length
            and all(map(finite, value)) and (not positive or all(v > 0 for v in value)),
            path, value,
            f"must be a list of {length} finite numbers{' > 0' if positive else ''}{meaning}")


def each(path: str, value, length: int, check) -> None:
    """A list of ``length`` finite numbers, each passing ``check(path[i], v)``."""
    vector(path, value, length)
    for i, v in enumerate(value):
        check(f"{path}[{i}]", v)
