"""numba kernels of SSIM: the zero-padded separable blur of many planes at once (planes in parallel), and the fused
per-pixel SSIM terms with their partial derivatives (the training loss's forward and backward)."""

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
        # Both passes run the taps in the outer loop and the pixels of a row in the inner one, a contiguous
        # multiply-add; each output still sums its taps in ascending order. The inner loops index with unsigned
        # integers: a signed index makes numba emit its negative-index wraparound on every access, which keeps LLVM
        # from vectorising the loop (measured 4-6x slower).
        rows = np.zeros((h, w), dtype=src.dtype)
        for i in range(h):
            dst = rows[i]
            line = src[p, i]
            for t in range(k):
                wt = taps[t]
                shift = t - r
                for j in range(max(0, -shift), min(w, w - shift)):
                    dst[np.uint64(j)] += wt * line[np.uint64(j + shift)]
        for i in range(h):
            target = out[p, i]
            for j in range(w):
                target[np.uint64(j)] = 0
            for t in range(max(0, r - i), min(k, h + r - i)):
                wt = taps[t]
                line = rows[i + t - r]
                for j in range(w):
                    target[np.uint64(j)] += wt * line[np.uint64(j)]


@njit(cache=True, nogil=True, parallel=True)
def ssim_terms(moments: np.ndarray, c1: float, c2: float, want_grad: bool, partials: np.ndarray) -> np.ndarray:
    """Per plane, the sum of the SSIM map over its pixels (float64), from the blurred moments
    [5, P, H, W] = (mu_x, mu_y, E[x^2], E[y^2], E[xy]). With want_grad, partials [3, P, H, W] receives dS/dmu_x,
    dS/dE[x^2] and dS/dE[xy] of every pixel (mu_y and E[y^2] belong to the reference: no gradient).

    S = A1 B1 / (A2 B2) with A1 = 2 mu_x mu_y + C1, B1 = 2 cov + C2, A2 = mu_x^2 + mu_y^2 + C1,
    B2 = var_x + var_y + C2, so dS/dmu_x = 2 mu_y (B1 - A1) / (A2 B2) - 2 mu_x A1 B1 (B2 - A2) / (A2 B2)^2,
    dS/dE[x^2] = -A1 B1 / (A2 B2^2), dS/dE[xy] = 2 A1 / (A2 B2) (no division by B1, which can be 0)."""
    _, planes, h, w = moments.shape
    sums = np.zeros(planes, dtype=np.float64)
    dtype = moments.dtype.type
    one, two = dtype(1.0), dtype(2.0)
    k1, k2 = dtype(c1), dtype(c2)
    for p in prange(planes):
        total = 0.0
        for i in range(h):
            for j in range(w):
                mx = moments[0, p, i, j]
                my = moments[1, p, i, j]
                mxx = mx * mx
                myy = my * my
                mxy = mx * my
                a1 = two * mxy + k1
                b1 = two * (moments[4, p, i, j] - mxy) + k2
                a2 = mxx + myy + k1
                b2 = (moments[2, p, i, j] - mxx) + (moments[3, p, i, j] - myy) + k2
                inv_den = one / (a2 * b2)
                s = a1 * b1 * inv_den
                total += s
                if want_grad:
                    partials[0, p, i, j] = two * my * (b1 - a1) * inv_den - two * mx * s * (b2 - a2) / (a2 * b2)
                    partials[1, p, i, j] = -s / b2
                    partials[2, p, i, j] = two * a1 * inv_den
        sums[p] = total
    return sums


@njit(cache=True, nogil=True, parallel=True)
def ssim_input_grad(blurred: np.ndarray, x: np.ndarray, y: np.ndarray, scale: float, out: np.ndarray) -> None:
    """out = scale (B(dS/dmu_x) + 2 x B(dS/dE[x^2]) + y B(dS/dE[xy])): the chain rule through mu_x = B(x),
    E[x^2] = B(x^2), E[xy] = B(x y), with B the (self-adjoint) blur; blurred [3, P, H, W], x, y, out [P, H, W]."""
    planes, h, w = x.shape
    k = x.dtype.type(scale)
    two = x.dtype.type(2.0)
    for p in prange(planes):
        for i in range(h):
            for j in range(w):
                out[p, i, j] = k * (blurred[0, p, i, j] + two * x[p, i, j] * blurred[1, p, i, j]
                                    + y[p, i, j] * blurred[2, p, i, j])
