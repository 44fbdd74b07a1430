"""Random Gaussian scenes in front of a pinhole camera, small enough for the oracle."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor


@dataclass
class Scene:
    means: Tensor
    quats: Tensor
    scales: Tensor
    opacities: Tensor
    features: Tensor
    K: Tensor
    viewmat: Tensor
    width: int
    height: int

    def params(self) -> list[Tensor]:
        return [self.means, self.quats, self.scales, self.opacities, self.features]

    def args(self) -> tuple:
        return (*self.params(), self.K, self.viewmat, self.width, self.height)

    def leaves(self) -> Scene:
        """A copy whose five parameter tensors are fresh leaves requiring grad."""
        p = [t.detach().clone().requires_grad_(True) for t in self.params()]
        return Scene(*p, self.K, self.viewmat, self.width, self.height)


def make_scene(
    n: int,
    width: int = 64,
    height: int = 48,
    channels: int = 3,
    focal: float = 60.0,
    principal_offset: tuple[float, float] = (0.0, 0.0),
    sigma_px: tuple[float, float] = (1.0, 6.0),
    seed: int = 0,
    dtype: torch.dtype = torch.float32,
    rotate_camera: bool = True,
) -> Scene:
    """n Gaussians at depth 3..7 spread over the frustum (+10%), per-axis pixel sigma log-uniform in sigma_px,
    random rotations, opacity U[0.05, 0.95], features U[0, 1]; the camera is a general rigid transform."""
    g = torch.Generator().manual_seed(seed)
    fx, fy = focal, focal * 1.07
    cx, cy = width / 2 + principal_offset[0], height / 2 + principal_offset[1]
    z = 3 + 4 * torch.rand(n, generator=g, dtype=torch.float64)
    u = (torch.rand(n, generator=g, dtype=torch.float64) * 1.2 - 0.1) * width
    v = (torch.rand(n, generator=g, dtype=torch.float64) * 1.2 - 0.1) * height
    cam_pts = torch.stack([(u - cx) / fx * z, (v - cy) / fy * z, z], -1)
    lo, hi = torch.log(torch.tensor(sigma_px, dtype=torch.float64))
    px_sigma = torch.exp(lo + (hi - lo) * torch.rand(n, 3, generator=g, dtype=torch.float64))
    scales = px_sigma * z[:, None] / focal
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    opacities = 0.05 + 0.9 * torch.rand(n, generator=g, dtype=torch.float64)
    features = torch.rand(n, channels, generator=g, dtype=torch.float64)
    K = torch.tensor([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=torch.float64)
    viewmat = torch.eye(4, dtype=torch.float64)
    if rotate_camera:
        # A rotated, translated camera: world points = c2w applied to the camera-space points above.
        angle = torch.tensor(0.3, dtype=torch.float64)
        c, s = torch.cos(angle), torch.sin(angle)
        R = torch.tensor([[c, 0, s], [0, 1, 0], [-s, 0, c]], dtype=torch.float64) @ torch.tensor(
            [[1, 0, 0], [0, c, -s], [0, s, c]], dtype=torch.float64
        )
        t = torch.tensor([0.3, -0.2, 0.5], dtype=torch.float64)
        viewmat[:3, :3] = R
        viewmat[:3, 3] = t
    means = (cam_pts - viewmat[:3, 3]) @ viewmat[:3, :3]  # R^T (p - t): camera -> world
    return Scene(
        *(x.to(dtype) for x in (means, quats, scales, opacities, features, K, viewmat)),
        width=width,
        height=height,
    )
