"""The kernels' exp(-s): a polynomial in float32 (so that it vectorises), exact in float64."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from stgc.render._numba_kernels import exp_neg


@njit(cache=False)
def _apply(s):
    out = np.empty_like(s)
    for i in range(s.shape[0]):
        out[i] = exp_neg(s[i])
    return out


def test_float32_exp_neg_is_within_1e_5_relative_of_exp_where_alpha_can_pass():
    # alpha >= 1/255 needs exp(-s) >= 1/255 at opacity <= 1, i.e. s <= 5.55; checked well beyond that.
    s = np.linspace(0.0, 12.0, 200_001, dtype=np.float32)
    approx = _apply(s).astype(np.float64)
    exact = np.exp(-s.astype(np.float64))
    assert np.max(np.abs(approx / exact - 1.0)) < 1e-5


def test_float32_exp_neg_clamps_outside_its_range():
    s = np.array([-3.0, 0.0, 16.0, 40.0, np.inf], dtype=np.float32)
    out = _apply(s)
    assert out[0] == out[1] and abs(out[1] - 1.0) < 1e-6  # negative s is treated as 0 (the kernels skip it)
    assert out[3] == out[2] == out[4] and 0.0 < out[2] < 2e-7  # exp(-16) = 1.1e-7: below any alpha threshold


def test_float64_exp_neg_is_exact():
    # Against libm's exp (math.exp), which numba's float64 path calls: numpy's own exp is a SIMD implementation on
    # some CPUs (AVX-512) and differs from libm in the last bit there.
    s = np.linspace(-2.0, 30.0, 1001)
    assert np.array_equal(_apply(s), np.array([math.exp(-x) for x in s]))
