"""Numba-compiled float64 twins of the loop's scalar-generic numeric functions.

The controller's math is written once with numpy so it runs on float and on
AutoDiffXd arrays (for linearization). numba compiles the very same source for
float64; each twin sees its module's globals, except that the names of the
other functions are bound to their twins, so a function that calls a helper
calls the helper's compiled twin.
"""

import types

import numba


def float64_twins(*functions) -> types.SimpleNamespace:
    """``twins.name`` is the numba-compiled twin of each function named ``name``."""
    namespace = {}
    for function in functions:
        namespace.update(function.__globals__)
    for function in functions:
        rebound = types.FunctionType(function.__code__, namespace, function.__name__,
                                     function.__defaults__)
        namespace[function.__name__] = numba.njit(cache=True)(rebound)
    return types.SimpleNamespace(**{f.__name__: namespace[f.__name__] for f in functions})


def scalar_value(x) -> float:
    """The float value of a float or AutoDiffXd scalar (for branching on it)."""
    return float(x.value()) if hasattr(x, "value") else float(x)
