"""numba kernel of the SSIM window: a zero-padded separable blur of many planes at once (planes in parallel)."""

from __future__ import annotations

import numpy as np
from numba import njit, prange


@njit(cache=True, nogil=True, parallel=True)
def blur_planes(src: np.ndarray, taps: np.ndarray, out: np.ndarray) -> None:
    """out[p] = taps (x) taps correlated with src[p], zero outside the plane; src, out [N, H, W], taps [K], K odd."""
    n, h, w = src.shape
    k = taps.shape[0]
    r = k // 2
    for p in prange(n):
        rows = np.zeros((h, w), dtype=src.dtype)
        for i in range(h):
            for j in range(w):
                lo = max(0, r - j)
                hi = min(k, w + r - j)
                acc = src.dtype.type(0)
                for t in range(lo, hi):
                    acc += taps[t] * src[p, i, j + t - r]
                rows[i, j] = acc
        for i in range(h):
            lo = max(0, r - i)
            hi = min(k, h + r - i)
            for j in range(w):
                out[p, i, j] = 0
            for t in range(lo, hi):
                wt = taps[t]
                for j in range(w):
                    out[p, i, j] += wt * rows[i + t - r, j]
