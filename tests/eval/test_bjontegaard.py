"""Bjøntegaard deltas: closed-form cases, published worked examples (VCEG-M33 cubic) and an independent
transcription of the spreadsheet PCHIP integral."""

from __future__ import annotations

import math

import numpy as np
import pytest

from stgc.eval.bjontegaard import METHODS, BDError, bd_psnr, bd_rate

ANCHOR_RATE = [100.0, 180.0, 330.0, 600.0]
ANCHOR_PSNR = [30.0, 32.1, 33.9, 35.2]


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("factor", [0.5, 0.8, 1.37])
def test_rate_scaled_curve_gives_exactly_that_factor(method: str, factor: float) -> None:
    test_rate = [r * factor for r in ANCHOR_RATE]
    assert bd_rate(ANCHOR_RATE, ANCHOR_PSNR, test_rate, ANCHOR_PSNR, method) == pytest.approx(
        (factor - 1) * 100, abs=1e-9)


@pytest.mark.parametrize("method", METHODS)
def test_psnr_offset_gives_exactly_that_offset(method: str) -> None:
    shifted = [q + 0.37 for q in ANCHOR_PSNR]
    assert bd_psnr(ANCHOR_RATE, ANCHOR_PSNR, ANCHOR_RATE, shifted, method) == pytest.approx(0.37, abs=1e-9)
    assert bd_rate(ANCHOR_RATE, ANCHOR_PSNR, ANCHOR_RATE, ANCHOR_PSNR, method) == pytest.approx(0)


@pytest.mark.parametrize("method", METHODS)
def test_log_linear_curve_closed_form(method: str) -> None:
    # PSNR = a + b ln R. Scaling rates by k shifts it by -b ln k at equal rate, and equal PSNR needs k x rate.
    a, b, k = 10.0, 3.0, 1.6
    rates = np.array([50.0, 90.0, 200.0, 410.0, 800.0])
    psnr = a + b * np.log(rates)
    assert bd_psnr(rates, psnr, rates * k, psnr, method) == pytest.approx(-b * math.log(k), abs=1e-9)
    assert bd_rate(rates, psnr, rates * k, psnr, method) == pytest.approx((k - 1) * 100, abs=1e-9)


# Two published curve pairs (the Matlab File Exchange "bjontegaard" sample and the FAU-LMS package's
# "Test 1"), with VCEG-M33 BD-rates as evaluated independently in a third-party test suite.
SAMPLE_1 = ([686.76, 309.58, 157.11, 85.95], [40.28, 37.18, 34.24, 31.42],
            [893.34, 407.8, 204.93, 112.75], [40.39, 37.21, 34.17, 31.24])
TEST_1 = ([9487.76, 4593.60, 2486.44, 1358.24], [40.037, 38.615, 36.845, 34.851],
          [9787.80, 4469.00, 2451.52, 1356.24], [40.121, 38.651, 36.970, 34.987])


def test_published_worked_examples_cubic() -> None:
    assert bd_rate(*SAMPLE_1, method="cubic") == pytest.approx(31.397374054908013, abs=1e-8)
    assert bd_rate(*TEST_1, method="cubic") == pytest.approx(-4.420462706090111, abs=1e-8)


def _pchip_slopes(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Fritsch-Carlson slopes with the three-point shape-preserving ends (the JCT-VC spreadsheet's pchip)."""
    h = np.diff(x)
    delta = np.diff(y) / h
    n = len(x)
    d = np.zeros(n)
    for k in range(1, n - 1):
        if delta[k - 1] * delta[k] > 0:
            w1, w2 = 2 * h[k] + h[k - 1], h[k] + 2 * h[k - 1]
            d[k] = (w1 + w2) / (w1 / delta[k - 1] + w2 / delta[k])

    def end(h1: float, h2: float, d1: float, d2: float) -> float:
        s = ((2 * h1 + h2) * d1 - h1 * d2) / (h1 + h2)
        if s * d1 <= 0:
            return 0.0
        if d1 * d2 < 0 and abs(s) > abs(3 * d1):
            return 3 * d1
        return s

    d[0] = end(h[0], h[1], delta[0], delta[1])
    d[-1] = end(h[-1], h[-2], delta[-1], delta[-2])
    return d


def _hermite_integral(x: np.ndarray, y: np.ndarray, lo: float, hi: float, samples: int = 200_001) -> float:
    """Integrate the Hermite interpolant numerically (Simpson on a fine grid): independent of scipy's pchip."""
    d = _pchip_slopes(x, y)
    t = np.linspace(lo, hi, samples)
    k = np.clip(np.searchsorted(x, t, side="right") - 1, 0, len(x) - 2)
    h = x[k + 1] - x[k]
    s = (t - x[k]) / h
    h00, h10, h01, h11 = 2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s, -2 * s**3 + 3 * s**2, s**3 - s**2
    v = h00 * y[k] + h10 * h * d[k] + h01 * y[k + 1] + h11 * h * d[k + 1]
    dt = (hi - lo) / (samples - 1)
    return float(dt / 3 * (v[0] + v[-1] + 4 * v[1:-1:2].sum() + 2 * v[2:-1:2].sum()))


def _reference_pchip_bd_rate(ra, qa, rt, qt) -> float:
    ia, it = np.argsort(qa), np.argsort(qt)
    qa, la = np.asarray(qa)[ia], np.log(np.asarray(ra))[ia]
    qt, lt = np.asarray(qt)[it], np.log(np.asarray(rt))[it]
    lo, hi = max(qa[0], qt[0]), min(qa[-1], qt[-1])
    diff = (_hermite_integral(qt, lt, lo, hi) - _hermite_integral(qa, la, lo, hi)) / (hi - lo)
    return (math.exp(diff) - 1) * 100


@pytest.mark.parametrize("curves", [SAMPLE_1, TEST_1])
def test_pchip_matches_an_independent_hermite_integral(curves: tuple) -> None:
    assert bd_rate(*curves, method="pchip") == pytest.approx(_reference_pchip_bd_rate(*curves), abs=1e-7)
    # The two interpolators agree to a few hundredths of a percent on these well-behaved curves.
    assert bd_rate(*curves, method="pchip") == pytest.approx(bd_rate(*curves, method="cubic"), abs=0.05)


def test_two_point_pchip_is_linear() -> None:
    # Through two points pchip is the straight line, so BD-PSNR is the mean vertical gap of two segments.
    ra, qa = [100.0, 400.0], [30.0, 34.0]
    rt, qt = [100.0, 400.0], [31.0, 34.0]
    assert bd_psnr(ra, qa, rt, qt) == pytest.approx(0.5, abs=1e-12)


def test_errors_explain_themselves() -> None:
    with pytest.raises(BDError, match="do not overlap"):
        bd_rate([1, 2], [30, 31], [3, 4], [40, 41])
    with pytest.raises(BDError, match="at least 4"):
        bd_rate([1, 2, 3], [30, 31, 32], [1, 2, 3], [30, 31, 32], method="cubic")
    with pytest.raises(BDError, match="at least 2"):
        bd_psnr([1], [30], [1, 2], [30, 31])
    with pytest.raises(BDError, match="positive"):
        bd_rate([0, 2], [30, 31], [1, 2], [30, 31])
    with pytest.raises(BDError, match="repeated"):
        bd_rate([1, 2, 3], [30, 30, 31], [1, 2, 3], [30, 30.5, 31])
    with pytest.raises(BDError, match="test: not an RD curve: PSNR falls from 35 to 33 as the rate rises from 2 to 3"):
        bd_rate([1, 2, 3, 4], [30, 32, 34, 36], [1, 2, 3, 4], [30, 35, 33, 36])  # gave -2.37 % without a word
    with pytest.raises(BDError, match="repeated"):  # two points at one rate: named as such, not as a fall
        bd_psnr([1, 2, 2, 3], [30, 32, 31, 33], [1, 2, 3, 4], [30, 31, 32, 33])
    with pytest.raises(BDError, match="anchor: not an RD curve"):
        bd_psnr([4, 1, 2], [30, 31, 32], [1, 2, 3], [30, 31, 32])  # the order given does not matter; the rates' does
    with pytest.raises(BDError, match="unknown"):
        bd_rate([1, 2], [30, 31], [1, 2], [30, 31], method="akima")  # type: ignore[arg-type]
