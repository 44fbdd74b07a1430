"""model.render: temporal culling, what reaches the rasterizer, the decoder stage, and PLY round-trip renders."""

from __future__ import annotations

import dataclasses

from types import SimpleNamespace

import numpy as np
import pytest
import torch

import stgc.model.stg as stg_module
import stgc.render
from stgc.model import MIN_VISIBLE_OPACITY, STGModel, camera_rays

from .helpers import look_at_camera, point_cloud


def _scene(variant: str) -> STGModel:
    """Gaussians spread over time with narrow temporal support, so that at t=0.5 many are culled; anisotropic, so
    that their rotations matter (an isotropic Gaussian's rotation gradient is rounding noise)."""
    model = STGModel.from_points(point_cloud(60, seed=1), variant=variant, trbf_scale_init=float(np.log(0.15)))
    generator = torch.Generator().manual_seed(2)
    with torch.no_grad():
        model.params["motion"].copy_(torch.randn(60, 9, generator=generator) * 0.2)
        model.params["omega"].copy_(torch.randn(60, 4, generator=generator) * 0.5)
        model.params["scaling"].add_(torch.randn(60, 3, generator=generator) * 0.7)
        model.params["opacity"].copy_(torch.randn(60, 1, generator=generator) + 1.0)
        if variant == "full":
            model.params["features_t"].copy_(torch.randn(60, 3, generator=generator))
    return model


class _RecordingRasterizer:
    """Stands in for stgc.render.rasterize: records its inputs, returns an opacity-weighted sum of the features
    as a constant image, so gradients flow like through a real one."""

    def __init__(self):
        self.calls = []

    def __call__(self, means, quats, scales, opacities, features, K, viewmat, width, height, background=None, **kw):
        self.calls.append(dict(means=means, quats=quats, scales=scales, opacities=opacities, features=features,
                               K=K, viewmat=viewmat, width=width, height=height, background=background, **kw))
        pixel = (opacities[:, None] * features).sum(0)
        image = pixel.expand(height, width, -1)
        alpha = opacities.sum().expand(height, width)
        return SimpleNamespace(image=image, alpha=alpha, depth=torch.zeros(height, width))


@pytest.mark.parametrize("variant", ["full", "lite"])
def test_render_culls_by_temporal_opacity_and_passes_time_evaluated_gaussians(monkeypatch, variant):
    fake = _RecordingRasterizer()
    monkeypatch.setattr(stgc.render, "rasterize", fake)
    model = _scene(variant)
    camera = look_at_camera(time=0.5)
    out = model.render(camera)

    opacity = model.temporal_opacity(0.5).detach()
    expected_index = torch.nonzero(opacity >= MIN_VISIBLE_OPACITY)[:, 0]
    assert 0 < len(expected_index) < model.num_gaussians  # the scene really exercises culling
    assert torch.equal(out.index, expected_index)
    call = fake.calls[0]
    torch.testing.assert_close(call["means"], model.means_at(0.5)[expected_index])
    # Passed unnormalised (every backend normalises): the same rotation, a positive multiple of rotations_at's.
    torch.testing.assert_close(torch.nn.functional.normalize(call["quats"], dim=1), model.rotations_at(0.5)[expected_index])
    torch.testing.assert_close(call["scales"], model.scales[expected_index])
    torch.testing.assert_close(call["opacities"], opacity[expected_index])
    torch.testing.assert_close(call["features"], model.features_at(0.5)[expected_index])
    assert call["K"].dtype == torch.float32 and np.allclose(call["K"].numpy(), camera.K)
    assert np.allclose(call["viewmat"].numpy(), camera.w2c)
    assert (call["width"], call["height"]) == (camera.width, camera.height)

    if variant == "full":
        rays = camera_rays(camera.K, camera.w2c, camera.width, camera.height)
        torch.testing.assert_close(out.rgb, model.decoder(out.features, rays))
    else:
        assert out.rgb is out.features

    out.rgb.sum().backward()
    grad_rows = model.params["opacity"].grad[:, 0] != 0
    culled = torch.ones(model.num_gaussians, dtype=torch.bool)
    culled[expected_index] = False
    assert not grad_rows[culled].any()  # culled Gaussians do not take part
    assert model.params["trbf_center"].grad[expected_index].abs().sum() > 0  # μ_t learns through the opacity

    # an explicit t overrides camera.time; the camera tensors are built once
    model.render(camera, t=0.1)
    assert fake.calls[1]["K"] is call["K"]
    assert not torch.equal(fake.calls[1]["opacities"], call["opacities"])


def test_background_is_given_in_feature_space(monkeypatch):
    fake = _RecordingRasterizer()
    monkeypatch.setattr(stgc.render, "rasterize", fake)
    camera = look_at_camera()
    _scene("full").render(camera, background=[0.2, 0.3, 0.4])
    assert fake.calls[-1]["background"].tolist() == pytest.approx([0.2, 0.3, 0.4, 0, 0, 0, 0, 0, 0])
    _scene("lite").render(camera, background=torch.ones(3))
    assert fake.calls[-1]["background"].tolist() == [1.0, 1.0, 1.0]
    with pytest.raises(ValueError, match="background"):
        _scene("lite").render(camera, background=torch.ones(9))


@pytest.mark.parametrize("variant, backend", [("full", "numba"), ("lite", "torch")])
def test_temporal_culling_is_exact_against_rasterizing_everything(variant, backend):
    """Same image and same parameter gradients as rasterizing all Gaussians (the official way)."""
    if backend not in stgc.render.available_backends():
        pytest.skip(f"render backend {backend} unavailable")
    model = _scene(variant)
    camera = look_at_camera(width=32, height=24, time=0.5)
    weights = torch.rand(camera.height, camera.width, 3, generator=torch.Generator().manual_seed(0))

    out = model.render(camera, backend=backend)
    (out.rgb * weights).sum().backward()
    culled_grads = {key: param.grad.clone() for key, param in model.params.items()}
    for param in model.params.values():
        param.grad = None
    everything = stgc.render.rasterize(
        model.means_at(0.5), model.rotations_at(0.5), model.scales, model.temporal_opacity(0.5),
        model.features_at(0.5), torch.tensor(camera.K, dtype=torch.float32),
        torch.tensor(camera.w2c, dtype=torch.float32), camera.width, camera.height, backend=backend,
    )
    rgb = everything.image
    if variant == "full":
        rgb = model.decoder(rgb, camera_rays(camera.K, camera.w2c, camera.width, camera.height))
    (rgb * weights).sum().backward()

    assert len(out.index) < model.num_gaussians
    assert out.alpha.max() > 0.3  # something is actually drawn
    torch.testing.assert_close(out.features, everything.image.detach(), rtol=0, atol=1e-6)
    torch.testing.assert_close(out.rgb.detach(), rgb.detach(), rtol=0, atol=1e-6)
    for key, param in model.params.items():
        assert culled_grads[key].abs().sum() > 0, key
        # Float32 rounding of the same sums in another order, relative to the largest entry.
        scale = float(param.grad.abs().max())
        torch.testing.assert_close(culled_grads[key], param.grad, rtol=1e-5, atol=1e-6 * scale, msg=key)


@pytest.mark.parametrize("variant", ["full", "lite"])
def test_a_saved_ply_renders_the_same_image(tmp_path, variant):
    model = _scene(variant)
    loaded = STGModel.load(model.save(tmp_path / "point_cloud" / "iteration_1"))
    camera = look_at_camera(width=32, height=24, time=0.5)
    with torch.no_grad():
        before = model.render(camera, backend="torch").rgb
        after = loaded.render(camera, backend="torch").rgb
    assert before.std() > 0
    assert torch.equal(before, after)


def test_nothing_is_culled_at_initialisation(monkeypatch):
    # s_t = 0 and opacity 0.1 give α(t) >= 0.1·e^{-1} > 1/255 for every t in [0, 1]: the no-copy path
    fake = _RecordingRasterizer()
    monkeypatch.setattr(stgc.render, "rasterize", fake)
    model = STGModel.from_points(point_cloud(30), variant="lite")
    out = model.render(look_at_camera(time=0.9))
    assert torch.equal(out.index, torch.arange(30))
    torch.testing.assert_close(fake.calls[0]["means"], model.means_at(0.9))
    torch.testing.assert_close(fake.calls[0]["opacities"], model.temporal_opacity(0.9))
    out.rgb.sum().backward()
    assert (model.params["opacity"].grad != 0).all()


@pytest.mark.parametrize("depth, seen", [(0.15, False), (0.25, True)])
def test_gaussians_closer_than_the_official_near_plane_are_not_drawn(depth, seen):
    """Official STG culls view depth <= 0.2 (NEAR_PLANE). One big opaque Gaussian in front of the lens: drawn at
    depth 0.25, dropped at 0.15, where the image is the background."""
    from stgc.model import NEAR_PLANE

    assert NEAR_PLANE == 0.2
    camera = look_at_camera(distance=4.0)  # camera centre at z = -4, looking along +z
    model = STGModel.from_points(SimpleNamespace(xyz=np.array([[0.0, 0.0, depth - 4.0]]), rgb=np.ones((1, 3)),
                                                 time=np.array([0.5])), variant="lite")
    with torch.no_grad():
        model.params["scaling"].fill_(float(np.log(0.05)))
        model.params["opacity"].fill_(5.0)
        model.params["features_dc"].fill_(1.0)
    out = model.render(camera, t=0.5, background=torch.zeros(3), backend="torch")
    assert (out.alpha.max().item() > 0.5) is seen
    near = model.render(camera, t=0.5, background=torch.zeros(3), backend="torch", near_plane=0.01)
    assert near.alpha.max().item() > 0.5  # the override reaches the rasterizer
    # A camera carries its own near plane (the format's): one at 0.3 culls both depths, one at 0.1 neither.
    for near_plane, drawn in ((0.3, False), (0.1, True)):
        out = model.render(dataclasses.replace(camera, near=near_plane), t=0.5, background=torch.zeros(3),
                           backend="torch")
        assert (out.alpha.max().item() > 0.5) is drawn


def test_gaussians_below_the_cut_at_their_peak_never_show_so_leaving_them_out_changes_no_render():
    model = _scene("full")
    with torch.no_grad():  # push some temporal centres outside [0, 1]: those fade before the sequence reaches them
        model.params["trbf_center"][:20] = torch.linspace(-0.6, 1.6, 20)[:, None]
    peak = model.peak_temporal_opacity()
    # Independent check of the peak: a dense sweep of t over [0, 1] never exceeds it and comes within 1e-4 of it.
    sweep = torch.stack([model.temporal_opacity(float(t)).detach() for t in np.linspace(0, 1, 2001)])
    assert torch.all(sweep.max(0).values <= peak + 1e-7)
    assert torch.all(sweep.max(0).values >= peak * (1 - 1e-4))
    keep = peak >= MIN_VISIBLE_OPACITY
    assert 0 < int((~keep).sum()) < model.num_gaussians
    pruned = STGModel.from_state_dict(model.state_dict())
    pruned.prune(keep)
    for t in (0.0, 0.13, 0.5, 0.97, 1.0):
        camera = look_at_camera(time=t)
        # Equal up to float32 rounding: the temporal opacities are computed over all rows, and torch's vectorised
        # loops round an element differently depending on where it falls in a tensor of another length.
        torch.testing.assert_close(model.render(camera).rgb, pruned.render(camera).rgb, rtol=0, atol=1e-6, msg=str(t))


@pytest.mark.parametrize("variant", ["full", "lite"])
def test_render_views_shares_the_gaussians_at_t_and_matches_rendering_each_view(monkeypatch, variant):
    """A training batch's views share t: render_views computes the Gaussians at t once, and gives the images and the
    gradients that rendering the views one by one gives."""
    model = _scene(variant)
    near = look_at_camera(time=0.5, distance=4.0)
    side = dataclasses.replace(look_at_camera(time=0.5, distance=5.0), name="cam01")
    side.w2c[0, 3] = 0.7  # a second viewpoint, shifted sideways
    calls = []
    real_rows_at = stg_module.rows_at
    monkeypatch.setattr(stg_module, "rows_at", lambda *a, **k: calls.append(1) or real_rows_at(*a, **k))
    weights = [torch.rand(16, 24, 3, generator=torch.Generator().manual_seed(s)) for s in (3, 4)]

    together = model.render_views([near, side], 0.5, backend="numba")
    assert len(calls) == 1
    sum((out.rgb * w).sum() for out, w in zip(together, weights)).backward()
    grads_together = {k: p.grad.clone() for k, p in model.params.items() if p.grad is not None}
    for p in model.params.values():
        p.grad = None

    one_by_one = [model.render(camera, t=0.5, backend="numba") for camera in (near, side)]
    assert len(calls) == 3
    sum((out.rgb * w).sum() for out, w in zip(one_by_one, weights)).backward()
    for a, b in zip(together, one_by_one):
        assert torch.equal(a.rgb, b.rgb) and torch.equal(a.index, b.index)
    assert not torch.equal(together[0].rgb, together[1].rgb)  # two different views
    assert grads_together.keys() == {k for k, p in model.params.items() if p.grad is not None}
    for key, grad in grads_together.items():
        assert grad.abs().max() > 0, key
        torch.testing.assert_close(grad, model.params[key].grad, rtol=1e-5, atol=1e-7, msg=key)
