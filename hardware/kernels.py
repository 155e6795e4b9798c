"""The compiled kernels of the 1 kHz loop, ready before the clock starts.

A kernel that Python calls is declared with ``@kernel(signature, ...)``: numba
compiles it (or loads it from its on-disk cache) for exactly those argument
types when ``compile_kernels()`` runs, which the runner does before a run's
clock starts. Without it numba would compile on the first call, inside the
loop: seconds for the first tick after an install. The kernels that only other
kernels call are compiled into their callers and need no signature.
"""

from __future__ import annotations

from typing import Callable, List, Optional, Tuple

import numba
from numba import types
from tqdm import tqdm

VECTOR = types.Array(types.float64, 1, "C")
READONLY_VECTOR = types.Array(types.float64, 1, "C", readonly=True)
MATRIX = types.Array(types.float64, 2, "C")
TENSOR3 = types.Array(types.float64, 3, "C")
FLOAT32_VECTOR = types.Array(types.float32, 1, "C")
FLOAT32_TENSOR4 = types.Array(types.float32, 4, "C")
INDEX_VECTOR = types.Array(types.int64, 1, "C")
INDEX_MATRIX = types.Array(types.int64, 2, "C")
UINT32_VECTOR = types.Array(types.uint32, 1, "C")  # indices without the negative-index fixup
MASK_MATRIX = types.Array(types.boolean, 2, "C")
SCALAR = types.float64
INDEX = types.int64
FLAG = types.boolean

PROGRESS_DELAY_S = 1.0  # the progress bar shows only when compiling takes longer

# (dispatcher, argument types) of every declared kernel signature
_DECLARED: List[Tuple[numba.core.registry.CPUDispatcher, tuple]] = []


def kernel(*signatures: tuple, cache: bool = True, **options) -> Callable:
    """``numba.njit`` for a kernel Python calls, compiled by ``compile_kernels``
    for each of ``signatures`` (tuples of numba argument types)."""
    def declare(function):
        dispatcher = numba.njit(cache=cache, **options)(function)
        _DECLARED.extend((dispatcher, tuple(signature)) for signature in signatures)
        return dispatcher
    return declare


def declared_kernels() -> List[Tuple[numba.core.registry.CPUDispatcher, tuple]]:
    """Every (kernel, argument types) declared so far in the imported modules."""
    return list(_DECLARED)


def compile_kernels(progress: bool = True, label: Optional[str] = None) -> int:
    """Compile, or load from numba's cache, every declared kernel signature not yet
    ready in this process; returns how many were. A bar shows after a second."""
    pending = [(dispatcher, signature) for dispatcher, signature in _DECLARED
               if signature not in dispatcher.overloads]
    with tqdm(total=len(pending), desc=label or "compiling kernels", unit="kernel",
              delay=PROGRESS_DELAY_S, disable=not progress or not pending) as bar:
        for dispatcher, signature in pending:
            dispatcher.compile(signature)
            bar.update(1)
    return len(pending)
