"""runtime.float_xp: each function gives, for Python floats, the double NumPy's ufunc of the same
name gives for float64 arrays (the controller's float path relies on it: tests/test_controller.py
compares the whole law)."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from runtime import float_xp

SPECIAL = [0.0, -0.0, 1.0, -1.0, 2.5, math.inf, -math.inf, math.nan]


def _same(a, b) -> bool:
    """The same double: equal bits (zeros' signs, NaN equal to NaN)."""
    return np.float64(a).tobytes() == np.float64(b).tobytes()


@pytest.mark.parametrize("name", ["maximum", "minimum"])
def test_maximum_and_minimum_are_numpys(name):
    for a, b in itertools.product(SPECIAL, SPECIAL):
        want = getattr(np, name)(np.full(4, a), np.full(4, b))[0]
        assert _same(getattr(float_xp, name)(a, b), want), (a, b)


def test_clip_is_numpys_with_array_bounds():
    for x, lo, hi in itertools.product(SPECIAL, SPECIAL, SPECIAL):
        want = np.clip(np.full(4, x), np.full(4, lo), np.full(4, hi))[0]
        assert _same(float_xp.clip(x, lo, hi), want), (x, lo, hi)


@pytest.mark.parametrize("name", ["sign", "abs", "isfinite", "sqrt"])
def test_unary_functions_are_numpys(name):
    for x in SPECIAL:
        with np.errstate(invalid="ignore"):  # sqrt of a negative: NaN, as float_xp's
            want = getattr(np, name)(np.full(4, x))[0]
        got = getattr(float_xp, name)(x)
        assert (got == want) if name == "isfinite" else _same(got, want), x


def test_sqrt_is_numpys_over_every_magnitude():
    """Correctly rounded on both sides, so equal bits: random doubles from subnormal to 1e300,
    exact squares and their neighbours, and negatives (NaN, the same bits as NumPy's)."""
    rng = np.random.default_rng(7)
    x = np.concatenate([10.0 ** rng.uniform(-320, 300, 20000), rng.uniform(0, 10, 5000),
                        np.arange(1, 2000, dtype=float) ** 2])
    x = np.concatenate([x, np.nextafter(x, 0), np.nextafter(x, np.inf), -x[:100], [5e-324, -5e-324, 2.0 ** -1074]])
    with np.errstate(invalid="ignore"):
        want = np.sqrt(x)
    got = np.array([float_xp.sqrt(v) for v in x.tolist()])
    assert got.tobytes() == want.tobytes()


def test_where_selects_and_inf_is_inf():
    assert float_xp.where(True, 1.0, 2.0) == 1.0 and float_xp.where(False, 1.0, 2.0) == 2.0
    assert float_xp.inf == np.inf
