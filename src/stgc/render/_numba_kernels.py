"""Numba CPU kernels: tile binning, front-to-back compositing and its hand-written backward.

Kernels are generic over float32/float64: every floating constant comes in through the `consts` array (same dtype as
the data), because a Python float literal would silently promote float32 arithmetic to float64 in numba.
consts = [0.5, 1.0, alpha_max, alpha_min, transmittance_min, 0.0].

Per-Gaussian data is packed row-wise in `gdata` [N, 8] so one Gaussian's data is contiguous:
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


@njit(cache=True, nogil=True, inline="always")
def _reaches_tile(gdata, g, x0, x1, y0, y1):
    """Whether some pixel centre in [x0, x1] x [y0, y1] has sigma <= the Gaussian's cutoff, i.e. could get
    alpha >= 1/255. sigma is a convex quadratic, so when the mean is outside the rectangle its minimum over the
    rectangle lies on one of the four edges; each edge is a 1-D quadratic minimised in closed form and clamped.
    Exact (never drops a pixel the compositor would use): the box of pixel centres contains every centre."""
    mx = gdata[g, GX]
    my = gdata[g, GY]
    if x0 <= mx <= x1 and y0 <= my <= y1:
        return True
    a = gdata[g, GA]
    b = gdata[g, GB]
    c = gdata[g, GC]
    cut = gdata[g, GCUT]
    for edge in range(4):
        if edge < 2:
            dx = mx - (x0 if edge == 0 else x1)
            dy = -b * dx / c if c > 0 else 0.0
            dy = min(max(dy, my - y1), my - y0)
        else:
            dy = my - (y0 if edge == 2 else y1)
            dx = -b * dy / a if a > 0 else 0.0
            dx = min(max(dx, mx - x1), mx - x0)
        if 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy <= cut:
            return True
    return False


@njit(parallel=True, cache=True, nogil=True)
def bin_tiles(gdata, radii, order, width, height, tile_size):
    """Tile binning: returns (offsets [T+1] int64, flat_ids [M] int32), each tile's list sorted by depth.

    A Gaussian's candidate tiles are its screen box [floor((m - r) / ts), ceil((m + r) / ts)) (gsplat's rule); of
    those, only tiles its alpha >= 1/255 ellipse actually reaches are kept (_reaches_tile). `order` lists Gaussian
    ids by increasing depth. The (tile, Gaussian) pairs are laid out in depth order (parallel over Gaussians), then
    a stable counting sort by tile makes every tile's list depth-sorted without sorting the M pairs."""
    tiles_x = (width + tile_size - 1) // tile_size
    tiles_y = (height + tile_size - 1) // tile_size
    n_tiles = tiles_x * tiles_y
    n = radii.shape[0]
    rect = np.zeros((n, 4), dtype=np.int64)
    per_gaussian = np.zeros(n, dtype=np.int64)
    for g in prange(n):
        rx = radii[g, 0]
        ry = radii[g, 1]
        if rx <= 0 and ry <= 0:
            continue
        mx = gdata[g, GX] / tile_size
        my = gdata[g, GY] / tile_size
        rect[g, 0] = min(max(np.floor(mx - rx / tile_size), 0), tiles_x)
        rect[g, 1] = min(max(np.floor(my - ry / tile_size), 0), tiles_y)
        rect[g, 2] = min(max(np.ceil(mx + rx / tile_size), 0), tiles_x)
        rect[g, 3] = min(max(np.ceil(my + ry / tile_size), 0), tiles_y)
        count = 0
        for ty in range(rect[g, 1], rect[g, 3]):
            y0 = ty * tile_size + 0.5
            y1 = min(ty * tile_size + tile_size, height) - 0.5
            for tx in range(rect[g, 0], rect[g, 2]):
                x0 = tx * tile_size + 0.5
                x1 = min(tx * tile_size + tile_size, width) - 0.5
                if _reaches_tile(gdata, g, x0, x1, y0, y1):
                    count += 1
        per_gaussian[g] = count
    # Where each Gaussian's pairs start, with Gaussians in depth order.
    first_pair = np.empty(n, dtype=np.int64)
    total = 0
    for k in range(order.shape[0]):
        g = order[k]
        first_pair[g] = total
        total += per_gaussian[g]
    pair_tile = np.empty(total, dtype=np.int32)
    pair_gaussian = np.empty(total, dtype=np.int32)
    for g in prange(n):
        if per_gaussian[g] == 0:
            continue
        i = first_pair[g]
        for ty in range(rect[g, 1], rect[g, 3]):
            y0 = ty * tile_size + 0.5
            y1 = min(ty * tile_size + tile_size, height) - 0.5
            for tx in range(rect[g, 0], rect[g, 2]):
                x0 = tx * tile_size + 0.5
                x1 = min(tx * tile_size + tile_size, width) - 0.5
                if _reaches_tile(gdata, g, x0, x1, y0, y1):
                    pair_tile[i] = ty * tiles_x + tx
                    pair_gaussian[i] = g
                    i += 1
    offsets = np.zeros(n_tiles + 1, dtype=np.int64)
    for i in range(total):
        offsets[pair_tile[i] + 1] += 1
    for t in range(n_tiles):
        offsets[t + 1] += offsets[t]
    cursor = offsets[:n_tiles].copy()
    flat = np.empty(total, dtype=np.int32)
    for i in range(total):
        t = pair_tile[i]
        flat[cursor[t]] = pair_gaussian[i]
        cursor[t] += 1
    return offsets, flat


# Tile lists are copied into per-thread contiguous scratch (one row of 8 + C values per list entry) in chunks of this
# many entries, on demand: pixels walk a prefix of the list (they terminate early), so entries no pixel reaches are
# never gathered, and the per-pixel loops read memory sequentially instead of through flat_ids.
GATHER_CHUNK = 32


@njit(cache=True, nogil=True, inline="always")
def _gather(gdata, colors, flat, start, lo, hi, local):
    """local[k] = [gdata[g, 0:8], colors[g, :]] for list entries k in [lo, hi) (g = flat[start + k])."""
    n_colors = colors.shape[1]
    for k in range(lo, hi):
        g = flat[start + k]
        for f in range(8):
            local[k, f] = gdata[g, f]
        for c in range(n_colors):
            local[k, 8 + c] = colors[g, c]


@njit(parallel=True, cache=True, nogil=True)
def composite_forward(
    gdata, colors, offsets, flat, centers_x, centers_y, tile_size, tiles_x, consts,
    want_depth, want_weights, out_color, out_trans, out_last, out_depth, weights_rows, scratch,
):  # fmt: skip
    """Front-to-back compositing per pixel with gsplat's rules.

    alpha = min(alpha_max, o exp(-sigma)); skipped when sigma < 0 or alpha < alpha_min; the pixel stops *before* a
    Gaussian that would take T to <= T_MIN (exclusive, as the CUDA kernels). Writes color (no background), the final
    T, the index one past the last contributor (for the backward), optionally the median depth (depth of the
    contributor that takes T from >= 0.5 to < 0.5; 0 where T never drops below 0.5) and per-Gaussian sum of
    alpha*T over pixels. scratch: [threads, longest tile list, 8 + C]."""
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
        n = offsets[tile + 1] - start
        x0 = (tile % tiles_x) * tile_size
        y0 = (tile // tiles_x) * tile_size
        x1 = min(x0 + tile_size, width)
        y1 = min(y0 + tile_size, height)
        thread = numba.get_thread_id()
        local = scratch[thread]
        gathered = 0
        acc = np.empty(n_colors, dtype=colors.dtype)
        for py in range(y0, y1):
            pcy = centers_y[py]
            for px in range(x0, x1):
                pcx = centers_x[px]
                T = one
                acc[:] = zero
                last = 0
                depth = zero
                for k in range(n):
                    if k == gathered:
                        gathered = min(n, gathered + GATHER_CHUNK)
                        _gather(gdata, colors, flat, start, k, gathered, local)
                    dx = local[k, GX] - pcx
                    dy = local[k, GY] - pcy
                    sigma = half * (local[k, GA] * dx * dx + local[k, GC] * dy * dy) + local[k, GB] * dx * dy
                    alpha = min(alpha_max, local[k, GO] * np.exp(-sigma))
                    # Branch-free skip (sigma < 0 or alpha < alpha_min -> alpha 0): ~40% of list entries miss a
                    # pixel in no predictable pattern, so a branch here mispredicts more than the exp costs.
                    alpha = alpha if (sigma >= zero) & (alpha >= alpha_min) else zero
                    next_T = T * (one - alpha)
                    if next_T <= t_min:
                        break
                    w = alpha * T
                    for c in range(n_colors):
                        acc[c] += w * local[k, 8 + c]
                    if want_depth and T >= half and next_T < half:
                        depth = local[k, GDEPTH]
                    if want_weights:
                        weights_rows[thread, flat[start + k]] += w
                    last = k + 1 if alpha > zero else last
                    T = next_T
                for c in range(n_colors):
                    out_color[py, px, c] = acc[c]
                out_trans[py, px] = T
                out_last[py, px] = start + last
                if want_depth:
                    out_depth[py, px] = depth


@njit(parallel=True, cache=True, nogil=True)
def composite_backward(
    gdata, colors, offsets, flat, centers_x, centers_y, tile_size, tiles_x, consts,
    final_trans, last_ids, grad_color, grad_trans, grad_rows, scratch, scratch_grads,
):  # fmt: skip
    """Gradients of (color, final T) w.r.t. means2d, conics, opacities and features, accumulated per thread.

    Walks each pixel's contributors back to front, recovering the transmittance in front of each by division
    (T_j = T_{j+1} / (1 - alpha_j), as the Inria and gsplat CUDA kernels do) and carrying the normalised color
    composited behind it (only its dot product with dL/dcolor is needed). With C_out = sum_j c_j a_j T_j and T_final = prod_j (1 - a_j):
        dC/da_j = T_j (c_j - behind_j),   dT_final/da_j = -T_final / (1 - a_j),
    and a_j = min(alpha_max, o G): no gradient through the clamp when o G > alpha_max.
    A tile's gradients go to contiguous per-list-entry rows (scratch_grads) and are added to the thread's
    per-Gaussian rows once per tile."""
    height = centers_y.shape[0]
    width = centers_x.shape[0]
    n_colors = colors.shape[1]
    n_grads = N_GEOM_GRADS + n_colors
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
        # Only the prefix up to the deepest contributor of any pixel in the tile is needed.
        used = 0
        for py in range(y0, y1):
            for px in range(x0, x1):
                used = max(used, last_ids[py, px] - start)
        if used == 0:
            continue
        thread = numba.get_thread_id()
        local = scratch[thread]
        lgrad = scratch_grads[thread]
        _gather(gdata, colors, flat, start, 0, used, local)
        for k in range(used):
            for f in range(n_grads):
                lgrad[k, f] = zero
        gpix = np.empty(n_colors, dtype=colors.dtype)
        for py in range(y0, y1):
            pcy = centers_y[py]
            for px in range(x0, x1):
                last = last_ids[py, px] - start
                if last <= 0:
                    continue
                g_trans = grad_trans[py, px]
                any_grad = g_trans != zero
                for c in range(n_colors):
                    gpix[c] = grad_color[py, px, c]
                    if gpix[c] != zero:
                        any_grad = True
                if not any_grad:
                    continue
                pcx = centers_x[px]
                T_final = final_trans[py, px]
                T = T_final
                # dot(color composited behind entry k, dL/dpixel color): carried as a scalar, since
                # behind_{k-1} = alpha_k c_k + (1 - alpha_k) behind_k is linear in the colors.
                behind_dot = zero
                for k in range(last - 1, -1, -1):
                    dx = local[k, GX] - pcx
                    dy = local[k, GY] - pcy
                    a = local[k, GA]
                    b = local[k, GB]
                    cc = local[k, GC]
                    sigma = half * (a * dx * dx + cc * dy * dy) + b * dx * dy
                    if sigma < zero or sigma > local[k, GCUT]:
                        continue
                    G = np.exp(-sigma)
                    opac = local[k, GO]
                    alpha = min(alpha_max, opac * G)
                    if alpha < alpha_min:
                        continue
                    inv_one_minus = one / (one - alpha)
                    T = T * inv_one_minus
                    w = alpha * T
                    col_dot = zero
                    for c in range(n_colors):
                        gc = gpix[c]
                        lgrad[k, N_GEOM_GRADS + c] += w * gc
                        col_dot += local[k, 8 + c] * gc
                    d_alpha = (col_dot - behind_dot) * T - g_trans * T_final * inv_one_minus
                    behind_dot = alpha * col_dot + (one - alpha) * behind_dot
                    if opac * G <= alpha_max:
                        lgrad[k, GO] += G * d_alpha
                        d_sigma = -opac * G * d_alpha
                        lgrad[k, GX] += d_sigma * (a * dx + b * dy)
                        lgrad[k, GY] += d_sigma * (cc * dy + b * dx)
                        lgrad[k, GA] += d_sigma * half * dx * dx
                        lgrad[k, GB] += d_sigma * dx * dy
                        lgrad[k, GC] += d_sigma * half * dy * dy
        for k in range(used):
            g = flat[start + k]
            for f in range(n_grads):
                grad_rows[thread, g, f] += lgrad[k, f]


@njit(parallel=True, cache=True, nogil=True)
def sum_rows(rows, out):
    """out[n, k] = sum_t rows[t, n, k], parallel over n (the per-thread reduction)."""
    n_threads = rows.shape[0]
    for n in prange(rows.shape[1]):
        for k in range(rows.shape[2]):
            s = rows[0, n, k]
            for t in range(1, n_threads):
                s += rows[t, n, k]
            out[n, k] = s
