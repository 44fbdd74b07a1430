"""Optional CUDA path through gsplat 1.5.3's fused kernels (projection, tile intersection, rasterization).

gsplat is imported only when this path is taken (CUDA tensors with backend "auto", or backend="gsplat"). Its CUDA
extension is JIT-built on first use; if that fails (no toolkit, build error) we warn once and the caller falls back
to the pure-PyTorch backend. Not exercised by the CPU test suite: written against gsplat 1.5.3's documented API
(`gsplat.fully_fused_projection`, `isect_tiles`, `isect_offset_encode`, `rasterize_to_pixels`).

Differences from the CPU backends, all documented in docs/rasterizer.md:
* alpha is clamped at gsplat's compiled-in maximum (0.999 in 1.5.3, 0.99 in 1.6) whatever `alpha_max` says;
* median depth and per-Gaussian weights are computed by the torch compositor under no_grad on gsplat's own 2D
  projection (gsplat has no median-depth output).
"""

from __future__ import annotations

import warnings
from typing import Any

import torch
from torch import Tensor

from .output import T_MIN, RenderOutput
from .projection import ALPHA_MIN, bin_tiles_torch, tile_grid, tile_rects
from .torch_backend import TILE_SIZE as TORCH_TILE
from .torch_backend import composite_torch

TILE_SIZE = 16

_state: dict[str, Any] = {"module": None, "failure": None, "alpha_warned": False}


def gsplat_alpha_max(module: Any) -> float:
    version = getattr(module, "__version__", "1.5.3")
    return 0.999 if version.startswith(("1.4", "1.5")) else 0.99


def _import_gsplat() -> Any:
    """Import gsplat and load its CUDA extension (the JIT build happens on this first import)."""
    import gsplat
    from gsplat.cuda._backend import _C

    if _C is None:
        raise ImportError("gsplat found no CUDA toolkit to build its extension")
    return gsplat


def load_gsplat() -> Any | None:
    """gsplat with a working CUDA extension, or None (after one warning per process) when it cannot be used."""
    if _state["module"] is not None:
        return _state["module"]
    if _state["failure"] is not None:
        return None
    try:
        module = _import_gsplat()
    except Exception as exc:  # any import/build failure means "not usable here": fall back, loudly, once
        _state["failure"] = f"{type(exc).__name__}: {exc}"
        warnings.warn(
            f"stgc.render: gsplat's CUDA rasterizer is unavailable ({_state['failure']}); "
            "falling back to the pure-PyTorch backend for the rest of this process.",
            RuntimeWarning,
            stacklevel=3,
        )
        return None
    _state["module"] = module
    return module


def gsplat_failure() -> str | None:
    """Why gsplat could not be loaded in this process, or None if it was not tried or worked."""
    failure: str | None = _state["failure"]
    return failure


def rasterize_gsplat(
    gsplat: Any,
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    features: Tensor,
    K: Tensor,
    viewmat: Tensor,
    width: int,
    height: int,
    background: Tensor | None,
    *,
    alpha_max: float,
    near_plane: float,
    eps2d: float,
    want_depth: bool,
    want_weights: bool,
) -> RenderOutput:
    """One camera through gsplat's CUDA kernels (no background composited separately: gsplat adds it itself)."""
    kernel_alpha_max = gsplat_alpha_max(gsplat)
    if abs(alpha_max - kernel_alpha_max) > 1e-9 and not _state["alpha_warned"]:
        _state["alpha_warned"] = True
        warnings.warn(
            f"stgc.render: gsplat {getattr(gsplat, '__version__', '?')} clamps alpha at {kernel_alpha_max} "
            f"(compiled in); alpha_max={alpha_max} is ignored on this backend.",
            RuntimeWarning,
            stacklevel=3,
        )
    # gsplat normalises quaternions with rsqrt: a zero one (the official error-guided sampling adds Gaussians with
    # rotation 0) turns NaN there and its Gaussian vanishes; numba, torch and the official code draw it unrotated.
    quats = torch.where(quats.norm(dim=-1, keepdim=True) > 0, quats, quats.new_tensor([1.0, 0.0, 0.0, 0.0]))
    radii, means2d_b, depths_b, conics_b, _ = gsplat.fully_fused_projection(
        means, None, quats, scales, viewmat[None], K[None], width, height,
        eps2d=eps2d, near_plane=near_plane, opacities=opacities,
    )  # fmt: skip
    # A [N,2] tensor on the autograd path, so that .retain_grad() exposes dL/dmeans2d like the other backends.
    means2d = means2d_b[0]
    tiles_x, tiles_y = tile_grid(width, height, TILE_SIZE)
    _, isect_ids, flatten_ids = gsplat.isect_tiles(
        means2d[None].detach(), radii, depths_b.detach(), TILE_SIZE, tiles_x, tiles_y
    )
    isect_offsets = gsplat.isect_offset_encode(isect_ids, 1, tiles_x, tiles_y)
    image, alpha = gsplat.rasterize_to_pixels(
        means2d[None], conics_b, features[None], opacities[None], width, height, TILE_SIZE,
        isect_offsets, flatten_ids, backgrounds=None if background is None else background[None],
    )  # fmt: skip
    radii = radii[0]
    visible = (radii > 0).any(-1)
    depth = weights = None
    if want_depth or want_weights:
        with torch.no_grad():
            rect = tile_rects(radii, means2d, width, height, TORCH_TILE)
            offsets, flat = bin_tiles_torch(rect, depths_b[0], visible, width, height, TORCH_TILE)
            _, _, depth, weights = composite_torch(
                means2d.detach(), conics_b[0].detach(), opacities.detach(), features.detach()[:, :1],
                depths_b[0].detach(), offsets, flat, width, height, TORCH_TILE,
                kernel_alpha_max, ALPHA_MIN, T_MIN, want_depth, want_weights, use_checkpoint=False,
            )  # fmt: skip
    return RenderOutput(image=image[0], alpha=alpha[0, ..., 0], depth=depth, radii=radii.to(torch.int32),
                        visible=visible, means2d=means2d, weights=weights, backend="gsplat",
                        num_intersections=int(flatten_ids.numel()))
