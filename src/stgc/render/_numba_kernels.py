"""Numba CPU kernels: tile binning, front-to-back compositing and its hand-written backward.

Kernels are generic over float32/float64: every floating constant comes in through the `consts` array (same dtype as
the data), because a Python float literal would silently promote float32 arithmetic to float64 in numba.
consts = [0.5, 1.0, alpha_max, alpha_min, transmittance_min, 0.0].

Per-Gaussian data is packed row-wise in `gdata` [N, 8] so one Gaussian is one cache line:
    0 mean x, 1 mean y, 2 conic a, 3 conic b, 4 conic c, 5 opacity, 6 sigma cutoff, 7 depth.
Work is split by tile (`prange`): a tile's pixels are owned by one thread, so image writes never race. Per-Gaussian
accumulations (gradients, importance weights) go to per-thread rows indexed by `numba.get_thread_id()` and are summed
afterwards.
"""

from __future__ import annotations

import numba
import numpy as np
from numba import njit, prange

HALF, ONE, ALPHA_MAX, ALPHA_MIN, T_MIN, ZERO = range(6)
GX, GY, GA, GB, GC, GO, GCUT, GDEPTH = range(8)
# Columns of the per-Gaussian gradient rows: d/d(mean x, mean y, conic a, b, c, opacity), then d/d(features).
N_GEOM_GRADS = 6


@njit(cache=True)
def bin_tiles(rect, order, n_tiles, tiles_x):
    """Counting sort of tile intersections: returns (offsets [T+1] int64, flat_ids [M] int32).

    rect [N, 4] int64 half-open tile box per Gaussian (empty for culled ones); order: Gaussian ids by increasing depth.
    Filling buckets in depth order makes every tile's list depth-sorted without sorting the M intersections."""
    counts = np.zeros(n_tiles + 1, dtype=np.int64)
    for g in range(rect.shape[0]):
        for ty in range(rect[g, 1], rect[g, 3]):
            for tx in range(rect[g, 0], rect[g, 2]):
                counts[ty * tiles_x + tx + 1] += 1
    for t in range(n_tiles):
        counts[t + 1] += counts[t]
    offsets = counts.copy()
    cursor = counts[:n_tiles].copy()
    flat = np.empty(offsets[n_tiles], dtype=np.int32)
    for k in range(order.shape[0]):
        g = order[k]
        for ty in range(rect[g, 1], rect[g, 3]):
            for tx in range(rect[g, 0], rect[g, 2]):
                t = ty * tiles_x + tx
                flat[cursor[t]] = g
                cursor[t] += 1
    return offsets, flat


@njit(parallel=True, cache=True)
def composite_forward(
    gdata, colors, offsets, flat, centers_x, centers_y, tile_size, tiles_x, consts,
    want_depth, want_weights, out_color, out_trans, out_last, out_depth, weights_rows,
):  # fmt: skip
    """Front-to-back compositing per pixel with gsplat's rules.

    alpha = min(alpha_max, o exp(-sigma)); skipped when sigma < 0 or alpha < alpha_min; the pixel stops *before* a
    Gaussian that would take T to <= T_MIN (exclusive, as the CUDA kernels). Writes color (no background), the final
    T, the index one past the last contributor (for the backward), optionally the median depth (depth of the
    contributor that takes T from >= 0.5 to < 0.5; 0 where T never drops below 0.5) and per-Gaussian sum of
    alpha*T over pixels."""
    height = centers_y.shape[0]
    width = centers_x.shape[0]
    n_colors = colors.shape[1]
    half = consts[HALF]
    one = consts[ONE]
    alpha_max = consts[ALPHA_MAX]
    alpha_min = consts[ALPHA_MIN]
    t_min = consts[T_MIN]
    zero = consts[ZERO]
    n_tiles = offsets.shape[0] - 1
    for tile in prange(n_tiles):
        start = offsets[tile]
        end = offsets[tile + 1]
        x0 = (tile % tiles_x) * tile_size
        y0 = (tile // tiles_x) * tile_size
        x1 = min(x0 + tile_size, width)
        y1 = min(y0 + tile_size, height)
        thread = numba.get_thread_id()
        acc = np.empty(n_colors, dtype=colors.dtype)
        for py in range(y0, y1):
            pcy = centers_y[py]
            for px in range(x0, x1):
                pcx = centers_x[px]
                T = one
                acc[:] = zero
                last = start
                depth = zero
                for j in range(start, end):
                    g = flat[j]
                    dx = gdata[g, GX] - pcx
                    dy = gdata[g, GY] - pcy
                    sigma = half * (gdata[g, GA] * dx * dx + gdata[g, GC] * dy * dy) + gdata[g, GB] * dx * dy
                    # sigma > cutoff implies alpha < alpha_min: skip the exp (exact, see projection.sigma_cutoff).
                    if sigma < zero or sigma > gdata[g, GCUT]:
                        continue
                    alpha = min(alpha_max, gdata[g, GO] * np.exp(-sigma))
                    if alpha < alpha_min:
                        continue
                    next_T = T * (one - alpha)
                    if next_T <= t_min:
                        break
                    w = alpha * T
                    for c in range(n_colors):
                        acc[c] += w * colors[g, c]
                    if want_depth and T >= half and next_T < half:
                        depth = gdata[g, GDEPTH]
                    if want_weights:
                        weights_rows[thread, g] += w
                    T = next_T
                    last = j + 1
                for c in range(n_colors):
                    out_color[py, px, c] = acc[c]
                out_trans[py, px] = T
                out_last[py, px] = last
                if want_depth:
                    out_depth[py, px] = depth


@njit(parallel=True, cache=True)
def composite_backward(
    gdata, colors, offsets, flat, centers_x, centers_y, tile_size, tiles_x, consts,
    final_trans, last_ids, grad_color, grad_trans, grad_rows,
):  # fmt: skip
    """Gradients of (color, final T) w.r.t. means2d, conics, opacities and features, accumulated per thread.

    Walks each pixel's contributors back to front, recovering the transmittance in front of each by division
    (T_j = T_{j+1} / (1 - alpha_j), as the Inria and gsplat CUDA kernels do) and carrying the normalised color
    composited behind it. With C_out = sum_j c_j a_j T_j and T_final = prod_j (1 - a_j):
        dC/da_j = T_j (c_j - behind_j),   dT_final/da_j = -T_final / (1 - a_j),
    and a_j = min(alpha_max, o G): no gradient through the clamp when o G > alpha_max."""
    height = centers_y.shape[0]
    width = centers_x.shape[0]
    n_colors = colors.shape[1]
    half = consts[HALF]
    one = consts[ONE]
    alpha_max = consts[ALPHA_MAX]
    alpha_min = consts[ALPHA_MIN]
    zero = consts[ZERO]
    n_tiles = offsets.shape[0] - 1
    for tile in prange(n_tiles):
        start = offsets[tile]
        x0 = (tile % tiles_x) * tile_size
        y0 = (tile // tiles_x) * tile_size
        x1 = min(x0 + tile_size, width)
        y1 = min(y0 + tile_size, height)
        thread = numba.get_thread_id()
        behind = np.empty(n_colors, dtype=colors.dtype)
        for py in range(y0, y1):
            pcy = centers_y[py]
            for px in range(x0, x1):
                last = last_ids[py, px]
                if last <= start:
                    continue
                g_trans = grad_trans[py, px]
                any_grad = g_trans != zero
                for c in range(n_colors):
                    if grad_color[py, px, c] != zero:
                        any_grad = True
                if not any_grad:
                    continue
                pcx = centers_x[px]
                T_final = final_trans[py, px]
                T = T_final
                behind[:] = zero
                for j in range(last - 1, start - 1, -1):
                    g = flat[j]
                    dx = gdata[g, GX] - pcx
                    dy = gdata[g, GY] - pcy
                    sigma = half * (gdata[g, GA] * dx * dx + gdata[g, GC] * dy * dy) + gdata[g, GB] * dx * dy
                    if sigma < zero or sigma > gdata[g, GCUT]:
                        continue
                    G = np.exp(-sigma)
                    opac = gdata[g, GO]
                    alpha = min(alpha_max, opac * G)
                    if alpha < alpha_min:
                        continue
                    inv_one_minus = one / (one - alpha)
                    T = T * inv_one_minus
                    w = alpha * T
                    d_alpha = zero
                    for c in range(n_colors):
                        gc = grad_color[py, px, c]
                        col = colors[g, c]
                        grad_rows[thread, g, N_GEOM_GRADS + c] += w * gc
                        d_alpha += (col - behind[c]) * gc
                        behind[c] = alpha * col + (one - alpha) * behind[c]
                    d_alpha = d_alpha * T - g_trans * T_final * inv_one_minus
                    if opac * G <= alpha_max:
                        grad_rows[thread, g, GO] += G * d_alpha
                        d_sigma = -opac * G * d_alpha
                        a = gdata[g, GA]
                        b = gdata[g, GB]
                        cc = gdata[g, GC]
                        grad_rows[thread, g, GX] += d_sigma * (a * dx + b * dy)
                        grad_rows[thread, g, GY] += d_sigma * (cc * dy + b * dx)
                        grad_rows[thread, g, GA] += d_sigma * half * dx * dx
                        grad_rows[thread, g, GB] += d_sigma * dx * dy
                        grad_rows[thread, g, GC] += d_sigma * half * dy * dy


@njit(parallel=True, cache=True)
def sum_rows(rows, out):
    """out[n, k] = sum_t rows[t, n, k], parallel over n (the per-thread reduction)."""
    n_threads = rows.shape[0]
    for n in prange(rows.shape[1]):
        for k in range(rows.shape[2]):
            s = rows[0, n, k]
            for t in range(1, n_threads):
                s += rows[t, n, k]
            out[n, k] = s
