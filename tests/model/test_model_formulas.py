"""STG formulas against hand-computed values, the official gradient detaching, and the official initialisation."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from stgc.model import STGModel, initial_log_scales, param_widths

from .helpers import point_cloud


def _two_gaussians(variant: str) -> STGModel:
    """Gaussian 0 evaluated at t=0.75 has Δ=+0.5; Gaussian 1 has Δ=−0.25."""
    widths = param_widths(variant)
    params = {key: torch.zeros(2, width) for key, width in widths.items()}
    params["xyz"] = torch.tensor([[1.0, 2.0, 3.0], [0.0, 0.0, 0.0]])
    params["motion"] = torch.tensor([[0.1, 0.2, 0.3, 1.0, 2.0, 3.0, -1.0, 0.0, 2.0], [1.0] * 9])
    params["trbf_center"] = torch.tensor([[0.25], [1.0]])
    params["trbf_scale"] = torch.tensor([[math.log(0.5)], [math.log(2.0)]])
    params["opacity"] = torch.tensor([[math.log(0.8 / 0.2)], [0.0]])
    params["rotation"] = torch.tensor([[1.0, 0.0, 0.0, 0.0], [0.0, 2.0, 0.0, 0.0]])
    params["omega"] = torch.tensor([[0.0, 0.0, 0.0, 2.0], [0.0, 0.0, 4.0, 0.0]])
    params["features_dc"] = torch.arange(2 * widths["features_dc"], dtype=torch.float32).reshape(2, -1)
    if variant == "full":
        params["features_t"] = torch.tensor([[2.0, 4.0, -6.0], [1.0, 1.0, 1.0]])
    from stgc.model import SandwichDecoder

    decoder = SandwichDecoder() if variant == "full" else None
    return STGModel(params, variant, decoder=decoder)


@pytest.mark.parametrize("variant", ["full", "lite"])
def test_time_evaluation_matches_hand_computed_values(variant):
    model = _two_gaussians(variant)
    t = 0.75
    # opacity: sigmoid(o)·exp(−(Δ/exp(s))²): 0.8·e^{−(0.5/0.5)²} and 0.5·e^{−(−0.25/2)²}
    expected_opacity = [0.8 * math.exp(-1.0), 0.5 * math.exp(-(0.125**2))]
    assert model.temporal_opacity(t).tolist() == pytest.approx(expected_opacity, rel=1e-6)
    # cubic position x + m[0:3]Δ + m[3:6]Δ² + m[6:9]Δ³
    expected_means = [
        [1 + 0.1 * 0.5 + 1 * 0.25 - 1 * 0.125, 2 + 0.2 * 0.5 + 2 * 0.25, 3 + 0.3 * 0.5 + 3 * 0.25 + 2 * 0.125],
        [-0.25 + 0.0625 - 0.015625] * 3,
    ]
    np.testing.assert_allclose(model.means_at(t).detach().numpy(), expected_means, atol=1e-6)
    # rotation normalize(q + ωΔ): (1,0,0,1)/√2 and (0,2,−1,0)/√5
    expected_rot = [[1 / math.sqrt(2), 0, 0, 1 / math.sqrt(2)], [0, 2 / math.sqrt(5), -1 / math.sqrt(5), 0]]
    np.testing.assert_allclose(model.rotations_at(t).detach().numpy(), expected_rot, atol=1e-6)
    features = model.features_at(t).detach().numpy()
    dc = model.params["features_dc"].detach().numpy()
    if variant == "full":
        assert features.shape == (2, 9)
        np.testing.assert_array_equal(features[:, :6], dc)
        np.testing.assert_allclose(features[:, 6:], [[1.0, 2.0, -3.0], [-0.25, -0.25, -0.25]], atol=1e-7)
    else:
        np.testing.assert_array_equal(features, dc)
    np.testing.assert_allclose(model.scales.detach().numpy(), 1.0)  # exp(0)


def test_trbf_center_gets_gradient_only_through_opacity():
    model = _two_gaussians("full")
    t = 0.75
    geometry = model.means_at(t).sum() + model.rotations_at(t)[:, 1:].sum() + model.features_at(t).sum()
    geometry.backward()
    # Δ' is detached in position/rotation/features, as in the official renderer
    assert model.params["trbf_center"].grad is None
    assert model.params["trbf_scale"].grad is None
    # but the polynomial coefficients see Δ', e.g. ∂x/∂m0 = Δ and ∂x/∂m6 = Δ³
    np.testing.assert_allclose(model.params["motion"].grad[:, 0].numpy(), [0.5, -0.25])
    np.testing.assert_allclose(model.params["motion"].grad[:, 6].numpy(), [0.125, -0.015625])

    model.temporal_opacity(t).sum().backward()
    # d/dμ [σ(o)·exp(−(Δ/s)²)] = σ(o)·exp(−(Δ/s)²)·2Δ/s²
    sigma = np.array([0.8, 0.5])
    delta = np.array([0.5, -0.25])
    s = np.array([0.5, 2.0])
    expected = sigma * np.exp(-((delta / s) ** 2)) * 2 * delta / s**2
    np.testing.assert_allclose(model.params["trbf_center"].grad[:, 0].numpy(), expected, rtol=1e-5)
    assert model.params["trbf_scale"].grad.abs().min() > 0


def _brute_force_log_scales(xyz: np.ndarray, k: int) -> np.ndarray:
    d2 = ((xyz[:, None, :] - xyz[None, :, :]) ** 2).sum(-1)
    np.fill_diagonal(d2, np.inf)
    nearest = np.sort(d2, axis=1)[:, :k]
    return np.clip(np.log(np.sqrt(np.maximum(nearest.mean(1), 1e-7))), -10, 1)


def test_initial_scales_on_constructed_points():
    h = 0.05
    cube = np.array([[x, y, z] for x in (0, h) for y in (0, h) for z in (0, h)], dtype=np.float64)
    # every corner of a cube has exactly 3 nearest neighbours at distance h
    np.testing.assert_allclose(initial_log_scales(cube), math.log(h), rtol=1e-6)

    # neighbours at 1, 2, 3 along the axes from the origin: mean squared distance 14/3
    star = np.array([[0, 0, 0], [1, 0, 0], [0, 2, 0], [0, 0, 3], [0, 0, 30.0]])
    assert initial_log_scales(star)[0] == pytest.approx(math.log(math.sqrt(14 / 3)), rel=1e-6)
    # an isolated point clamps to the official upper bound 1; duplicates to the 1e-7 floor of the squared distance
    assert initial_log_scales(star)[4] == pytest.approx(1.0)
    duplicates = np.zeros((4, 3))
    np.testing.assert_allclose(initial_log_scales(duplicates), math.log(math.sqrt(1e-7)), rtol=1e-6)

    rng = np.random.default_rng(3)
    cloud = rng.normal(size=(200, 3)) * rng.uniform(0.01, 3, size=(200, 1))
    np.testing.assert_allclose(initial_log_scales(cloud), _brute_force_log_scales(cloud, 3), rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("variant", ["full", "lite"])
def test_from_points_uses_the_official_initial_values(variant):
    cloud = point_cloud(40)
    model = STGModel.from_points(cloud, variant=variant, scene_extent=3.0, trbf_scale_init=-2.0)
    p = {key: value.detach().numpy() for key, value in model.params.items()}
    assert model.num_gaussians == 40 and model.scene_extent == 3.0
    assert sum(v.shape[1] for v in p.values()) == (35 if variant == "full" else 29)
    np.testing.assert_allclose(p["xyz"], cloud.xyz, rtol=1e-6)
    np.testing.assert_allclose(p["scaling"], np.repeat(_brute_force_log_scales(cloud.xyz, 3)[:, None], 3, 1), rtol=1e-5)
    np.testing.assert_array_equal(p["rotation"], np.tile([1.0, 0, 0, 0], (40, 1)))
    np.testing.assert_allclose(torch.sigmoid(model.params["opacity"]).detach().numpy(), 0.1, rtol=1e-6)
    np.testing.assert_allclose(p["trbf_center"][:, 0], cloud.time, rtol=1e-7)
    np.testing.assert_array_equal(p["trbf_scale"], -2.0)
    for zero in ("omega", "motion") + (("features_t",) if variant == "full" else ()):
        assert not p[zero].any()
    rgb = cloud.rgb.astype(np.float32)
    expected_dc = np.concatenate([rgb, rgb], 1) if variant == "full" else rgb
    np.testing.assert_array_equal(p["features_dc"], expected_dc)
    assert (model.decoder is not None) == (variant == "full")


def test_from_points_accepts_uint8_colours_and_rejects_bad_clouds():
    cloud = point_cloud(10)
    as_bytes = SimpleNamespace(xyz=cloud.xyz, rgb=(cloud.rgb * 255).astype(np.uint8), time=cloud.time)
    model = STGModel.from_points(as_bytes, variant="lite")
    np.testing.assert_allclose(model.params["features_dc"].detach().numpy(), as_bytes.rgb / 255.0, rtol=1e-6)
    from stgc.errors import DataError

    with pytest.raises(DataError, match="shapes"):
        STGModel.from_points(SimpleNamespace(xyz=cloud.xyz, rgb=cloud.rgb[:5], time=cloud.time))
    with pytest.raises(DataError, match="non-finite"):
        bad = cloud.xyz.copy()
        bad[0, 0] = np.nan
        STGModel.from_points(SimpleNamespace(xyz=bad, rgb=cloud.rgb, time=cloud.time))
