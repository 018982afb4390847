"""NumPy's elementwise functions for single Python floats: an ``xp`` for code written against an
array module (numpy, jax.numpy), run one element at a time.

runtime.controller writes its law once against ``xp``; the MJX training environment passes
jax.numpy, tests and the zero-period fallback pass numpy, and JointVelocityController.step passes
this module joint by joint (a (4,)-array NumPy call costs about a microsecond, the same float
operation a few tens of nanoseconds). runtime.machine.clearance_violations likewise runs its
flags on the floats of one float64 state (the executor's every tick, every preview step).

Each function returns, for float arguments, the value the NumPy ufunc of the same name returns
for float64 arrays (NumPy 2.4, measured on (1,), (4,) and (16,) arrays): ``maximum``, ``minimum``
and ``clip`` propagate NaN, ``sign`` is 0.0 at zero and NaN at NaN, ``abs`` and ``isfinite`` are
Python's (IEEE-exact), ``sqrt`` is math.sqrt (correctly rounded, as NumPy's) with NumPy's NaN
below zero. Only the sign of a zero may differ from NumPy's: NumPy itself answers
``clip(-0.0, 0.0, 1.0)`` with 0.0 for array bounds and -0.0 for scalar bounds;
tests/test_float_xp.py compares every function with NumPy over zeros of both signs, +-1, +-inf
and NaN (``sqrt`` also over random doubles of every magnitude). Comparisons and ``&`` / ``|``
are Python's on bools. There is no ``exp``: math.exp and NumPy's exp may differ in the last bit,
so the controller takes exponentials from NumPy.
"""

from __future__ import annotations

import builtins
import math

inf = math.inf
isfinite = math.isfinite
abs = builtins.abs


def where(cond: bool, a: float, b: float) -> float:
    """``a`` if ``cond`` else ``b`` (both are evaluated by the caller, as with arrays)."""
    return a if cond else b


def maximum(a: float, b: float) -> float:
    """numpy.maximum: the larger, NaN if either is NaN (on a tie, ``b``, as NumPy's loops)."""
    return a if (a > b or a != a) else b


def minimum(a: float, b: float) -> float:
    """numpy.minimum: the smaller, NaN if either is NaN (on a tie, ``b``, as NumPy's loops)."""
    return a if (a < b or a != a) else b


def clip(x: float, lo: float, hi: float) -> float:
    """numpy.clip with array bounds: minimum(maximum(x, lo), hi), inlined."""
    x = x if (x > lo or x != x) else lo
    return x if (x < hi or x != x) else hi


def sign(x: float) -> float:
    """numpy.sign: 1.0, -1.0, 0.0 at either zero, NaN at NaN."""
    if x > 0:
        return 1.0
    if x < 0:
        return -1.0
    return 0.0 if x == 0 else x


def sqrt(x: float) -> float:
    """numpy.sqrt: math.sqrt for x >= 0 (IEEE 754 square root, correctly rounded, as NumPy's;
    sqrt(-0.0) is -0.0); NaN for x < 0 (where math.sqrt raises) and at NaN. The NaN below zero
    is ``(x - x) * inf``, an invalid operation like NumPy's hardware square root of a negative,
    so it is the processor's default NaN (sign bit set on x86), as NumPy's; NaN stays NaN."""
    return math.sqrt(x) if x >= 0.0 else (x - x) * inf
