"""Pure-PyTorch tile-vectorised compositing: device-agnostic (CPU, CUDA, ...), autograd supplies the backward.

Tiles are sorted by their intersection count and processed in groups of GROUP tiles, each padded to the group's
longest list with a dummy zero-opacity Gaussian. Within a group the depth-sorted lists are consumed in chunks of CHUNK
Gaussians as dense [G, pixels, CHUNK] tensors; transmittance is carried across chunks and a group stops as soon as
every pixel in it has terminated. Per-group activation checkpointing bounds memory (the chunk loop is recomputed in
the backward). Semantics are identical to the numba kernels (see _numba_kernels.composite_forward)."""

from __future__ import annotations

import torch
from torch import Tensor
from torch.utils.checkpoint import checkpoint

from .projection import tile_grid

TILE_SIZE = 16
GROUP = 8
CHUNK = 64


def _render_group(pix: Tensor, inside: Tensor, ids: Tensor, means2d: Tensor, conics: Tensor, opac: Tensor,
                  colors: Tensor, depths: Tensor, alpha_max: float, alpha_min: float, t_min: float, want_depth: bool,
                  want_weights: bool) -> tuple[Tensor, Tensor, Tensor, Tensor]:  # fmt: skip
    """pix [G,P,2] pixel centres, inside [G,P] (False for the padding pixels of border tiles), ids [G,K] Gaussian
    ids (padding = dummy index). Returns color [G,P,C], T [G,P], median depth [G,P] (zeros unless want_depth) and
    the contribution weights summed over pixels [G,K] (empty unless want_weights)."""
    G, P, _ = pix.shape
    K = ids.shape[1]
    dtype, device = means2d.dtype, means2d.device
    T = torch.ones(G, P, dtype=dtype, device=device)
    # Pixels beyond the image border start "done": they must not contribute weights or delay the group's stop.
    done = ~inside
    out = torch.zeros(G, P, colors.shape[1], dtype=dtype, device=device)
    depth = torch.zeros(G, P, dtype=dtype, device=device)
    weight_sums = []
    zero = torch.zeros((), dtype=dtype, device=device)
    for k0 in range(0, K, CHUNK):
        chunk = ids[:, k0 : k0 + CHUNK]
        m = means2d[chunk]
        cn = conics[chunk]
        dx = m[:, None, :, 0] - pix[:, :, None, 0]  # [G,P,k]
        dy = m[:, None, :, 1] - pix[:, :, None, 1]
        a, b, c = cn[..., 0][:, None], cn[..., 1][:, None], cn[..., 2][:, None]
        sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
        alpha = torch.clamp(opac[chunk][:, None] * torch.exp(-sigma), max=alpha_max)
        valid = (sigma >= 0) & (alpha >= alpha_min)
        alpha = torch.where(valid, alpha, zero)
        one_minus = 1 - alpha
        T_after = T[..., None] * torch.cumprod(one_minus, -1)
        # Exclusive stop: a Gaussian that would take T to <= t_min, and everything behind it, is not composited.
        included = (T_after > t_min) & ~done[..., None]
        T_before = torch.cat([T[..., None], T_after[..., :-1]], -1)
        w = torch.where(included, alpha * T_before, zero)
        out = out + torch.einsum("gpk,gkc->gpc", w, colors[chunk])
        with torch.no_grad():
            if want_depth:
                crossing = included & (T_before >= 0.5) & (T_after < 0.5)
                depth = depth + (crossing.to(dtype) * depths[chunk][:, None, :]).sum(-1)
            if want_weights:
                weight_sums.append(w.detach().sum(1))
        done = done | (valid & ~included).any(-1)
        T = T * torch.where(included, one_minus, torch.ones((), dtype=dtype, device=device)).prod(-1)
        if bool(done.all()):
            break
    weights = torch.cat(weight_sums, 1) if weight_sums else torch.zeros(G, 0, dtype=dtype, device=device)
    return out, T, depth, weights


def composite_torch(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    colors: Tensor,
    depths: Tensor,
    offsets: Tensor,
    flat: Tensor,
    width: int,
    height: int,
    tile_size: int,
    alpha_max: float,
    alpha_min: float,
    t_min: float,
    want_depth: bool,
    want_weights: bool,
    use_checkpoint: bool = True,
) -> tuple[Tensor, Tensor, Tensor | None, Tensor | None]:
    """Same contract as numba_backend.composite_numba: (color, final T, median depth | None, weights | None)."""
    device, dtype = means2d.device, means2d.dtype
    N, C = colors.shape
    tiles_x, tiles_y = tile_grid(width, height, tile_size)
    n_tiles = tiles_x * tiles_y
    # Index N is a dummy Gaussian with zero opacity that pads every group's lists to the same length.
    means2d_p = torch.cat([means2d, means2d.new_zeros(1, 2)])
    conics_p = torch.cat([conics, conics.new_zeros(1, 3)])
    opac_p = torch.cat([opacities, opacities.new_zeros(1)])
    colors_p = torch.cat([colors, colors.new_zeros(1, C)])
    depths_p = torch.cat([depths.to(dtype), depths.new_zeros(1, dtype=dtype)])
    counts = offsets[1:] - offsets[:-1]
    order = torch.argsort(counts, descending=True)
    counts_sorted = counts[order].tolist()
    ys, xs = torch.meshgrid(
        torch.arange(tile_size, device=device), torch.arange(tile_size, device=device), indexing="ij"
    )
    local = torch.stack([xs.reshape(-1), ys.reshape(-1)], -1).to(dtype) + 0.5  # [P,2]
    P = tile_size * tile_size
    outs, trans, deps, tiles_done = [], [], [], []
    weights = torch.zeros(N + 1, dtype=dtype, device=device) if want_weights else None
    for g0 in range(0, n_tiles, GROUP):
        K = int(counts_sorted[g0])
        if K == 0:
            break  # tiles are sorted by count: the rest are empty
        tiles = order[g0 : g0 + GROUP]
        ar = torch.arange(K, device=device)
        pos = offsets[tiles][:, None] + ar[None]
        in_list = ar[None] < counts[tiles][:, None]
        ids = torch.where(in_list, flat[pos.clamp(max=max(flat.numel() - 1, 0))], torch.full_like(pos, N))
        origin = torch.stack([tiles % tiles_x, torch.div(tiles, tiles_x, rounding_mode="floor")], -1).to(dtype)
        pix = local[None] + origin[:, None, :] * tile_size
        inside = (pix[..., 0] < width) & (pix[..., 1] < height)
        args = (pix, inside, ids, means2d_p, conics_p, opac_p, colors_p, depths_p, alpha_max, alpha_min, t_min,
                want_depth, want_weights)  # fmt: skip
        if use_checkpoint and torch.is_grad_enabled():
            o, T, d, w = checkpoint(_render_group, *args, use_reentrant=False)
        else:
            o, T, d, w = _render_group(*args)
        outs.append(o)
        trans.append(T)
        deps.append(d)
        tiles_done.append(tiles)
        if weights is not None:
            weights.index_add_(0, ids[:, : w.shape[1]].reshape(-1), w.detach().reshape(-1))
    color = means2d.new_zeros(n_tiles, P, C)
    final_T = means2d.new_ones(n_tiles, P)
    depth = means2d.new_zeros(n_tiles, P)
    if outs:
        tiles_cat = torch.cat(tiles_done)
        color = color.index_copy(0, tiles_cat, torch.cat(outs))
        final_T = final_T.index_copy(0, tiles_cat, torch.cat(trans))
        depth = depth.index_copy(0, tiles_cat, torch.cat(deps))
    elif torch.is_grad_enabled():
        # Nothing was composited: keep the inputs on the graph so their gradients are zeros (as with numba), not None;
        # through nan_to_num, since 0 x NaN (a culled Gaussian's overflowed conic) would turn the image into NaN.
        link = sum(x.nan_to_num(0.0, 0.0, 0.0).sum() for x in (means2d, conics, opacities, colors))
        color = color + 0.0 * link

    def to_image(x: Tensor) -> Tensor:
        rest = x.shape[2:]
        x = x.reshape((tiles_y, tiles_x, tile_size, tile_size) + rest).transpose(1, 2)
        return x.reshape((tiles_y * tile_size, tiles_x * tile_size) + rest)[:height, :width]

    return (
        to_image(color),
        to_image(final_T),
        to_image(depth).detach() if want_depth else None,
        weights[:N] if weights is not None else None,
    )
