"""CPU projection and compositing with numba kernels, each wrapped as a torch.autograd.Function (hand-written
backwards)."""

from __future__ import annotations

from typing import Any

import numba
import numpy as np
import torch
from torch import Tensor

from . import _numba_kernels as kernels
from . import _numba_projection as projection_kernels
from .projection import ALPHA_MIN, SIGMA_CUT_MARGIN, Projected, tile_grid

# Tile edge in pixels. 8 beats 16 on CPU: per-tile lists are shorter relative to the pixels that walk them
# (measured in benchmarks/rasterizer.py --tile-size; docs/rasterizer.md has the numbers).
TILE_SIZE = 8


def _consts(dtype: type[np.floating], alpha_max: float, alpha_min: float, t_min: float) -> np.ndarray:
    return np.array([0.5, 1.0, alpha_max, alpha_min, t_min, 0.0], dtype=dtype)


def _pack(means2d: Tensor, conics: Tensor, opacities: Tensor, depths: Tensor, dtype: type[np.floating],
          alpha_min: float = ALPHA_MIN) -> np.ndarray:
    gdata = np.empty((means2d.shape[0], 8), dtype=dtype)
    m2, co, op, de = (np.ascontiguousarray(t.detach().numpy()) for t in (means2d, conics, opacities, depths))
    kernels.pack_gaussians(m2, co, op, de, alpha_min, SIGMA_CUT_MARGIN, gdata)
    return gdata


def depth_order(depths: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """Ids of the Gaussians binning can use (radii > 0), front to back; equal depths in id order.

    Culled Gaussians get no tile, so they are left out of the sort (in training most of a model is culled at any
    one time). The projection culls every depth at or below the near plane, which is positive, so the rest are
    positive finite floats, whose bit patterns sort as unsigned integers in the same order, which a radix sort
    orders in a few linear passes (stable; a tenth of numpy's stable argsort at 50k: the sort is serial work that
    the second thread cannot share)."""
    visible = kernels.ids_with_a_tile(np.ascontiguousarray(radii))
    keys = depths[visible]
    if keys.size and not keys.min() > 0:
        raise ValueError("depth_order: a Gaussian with a tile has a depth <= 0; the projection should have culled it")
    unsigned = np.uint32 if keys.dtype == np.float32 else np.uint64
    order: np.ndarray = kernels.radix_argsort(keys.view(unsigned), visible)
    return order


def _scratch(n_threads: int, longest: int, *rows: tuple[int, ...], dtype: type[np.floating]) -> list[np.ndarray]:
    """Per-thread kernel scratch: one [threads, *r, L] array per `rows` entry, L = the longest tile list."""
    return [np.empty((n_threads, *r, max(longest, 1)), dtype=dtype) for r in rows]


class _NumbaProjection(torch.autograd.Function):
    """(means, quats, scales) -> (means2d, conics); depths, radii and the camera are side outputs without
    gradient (`out` receives them)."""

    @staticmethod
    def forward(ctx: Any, means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, camera: np.ndarray,
                width: int, height: int, out: dict[str, Tensor]) -> tuple[Tensor, Tensor]:  # fmt: skip
        m, q, s = (np.ascontiguousarray(t.detach().numpy()) for t in (means, quats, scales))
        n = m.shape[0]
        dtype = m.dtype
        means2d = np.empty((n, 2), dtype=dtype)
        conics = np.empty((n, 3), dtype=dtype)
        depths = np.empty(n, dtype=dtype)
        radii = np.empty((n, 2), dtype=np.int32)
        projection_kernels.project_forward(m, q, s, np.ascontiguousarray(opacities.detach().numpy()), camera,
                                           width, height, means2d, conics, depths, radii)  # fmt: skip
        # Saved as tensors, so that autograd refuses a backward after they were changed in place.
        ctx.save_for_backward(means, quats, scales)
        ctx.camera = camera
        out["depths"] = torch.from_numpy(depths)
        out["radii"] = torch.from_numpy(radii)
        return torch.from_numpy(means2d), torch.from_numpy(conics)

    @staticmethod
    def backward(ctx: Any, grad_means2d: Tensor | None, grad_conics: Tensor | None) -> tuple[Tensor | None, ...]:
        m, q, s = (np.ascontiguousarray(t.detach().numpy()) for t in ctx.saved_tensors)
        camera = ctx.camera
        n, dtype = m.shape[0], m.dtype
        # Views, not copies: these are columns of the compositing backward's per-Gaussian rows (the kernel reads
        # them with their strides; a copy of each took 0.45 ms at 50k).
        gm2 = np.zeros((n, 2), dtype) if grad_means2d is None else np.asarray(grad_means2d.numpy(), dtype)
        gco = np.zeros((n, 3), dtype) if grad_conics is None else np.asarray(grad_conics.numpy(), dtype)
        grad_means = np.empty((n, 3), dtype=dtype)
        grad_quats = np.empty((n, 4), dtype=dtype)
        grad_scales = np.empty((n, 3), dtype=dtype)
        projection_kernels.project_backward(m, q, s, camera, gm2, gco, grad_means, grad_quats, grad_scales)
        return (torch.from_numpy(grad_means), torch.from_numpy(grad_quats), torch.from_numpy(grad_scales),
                None, None, None, None, None)


def project_numba(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, K: Tensor, viewmat: Tensor,
                  width: int, height: int, *, eps2d: float, near_plane: float, far_plane: float = 1e10) -> Projected:
    """projection.project_gaussians on CPU in one numba pass per direction (same math, same outputs; each
    Gaussian in float64, so float32 results differ from the torch projection's by its float32 rounding: in the last
    bits mostly, more for long thin footprints, whose conic's determinant cancels in float32 there and in gsplat's
    CUDA projection, e.g. a 9 % conic error at 300 x 0.01 px, measured in session 37's render review). The camera is a
    constant here: K and viewmat get no gradient (the torch backend differentiates them)."""
    if K.requires_grad or viewmat.requires_grad:
        raise ValueError("the numba backend has no gradient for K or viewmat; use backend='torch' to optimise cameras")
    camera = projection_kernels.camera_array(
        K.detach().to(torch.float64).numpy(), viewmat.detach().to(torch.float64).numpy(), width, height,
        float(eps2d), float(near_plane), float(far_plane),
    )  # fmt: skip
    side: dict[str, Tensor] = {}
    means2d, conics = _NumbaProjection.apply(means, quats, scales, opacities, camera, width, height, side)  # type: ignore[no-untyped-call]
    radii = side["radii"]
    visible = torch.from_numpy((radii.numpy() > 0).any(axis=1))  # numpy: no parallel region (see render.api)
    return Projected(means2d=means2d, conics=conics, depths=side["depths"], radii=radii, visible=visible)


class _NumbaComposite(torch.autograd.Function):
    """(means2d, conics, opacities, colors) -> (color [H,W,C] without background, final transmittance [H,W],
    median depth [H,W] | None, weights [N] | None). `gdata` is the packed numpy copy of the first three."""

    @staticmethod
    def forward(ctx: Any, means2d: Tensor, conics: Tensor, opacities: Tensor, colors: Tensor, gdata: np.ndarray,
                offsets: np.ndarray, flat: np.ndarray, width: int, height: int, tile_size: int, consts: np.ndarray,
                want_depth: bool, want_weights: bool) -> tuple[Tensor, Tensor, Tensor | None, Tensor | None]:  # fmt: skip
        np_dtype = gdata.dtype.type
        # A copy: the backward replays these colours, and a view of the caller's tensor changed in place in between
        # would give wrong gradients that autograd's version check never sees.
        col = np.array(colors.detach().numpy(), dtype=np_dtype, order="C", copy=True)
        N, C = col.shape
        tiles_x, _ = tile_grid(width, height, tile_size)
        centers_x = np.arange(width, dtype=np_dtype) + np_dtype(0.5)
        centers_y = np.arange(height, dtype=np_dtype) + np_dtype(0.5)
        out_color = np.empty((height, width, C), dtype=np_dtype)
        out_trans = np.empty((height, width), dtype=np_dtype)
        out_last = np.empty((height, width), dtype=np.int64)
        out_depth = np.zeros((height, width) if want_depth else (1, 1), dtype=np_dtype)
        n_threads = numba.get_num_threads()
        weight_rows = np.zeros((n_threads, N) if want_weights else (1, 1), dtype=np_dtype)
        longest = int((offsets[1:] - offsets[:-1]).max()) if offsets.shape[0] > 1 else 0
        tile_order = kernels.interleaved_tiles(offsets.shape[0] - 1, n_threads)
        kernels.composite_forward(
            gdata, col, offsets, flat, centers_x, centers_y, tile_size, tiles_x, consts, tile_order,
            want_depth, want_weights, out_color, out_trans, out_last, out_depth, weight_rows,
            *_scratch(n_threads, longest, (8,), (C,), (2,), dtype=np_dtype),
        )  # fmt: skip
        ctx.arrays = (gdata, col, offsets, flat, centers_x, centers_y, consts, tile_order, out_trans, out_last)
        ctx.layout = (tile_size, tiles_x, N, C, longest)
        depth = torch.from_numpy(out_depth) if want_depth else None
        weights = torch.from_numpy(weight_rows.sum(axis=0)) if want_weights else None
        for t in (depth, weights):
            if t is not None:
                ctx.mark_non_differentiable(t)
        return torch.from_numpy(out_color), torch.from_numpy(out_trans.copy()), depth, weights

    @staticmethod
    def backward(ctx: Any, grad_color: Tensor | None, grad_trans: Tensor | None, _grad_depth: Tensor | None,
                 _grad_weights: Tensor | None) -> tuple[Tensor | None, ...]:
        gdata, col, offsets, flat, centers_x, centers_y, consts, tile_order, out_trans, out_last = ctx.arrays
        tile_size, tiles_x, N, C, longest = ctx.layout
        np_dtype = gdata.dtype.type
        H, W = out_trans.shape
        gc = np.zeros((H, W, C), np_dtype) if grad_color is None else np.ascontiguousarray(grad_color.numpy(), np_dtype)
        gt = np.zeros((H, W), np_dtype) if grad_trans is None else np.ascontiguousarray(grad_trans.numpy(), np_dtype)
        n_threads = numba.get_num_threads()
        rows = np.empty((n_threads, N, kernels.N_GEOM_GRADS + C), dtype=np_dtype)  # zeroed by the kernel
        kernels.composite_backward(
            gdata, col, offsets, flat, centers_x, centers_y, tile_size, tiles_x, consts, tile_order, out_trans,
            out_last, gc, gt, rows,
            *_scratch(n_threads, longest, (8,), (C,), (kernels.N_GEOM_GRADS + C,), (5,), dtype=np_dtype),
        )  # fmt: skip
        if rows.shape[0] == 1:
            total = rows[0]
        else:
            total = np.empty(rows.shape[1:], dtype=np_dtype)
            kernels.sum_rows(rows, total)
        total = torch.from_numpy(total)
        k = kernels
        d_means2d = total[:, k.GX : k.GY + 1]
        d_conics = total[:, k.GA : k.GC + 1]
        d_opac = total[:, k.GO]
        d_colors = total[:, k.N_GEOM_GRADS :]
        return (d_means2d, d_conics, d_opac, d_colors) + (None,) * 9


def composite_numba(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    colors: Tensor,
    depths: Tensor,
    radii: Tensor,
    width: int,
    height: int,
    alpha_max: float,
    alpha_min: float,
    t_min: float,
    want_depth: bool,
    want_weights: bool,
    tile_size: int | None = None,
) -> tuple[Tensor, Tensor, Tensor | None, Tensor | None, int]:
    """Bin and composite on CPU: (color, final T, median depth | None, weights | None, number of intersections).
    tile_size None = the module's TILE_SIZE (read at call time, so a benchmark can change it)."""
    tile_size = TILE_SIZE if tile_size is None else tile_size
    np_dtype = np.float64 if colors.dtype == torch.float64 else np.float32
    gdata = _pack(means2d, conics, opacities, depths, np_dtype, alpha_min)
    radii_np = radii.numpy()
    order = depth_order(depths.detach().numpy(), radii_np)
    offsets, flat = kernels.bin_tiles(gdata, radii_np, order, width, height, tile_size, numba.get_num_threads())
    consts = _consts(np_dtype, alpha_max, alpha_min, t_min)
    color, trans, depth, weights = _NumbaComposite.apply(  # type: ignore[no-untyped-call]
        means2d, conics, opacities, colors, gdata, offsets, flat, width, height, tile_size, consts,
        want_depth, want_weights,
    )  # fmt: skip
    return color, trans, depth, weights, int(flat.shape[0])
