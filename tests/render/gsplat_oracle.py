"""Test oracle: gsplat 1.5.3's pure-PyTorch reference pipeline, made to run on CPU.

gsplat's `_torch_impl._rasterize_to_pixels` needs two CUDA-only pieces: the kernel
`_wrapper.rasterize_to_indices_in_range` (which (Gaussian, pixel) pairs contribute, front to back) and nerfacc's packed
scans (`render_weight_from_alpha`, `accumulate_along_rays`). Both are replaced here, only for the duration of a call,
by small torch equivalents. Everything else is gsplat's own code: covariance, projection, tile intersection, the
alpha formula (clamped at 0.999) and the compositing structure, with autograd for the gradients.
"""

from __future__ import annotations

import math
import sys
import types
from unittest import mock

import gsplat.cuda._torch_impl as gs_impl
import gsplat.cuda._wrapper as gs_wrapper
import torch
from torch import Tensor

ORACLE_ALPHA_MAX = 0.999  # hard-coded in gsplat 1.5.3 (kernels and torch reference)


@torch.no_grad()
def _indices_in_range(range_start, range_end, transmittances, means2d, conics, opacities, image_width, image_height,
                      tile_size, isect_offsets, flatten_ids):  # fmt: skip
    """CPU version of RasterizeToIndices3DGS.cu for one image: for each pixel, the Gaussians of its tile's list in
    batches [range_start, range_end) that pass sigma >= 0 and alpha >= 1/255 and do not take T to <= 1e-4 (the pixel
    stops there). Returns (gaussian_ids, pixel_ids, image_ids) sorted by pixel, then depth."""
    N = means2d.shape[-2]
    xy, con, opac = means2d.reshape(N, 2), conics.reshape(N, 3), opacities.reshape(N)
    tiles_y, tiles_x = isect_offsets.shape[-2:]
    starts = isect_offsets.flatten().long()
    ends = torch.cat([starts[1:], torch.tensor([flatten_ids.numel()])])
    block = tile_size * tile_size
    T0 = transmittances.reshape(image_height, image_width)
    ly, lx = torch.meshgrid(torch.arange(tile_size), torch.arange(tile_size), indexing="ij")
    gauss_out, pix_out = [], []
    for tile in range(tiles_x * tiles_y):
        lo = int(starts[tile]) + range_start * block
        hi = min(int(ends[tile]), int(starts[tile]) + range_end * block)
        if hi <= lo:
            continue
        ids = flatten_ids[lo:hi].long() % N
        X = (lx + (tile % tiles_x) * tile_size).reshape(-1)
        Y = (ly + (tile // tiles_x) * tile_size).reshape(-1)
        keep = (X < image_width) & (Y < image_height)
        X, Y = X[keep], Y[keep]
        dx = xy[ids, 0][None] - (X.to(xy.dtype) + 0.5)[:, None]
        dy = xy[ids, 1][None] - (Y.to(xy.dtype) + 0.5)[:, None]
        c = con[ids]
        sigma = 0.5 * (c[:, 0][None] * dx * dx + c[:, 2][None] * dy * dy) + c[:, 1][None] * dx * dy
        alpha = torch.clamp_max(opac[ids][None] * torch.exp(-sigma), ORACLE_ALPHA_MAX)
        passes = (sigma >= 0) & (alpha >= 1.0 / 255.0)
        a = torch.where(passes, alpha, torch.zeros(()))
        T_after = T0[Y, X][:, None].double() * torch.cumprod((1 - a).double(), dim=-1)
        # T_after never increases, so "T_after > 1e-4" also drops everything after the first stopping Gaussian.
        contributes = passes & (T_after > 1e-4)
        pi, gi = torch.nonzero(contributes, as_tuple=True)  # row-major: by pixel, then list (depth) order
        gauss_out.append(ids[gi])
        pix_out.append(Y[pi] * image_width + X[pi])
    if not gauss_out:
        empty = torch.zeros(0, dtype=torch.long)
        return empty, empty, empty
    gauss, pix = torch.cat(gauss_out), torch.cat(pix_out)
    order = torch.argsort(pix, stable=True)
    return gauss[order], pix[order], torch.zeros_like(gauss)


def _render_weight_from_alpha(alphas, packed_info=None, ray_indices=None, n_rays=None, prefix_trans=None):
    """nerfacc equivalent: weights = alpha * T, T = exclusive product of (1 - alpha) along each ray (differentiable).
    Samples of a ray are contiguous; the product is exp of a segmented cumulative sum of logs (float64)."""
    log_keep = torch.log1p(-alphas.double())
    csum = torch.cumsum(log_keep, 0)
    counts = torch.bincount(ray_indices, minlength=n_rays)
    first = torch.cumsum(counts, 0) - counts
    before_ray = torch.cat([csum.new_zeros(1), csum])[first[ray_indices]]
    trans = torch.exp(csum - log_keep - before_ray).to(alphas.dtype)
    return trans * alphas, trans


def _accumulate_along_rays(weights, values=None, ray_indices=None, n_rays=None):
    src = weights[:, None] if values is None else weights[:, None] * values
    return torch.zeros(n_rays, src.shape[-1], dtype=src.dtype).index_add(0, ray_indices, src)


_fake_nerfacc = types.ModuleType("nerfacc")
_fake_nerfacc.render_weight_from_alpha = _render_weight_from_alpha
_fake_nerfacc.accumulate_along_rays = _accumulate_along_rays


def gsplat_reference(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    features: Tensor,
    K: Tensor,
    viewmat: Tensor,
    width: int,
    height: int,
    background: Tensor | None = None,
    tile_size: int = 16,
) -> dict[str, Tensor]:
    """gsplat's torch reference for one camera: image [H,W,C], alpha [H,W], means2d [N,2] (grad retained), radii."""
    covars, _ = gs_impl._quat_scale_to_covar_preci(quats, scales, True, False)
    radii, means2d, depths, conics, _ = gs_impl._fully_fused_projection(
        means, covars, viewmat[None], K[None], width, height
    )
    if means2d.requires_grad:
        means2d.retain_grad()
    tiles_x, tiles_y = math.ceil(width / tile_size), math.ceil(height / tile_size)
    _, isect_ids, flat = gs_impl._isect_tiles(means2d.detach(), radii, depths.detach(), tile_size, tiles_x, tiles_y)
    offsets = gs_impl._isect_offset_encode(isect_ids, 1, tiles_x, tiles_y)
    with mock.patch.dict(sys.modules, {"nerfacc": _fake_nerfacc}), mock.patch.object(
        gs_wrapper, "rasterize_to_indices_in_range", _indices_in_range
    ):
        image, alpha = gs_impl._rasterize_to_pixels(
            means2d, conics, features[None], opacities[None], width, height, tile_size, offsets, flat,
            backgrounds=None if background is None else background[None],
        )  # fmt: skip
    return {"image": image[0], "alpha": alpha[0, ..., 0], "means2d": means2d, "radii": radii[0]}
