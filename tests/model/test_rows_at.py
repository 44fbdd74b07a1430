"""The Gaussians at time t: the fused numba kernels against the torch formulas (a second implementation) and finite
differences."""

from __future__ import annotations

import functools

import numpy as np
import pytest
import torch

from stgc.model import MIN_VISIBLE_OPACITY, STGModel, param_widths, stg
from stgc.model.stg import _temporal_opacity, rows_at

from .helpers import look_at_camera, random_model

OUTPUTS = ("means", "quats", "scales", "opacity", "features")


def _params(variant: str, dtype: torch.dtype, count: int = 600, seed: int = 0) -> dict[str, torch.Tensor]:
    generator = torch.Generator().manual_seed(seed)
    params = {k: torch.randn(count, w, generator=generator, dtype=dtype) for k, w in param_widths(variant).items()}
    params["trbf_center"] = torch.rand(count, 1, generator=generator, dtype=dtype)
    params["trbf_scale"] = torch.randn(count, 1, generator=generator, dtype=dtype) - 1.5
    # Rows the torch formulas treat specially: exp(s_t) underflowed at t = mu_t (x = 0) and away from it (culled),
    # beyond the cutoff, a NaN parameter (culled), and one exactly at its centre.
    params["trbf_scale"][0], params["trbf_center"][0] = -800.0, 0.3
    params["trbf_scale"][1] = -800.0
    params["trbf_scale"][2], params["trbf_center"][2] = -6.0, 0.3 + 40.0 * float(np.exp(-6.0))
    params["opacity"][3] = float("nan")
    params["trbf_center"][4] = 0.3
    return {k: v.requires_grad_() for k, v in params.items()}


def _run(params, opacity_scale, fused: bool, t: float = 0.3):
    """rows_at's rows and the gradients of a loss whose weights follow the row ids (so that both paths' losses
    weigh a row alike even where one keeps a row the other culls)."""
    rows = rows_at(params, t, opacity_scale, fused=fused)
    n = params["xyz"].shape[0]
    loss = torch.zeros((), dtype=params["xyz"].dtype)
    for i, name in enumerate(OUTPUTS):
        value = getattr(rows, name)
        weights = torch.randn((n, *value.shape[1:]), generator=torch.Generator().manual_seed(i), dtype=value.dtype)
        loss = loss + (value * weights[rows.index]).sum()
    inputs = list(params.values()) + ([opacity_scale] if opacity_scale is not None else [])
    return rows, torch.autograd.grad(loss, inputs)


@pytest.mark.parametrize("variant", ["full", "lite"])
@pytest.mark.parametrize("scaled", [False, True])
def test_fused_rows_match_the_torch_formulas_in_float64(variant, scaled):
    params = _params(variant, torch.float64)
    opacity_scale = torch.rand(600, dtype=torch.float64, requires_grad=True) if scaled else None
    fused, fused_grads = _run(params, opacity_scale, fused=True)
    formulas, formula_grads = _run(params, opacity_scale, fused=False)
    assert type(fused.means.grad_fn).__name__ == "_FusedRowsAtBackward"
    assert torch.equal(fused.index, formulas.index)
    assert 0 in fused.index and 4 in fused.index and not {1, 2, 3} & set(fused.index.tolist())
    for name in OUTPUTS:
        torch.testing.assert_close(getattr(fused, name), getattr(formulas, name), rtol=1e-13, atol=1e-13)
    others = torch.arange(600) != 3  # the NaN row: culled, so 0 here where the formulas give 0 * NaN
    for a, b in zip(fused_grads, formula_grads):
        assert bool(torch.isfinite(a).all())
        torch.testing.assert_close(a[others], b[others], rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("variant", ["full", "lite"])
def test_fused_rows_match_the_torch_formulas_in_float32(variant):
    """float32: the kernels compute each row in float64 and round once, the formulas round every op; so values and
    gradients agree to float32 rounding, and only a row whose opacity is within rounding of the threshold may be
    kept by one and culled by the other."""
    params = _params(variant, torch.float32, count=4000)
    opacity_scale = torch.rand(4000, requires_grad=True)
    fused, fused_grads = _run(params, opacity_scale, fused=True)
    formulas, formula_grads = _run(params, opacity_scale, fused=False)
    a, b = set(fused.index.tolist()), set(formulas.index.tolist())
    exact = (_temporal_opacity({k: v.double() for k, v in params.items()}, 0.3) * opacity_scale.double()).detach()
    for row in a ^ b:
        assert abs(float(exact[row]) / MIN_VISIBLE_OPACITY - 1.0) < 1e-6, row
    common = torch.tensor(sorted((a & b) - {3}))
    assert len(common) > 2000
    in_fused = torch.searchsorted(fused.index, common)
    in_formulas = torch.searchsorted(formulas.index, common)
    for name in OUTPUTS:
        torch.testing.assert_close(getattr(fused, name)[in_fused], getattr(formulas, name)[in_formulas],
                                   rtol=1e-5, atol=1e-5)  # fmt: skip
    culled = torch.ones(4000, dtype=torch.bool)
    culled[fused.index] = False
    for x, y in zip(fused_grads, formula_grads):
        torch.testing.assert_close(x[common], y[common], rtol=1e-4, atol=1e-5)
        assert bool((x[culled] == 0).all())


def test_fused_rows_pass_a_finite_difference_gradient_check():
    params = _params("full", torch.float64, count=40, seed=1)
    with torch.no_grad():
        params["trbf_scale"].clamp_(min=-6.0)  # finite differences of exp(s) need a step they resolve
        params["opacity"].add_(3.0)  # no row within a step of the threshold, where the cut is discontinuous
        params["opacity"][3] = 0.0
    keys = list(params)
    opacity_scale = torch.rand(40, dtype=torch.float64, requires_grad=True)
    rows = rows_at(params, 0.3, opacity_scale)
    assert 5 < len(rows.index) < 40

    def with_centres_fixed(*tensors: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """Every output, mu_t held: the state at t takes Delta' = t - mu_t without gradient (the official
        renderer's detach), which finite differences in mu_t would see."""
        given = dict(zip(moving, tensors[:-1]), trbf_center=params["trbf_center"])
        out = rows_at(given, 0.3, tensors[-1], fused=True)
        return tuple(getattr(out, name) for name in OUTPUTS)

    def opacity(*tensors: torch.Tensor) -> torch.Tensor:
        return rows_at(dict(zip(keys, tensors[:-1])), 0.3, tensors[-1], fused=True).opacity

    moving = [k for k in keys if k != "trbf_center"]
    assert torch.autograd.gradcheck(with_centres_fixed, (*(params[k] for k in moving), opacity_scale), eps=1e-7,
                                    atol=1e-8, rtol=1e-6)  # fmt: skip
    assert torch.autograd.gradcheck(opacity, (*params.values(), opacity_scale), eps=1e-7, atol=1e-8, rtol=1e-6)


def test_a_render_through_the_fused_rows_matches_one_through_the_formulas(monkeypatch):
    """The whole render (projection, compositing) in float64, with some rows culled at t: the same image and the
    same gradient of every parameter."""
    base = random_model("lite", count=120, seed=2)
    params = {k: v.detach().double() for k, v in base.params.items()}
    params["trbf_scale"] = params["trbf_scale"] - 2.0  # narrow lifetimes: some rows culled at t
    camera = look_at_camera(time=0.4)
    results = []
    for fused in (True, False):
        monkeypatch.setattr(stg, "rows_at", functools.partial(rows_at, fused=fused))
        model = STGModel(params, "lite", scene_extent=1.5)
        model.params = {k: torch.nn.Parameter(v.clone()) for k, v in params.items()}  # the model stores float32
        out = model.render(camera, background=torch.zeros(3, dtype=torch.float64), backend="numba")
        (out.rgb * torch.linspace(0.0, 1.0, out.rgb.numel(), dtype=torch.float64).reshape(out.rgb.shape)).sum().backward()
        results.append((out, {k: p.grad for k, p in model.params.items()}))
    (fused_out, fused_grads), (formula_out, formula_grads) = results
    assert 0 < len(fused_out.index) < 120
    assert torch.equal(fused_out.index, formula_out.index)
    torch.testing.assert_close(fused_out.rgb, formula_out.rgb, rtol=1e-12, atol=1e-12)
    for key in fused_grads:
        assert float(fused_grads[key].abs().max()) > 0.0, key
        torch.testing.assert_close(fused_grads[key], formula_grads[key], rtol=1e-9, atol=1e-12)


def test_the_fused_kernels_are_the_default_on_cpu_for_one_float_dtype():
    params = _params("full", torch.float32, count=50)
    assert type(rows_at(params, 0.3).means.grad_fn).__name__ == "_FusedRowsAtBackward"
    mixed = dict(params, xyz=params["xyz"].detach().double().requires_grad_())
    assert type(rows_at(mixed, 0.3).means.grad_fn).__name__ != "_FusedRowsAtBackward"  # the formulas promote
    with pytest.raises(ValueError, match="fused=True"):
        rows_at(mixed, 0.3, fused=True)


def test_degenerate_lifetimes_in_float32_get_the_formulas_values_and_finite_gradients():
    """Rows from the ordinary to the degenerate at t = 0.5 (trbf_scale -44 .. -200: exp(s)^2 underflows, exp(s)
    itself below -103; at and far from their centres), float32 as in training: the same cut and values as the
    guarded formulas, every gradient finite, and exactly 0 for the culled rows."""
    scale = [-0.5, -1.0, -2.0, -3.0, -3.0, -5.0, -20.0, -44.0, -50.0, -90.0, -110.0, -200.0, 3.0, 40.0, -50.0, -120.0]
    centre = [0.5, 0.2, 0.45, 0.4, 0.1, 0.3, 0.1, 0.1, 0.8, 0.0, 0.0, 1.0, 0.9, 0.3, 0.5, 0.5]
    params = _params("full", torch.float32, count=len(scale), seed=3)
    with torch.no_grad():
        params["trbf_scale"].copy_(torch.tensor(scale)[:, None])
        params["trbf_center"].copy_(torch.tensor(centre)[:, None])
    fused, fused_grads = _run(params, None, fused=True, t=0.5)
    formulas, formula_grads = _run(params, None, fused=False, t=0.5)
    assert torch.equal(fused.index, formulas.index)
    assert {14, 15} <= set(fused.index.tolist()) and {7, 8, 9, 10, 11} & set(fused.index.tolist()) == set()
    for name in OUTPUTS:
        torch.testing.assert_close(getattr(fused, name), getattr(formulas, name), rtol=1e-5, atol=1e-6)
    culled = torch.ones(len(scale), dtype=torch.bool)
    culled[fused.index] = False
    for a, b in zip(fused_grads, formula_grads):
        assert bool(torch.isfinite(a).all())
        assert bool((a[culled] == 0).all())
        torch.testing.assert_close(a[~culled], b[~culled], rtol=1e-4, atol=1e-6)


def test_nothing_visible_gives_empty_rows_and_zero_gradients():
    params = _params("lite", torch.float32, count=30)
    with torch.no_grad():
        params["trbf_scale"].fill_(-3.0)
        params["trbf_center"].fill_(0.9)
    opacity_scale = torch.rand(30, dtype=torch.float64, requires_grad=True)  # a dtype of its own
    rows = rows_at(params, 0.1, opacity_scale)
    assert rows.index.shape == (0,) and rows.means.shape == (0, 3) and rows.features.shape == (0, 3)
    (rows.means.sum() + rows.opacity.sum()).backward()
    for key, value in params.items():
        assert value.grad is not None and bool((value.grad == 0).all()), key
    assert opacity_scale.grad is not None and opacity_scale.grad.dtype == torch.float64
    assert bool((opacity_scale.grad == 0).all())
