"""The full model's decoder against a hand example and an official-style Conv2d implementation; its view rays."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from torch import nn

from stgc.model import SandwichDecoder, camera_rays


def test_decoder_on_a_hand_example_fixes_the_input_order():
    decoder = SandwichDecoder("sigmoid")
    w1 = torch.zeros(6, 12)
    w1[0, 0] = 1.0  # specular[0]
    w1[1, 3] = -1.0  # −time feature[0]
    w1[2, 6] = 1.0  # ray origin x
    w1[3, 9] = 1.0  # ray direction x
    w2 = torch.zeros(3, 6)
    w2[0, 0] = 1.0
    w2[1, 1] = 1.0
    w2[2, 2] = 1.0
    w2[2, 3] = 1.0
    decoder.load_state_dict({"mlp1.weight": w1.reshape(6, 12, 1, 1), "mlp2.weight": w2.reshape(3, 6, 1, 1)})
    features = torch.tensor([[[0.1, 0.2, 0.3, 0.7, -5.0, -5.0, -0.4, 9.0, 9.0]]])  # [1, 1, 9]
    rays = torch.tensor([[[-2.0, 8.0, 8.0, 0.6, 0.0, 0.8]]])
    out = decoder(features, rays)[0, 0]
    # r: σ(0.1 + relu(0.7)); g: σ(0.2 + relu(0.4)); b: σ(0.3 + relu(−2) + relu(0.6))
    expected = [1 / (1 + math.exp(-v)) for v in (0.8, 0.6, 0.9)]
    np.testing.assert_allclose(out.detach().numpy(), expected, rtol=1e-6)

    decoder.activation = "none"
    np.testing.assert_allclose(decoder(features, rays)[0, 0].detach().numpy(), [0.8, 0.6, 0.9], rtol=1e-6)
    decoder.activation = "clamp"
    assert decoder(features * 10, rays)[0, 0].tolist() == [1.0, 1.0, 1.0]


class OfficialStyleSandwich(nn.Module):
    """The official decoder's structure: 1x1 convs on [1, C, H, W], input cat(spec, timefeature, rays)."""

    def __init__(self):
        super().__init__()
        self.mlp1 = nn.Conv2d(12, 6, kernel_size=1, bias=False)
        self.mlp2 = nn.Conv2d(6, 3, kernel_size=1, bias=False)

    def forward(self, image, rays):
        albedo, spec, timefeature = image.chunk(3, dim=1)
        hidden = torch.relu(self.mlp1(torch.cat([spec, timefeature, rays], dim=1)))
        return torch.sigmoid(albedo + self.mlp2(hidden))


def test_decoder_equals_official_conv_structure_and_shares_its_state_dict():
    torch.manual_seed(0)
    official = OfficialStyleSandwich()
    ours = SandwichDecoder("sigmoid")
    assert {k: tuple(v.shape) for k, v in ours.state_dict().items()} == {
        k: tuple(v.shape) for k, v in official.state_dict().items()
    }
    ours.load_state_dict(official.state_dict())
    features = torch.randn(5, 7, 9)
    rays = torch.randn(5, 7, 6)
    expected = official(features.permute(2, 0, 1)[None], rays.permute(2, 0, 1)[None])[0].permute(1, 2, 0)
    torch.testing.assert_close(ours(features, rays), expected, rtol=1e-6, atol=1e-6)


def _official_rays(fx, fy, width, height, w2c):
    """Rays the way the official Camera builds them: pix2ndc, inverse 3DGS projection, rotate by c2w."""
    znear, zfar = 0.01, 100.0
    tan_x, tan_y = width / (2 * fx), height / (2 * fy)
    P = np.zeros((4, 4))
    P[0, 0] = 1 / tan_x
    P[1, 1] = 1 / tan_y
    P[3, 2] = 1.0
    P[2, 2] = zfar / (zfar - znear)
    P[2, 3] = -(zfar * znear) / (zfar - znear)
    ys, xs = np.meshgrid(np.arange(height), np.arange(width), indexing="ij")
    ndc = np.stack([(2 * xs + 1) / width - 1, (2 * ys + 1) / height - 1, np.ones_like(xs), np.ones_like(xs)], -1)
    local = ndc @ np.linalg.inv(P).T
    local = local[..., :3] / local[..., 3:]
    c2w = np.linalg.inv(w2c)
    direction = local @ c2w[:3, :3].T
    direction /= np.linalg.norm(direction, axis=-1, keepdims=True)
    origin = np.broadcast_to(c2w[:3, 3], direction.shape)
    return np.concatenate([origin, direction], -1)


def _random_w2c(seed):
    rng = np.random.default_rng(seed)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.linalg.det(q))
    w2c = np.eye(4)
    w2c[:3, :3] = q
    w2c[:3, 3] = rng.normal(size=3)
    return w2c


def test_rays_match_the_official_construction_for_a_centred_principal_point():
    width, height, fx, fy = 20, 12, 17.0, 15.0
    w2c = _random_w2c(1)
    K = np.array([[fx, 0, width / 2], [0, fy, height / 2], [0, 0, 1.0]])
    rays = camera_rays(K, w2c, width, height).numpy()
    assert rays.shape == (height, width, 6)
    np.testing.assert_allclose(rays, _official_rays(fx, fy, width, height, w2c), atol=2e-6)


def test_rays_pass_through_pixel_centres_for_an_offset_principal_point():
    width, height = 9, 7
    K = np.array([[11.0, 0, 3.2], [0, 13.0, 4.9], [0, 0, 1.0]])
    w2c = _random_w2c(2)
    rays = camera_rays(K, w2c, width, height).numpy().astype(np.float64)
    points = rays[..., :3] + 2.5 * rays[..., 3:]
    cam = points @ w2c[:3, :3].T + w2c[:3, 3]
    pix = cam @ K.T
    pix = pix[..., :2] / pix[..., 2:]
    ys, xs = np.meshgrid(np.arange(height), np.arange(width), indexing="ij")
    np.testing.assert_allclose(pix, np.stack([xs + 0.5, ys + 0.5], -1), atol=1e-4)
    np.testing.assert_allclose(np.linalg.norm(rays[..., 3:], axis=-1), 1.0, atol=1e-6)


def test_unknown_activation_is_rejected():
    with pytest.raises(ValueError, match="activation"):
        SandwichDecoder("relu")
