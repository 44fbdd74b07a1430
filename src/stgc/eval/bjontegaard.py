"""Bjøntegaard deltas between two rate-distortion curves: BD-rate (%) and BD-PSNR (dB).

Both fit each curve in the (log rate, PSNR) plane, integrate the difference over the range the two curves
share, and average it:
- BD-rate: log-rate as a function of PSNR; the mean log-rate difference d gives (e^d - 1)·100 %, i.e. the
  average extra rate the test curve needs for the same quality (negative = test saves rate).
- BD-PSNR: PSNR as a function of log-rate; the mean difference in dB at equal rate.

Two interpolators:
- "pchip" (default): piecewise cubic Hermite interpolation through the points, integrated exactly; what the
  JCT-VC/JVET common-test-condition spreadsheets use since HEVC (JCTVC-L1100), because a global cubic can
  overshoot between points. Needs >= 2 points per curve.
- "cubic": G. Bjøntegaard, VCEG-M33 (2001): a least-squares cubic polynomial per curve (exact through 4
  points), integrated analytically. Needs >= 4 points per curve.
The log base cancels out, so natural logs are used throughout. Each curve must be an RD curve: PSNR never falls as
the rate rises (a report passes each family's Pareto front).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal, get_args

import numpy as np
from scipy.interpolate import PchipInterpolator

Method = Literal["pchip", "cubic"]
METHODS: tuple[str, ...] = get_args(Method)


class BDError(ValueError):
    """The two curves cannot be compared (too few points, no overlap, repeated values)."""


def _curve(rate: Sequence[float], psnr: Sequence[float], name: str) -> tuple[np.ndarray, np.ndarray]:
    r = np.asarray(rate, dtype=np.float64).ravel()
    q = np.asarray(psnr, dtype=np.float64).ravel()
    if r.shape != q.shape:
        raise BDError(f"{name}: {r.size} rates but {q.size} PSNR values")
    if not np.all(np.isfinite(r)) or not np.all(np.isfinite(q)):
        raise BDError(f"{name}: rates and PSNRs must be finite")
    if np.any(r <= 0):
        raise BDError(f"{name}: rates must be positive")
    # Both fits take the curve as a function (PSNR of rate, and rate of PSNR): a point below an earlier one at more
    # rate is no RD curve, and interpolating through it gave a number without a word.
    order = np.lexsort((q, r))  # by rate, ties by PSNR (equal rates reach the repeated-values check)
    falls = np.flatnonzero(np.diff(q[order]) < 0)
    if falls.size:
        a, b = order[falls[0]], order[falls[0] + 1]
        raise BDError(f"{name}: not an RD curve: PSNR falls from {q[a]:g} to {q[b]:g} as the rate rises from "
                      f"{r[a]:g} to {r[b]:g}; compare the curves' Pareto fronts (what `stgc report` does)")
    return np.log(r), q


def _require_points(method: str, *sizes: int) -> None:
    needed = {"pchip": 2, "cubic": 4}.get(method)
    if needed is None:
        raise BDError(f"unknown BD interpolation {method!r}; expected one of {METHODS}")
    for name, n in zip(("anchor", "test"), sizes):
        if n < needed:
            what = "pchip" if method == "pchip" else "the VCEG-M33 cubic fit"
            raise BDError(f"{name}: {what} needs at least {needed} points, got {n}")


def _mean_over(x: np.ndarray, y: np.ndarray, lo: float, hi: float, method: str, name: str) -> float:
    """Mean of y(x) over [lo, hi] for the curve through (x, y) under the chosen interpolator."""
    order = np.argsort(x)
    x, y = x[order], y[order]
    if np.any(np.diff(x) <= 0):
        raise BDError(f"{name}: repeated values on the interpolation axis; the curve is not a function")
    if method == "pchip":
        if x.size < 2:
            raise BDError(f"{name}: pchip needs at least 2 points, got {x.size}")
        integral = PchipInterpolator(x, y, extrapolate=False).integrate(lo, hi)
    elif method == "cubic":
        if x.size < 4:
            raise BDError(f"{name}: the VCEG-M33 cubic fit needs at least 4 points, got {x.size}")
        antiderivative = np.polyint(np.polyfit(x, y, 3))
        integral = np.polyval(antiderivative, hi) - np.polyval(antiderivative, lo)
    else:
        raise BDError(f"unknown BD interpolation {method!r}; expected one of {METHODS}")
    return float(integral) / (hi - lo)


def _overlap(a: np.ndarray, b: np.ndarray, what: str) -> tuple[float, float]:
    lo, hi = max(a.min(), b.min()), min(a.max(), b.max())
    if not hi > lo:
        raise BDError(f"the two curves do not overlap in {what}; BD deltas are undefined")
    return float(lo), float(hi)


def bd_rate(
    rate_anchor: Sequence[float],
    psnr_anchor: Sequence[float],
    rate_test: Sequence[float],
    psnr_test: Sequence[float],
    method: Method = "pchip",
) -> float:
    """Average rate difference of the test curve vs the anchor at equal PSNR, in percent."""
    log_ra, qa = _curve(rate_anchor, psnr_anchor, "anchor")
    log_rt, qt = _curve(rate_test, psnr_test, "test")
    _require_points(method, qa.size, qt.size)
    lo, hi = _overlap(qa, qt, "PSNR")
    mean_anchor = _mean_over(qa, log_ra, lo, hi, method, "anchor")
    mean_test = _mean_over(qt, log_rt, lo, hi, method, "test")
    return float(np.expm1(mean_test - mean_anchor) * 100.0)


def bd_psnr(
    rate_anchor: Sequence[float],
    psnr_anchor: Sequence[float],
    rate_test: Sequence[float],
    psnr_test: Sequence[float],
    method: Method = "pchip",
) -> float:
    """Average PSNR difference of the test curve vs the anchor at equal rate, in dB."""
    log_ra, qa = _curve(rate_anchor, psnr_anchor, "anchor")
    log_rt, qt = _curve(rate_test, psnr_test, "test")
    _require_points(method, qa.size, qt.size)
    lo, hi = _overlap(log_ra, log_rt, "rate")
    return _mean_over(log_rt, qt, lo, hi, method, "test") - _mean_over(log_ra, qa, lo, hi, method, "anchor")
