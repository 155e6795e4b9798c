"""The kernels' arithmetic gives Python's and NumPy's results to the last bit."""

import math
from fractions import Fraction

import numba
import numpy as np

from maglev_haptics.hardware.exact_arithmetic import (
    euclidean_norm, fused_multiply_add, hypot, largest, libm_pow)

EDGES = ([0.0, 0.0, 0.0], [math.inf, 1.0, 1.0], [-math.inf, math.nan, 1.0], [math.nan, 1.0, 1.0],
         [5e-324, 0.0, 0.0], [1.7e308, 1.7e308, 0.0], [1e-300, 1e-300, 1e-300])


def random_vectors(n=20000, seed=1):
    rng = np.random.default_rng(seed)
    scales = 10.0 ** rng.uniform(-300, 300, (n, 1))
    return rng.standard_normal((n, 3)) * scales * rng.uniform(0, 2, (n, 3))


def same(a, b):
    return a == b or (math.isnan(a) and math.isnan(b))


def test_hypot_is_pythons_correctly_rounded_norm():
    """A plain square root of the sum of squares differs in the last bit for about one
    vector in five: a watchdog's limit would be passed at another sample."""
    for v in list(random_vectors()) + [np.array(e) for e in EDGES]:
        assert same(hypot(v), math.hypot(*v.tolist())), v


def test_euclidean_norm_and_largest_are_numpys():
    for v in list(random_vectors(5000, seed=2)) + [np.array(e) for e in EDGES]:
        with np.errstate(over="ignore"):  # both overflow to inf alike
            numpys = float(np.linalg.norm(v))
        assert same(euclidean_norm(v), numpys), v
        assert same(largest(v), float(np.max(v))), v  # a NaN is the largest


@numba.njit
def _pow_and_fma(x):
    return libm_pow(x, 2.0), fused_multiply_add(x, x, -(x * x))


def test_pow_is_the_c_librarys_and_fma_rounds_once():
    xs = np.random.default_rng(3).uniform(0.0, 1.0, 20000)
    for x in xs.tolist():
        power, error = _pow_and_fma(x)
        assert power == x ** 2  # Python's float power: the C library's pow, as numpy's
        # x * x plus what its rounding dropped is x^2 exactly.
        assert Fraction(x) ** 2 == Fraction(x * x) + Fraction(error)
