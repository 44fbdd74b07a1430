"""CPU compositing with numba kernels, wrapped as a torch.autograd.Function (hand-written backward)."""

from __future__ import annotations

import numba
import numpy as np
import torch
from torch import Tensor

from . import _numba_kernels as kernels
from .projection import tile_grid

# Tile edge in pixels. 8 beats 16 on CPU: per-tile lists are shorter relative to the pixels that walk them
# (measured in benchmarks/rasterizer.py --tile-size; docs/rasterizer.md has the numbers).
TILE_SIZE = 8


def bin_tiles(rect: Tensor, depths: Tensor, width: int, height: int, tile_size: int) -> tuple[Tensor, Tensor]:
    """Counting-sort binning on CPU; same ordering as projection.bin_tiles_torch (stable by depth)."""
    tiles_x, tiles_y = tile_grid(width, height, tile_size)
    order = torch.argsort(depths, stable=True).numpy()
    offsets, flat = kernels.bin_tiles(rect.numpy(), order, tiles_x * tiles_y, tiles_x)
    return torch.from_numpy(offsets), torch.from_numpy(flat)


def _consts(dtype: np.dtype, alpha_max: float, alpha_min: float, t_min: float) -> np.ndarray:
    return np.array([0.5, 1.0, alpha_max, alpha_min, t_min, 0.0], dtype=dtype)


def _pack(means2d: Tensor, conics: Tensor, opacities: Tensor, sigma_cut: Tensor, depths: Tensor, dtype) -> np.ndarray:
    N = means2d.shape[0]
    gdata = np.empty((N, 8), dtype=dtype)
    gdata[:, 0:2] = means2d.detach().numpy()
    gdata[:, 2:5] = conics.detach().numpy()
    gdata[:, 5] = opacities.detach().numpy()
    gdata[:, 6] = sigma_cut.numpy()
    gdata[:, 7] = depths.numpy()
    return gdata


class _NumbaComposite(torch.autograd.Function):
    """(means2d, conics, opacities, colors) -> (color [H,W,C] without background, final transmittance [H,W],
    median depth [H,W] | None, weights [N] | None)."""

    @staticmethod
    def forward(ctx, means2d, conics, opacities, colors, sigma_cut, depths, offsets, flat, width, height, tile_size,
                alpha_max, alpha_min, t_min, want_depth, want_weights):  # fmt: skip
        np_dtype = np.float64 if colors.dtype == torch.float64 else np.float32
        gdata = _pack(means2d, conics, opacities, sigma_cut, depths, np_dtype)
        col = np.ascontiguousarray(colors.detach().numpy(), dtype=np_dtype)
        N, C = col.shape
        tiles_x, _ = tile_grid(width, height, tile_size)
        consts = _consts(np_dtype, alpha_max, alpha_min, t_min)
        centers_x = np.arange(width, dtype=np_dtype) + np_dtype(0.5)
        centers_y = np.arange(height, dtype=np_dtype) + np_dtype(0.5)
        out_color = np.empty((height, width, C), dtype=np_dtype)
        out_trans = np.empty((height, width), dtype=np_dtype)
        out_last = np.empty((height, width), dtype=np.int64)
        out_depth = np.zeros((height, width) if want_depth else (1, 1), dtype=np_dtype)
        n_threads = numba.get_num_threads()
        weight_rows = np.zeros((n_threads, N) if want_weights else (1, 1), dtype=np_dtype)
        of, fl = offsets.numpy(), flat.numpy()
        kernels.composite_forward(
            gdata, col, of, fl, centers_x, centers_y, tile_size, tiles_x, consts,
            want_depth, want_weights, out_color, out_trans, out_last, out_depth, weight_rows,
        )  # fmt: skip
        ctx.arrays = (gdata, col, of, fl, centers_x, centers_y, consts, out_trans, out_last)
        ctx.layout = (tile_size, tiles_x, N, C)
        depth = torch.from_numpy(out_depth) if want_depth else None
        weights = torch.from_numpy(weight_rows.sum(axis=0)) if want_weights else None
        for t in (depth, weights):
            if t is not None:
                ctx.mark_non_differentiable(t)
        return torch.from_numpy(out_color), torch.from_numpy(out_trans.copy()), depth, weights

    @staticmethod
    def backward(ctx, grad_color, grad_trans, _grad_depth, _grad_weights):
        gdata, col, of, fl, centers_x, centers_y, consts, out_trans, out_last = ctx.arrays
        tile_size, tiles_x, N, C = ctx.layout
        np_dtype = gdata.dtype
        H, W = out_trans.shape
        gc = np.zeros((H, W, C), np_dtype) if grad_color is None else np.ascontiguousarray(grad_color.numpy(), np_dtype)
        gt = np.zeros((H, W), np_dtype) if grad_trans is None else np.ascontiguousarray(grad_trans.numpy(), np_dtype)
        rows = np.zeros((numba.get_num_threads(), N, kernels.N_GEOM_GRADS + C), dtype=np_dtype)
        kernels.composite_backward(
            gdata, col, of, fl, centers_x, centers_y, tile_size, tiles_x, consts, out_trans, out_last, gc, gt, rows
        )
        if rows.shape[0] == 1:
            total = rows[0]
        else:
            total = np.empty(rows.shape[1:], dtype=np_dtype)
            kernels.sum_rows(rows, total)
        total = torch.from_numpy(total)
        g = kernels
        d_means2d = total[:, g.GX : g.GY + 1]
        d_conics = total[:, g.GA : g.GC + 1]
        d_opac = total[:, g.GO]
        d_colors = total[:, g.N_GEOM_GRADS :]
        return (d_means2d, d_conics, d_opac, d_colors) + (None,) * 12


def composite_numba(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    colors: Tensor,
    sigma_cut: Tensor,
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
) -> tuple[Tensor, Tensor, Tensor | None, Tensor | None]:
    return _NumbaComposite.apply(
        means2d, conics, opacities, colors, sigma_cut, depths, offsets, flat, width, height, tile_size,
        alpha_max, alpha_min, t_min, want_depth, want_weights,
    )  # fmt: skip
