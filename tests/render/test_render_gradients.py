"""Gradients against finite differences (float64) and the numba backend against the torch backend."""

from __future__ import annotations

import pytest
import torch

from stgc.render import rasterize

from .scenes import make_scene


def rel_l2(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a - b).norm() / b.norm().clamp(min=1e-30))


def _tiny_scene():
    """8 Gaussians over a 13x11 image, wide enough (2..4 px) that every parameter moves many pixels and translucent
    enough (opacity <= 0.7) that neither the alpha clamp nor early termination sits near a decision boundary."""
    scene = make_scene(8, width=13, height=11, channels=3, focal=14.0, sigma_px=(2.0, 4.0), seed=3,
                       dtype=torch.float64)  # fmt: skip
    scene.opacities.clamp_(max=0.7)
    return scene


@pytest.mark.parametrize("backend", ["torch", "numba"])
def test_float64_finite_differences(backend):
    scene = _tiny_scene()
    inputs = [t.detach().clone().requires_grad_(True) for t in scene.params()]
    background = torch.tensor([0.2, 0.5, 0.8], dtype=torch.float64, requires_grad=True)

    def render(means, quats, scales, opacities, features, bg):
        out = rasterize(means, quats, scales, opacities, features, scene.K, scene.viewmat, scene.width,
                        scene.height, bg, backend=backend)  # fmt: skip
        return out.image, out.alpha

    assert render(*inputs, background)[1].mean() > 0.3  # the scene covers the image
    assert torch.autograd.gradcheck(render, (*inputs, background), eps=1e-6, atol=1e-6, rtol=1e-4, fast_mode=True)


def test_numba_matches_torch_backend():
    scene = make_scene(1200, width=80, height=60, channels=9, principal_offset=(3.5, -2.25), seed=11)
    scene.opacities[::7] = 1.0  # alpha clamp at 0.99 active, early termination frequent
    background = torch.linspace(0.0, 1.0, 9)
    results = {}
    for backend in ("numba", "torch"):
        s = scene.leaves()
        bg = background.clone().requires_grad_(True)
        out = rasterize(*s.args(), bg, backend=backend, return_depth=True, return_weights=True)
        g = torch.Generator().manual_seed(5)
        loss = (out.image * torch.rand(out.image.shape, generator=g)).sum()
        loss = loss + (out.alpha * torch.rand(out.alpha.shape, generator=g)).sum()
        loss.backward()
        results[backend] = (out, [p.grad for p in s.params()] + [bg.grad, out.means2d.grad])
    (a, ga), (b, gb) = results["numba"], results["torch"]
    assert (a.image - b.image).abs().max() < 1e-5
    assert (a.alpha - b.alpha).abs().max() < 1e-5
    assert torch.equal(a.radii, b.radii)
    assert (a.depth - b.depth).abs().max() < 1e-5
    assert rel_l2(a.weights, b.weights) < 1e-5
    names = ["means", "quats", "scales", "opacities", "features", "background", "means2d"]
    for name, x, y in zip(names, ga, gb):
        assert rel_l2(x, y) < 1e-5, (name, rel_l2(x, y))
