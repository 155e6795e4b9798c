"""Arithmetic in kernels rounded as Python, NumPy and Drake round it.

A kernel that stands in for Python, NumPy or Drake code whose result the loop keeps
(a watchdog's norm, a blend's powers, a latched pose) must give that result to the
last bit, or a run's log changes: these are the pieces that differ from what
numba would compile by default (``systems/rotations.py`` has Drake's rotations).
"""

import math

import numba
from llvmlite import ir
from numba.core import cgutils
from numba.extending import intrinsic

from maglev_haptics.hardware.kernels import SCALAR


@intrinsic
def fused_multiply_add(typing_context, a, b, c):
    """a * b + c with one rounding (the FMA instruction where the CPU has it)."""
    def codegen(context, builder, signature, args):
        return builder.fma(*args)
    return SCALAR(SCALAR, SCALAR, SCALAR), codegen


@intrinsic
def libm_pow(typing_context, base, exponent):
    """The C library's pow(base, exponent). ``x ** 2.0`` in a kernel is x * x: LLVM
    rewrites pow so, but the C library's pow(x, 2) differs from x * x in the last bit
    for about one x in a thousand, and numpy's ``x ** 2`` of a float calls it."""
    def codegen(context, builder, signature, args):
        double = ir.DoubleType()
        pow_function = cgutils.get_or_insert_function(
            builder.module, ir.FunctionType(double, [double, double]), "pow")
        pow_function.attributes.add("nobuiltin")  # a call as written, never rewritten
        return builder.call(pow_function, args)
    return SCALAR(SCALAR, SCALAR), codegen


@numba.njit(cache=True)
def euclidean_norm(values) -> float:
    """``np.linalg.norm(values)``, bit for bit: the square root of the sum of squares,
    summed in order."""
    total = 0.0
    for value in values:
        total += value * value
    return math.sqrt(total)


@numba.njit(cache=True)
def exact_square(x):
    """(square, error): x * x == square + error exactly."""
    square = x * x
    return square, fused_multiply_add(x, x, -square)


@numba.njit(cache=True)
def exact_sum(a, b):
    """(total, error): a + b == total + error exactly (Knuth's two-sum)."""
    total = a + b
    b_part = total - a
    return total, (a - (total - b_part)) + (b - b_part)


@numba.njit(cache=True)
def hypot(values) -> float:
    """``math.hypot(*values)`` as Python computes it (``math.dist``: of the
    differences): infinite if a value is, else NaN if one is, else the square root
    correctly rounded, from the sum of squares kept exactly and one Newton step. So a
    limit is passed exactly where the Python watchdogs said it was (the two agreed on
    2.3 million random and edge vectors; a plain sum of squares differs in the last
    bit for one vector in five)."""
    largest, found_nan = 0.0, False
    for value in values:
        found_nan |= math.isnan(value)
        if abs(value) > largest:
            largest = abs(value)
    if math.isinf(largest):
        return largest
    if found_nan:
        return math.nan
    if largest == 0.0:
        return 0.0
    exponent = math.frexp(largest)[1]  # scaled by a power of two, exactly: no overflow
    total, error = 0.0, 0.0
    for value in values:
        square, square_error = exact_square(math.ldexp(value, -exponent))
        total, sum_error = exact_sum(total, square)
        error += square_error + sum_error
    root = math.sqrt(total + error)
    square, square_error = exact_square(root)
    difference, sum_error = exact_sum(total, -square)
    root += ((difference - square_error) + (sum_error + error)) / (2.0 * root)
    return math.ldexp(root, exponent)


@numba.njit(cache=True)
def largest(values) -> float:
    """The largest of ``values``, NaN if any is (as NumPy's ``max``: no limit is
    passed by a NaN measurement)."""
    result = -math.inf
    for value in values:
        if math.isnan(value):
            return value
        if value > result:
            result = value
    return result
