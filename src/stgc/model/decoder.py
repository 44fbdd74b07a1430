"""The full model's per-pixel colour decoder (the official "Sandwich") and its view-ray image.

The rasterizer produces a 9-channel feature image F = [albedo(3) | specular(3) | time feature(3)]. Per pixel,
    rgb = act(albedo + W2 · ReLU(W1 · [specular, time feature, ray origin, ray direction]))
with W1: 12 -> 6 and W2: 6 -> 3, no biases. The weights are stored as 1x1-convolution kernels ([out, in, 1, 1])
under the names `mlp1.weight` / `mlp2.weight` so that the state_dict is interchangeable with the official
`point_cloud.pt`; the maths is done as matrix products on channel-last images.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch
from torch import nn

from stgc.model.config import DECODER_ACTIVATIONS

FEATURE_CHANNELS = 9
RAY_CHANNELS = 6
HIDDEN_CHANNELS = 6
# Columns of the first layer's input [specular(3), time feature(3), ray origin(3), ray direction(3)] that carry the
# ray origin and the ray direction.
RAY_ORIGIN_INPUTS = slice(6, 9)
RAY_DIRECTION_INPUTS = slice(9, 12)


class SandwichDecoder(nn.Module):
    """Maps a [H, W, 9] feature image and a [H, W, 6] ray image to [H, W, 3] colour."""

    def __init__(self, activation: str = "sigmoid", generator: torch.Generator | None = None):
        super().__init__()
        if activation not in DECODER_ACTIVATIONS:
            raise ValueError(f"decoder activation must be one of {DECODER_ACTIVATIONS}, got {activation!r}")
        self.activation = activation
        in_channels = 3 + 3 + RAY_CHANNELS
        self.mlp1 = _Conv1x1Weight(_conv_default_init(HIDDEN_CHANNELS, in_channels, generator))
        self.mlp2 = _Conv1x1Weight(_conv_default_init(3, HIDDEN_CHANNELS, generator))
        self._ignored: list[slice] = []  # ray-input columns held at zero (ignore_ray_inputs)
        self._ignore_hook: Any = None

    def extra_repr(self) -> str:
        return f"activation={self.activation!r}"

    def ignore_ray_inputs(self, *, origin: bool = False, direction: bool = False) -> None:
        """Zero the first layer's weights on the ray origin and/or direction and keep them zero while training
        (their gradient is masked), so the colour no longer depends on the camera's position (origin) or on the
        viewing direction (direction). Idempotent; inputs ignored once stay ignored."""
        wanted = [cols for cols, on in ((RAY_ORIGIN_INPUTS, origin), (RAY_DIRECTION_INPUTS, direction))
                  if on and cols not in self._ignored]
        if not wanted:
            return
        self._ignored.extend(wanted)
        mask = torch.ones_like(self.mlp1.weight)
        for cols in self._ignored:
            mask[:, cols] = 0.0
        with torch.no_grad():
            self.mlp1.weight.mul_(mask)
        if self._ignore_hook is not None:
            self._ignore_hook.remove()
        self._ignore_hook = self.mlp1.weight.register_hook(lambda grad: grad * mask)  # type: ignore[no-untyped-call]

    @property
    def uses_ray_origin(self) -> bool:
        return bool(self.mlp1.weight.detach()[:, RAY_ORIGIN_INPUTS].abs().sum() > 0)

    @property
    def uses_ray_direction(self) -> bool:
        return bool(self.mlp1.weight.detach()[:, RAY_DIRECTION_INPUTS].abs().sum() > 0)

    def forward(self, features: torch.Tensor, rays: torch.Tensor) -> torch.Tensor:
        if features.shape[-1] != FEATURE_CHANNELS:
            raise ValueError(f"decoder expects {FEATURE_CHANNELS} feature channels, got {features.shape[-1]}")
        albedo = features[..., 0:3]
        decoder_input = torch.cat([features[..., 3:9], rays.to(features.dtype)], dim=-1)
        hidden = torch.relu(decoder_input @ self.mlp1.weight.flatten(1).T)
        out = albedo + hidden @ self.mlp2.weight.flatten(1).T
        if self.activation == "sigmoid":
            return torch.sigmoid(out)
        if self.activation == "clamp":
            return out.clamp(0.0, 1.0)
        return out


class _Conv1x1Weight(nn.Module):
    """Holds one bias-free 1x1-convolution kernel [out, in, 1, 1] (state_dict key `<name>.weight`)."""

    def __init__(self, weight: torch.Tensor):
        super().__init__()
        self.weight = nn.Parameter(weight)

    def extra_repr(self) -> str:
        out_channels, in_channels = self.weight.shape[:2]
        return f"{in_channels} -> {out_channels}, 1x1, no bias"


def _conv_default_init(out_channels: int, in_channels: int, generator: torch.Generator | None) -> torch.Tensor:
    # Same distribution as torch's default Conv2d init (kaiming_uniform with a=sqrt(5) gives U(±1/sqrt(fan_in))),
    # drawn from our own generator so that a model's initial decoder depends only on its seed.
    bound = 1.0 / math.sqrt(in_channels)
    weight = torch.rand(out_channels, in_channels, 1, 1, generator=generator, dtype=torch.float32)
    return weight * (2.0 * bound) - bound


def camera_rays(K: np.ndarray, w2c: np.ndarray, width: int, height: int) -> torch.Tensor:
    """Per-pixel [ray origin (3), unit world ray direction (3)] through pixel centres, float32 [H, W, 6].

    K uses the pixel-centre-at-+0.5 convention, so pixel (u, v) looks along K^-1 (u + 0.5, v + 0.5, 1). This equals
    the official rays (pix2ndc then the inverse projection) when the principal point is the image centre, and
    follows the intrinsics otherwise.
    """
    K = np.asarray(K, dtype=np.float64)
    w2c = np.asarray(w2c, dtype=np.float64)
    rotation_w2c = w2c[:3, :3]
    centre = -rotation_w2c.T @ w2c[:3, 3]
    u, v = np.meshgrid(np.arange(width, dtype=np.float64) + 0.5, np.arange(height, dtype=np.float64) + 0.5)
    pixels = np.stack([u, v, np.ones_like(u)], axis=-1)
    directions_cam = pixels @ np.linalg.inv(K).T
    directions_world = directions_cam @ rotation_w2c  # (R^T d) for every row vector d
    directions_world /= np.linalg.norm(directions_world, axis=-1, keepdims=True)
    origins = np.broadcast_to(centre, directions_world.shape)
    return torch.from_numpy(np.concatenate([origins, directions_world], axis=-1).astype(np.float32))
