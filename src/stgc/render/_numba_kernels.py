"""Numba CPU kernels: tile binning, front-to-back compositing and its hand-written backward.

Kernels are generic over float32/float64: every floating constant comes in through the `consts` array (same dtype as
the data), because a Python float literal would silently promote float32 arithmetic to float64 in numba.
consts = [0.5, 1.0, alpha_max, alpha_min, transmittance_min, 0.0].

Per-Gaussian data is packed row-wise in `gdata` [N, 8] so one Gaussian's data is contiguous:
    0 mean x, 1 mean y, 2 conic a, 3 conic b, 4 conic c, 5 opacity, 6 sigma cutoff (binning), 7 depth.
Work is split by tile (`prange` over `tile_order`, see interleaved_tiles): a tile's pixels are owned by one thread,
so image writes never race. Per-Gaussian accumulations (gradients, importance weights) go to per-thread rows indexed
by `numba.get_thread_id()` and are summed afterwards.
"""

from __future__ import annotations

import numba
import numpy as np
from numba import njit, prange, types
from numba.extending import overload

HALF, ONE, ALPHA_MAX, ALPHA_MIN, T_MIN, ZERO = range(6)
GX, GY, GA, GB, GC, GO, GCUT, GDEPTH = range(8)
# Columns of the per-Gaussian gradient rows: d/d(mean x, mean y, conic a, b, c, opacity), then d/d(features).
N_GEOM_GRADS = 6


@njit(parallel=True, cache=True, nogil=True)
def pack_gaussians(means2d, conics, opacities, depths, alpha_min, sigma_margin, gdata):
    """gdata[g] = (mean x, y, conic a, b, c, opacity, sigma cutoff, depth), in gdata's dtype. The cutoff,
    log(255 max(o, alpha_min)) + margin in float64, is the sigma above which o exp(-sigma) < 1/255 for certain
    (the margin covers float32's exp and log rounding): what binning tests tiles against."""
    for g in prange(gdata.shape[0]):
        gdata[g, GX] = means2d[g, 0]
        gdata[g, GY] = means2d[g, 1]
        gdata[g, GA] = conics[g, 0]
        gdata[g, GB] = conics[g, 1]
        gdata[g, GC] = conics[g, 2]
        gdata[g, GO] = opacities[g]
        gdata[g, GCUT] = np.log(max(np.float64(opacities[g]), alpha_min) * 255.0) + sigma_margin
        gdata[g, GDEPTH] = depths[g]


@njit(cache=True, nogil=True, inline="always")
def _reaches_tile(gdata, g, x0, x1, y0, y1):
    """Whether some pixel centre in [x0, x1] x [y0, y1] has sigma <= the Gaussian's cutoff, i.e. could get
    alpha >= 1/255. sigma is a quadratic form in the offset from the mean, so along the segment from the mean to any
    point p it grows as t^2 sigma(p): if p in the rectangle has sigma <= cutoff (>= 0), so does the point where that
    segment enters the rectangle, which lies on an edge that faces the mean (the left edge if the mean is left of it,
    and so on: one edge or two). That needs a and c > 0 only, not a c > b^2, so it holds for a conic that float32
    rounding left without a c > b^2 too (tested). Along an edge sigma is a 1-D quadratic with a positive leading
    coefficient, minimised in closed form and clamped. Exact (never drops a pixel the compositor would use): the box
    of pixel centres contains every centre."""
    mx = gdata[g, GX]
    my = gdata[g, GY]
    left = mx < x0
    right = mx > x1
    above = my < y0
    below = my > y1
    if not (left or right or above or below):
        return True
    a = gdata[g, GA]
    b = gdata[g, GB]
    c = gdata[g, GC]
    cut = gdata[g, GCUT]
    for edge in range(4):
        if edge < 2:
            if not (left if edge == 0 else right):
                continue
            dx = mx - (x0 if edge == 0 else x1)
            dy = -b * dx / c if c > 0 else 0.0
            dy = min(max(dy, my - y1), my - y0)
        else:
            if not (above if edge == 2 else below):
                continue
            dy = my - (y0 if edge == 2 else y1)
            dx = -b * dy / a if a > 0 else 0.0
            dx = min(max(dx, mx - x1), mx - x0)
        # The compositor evaluates sigma in float32, where these terms can cancel (a c close to b^2): a margin
        # relative to their size (float32's epsilon is 1.2e-7) keeps every tile it would draw in.
        terms = 0.5 * (abs(a) * dx * dx + abs(c) * dy * dy) + abs(b * dx * dy)
        if 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy <= cut + 1e-6 * terms:
            return True
    return False


@njit(cache=True, nogil=True, inline="always")
def _has_a_tile(radii, g):
    """Whether Gaussian g gets tiles at all: the one rule of bin_tiles and of the depth order it is given."""
    return radii[g, 0] > 0 or radii[g, 1] > 0


@njit(parallel=True, cache=True, nogil=True)
def bin_tiles(gdata, radii, order, width, height, tile_size, n_chunks):
    """Tile binning: returns (offsets [T+1] int64, flat_ids [M] int32), each tile's list sorted by depth.

    A Gaussian's candidate tiles are its screen box [floor((m - r) / ts), ceil((m + r) / ts)) (gsplat's rule); of
    those, only tiles its alpha >= 1/255 ellipse actually reaches are kept (_reaches_tile). The ellipse meets a row
    of tiles in one run of them (it is convex, and so is its part inside the row's band of pixel centres), so each
    row's run is found by testing tiles from the box's two ends inwards, and kept as (first, last): no tile is tested
    twice, tiles inside a run not at all, and the memory goes with the box's rows, not its area (a long thin
    Gaussian's box holds many more tiles than it reaches). `order` lists the ids of every Gaussian with radii > 0
    (it may leave out the others) by increasing depth, and every pass runs in that order over buffers laid out by
    depth rank, so that the stable counting sort by tile reads them front to back, in `n_chunks` (the thread count)
    runs of about as many pairs each: every tile's list comes out depth-sorted without sorting the M pairs."""
    tiles_x = (width + tile_size - 1) // tile_size
    tiles_y = (height + tile_size - 1) // tile_size
    n_tiles = tiles_x * tiles_y
    m = order.shape[0]
    rect = np.zeros((m, 4), dtype=np.int64)
    row_start = np.zeros(m + 1, dtype=np.int64)
    for k in prange(m):
        g = order[k]
        if not _has_a_tile(radii, g):
            continue
        rx = radii[g, 0]
        ry = radii[g, 1]
        mx = gdata[g, GX] / tile_size
        my = gdata[g, GY] / tile_size
        rect[k, 0] = min(max(np.floor(mx - rx / tile_size), 0), tiles_x)
        rect[k, 1] = min(max(np.floor(my - ry / tile_size), 0), tiles_y)
        rect[k, 2] = min(max(np.ceil(mx + rx / tile_size), 0), tiles_x)
        rect[k, 3] = min(max(np.ceil(my + ry / tile_size), 0), tiles_y)
        if rect[k, 2] > rect[k, 0]:
            row_start[k + 1] = rect[k, 3] - rect[k, 1]
    for k in range(m):
        row_start[k + 1] += row_start[k]
    runs = np.empty((row_start[m], 2), dtype=np.int32)  # per box row: first and last tile column reached
    kept = np.zeros(m, dtype=np.int64)
    for k in prange(m):
        g = order[k]
        count = 0
        for r in range(row_start[k + 1] - row_start[k]):
            ty = rect[k, 1] + r
            y0 = ty * tile_size + 0.5
            y1 = min(ty * tile_size + tile_size, height) - 0.5
            first = rect[k, 0]
            last = rect[k, 2] - 1
            while first <= last and not _reaches_tile(gdata, g, first * tile_size + 0.5,
                                                      min(first * tile_size + tile_size, width) - 0.5, y0, y1):
                first += 1
            while last > first and not _reaches_tile(gdata, g, last * tile_size + 0.5,
                                                     min(last * tile_size + tile_size, width) - 0.5, y0, y1):
                last -= 1
            runs[row_start[k] + r, 0] = first
            runs[row_start[k] + r, 1] = last
            count += max(last - first + 1, 0)
        kept[k] = count
    total = 0
    for k in range(m):
        total += kept[k]
    n_chunks = max(1, min(n_chunks, total))
    per_chunk = (total + n_chunks - 1) // n_chunks if total else 0
    chunk_start = np.empty(n_chunks + 1, dtype=np.int64)
    chunk_start[n_chunks] = m
    c = 0
    pairs = 0
    for k in range(m):
        while c < n_chunks and pairs >= c * per_chunk:
            chunk_start[c] = k
            c += 1
        pairs += kept[k]
    while c < n_chunks:
        chunk_start[c] = m
        c += 1
    # Each chunk counts its pairs per tile; a chunk's pairs of a tile go after the earlier chunks' (so the sort
    # stays stable: depth order within each tile).
    cursor = np.zeros((n_chunks, n_tiles), dtype=np.int64)
    for c in prange(n_chunks):
        for k in range(chunk_start[c], chunk_start[c + 1]):
            for r in range(row_start[k + 1] - row_start[k]):
                row = (rect[k, 1] + r) * tiles_x
                for tx in range(runs[row_start[k] + r, 0], runs[row_start[k] + r, 1] + 1):
                    cursor[c, row + tx] += 1
    offsets = np.zeros(n_tiles + 1, dtype=np.int64)
    for t in range(n_tiles):
        at = offsets[t]
        for c in range(n_chunks):
            count = cursor[c, t]
            cursor[c, t] = at
            at += count
        offsets[t + 1] = at
    flat = np.empty(total, dtype=np.int32)
    for c in prange(n_chunks):
        for k in range(chunk_start[c], chunk_start[c + 1]):
            g = order[k]
            for r in range(row_start[k + 1] - row_start[k]):
                row = (rect[k, 1] + r) * tiles_x
                for tx in range(runs[row_start[k] + r, 0], runs[row_start[k] + r, 1] + 1):
                    t = row + tx
                    flat[cursor[c, t]] = g
                    cursor[c, t] += 1
    return offsets, flat


@njit(cache=True, nogil=True)
def ids_with_a_tile(radii):
    """Ids of the Gaussians with radii > 0 on some axis (those bin_tiles bins), ascending. One pass; numpy's
    (radii > 0).any(axis=1) takes 0.8 ms at 50k, serial time the second thread cannot share."""
    n = radii.shape[0]
    ids = np.empty(n, dtype=np.int64)
    count = 0
    for g in range(n):
        if _has_a_tile(radii, g):
            ids[count] = g
            count += 1
    return ids[:count].copy()


RADIX_BITS = 11


@njit(cache=True, nogil=True)
def radix_argsort(keys, ids):
    """`ids` ordered by `keys` (unsigned integers), stable: an LSD radix sort, 11 bits a pass (3 passes for 32-bit
    keys, 6 for 64-bit). About 9x faster than numpy's stable argsort on 50k 32-bit keys, which is a merge sort."""
    n = keys.shape[0]
    src_keys = keys.copy()
    src_ids = ids.copy()
    dst_keys = np.empty_like(src_keys)
    dst_ids = np.empty_like(src_ids)
    buckets = 1 << RADIX_BITS
    mask = np.uint64(buckets - 1)
    counts = np.empty(buckets, dtype=np.int64)
    for p in range((keys.itemsize * 8 + RADIX_BITS - 1) // RADIX_BITS):
        shift = np.uint64(p * RADIX_BITS)
        counts[:] = 0
        for j in range(n):
            counts[np.int64((np.uint64(src_keys[j]) >> shift) & mask)] += 1
        total = 0
        for b in range(buckets):
            c = counts[b]
            counts[b] = total
            total += c
        for j in range(n):
            bucket = np.int64((np.uint64(src_keys[j]) >> shift) & mask)
            at = counts[bucket]
            dst_keys[at] = src_keys[j]
            dst_ids[at] = src_ids[j]
            counts[bucket] = at + 1
        src_keys, dst_keys = dst_keys, src_keys
        src_ids, dst_ids = dst_ids, src_ids
    return src_ids


# Each pixel walks its tile's depth-sorted list; the per-entry work is split into passes over list entries so that
# everything but the transmittance recursion runs as loops LLVM vectorises (8 float32 lanes with AVX2): alpha of a
# run of entries (positions, conic, opacity and the exponential), the colour sums, and in the backward the per-entry
# gradients. Only T's recursion (and dL/dalpha's, which depends on what lies behind) stays scalar. So that those
# loops read memory with unit stride, a tile's list is copied into per-thread scratch transposed: geometry [8, L]
# and colours [C, L]. The forward copies it in chunks of GATHER_CHUNK entries on demand (pixels stop early, so
# entries no pixel reaches are never copied) and computes alpha a chunk at a time.
GATHER_CHUNK = 32


def exp_neg(s: float) -> float:
    """exp(-s), for the kernels: float32 by a polynomial that vectorises, float64 exactly (see the overload)."""
    return float(np.exp(-s))


# exp(-s) = q(s/16)**16 with q a degree-6 fit of exp(-u) on [0, 1] (relative error 4e-7; 6e-6 after float32
# rounding and the four squarings), s clamped to [0, 16] (exp(-16) = 1.1e-7: far below any alpha threshold). libm's
# expf is a call LLVM cannot vectorise: measured, the forward 1.5x and the backward 1.3x faster with this on
# panoptic at 640x360 (benchmarks/RESULTS.md). Forward and backward call the same function, so alpha, the list of
# contributors and the recovered transmittances agree between them exactly. float64 (gradient checks) stays exact.
_EXP_NEG_COEFFICIENTS = (9.99999975e-01, -9.99997857e-01, 4.99968531e-01, -1.66488382e-01, 4.11733757e-02,
                         -7.61110495e-03, 8.34911545e-04)


@overload(exp_neg, inline="always")
def _exp_neg_overload(s):
    if not (isinstance(s, types.Float) and s.bitwidth == 32):
        return lambda s: np.exp(-s)
    c0, c1, c2, c3, c4, c5, c6 = (np.float32(c) for c in _EXP_NEG_COEFFICIENTS)
    zero, limit, scale = np.float32(0.0), np.float32(16.0), np.float32(1.0 / 16.0)

    def fast(s):
        u = min(max(s, zero), limit) * scale
        q = ((((((c6 * u + c5) * u + c4) * u + c3) * u + c2) * u + c1) * u + c0)
        q = q * q
        q = q * q
        q = q * q
        return q * q

    return fast


@njit(cache=True, nogil=True, inline="always")
def _gather(gdata, colors, flat, start, lo, hi, geometry, local_colors):
    """geometry[:, k] = gdata[g, 0:8], local_colors[:, k] = colors[g, :] for entries k in [lo, hi), g = flat[start + k]."""
    n_colors = colors.shape[1]
    for k in range(lo, hi):
        g = flat[start + k]
        for f in range(8):
            geometry[f, k] = gdata[g, f]
        for c in range(n_colors):
            local_colors[c, k] = colors[g, c]


@njit(cache=True, nogil=True, inline="always")
def _alphas(geometry, lo, hi, pcx, pcy, consts, alphas, gaussians):
    """alphas[k] for entries k in [lo, hi) at pixel centre (pcx, pcy), gsplat's rule: min(alpha_max, o exp(-sigma)),
    0 when sigma < 0 or alpha < alpha_min. With `gaussians` (size > 0, for the backward): exp(-sigma) where alpha
    passes it on (0 where the entry is skipped or the alpha_max clamp binds: no gradient reaches o or sigma)."""
    half = consts[HALF]
    alpha_max = consts[ALPHA_MAX]
    alpha_min = consts[ALPHA_MIN]
    zero = consts[ZERO]
    with_gaussians = gaussians.shape[0] > 0
    # Unsigned indices: with a signed one numba wraps negative indices on every access, which keeps LLVM from
    # vectorising the loop (1.3x on the forward kernel, measured).
    gx, gy, ga, gb, gc, go = geometry[GX], geometry[GY], geometry[GA], geometry[GB], geometry[GC], geometry[GO]
    for i in range(lo, hi):
        k = np.uint64(i)
        dx = gx[k] - pcx
        dy = gy[k] - pcy
        sigma = half * (ga[k] * dx * dx + gc[k] * dy * dy) + gb[k] * dx * dy
        G = exp_neg(sigma)
        raw = go[k] * G
        alpha = min(alpha_max, raw)
        keep = (sigma >= zero) & (alpha >= alpha_min)
        alphas[k] = alpha if keep else zero
        if with_gaussians:
            gaussians[k] = G if keep & (raw <= alpha_max) else zero


# Reassociation lets LLVM split the sum into vector lanes; it applies to this function's instructions only.
@njit(cache=True, nogil=True, fastmath={"reassoc"})
def _dot(a, b, n):
    s = a[0] * b[0]
    for i in range(1, n):
        s += a[np.uint64(i)] * b[np.uint64(i)]
    return s


def interleaved_tiles(n_tiles: int, n_threads: int) -> np.ndarray:
    """The order the compositing kernels' parallel loops take the tiles in: tiles 0, T, 2T, ..., then 1, T + 1, ...
    (T threads). numba's default (static) schedule hands each thread one contiguous block of a `prange`, so each
    thread gets every T-th tile of the image instead of one band of it. A real scene's work is far from even across
    bands (sky, floor, the subject): in a panoptic training view the top half of the tiles held 31 % of the
    backward's work, and the 2-thread backward took 19.7 ms with bands, 18.2 ms interleaved (31 ms on one thread)."""
    return np.concatenate([np.arange(j, n_tiles, n_threads, dtype=np.int64) for j in range(max(n_threads, 1))])


@njit(parallel=True, cache=True, nogil=True)
def composite_forward(
    gdata, colors, offsets, flat, centers_x, centers_y, tile_size, tiles_x, consts, tile_order,
    want_depth, want_weights, out_color, out_trans, out_last, out_depth, weights_rows,
    scratch_geometry, scratch_colors, scratch_entries,
):  # fmt: skip
    """Front-to-back compositing per pixel with gsplat's rules.

    alpha = min(alpha_max, o exp(-sigma)); skipped when sigma < 0 or alpha < alpha_min; the pixel stops *before* a
    Gaussian that would take T to <= T_MIN (exclusive, as the CUDA kernels). Writes color (no background), the final
    T, the index one past the last contributor (for the backward), optionally the median depth (depth of the
    contributor that takes T from >= 0.5 to < 0.5; 0 where T never drops below 0.5) and per-Gaussian sum of
    alpha*T over pixels. Scratch per thread (L = the longest tile list): geometry [8, L], colours [C, L], and
    [2, L] for each entry's alpha and weight alpha*T."""
    height = centers_y.shape[0]
    width = centers_x.shape[0]
    n_colors = colors.shape[1]
    half = consts[HALF]
    one = consts[ONE]
    t_min = consts[T_MIN]
    zero = consts[ZERO]
    no_gaussians = np.empty(0, dtype=colors.dtype)
    n_tiles = offsets.shape[0] - 1
    for i in prange(n_tiles):
        tile = tile_order[i]
        start = offsets[tile]
        n = offsets[tile + 1] - start
        x0 = (tile % tiles_x) * tile_size
        y0 = (tile // tiles_x) * tile_size
        x1 = min(x0 + tile_size, width)
        y1 = min(y0 + tile_size, height)
        thread = numba.get_thread_id()
        geometry = scratch_geometry[thread]
        local_colors = scratch_colors[thread]
        alphas = scratch_entries[thread, 0]
        weights = scratch_entries[thread, 1]
        gathered = 0
        for py in range(y0, y1):
            pcy = centers_y[py]
            for px in range(x0, x1):
                pcx = centers_x[px]
                T = one
                last = 0
                depth = zero
                ready = 0  # alphas[:ready] are this pixel's
                for k in range(n):
                    if k == ready:
                        ready = min(n, ready + GATHER_CHUNK)
                        if ready > gathered:
                            _gather(gdata, colors, flat, start, gathered, ready, geometry, local_colors)
                            gathered = ready
                        _alphas(geometry, k, ready, pcx, pcy, consts, alphas, no_gaussians)
                    alpha = alphas[k]
                    next_T = T * (one - alpha)
                    if next_T <= t_min:
                        break
                    w = alpha * T
                    weights[k] = w
                    if want_depth and T >= half and next_T < half:
                        depth = geometry[GDEPTH, k]
                    if want_weights:
                        weights_rows[thread, flat[start + k]] += w
                    last = k + 1 if alpha > zero else last
                    T = next_T
                for c in range(n_colors):
                    out_color[py, px, c] = _dot(weights, local_colors[c], last) if last > 0 else zero
                out_trans[py, px] = T
                out_last[py, px] = start + last
                if want_depth:
                    out_depth[py, px] = depth


@njit(parallel=True, cache=True, nogil=True)
def composite_backward(
    gdata, colors, offsets, flat, centers_x, centers_y, tile_size, tiles_x, consts, tile_order,
    final_trans, last_ids, grad_color, grad_trans, grad_rows, scratch_geometry, scratch_colors, scratch_grads,
    scratch_entries,
):  # fmt: skip
    """Gradients of (color, final T) w.r.t. means2d, conics, opacities and features, accumulated per thread.

    Walks each pixel's contributors back to front, recovering the transmittance in front of each by division
    (T_j = T_{j+1} / (1 - alpha_j), as the Inria and gsplat CUDA kernels do) and carrying the normalised color
    composited behind it (only its dot product with dL/dcolor is needed). With C_out = sum_j c_j a_j T_j and T_final = prod_j (1 - a_j):
        dC/da_j = T_j (c_j - behind_j),   dT_final/da_j = -T_final / (1 - a_j),
    and a_j = min(alpha_max, o G): no gradient through the clamp when o G > alpha_max.
    A tile's gradients go to per-list-entry columns (scratch_grads [6 + C, L]) and are added to the thread's
    per-Gaussian rows once per tile. scratch_entries per thread: [5, L] (alpha, exp(-sigma), dL/dcolor . c,
    dL/dalpha, weight alpha*T of each entry at the current pixel). grad_rows [threads, N, 6 + C] may come
    uninitialised: they are zeroed here, in parallel (a serial memset of them took 0.85 ms at 50k)."""
    every_row = grad_rows.reshape(-1)
    block = 4096
    for b in prange((every_row.shape[0] + block - 1) // block):
        every_row[b * block : min((b + 1) * block, every_row.shape[0])] = consts[ZERO]
    height = centers_y.shape[0]
    width = centers_x.shape[0]
    n_colors = colors.shape[1]
    n_grads = N_GEOM_GRADS + n_colors
    half = consts[HALF]
    one = consts[ONE]
    zero = consts[ZERO]
    n_tiles = offsets.shape[0] - 1
    for i in prange(n_tiles):
        tile = tile_order[i]
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
        geometry = scratch_geometry[thread]
        local_colors = scratch_colors[thread]
        lgrad = scratch_grads[thread]
        alphas = scratch_entries[thread, 0]
        gaussians = scratch_entries[thread, 1]
        color_dots = scratch_entries[thread, 2]
        d_alphas = scratch_entries[thread, 3]
        weights = scratch_entries[thread, 4]
        _gather(gdata, colors, flat, start, 0, used, geometry, local_colors)
        for f in range(n_grads):
            for k in range(used):
                lgrad[f, k] = zero
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
                # dot(c_k, dL/dpixel color) of every entry, summed in channel order
                g0 = gpix[0]
                for k in range(last):
                    color_dots[k] = g0 * local_colors[0, k]
                for c in range(1, n_colors):
                    gc = gpix[c]
                    for k in range(last):
                        color_dots[k] += gc * local_colors[c, k]
                _alphas(geometry, 0, last, pcx, pcy, consts, alphas, gaussians)
                # The recursion, back to front. A skipped entry has alpha 0: T, behind_dot unchanged, weight 0.
                # behind_dot = dot(color composited behind entry k, dL/dpixel color), carried as a scalar since
                # behind_{k-1} = alpha_k c_k + (1 - alpha_k) behind_k is linear in the colors.
                T_final = final_trans[py, px]
                T = T_final
                behind_dot = zero
                for k in range(last - 1, -1, -1):
                    alpha = alphas[k]
                    inv_one_minus = one / (one - alpha)
                    T = T * inv_one_minus
                    weights[k] = alpha * T
                    col_dot = color_dots[k]
                    d_alphas[k] = (col_dot - behind_dot) * T - g_trans * T_final * inv_one_minus
                    behind_dot = alpha * col_dot + (one - alpha) * behind_dot
                for k in range(last):
                    d_opacity = d_alphas[k] * gaussians[k]
                    d_sigma = -geometry[GO, k] * d_opacity
                    dx = geometry[GX, k] - pcx
                    dy = geometry[GY, k] - pcy
                    lgrad[GO, k] += d_opacity
                    lgrad[GX, k] += d_sigma * (geometry[GA, k] * dx + geometry[GB, k] * dy)
                    lgrad[GY, k] += d_sigma * (geometry[GC, k] * dy + geometry[GB, k] * dx)
                    lgrad[GA, k] += d_sigma * half * dx * dx
                    lgrad[GB, k] += d_sigma * dx * dy
                    lgrad[GC, k] += d_sigma * half * dy * dy
                for c in range(n_colors):
                    gc = gpix[c]
                    for k in range(last):
                        lgrad[N_GEOM_GRADS + c, k] += weights[k] * gc
        for k in range(used):
            g = flat[start + k]
            for f in range(n_grads):
                grad_rows[thread, g, f] += lgrad[f, k]


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
