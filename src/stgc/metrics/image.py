"""Image quality metrics as 3DGS / Spacetime Gaussians compute them: PSNR, SSIM, (optional) LPIPS.

Layouts: a 2-D tensor is [H, W] (one channel), a 3-D tensor is [H, W, C] (what renderers and image loaders
give), a 4-D tensor is a batch [B, C, H, W] (what losses usually see). Images are floats in [0, 1]; uint8
inputs are divided by 255. Everything is differentiable torch; numpy arrays are accepted and converted.

SSIM is the 3DGS definition (`gaussian_splatting/utils/loss_utils.py: ssim`): an 11x11 Gaussian window with
sigma 1.5, normalised to sum 1, applied per channel with *zero* padding of 5 pixels, C1 = 0.01^2,
C2 = 0.03^2, population (not sample) statistics, and the SSIM map averaged over *every* pixel including the
5-pixel border where the window hangs over the zero padding. scikit-image's `structural_similarity`
(gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1) uses the same window but
reflect padding and averages only the interior (it crops 5 pixels per side), so the two agree exactly on the
interior and differ slightly on the whole-image mean; see docs/evaluation.md.
"""

from __future__ import annotations

import functools
import importlib.util
import math
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from stgc.data.yuv import rgb_to_yuv420
from stgc.metrics._blur_kernel import blur_planes, ssim_input_grad, ssim_terms

SSIM_WINDOW_SIZE = 11
SSIM_SIGMA = 1.5
SSIM_C1 = 0.01**2
SSIM_C2 = 0.03**2


# A view rendered exactly has an infinite PSNR, which would make every mean it enters infinite (and the record
# null). Means count such a view at this ceiling (an MSE of 1e-10 on [0, 1] images), as video-coding tools cap
# identical pictures (the per-view CSV keeps the exact value); so does YUV's weighted combination of its planes.
PSNR_CEILING_DB = 100.0


def _as_float_tensor(x: Any) -> torch.Tensor:
    if isinstance(x, np.ndarray):
        x = torch.from_numpy(np.ascontiguousarray(x))
    if not isinstance(x, torch.Tensor):
        raise TypeError(f"expected a torch.Tensor or numpy array, got {type(x).__name__}")
    if x.dtype == torch.uint8:
        return x.to(torch.float32) / 255.0
    if not x.is_floating_point():
        return x.to(torch.float32)
    return x


def _check_pair(img: torch.Tensor, ref: torch.Tensor) -> None:
    if img.shape != ref.shape:
        raise ValueError(f"image shapes differ: {tuple(img.shape)} vs reference {tuple(ref.shape)}")
    if img.ndim not in (2, 3, 4):
        raise ValueError(f"expected [H,W], [H,W,C] or [B,C,H,W], got shape {tuple(img.shape)}")


def _to_bchw(x: torch.Tensor) -> torch.Tensor:
    if x.ndim == 2:
        return x[None, None]
    if x.ndim == 3:
        return x.permute(2, 0, 1)[None]
    return x


def mse(img: Any, ref: Any) -> torch.Tensor:
    """Mean squared error over all pixels and channels (and batch items)."""
    img, ref = _as_float_tensor(img), _as_float_tensor(ref)
    _check_pair(img, ref)
    return ((img - ref.to(img.dtype)) ** 2).mean()


def psnr(img: Any, ref: Any, max_value: float = 1.0) -> torch.Tensor:
    """PSNR in dB: 20·log10(max / sqrt(MSE)), MSE over all pixels and channels (STG `test.py`).

    For a batch this is the PSNR of the pooled MSE; evaluation averages per-image PSNRs instead (use
    `psnr_per_image`). Identical images give +inf."""
    err = mse(img, ref)
    return 20.0 * torch.log10(max_value / torch.sqrt(err))


def psnr_of_mse(mse_value: float, max_value: float = 1.0) -> float:
    """PSNR in dB of a mean squared error: 10·log10(max² / MSE); +inf for 0, NaN for a negative or NaN error."""
    if not mse_value >= 0:
        return float("nan")
    return float("inf") if mse_value == 0 else 10.0 * math.log10(max_value * max_value / mse_value)


def psnr_per_image(img: Any, ref: Any, max_value: float = 1.0) -> torch.Tensor:
    """PSNR of each item of a [B,C,H,W] batch, shape [B] (the 3DGS `image_utils.psnr`)."""
    img, ref = _as_float_tensor(img), _as_float_tensor(ref)
    _check_pair(img, ref)
    if img.ndim != 4:
        return psnr(img, ref, max_value).reshape(1)
    err = ((img - ref.to(img.dtype)) ** 2).flatten(1).mean(1)
    return 20.0 * torch.log10(max_value / torch.sqrt(err))


# MPEG's video-coding habit (JVET and the Gaussian-splat-coding common test conditions report quality in YUV): the
# render and the reference go to BT.709 YUV 4:2:0 at 10 bits, limited range (the codes a YUV file would hold), PSNR
# is taken per plane with the peak code 1023, and the planes are combined as (6 Y + U + V) / 8.
YUV_BIT_DEPTH = 10
YUV_WEIGHTS = {"y": 6.0, "u": 1.0, "v": 1.0}


def yuv_psnr(img: Any, ref: Any, bit_depth: int = YUV_BIT_DEPTH, color_range: str = "limited") -> dict[str, float]:
    """{"y", "u", "v": PSNR dB of each plane, "yuv": their 6:1:1 weighted mean} of two [H, W, 3] RGB images
    (floats in [0, 1] or uint8). Identical planes give +inf."""
    def planes(x: Any) -> tuple[np.ndarray, ...]:
        array = x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)
        if array.ndim != 3 or array.shape[-1] < 3:
            raise ValueError(f"yuv_psnr expects [H, W, 3] RGB images, got shape {array.shape}")
        array = array[..., :3]
        return rgb_to_yuv420(array if array.dtype == np.uint8 else np.clip(array, 0.0, 1.0), bit_depth, color_range)

    peak = float((1 << bit_depth) - 1)
    scores: dict[str, float] = {}
    for name, a, b in zip(("y", "u", "v"), planes(img), planes(ref)):
        err = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
        scores[name] = psnr_of_mse(err, peak)
    # An exact plane counts at the ceiling in the combination: one exact chroma plane (grey content) made it inf,
    # which hid the luma's error. Only a wholly exact picture combines to inf.
    exact = all(math.isinf(scores[k]) for k in YUV_WEIGHTS)
    scores["yuv"] = math.inf if exact else sum(
        YUV_WEIGHTS[k] * min(scores[k], PSNR_CEILING_DB) for k in YUV_WEIGHTS) / sum(YUV_WEIGHTS.values())
    return scores


@functools.lru_cache(maxsize=8)
def _gaussian_taps(window_size: int, sigma: float, dtype: torch.dtype) -> torch.Tensor:
    centre = window_size // 2
    taps = torch.tensor(
        [math.exp(-((i - centre) ** 2) / (2.0 * sigma**2)) for i in range(window_size)], dtype=torch.float64
    )
    return (taps / taps.sum()).to(dtype)


def gaussian_window(window_size: int = SSIM_WINDOW_SIZE, sigma: float = SSIM_SIGMA) -> torch.Tensor:
    """The normalised 1-D Gaussian taps (float64); the 2-D SSIM window is their outer product."""
    return _gaussian_taps(window_size, sigma, torch.float64).clone()


@functools.lru_cache(maxsize=16)
def _window_2d(window_size: int, sigma: float, planes: int, dtype: torch.dtype) -> torch.Tensor:
    taps = _gaussian_taps(window_size, sigma, torch.float64)
    return torch.outer(taps, taps).to(dtype).expand(planes, 1, window_size, window_size).contiguous()


def _blur(stack: torch.Tensor, window_size: int, sigma: float) -> torch.Tensor:
    """Zero-padded Gaussian blur of every [H, W] plane of `stack` [N, H, W].

    On the CPU (float32/float64): two 1-D passes in numba (`_SeparableBlur`, 22 instead of 121 taps a pixel; in a
    training iteration at 320x180 it replaced an 11x11 depthwise convolution that cost more than the rasterizer,
    forward and backward; benchmarks/eval_metrics.py). Elsewhere (CUDA tensors, other dtypes): one depthwise 11x11
    convolution, faster than torch's own 1-D-shaped convolutions."""
    if stack.device.type == "cpu" and stack.dtype in (torch.float32, torch.float64):
        taps = _gaussian_taps(window_size, sigma, stack.dtype)
        return _SeparableBlur.apply(stack, taps)
    n = stack.shape[0]
    window = _window_2d(window_size, sigma, n, stack.dtype).to(stack.device)
    return F.conv2d(stack[None], window, padding=window_size // 2, groups=n)[0]


class _SeparableBlur(torch.autograd.Function):
    """Zero-padded separable blur with a symmetric kernel. It is linear and self-adjoint (with zero padding, the
    transpose of correlating with a symmetric kernel is the same correlation), so the backward is the same blur."""

    @staticmethod
    def forward(ctx: Any, stack: torch.Tensor, taps: torch.Tensor) -> torch.Tensor:  # type: ignore[override]
        ctx.taps = taps
        return _run_blur(stack, taps)

    @staticmethod
    def backward(ctx: Any, grad: torch.Tensor) -> tuple[torch.Tensor, None]:  # type: ignore[override]
        return _run_blur(grad, ctx.taps), None


def _run_blur(stack: torch.Tensor, taps: torch.Tensor) -> torch.Tensor:
    src = stack.detach().contiguous().numpy()
    out = np.empty_like(src)
    blur_planes(src, taps.numpy(), out)
    return torch.from_numpy(out)


def ssim_map(
    img: Any, ref: Any, window_size: int = SSIM_WINDOW_SIZE, sigma: float = SSIM_SIGMA
) -> torch.Tensor:
    """Per-pixel SSIM, shape [B, C, H, W] (a 2-D/3-D input is treated as a batch of one)."""
    img, ref = _as_float_tensor(img), _as_float_tensor(ref)
    _check_pair(img, ref)
    x, y = _to_bchw(img), _to_bchw(ref).to(img.dtype)
    b, c, h, w = x.shape
    # One convolution call for the five local moments, every channel as its own plane.
    stack = torch.stack([x, y, x * x, y * y, x * y]).reshape(5 * b * c, h, w)
    mu_x, mu_y, exx, eyy, exy = _blur(stack, window_size, sigma).reshape(5, b, c, h, w)
    mu_xx, mu_yy, mu_xy = mu_x * mu_x, mu_y * mu_y, mu_x * mu_y
    var_x, var_y, cov_xy = exx - mu_xx, eyy - mu_yy, exy - mu_xy
    num = (2.0 * mu_xy + SSIM_C1) * (2.0 * cov_xy + SSIM_C2)
    den = (mu_xx + mu_yy + SSIM_C1) * (var_x + var_y + SSIM_C2)
    return num / den


def ssim(img: Any, ref: Any, window_size: int = SSIM_WINDOW_SIZE, sigma: float = SSIM_SIGMA) -> torch.Tensor:
    """Mean SSIM over all pixels, channels and batch items (3DGS `ssim(..., size_average=True)`).

    On the CPU (float32/float64, a reference without gradient: the training loss and evaluation) one fused pass
    (`_SSIMMean`); otherwise the mean of `ssim_map`."""
    img, ref = _as_float_tensor(img), _as_float_tensor(ref)
    _check_pair(img, ref)
    ref = ref.to(img.dtype)
    if img.device.type == "cpu" and img.dtype in (torch.float32, torch.float64) and not ref.requires_grad:
        return _SSIMMean.apply(img, ref, _gaussian_taps(window_size, sigma, img.dtype))
    return ssim_map(img, ref, window_size, sigma).mean()


def _planes(x: torch.Tensor) -> np.ndarray:
    """[P, H, W] contiguous numpy planes (P = batch x channels) of an image in any of the accepted layouts."""
    bchw = _to_bchw(x.detach())
    return np.ascontiguousarray(bchw.reshape(-1, *bchw.shape[-2:]).numpy())


class _SSIMMean(torch.autograd.Function):
    """Mean SSIM with a hand-written backward (gradient for the image only). The five local moments are one blur
    call, the SSIM terms and their partial derivatives one numba pass; the backward blurs the three partials (the
    blur is self-adjoint) instead of backpropagating through the five moments and some twenty element-wise torch
    ops."""

    @staticmethod
    def forward(ctx: Any, img: torch.Tensor, ref: torch.Tensor, taps: torch.Tensor) -> torch.Tensor:  # type: ignore[override]
        x, y = _planes(img), _planes(ref)
        stack = np.stack([x, y, x * x, y * y, x * y])
        moments = np.empty_like(stack)
        blur_planes(stack.reshape(-1, *x.shape[1:]), taps.numpy(), moments.reshape(-1, *x.shape[1:]))
        want_grad = ctx.needs_input_grad[0]
        partials = np.empty((3, *x.shape) if want_grad else (3, 0, 0, 0), dtype=x.dtype)
        sums = ssim_terms(moments, SSIM_C1, SSIM_C2, want_grad, partials)
        if want_grad:
            ctx.arrays = (x, y, partials, taps)
            ctx.shape = img.shape
        return torch.tensor(float(sums.sum()) / x.size, dtype=img.dtype)

    @staticmethod
    def backward(ctx: Any, grad: torch.Tensor) -> tuple[torch.Tensor | None, None, None]:  # type: ignore[override]
        x, y, partials, taps = ctx.arrays
        blurred = np.empty_like(partials)
        blur_planes(partials.reshape(-1, *x.shape[1:]), taps.numpy(), blurred.reshape(-1, *x.shape[1:]))
        out = np.empty_like(x)
        ssim_input_grad(blurred, x, y, float(grad) / x.size, out)
        result = torch.from_numpy(out)
        shape = ctx.shape
        if len(shape) == 3:  # [H, W, C] was taken as planes [C, H, W]
            return result.reshape(shape[2], shape[0], shape[1]).permute(1, 2, 0), None, None
        return result.reshape(shape), None, None


def ssim_per_image(img: Any, ref: Any) -> torch.Tensor:
    """Mean SSIM of each batch item, shape [B]."""
    return ssim_map(img, ref).flatten(1).mean(1)


# --------------------------------------------------------------------------------------------- LPIPS


def _torch_hub_checkpoints() -> Path:
    return Path(torch.hub.get_dir()) / "checkpoints"


# Backbone checkpoints the `lpips` package pulls through torchvision on first use.
_LPIPS_BACKBONE_FILES = {
    "alex": "alexnet-owt-7be5be79.pth",
    "vgg": "vgg16-397923af.pth",
}


def lpips_status(net: str = "alex") -> tuple[bool, str]:
    """Whether LPIPS can be computed *without downloading anything*, and if not, why.

    Needs the `lpips` and `torchvision` packages, lpips' own linear-layer weights (shipped inside the
    package) and the torchvision backbone checkpoint already in the torch hub cache."""
    if net not in _LPIPS_BACKBONE_FILES:
        return False, f"unknown LPIPS network {net!r}; expected one of {sorted(_LPIPS_BACKBONE_FILES)}"
    for package in ("lpips", "torchvision"):
        if importlib.util.find_spec(package) is None:
            return False, f"skipped: python package {package!r} is not installed"
    spec = importlib.util.find_spec("lpips")
    assert spec is not None and spec.origin is not None
    linear = Path(spec.origin).parent / "weights" / "v0.1" / f"{net}.pth"
    if not linear.is_file():
        return False, f"skipped: lpips linear weights missing ({linear})"
    backbone = _torch_hub_checkpoints() / _LPIPS_BACKBONE_FILES[net]
    if not backbone.is_file():
        return False, f"skipped: {net} backbone weights not in the torch hub cache ({backbone}); not downloading"
    return True, "available"


class LPIPS:
    """LPIPS with locally available weights only. Construct via `LPIPS.create(net)`, which returns None
    (and a reason) when the weights are not on this machine.

    `rescale=True` maps [0,1] images to [-1,1] as the lpips package expects; the 3DGS/STG evaluation feeds
    [0,1] directly (rescale=False reproduces their numbers)."""

    def __init__(self, net: str = "alex", rescale: bool = True):
        import lpips as lpips_pkg  # optional dependency

        self.net = net
        self.rescale = rescale
        # pretrained=True loads the linear layers from the package; the backbone comes from the hub cache.
        self._model = lpips_pkg.LPIPS(net=net, verbose=False).eval()

    @classmethod
    def create(cls, net: str = "alex", rescale: bool = True) -> tuple[LPIPS | None, str]:
        ok, reason = lpips_status(net)
        if not ok:
            return None, reason
        try:
            # The record says which convention scored it: the two differ by more than methods do.
            inputs = "[0, 1] mapped to [-1, 1] as the lpips package expects" if rescale else \
                "[0, 1] fed directly, as the 3DGS/STG evaluation scripts do"
            return cls(net, rescale), f"LPIPS-{net}, images {inputs}"
        except Exception as exc:  # a broken optional install must not break evaluation
            return None, f"skipped: could not load LPIPS-{net}: {exc}"

    @torch.no_grad()
    def __call__(self, img: Any, ref: Any) -> float:
        img, ref = _as_float_tensor(img), _as_float_tensor(ref)
        _check_pair(img, ref)
        x, y = _to_bchw(img).float(), _to_bchw(ref).float()
        return float(self._model(x, y, normalize=self.rescale).mean())
