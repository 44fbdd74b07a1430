"""The one rasterizer entry point: `rasterize(...) -> RenderOutput`, backend selection and input validation."""

from __future__ import annotations

import importlib.util
import numbers
from typing import Literal, get_args

import numpy as np
import torch
from torch import Tensor

from . import numba_backend as nb
from . import torch_backend as tb
from .gsplat_backend import gsplat_failure, load_gsplat, rasterize_gsplat
from .output import T_MIN, RenderOutput
from .projection import ALPHA_MIN, bin_tiles_torch, project_gaussians, tile_rects

Backend = Literal["auto", "numba", "torch", "gsplat"]
BACKENDS = get_args(Backend)


def available_backends() -> list[str]:
    """Backends that can run in this process (without importing gsplat: it is only probed on first use)."""
    names = ["numba", "torch"]  # numba is a required dependency
    if torch.cuda.is_available() and importlib.util.find_spec("gsplat") is not None:
        if gsplat_failure() is None:
            names.append("gsplat")
    return names


def select_backend(requested: str, device: torch.device) -> str:
    """The backend `rasterize` will try for tensors on `device` ("gsplat" may still fall back to "torch")."""
    if requested not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {requested!r}")
    if requested == "auto":
        if device.type == "cpu":
            return "numba"
        if device.type == "cuda" and "gsplat" in available_backends():
            return "gsplat"
        return "torch"
    if requested == "numba":
        if device.type != "cpu":
            raise ValueError(f"backend 'numba' needs CPU tensors, got device {device}")
    if requested == "gsplat" and device.type != "cuda":
        raise ValueError(f"backend 'gsplat' needs CUDA tensors, got device {device}")
    return requested


def _to_tensor(name: str, value: object, shape: tuple[int | None, ...], dtype: torch.dtype, device: torch.device) -> Tensor:
    """Tensor of `shape` (None = any size, checked by the caller) on `device`/`dtype`; ValueError otherwise."""
    if isinstance(value, np.ndarray):
        value = torch.from_numpy(value)
    if not isinstance(value, Tensor):
        try:
            value = torch.as_tensor(value)
        except Exception as exc:
            raise ValueError(f"{name}: expected a tensor or array, got {type(value).__name__}") from exc
    if value.dim() != len(shape) or any(s is not None and s != v for s, v in zip(shape, value.shape)):
        want = "[" + ", ".join("*" if s is None else str(s) for s in shape) + "]"
        raise ValueError(f"{name}: expected shape {want}, got {list(value.shape)}")
    if not (value.is_floating_point() or value.dtype in (torch.int32, torch.int64)):
        raise ValueError(f"{name}: expected a floating point tensor, got {value.dtype}")
    if value.device != device:
        raise ValueError(f"{name}: on {value.device}, expected {device} (the device of means)")
    value = value.to(dtype)
    if value.numel() and not _all_finite(value):
        raise ValueError(f"{name}: contains NaN or inf")
    return value


def _all_finite(value: Tensor) -> bool:
    if value.device.type == "cpu":
        # numpy's reductions run on the calling thread: torch's would each be a parallel region, which wakes a
        # sleeping thread under the passive OpenMP wait (about 75 us at 2 threads, more than this check's work).
        array = value.detach().numpy()
        return bool(np.isfinite(array.min()) and np.isfinite(array.max()))
    # The extremes are NaN when any value is and infinite when any value is: two reductions, no mask allocated.
    return all(bool(torch.isfinite(e)) for e in torch.aminmax(value))


def _check_size(name: str, value: object) -> int:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or int(value) < 1:
        raise ValueError(f"{name}: expected a positive integer, got {value!r}")
    return int(value)


ArrayLike = Tensor | np.ndarray


def rasterize(
    means: ArrayLike,
    quats: ArrayLike,
    scales: ArrayLike,
    opacities: ArrayLike,
    features: ArrayLike,
    K: ArrayLike,
    viewmat: ArrayLike,
    width: int,
    height: int,
    background: ArrayLike | None = None,
    *,
    backend: str = "auto",
    alpha_max: float = 0.99,
    near_plane: float = 0.01,
    eps2d: float = 0.3,
    return_depth: bool = False,
    return_weights: bool = False,
) -> RenderOutput:
    """Render N Gaussians into one pinhole camera (conventions in docs/rasterizer.md).

    means [N,3] world positions; quats [N,4] (w,x,y,z), any norm; scales [N,3] linear; opacities [N];
    features [N,C], C >= 1; K [3,3] with pixel centres at +0.5; viewmat [4,4] world-to-camera (OpenCV);
    background [C] or None (zeros). Computation is float64 when means is float64, float32 otherwise.
    backend: "auto" (numba on CPU, gsplat on CUDA when it loads, else torch), "numba", "torch" or "gsplat"."""
    if isinstance(means, np.ndarray):
        means = torch.from_numpy(means)
    if not isinstance(means, Tensor):
        raise ValueError(f"means: expected a tensor or array, got {type(means).__name__}")
    device = means.device
    dtype = torch.float64 if means.dtype == torch.float64 else torch.float32
    means = _to_tensor("means", means, (None, 3), dtype, device)
    N = means.shape[0]
    quats = _to_tensor("quats", quats, (N, 4), dtype, device)
    scales = _to_tensor("scales", scales, (N, 3), dtype, device)
    opacities = _to_tensor("opacities", opacities, (N,), dtype, device)
    features = _to_tensor("features", features, (N, None), dtype, device)
    C = features.shape[1]
    if C < 1:
        raise ValueError("features: need at least one channel, got shape [N, 0]")
    K = _to_tensor("K", K, (3, 3), dtype, device)
    viewmat = _to_tensor("viewmat", viewmat, (4, 4), dtype, device)
    if background is not None:
        background = _to_tensor("background", background, (C,), dtype, device)
    width = _check_size("width", width)
    height = _check_size("height", height)
    if not (ALPHA_MIN < float(alpha_max) < 1.0):
        raise ValueError(f"alpha_max: expected a value in (1/255, 1), got {alpha_max}")
    if not (float(near_plane) > 0 and np.isfinite(near_plane)):
        raise ValueError(f"near_plane: expected a positive finite value, got {near_plane}")
    if not (float(eps2d) >= 0 and np.isfinite(eps2d)):
        raise ValueError(f"eps2d: expected a finite value >= 0, got {eps2d}")
    if float(K[0, 0].detach()) <= 0 or float(K[1, 1].detach()) <= 0:
        raise ValueError(f"K: focal lengths must be positive, got fx={float(K[0, 0])}, fy={float(K[1, 1])}")

    chosen = select_backend(backend, device)
    if chosen == "gsplat" and N == 0:
        # gsplat divides by N on the host (a SIGFPE that kills the process); a model's render culls to no
        # Gaussians at a time far from all of them.
        chosen = "torch"
    if chosen == "gsplat" and K.requires_grad and backend == "gsplat":
        raise ValueError("backend='gsplat' has no gradient for K (its projection drops it); use backend='torch' "
                         "to optimise cameras")
    camera_gradient = K.requires_grad or (chosen == "numba" and viewmat.requires_grad)
    if backend == "auto" and chosen in ("gsplat", "numba") and camera_gradient:
        chosen = "torch"  # the backend that differentiates the camera (numba refuses both, gsplat drops K's)
    if chosen == "gsplat" and backend == "gsplat" and dtype != torch.float32:
        raise ValueError(f"backend='gsplat' renders float32 only (got {dtype}); use backend='auto' (falls back "
                         "to torch for float64) or 'torch'")
    if chosen == "gsplat":
        module = load_gsplat()
        if module is not None and dtype == torch.float32:
            out = rasterize_gsplat(
                module, means, quats, scales, opacities, features, K, viewmat, width, height, background,
                alpha_max=alpha_max, near_plane=near_plane, eps2d=eps2d,
                want_depth=return_depth, want_weights=return_weights,
            )  # fmt: skip
            if out.means2d.requires_grad:
                out.means2d.retain_grad()
            return out
        chosen = "torch"

    if chosen == "numba":
        proj = nb.project_numba(means, quats, scales, opacities, K, viewmat, width, height, eps2d=eps2d,
                                near_plane=near_plane)  # fmt: skip
    else:
        proj = project_gaussians(
            means, quats, scales, opacities, K, viewmat, width, height, eps2d=eps2d, near_plane=near_plane
        )
    if proj.means2d.requires_grad:
        proj.means2d.retain_grad()
    if chosen == "numba":
        color, trans, depth, weights, n_isects = nb.composite_numba(
            proj.means2d, proj.conics, opacities, features, proj.depths, proj.radii,
            width, height, float(alpha_max), ALPHA_MIN, T_MIN, return_depth, return_weights,
        )  # fmt: skip
    else:
        rect = tile_rects(proj.radii, proj.means2d, width, height, tb.TILE_SIZE)
        offsets, flat = bin_tiles_torch(rect, proj.depths, proj.visible, width, height, tb.TILE_SIZE)
        color, trans, depth, weights = tb.composite_torch(
            proj.means2d, proj.conics, opacities, features, proj.depths, offsets, flat,
            width, height, tb.TILE_SIZE, float(alpha_max), ALPHA_MIN, T_MIN, return_depth, return_weights,
        )  # fmt: skip
        n_isects = int(flat.numel())
    image = color if background is None else color + trans[..., None] * background
    return RenderOutput(
        image=image,
        alpha=1.0 - trans,
        depth=depth,
        radii=proj.radii,
        visible=proj.visible,
        means2d=proj.means2d,
        weights=weights,
        backend=chosen,
        num_intersections=n_isects,
    )
