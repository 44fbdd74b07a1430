"""What a rasterizer backend returns, and the compositing constant every backend shares."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

# Front-to-back compositing stops before a Gaussian that would take the transmittance to <= T_MIN (exclusive).
T_MIN = 1e-4


@dataclass
class RenderOutput:
    """Result of rasterizing one camera. Images are [H, W, ...]; per-Gaussian arrays have the input's N."""

    image: Tensor  # [H, W, C] features composited over the background; differentiable
    alpha: Tensor  # [H, W] accumulated opacity 1 - T_final; differentiable
    depth: Tensor | None  # [H, W] median depth (0 where T never drops below 0.5), no gradient; if requested
    radii: Tensor  # [N, 2] int32 screen radii in pixels, 0 = culled
    visible: Tensor  # [N] bool, radii > 0
    means2d: Tensor  # [N, 2] pixel-space means; .grad is dL/dmeans2d after backward (when inputs require grad)
    weights: Tensor | None  # [N] sum over pixels of alpha * T (blending weight), no gradient; if requested
    backend: str  # the backend that actually ran
    num_intersections: int  # (Gaussian, tile) pairs composited

    @property
    def width(self) -> int:
        return int(self.alpha.shape[1])

    @property
    def height(self) -> int:
        return int(self.alpha.shape[0])

    def means2d_grad_ndc_norm(self) -> Tensor:
        """[N] ||dL/dmean2d|| in NDC units, as 3DGS/STG accumulate it for densification: the pixel gradient scaled
        by (W/2, H/2) (d pixel / d ndc), 0 for invisible Gaussians or before any backward."""
        grad = self.means2d.grad
        if grad is None:
            return torch.zeros(self.means2d.shape[0], dtype=self.means2d.dtype, device=self.means2d.device)
        scale = torch.tensor([0.5 * self.width, 0.5 * self.height], dtype=grad.dtype, device=grad.device)
        norm = (grad * scale).norm(dim=-1)
        return torch.where(self.visible, norm, torch.zeros_like(norm))
