"""prune / extend / reset_opacity keep Adam's per-row state aligned with the Gaussians."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from stgc.model import STGModel

from .helpers import random_model

LRS = {
    "xyz": 1e-2,
    "scaling": 5e-3,
    "rotation": 1e-3,
    "omega": 1e-4,
    "opacity": 5e-2,
    "trbf_center": 1e-4,
    "trbf_scale": 3e-2,
    "motion": 3e-3,
    "features_dc": 2.5e-3,
    "features_t": 1e-3,
}


def _lrs(model):
    return {key: LRS[key] for key in model.params}


def _random_grads(model, seed):
    generator = torch.Generator().manual_seed(seed)
    for param in model.params.values():
        param.grad = torch.randn(param.shape, generator=generator)
    if model.decoder is not None:
        for param in model.decoder.parameters():
            param.grad = torch.randn(param.shape, generator=generator)


def _trained_copy_pair(variant):
    """Two identical models with identical optimizer state after two Adam steps."""
    a = random_model(variant, count=12)
    opt_a = a.make_optimizer(_lrs(a), decoder_lr=1e-3)
    for step in range(2):
        _random_grads(a, seed=step)
        opt_a.step()
    b = STGModel.from_state_dict(a.state_dict())
    opt_b = b.make_optimizer(_lrs(b), decoder_lr=1e-3)
    # deepcopy: load_state_dict keeps same-device tensors by reference (the step counters would be shared)
    opt_b.load_state_dict(copy.deepcopy(opt_a.state_dict()))
    return a, b


@pytest.mark.parametrize("variant", ["full", "lite"])
def test_optimizer_groups_are_named_by_param(variant):
    model = random_model(variant)
    optimizer = model.make_optimizer(_lrs(model), decoder_lr=1e-4)
    names = [group["name"] for group in optimizer.param_groups]
    assert names == list(model.params) + (["decoder"] if variant == "full" else [])
    for group in optimizer.param_groups:
        assert group["eps"] == 1e-15
        if group["name"] != "decoder":
            assert group["params"][0] is model.params[group["name"]]
            assert group["lr"] == LRS[group["name"]]
    with pytest.raises(ValueError, match="missing"):
        model.make_optimizer({"xyz": 1.0})


@pytest.mark.parametrize("variant", ["full", "lite"])
def test_prune_then_step_equals_step_then_prune(variant):
    pruned, reference = _trained_copy_pair(variant)
    keep = torch.tensor([True, False, True, True, False, False, True, True, True, False, True, False])
    pruned.prune(keep)
    assert pruned.num_gaussians == int(keep.sum())
    for key, param in pruned.params.items():
        state = pruned.optimizer.state[param]
        ref_state = reference.optimizer.state[reference.params[key]]
        assert torch.equal(state["exp_avg"], ref_state["exp_avg"][keep])
        assert torch.equal(state["exp_avg_sq"], ref_state["exp_avg_sq"][keep])
        assert pruned.optimizer.param_groups[list(pruned.params).index(key)]["params"][0] is param

    _random_grads(reference, seed=7)
    for key, param in pruned.params.items():
        param.grad = reference.params[key].grad[keep].clone()
    if variant == "full":
        for mine, theirs in zip(pruned.decoder.parameters(), reference.decoder.parameters()):
            mine.grad = theirs.grad.clone()
    pruned.optimizer.step()
    reference.optimizer.step()
    for key in pruned.params:
        # float32 rounding allowed: the fused Adam kernel's rounding of an element can depend on the tensor's length
        # (see the extend test below); a moment on the wrong row changes the step by about a learning rate.
        torch.testing.assert_close(pruned.params[key].detach(), reference.params[key].detach()[keep],
                                   rtol=1e-6, atol=1e-9)



def test_step_after_prune_equals_step_on_a_model_built_from_the_kept_rows():
    source, _ = _trained_copy_pair("lite")
    keep = torch.zeros(source.num_gaussians, dtype=torch.bool)
    keep[[0, 3, 4, 9]] = True
    kept_rows = source.gather(keep)
    kept_moments = {
        key: {name: value[keep].clone() if value.ndim else value.clone() for name, value in source.optimizer.state[p].items()}
        for key, p in source.params.items()
    }
    source.prune(keep)

    direct = STGModel(kept_rows, "lite", scene_extent=source.scene_extent)
    optimizer = direct.make_optimizer(_lrs(direct))
    for key, param in direct.params.items():
        optimizer.state[param] = kept_moments[key]
    generator = torch.Generator().manual_seed(11)
    for key in direct.params:
        grad = torch.randn(direct.params[key].shape, generator=generator)
        direct.params[key].grad = grad
        source.params[key].grad = grad.clone()
    optimizer.step()
    source.optimizer.step()
    for key in direct.params:
        assert torch.equal(direct.params[key].detach(), source.params[key].detach())


@pytest.mark.parametrize("variant", ["full", "lite"])
def test_extend_gives_new_rows_zero_moments_and_leaves_old_rows_alone(variant):
    extended, reference = _trained_copy_pair(variant)
    old_count = extended.num_gaussians
    new = extended.gather(torch.tensor([1, 5]))
    new["trbf_center"] = torch.tensor([[0.9], [0.1]])
    extended.extend(new)
    assert extended.num_gaussians == old_count + 2
    step = None
    for key, param in extended.params.items():
        state = extended.optimizer.state[param]
        assert not state["exp_avg"][old_count:].any() and not state["exp_avg_sq"][old_count:].any()
        assert torch.equal(state["exp_avg"][:old_count], reference.optimizer.state[reference.params[key]]["exp_avg"])
        step = state["step"]
    assert float(step) == 2.0
    np.testing.assert_array_equal(extended.params["trbf_center"][old_count:, 0].detach().numpy(), np.float32([0.9, 0.1]))

    _random_grads(reference, seed=5)
    generator = torch.Generator().manual_seed(6)
    new_grads = {}
    for key, param in extended.params.items():
        new_grads[key] = torch.randn(2, param.shape[1], generator=generator)
        param.grad = torch.cat([reference.params[key].grad, new_grads[key]])
    if variant == "full":
        for mine, theirs in zip(extended.decoder.parameters(), reference.decoder.parameters()):
            mine.grad = theirs.grad.clone()
    before = {key: value.detach().clone() for key, value in extended.params.items()}
    extended.optimizer.step()
    reference.optimizer.step()
    beta1, beta2, eps, k = 0.9, 0.999, 1e-15, 3  # third step of the optimizer, first for the new rows
    for key in extended.params:
        # Equal to float32 rounding: the fused Adam kernel's rounding of an element can depend on the tensor's
        # length (here one xyz value of 36 differs by 1 ulp after the extension), where a moment that moved with
        # the wrong row would change the step by about a learning rate.
        torch.testing.assert_close(extended.params[key].detach()[:old_count], reference.params[key].detach(),
                                   rtol=1e-6, atol=1e-9)
        g = new_grads[key].double()
        m_hat = (1 - beta1) * g / (1 - beta1**k)
        v_hat = (1 - beta2) * g * g / (1 - beta2**k)
        expected = before[key][old_count:].double() - LRS[key] * m_hat / (v_hat.sqrt() + eps)
        torch.testing.assert_close(extended.params[key].detach()[old_count:].double(), expected, rtol=1e-5, atol=1e-7)


def test_reset_opacity_caps_values_and_zeroes_only_the_opacity_moments():
    model, reference = _trained_copy_pair("full")
    sigma_before = torch.sigmoid(model.params["opacity"]).detach()
    model.reset_opacity(0.01)
    sigma_after = torch.sigmoid(model.params["opacity"]).detach()
    torch.testing.assert_close(sigma_after, torch.clamp(sigma_before, max=0.01), rtol=1e-5, atol=1e-8)
    assert not model.optimizer.state[model.params["opacity"]]["exp_avg"].any()
    assert model.optimizer.state[model.params["xyz"]]["exp_avg"].abs().sum() > 0
    assert torch.equal(
        model.optimizer.state[model.params["xyz"]]["exp_avg"],
        reference.optimizer.state[reference.params["xyz"]]["exp_avg"],
    )


def test_reset_opacity_keeps_very_low_opacities_finite_and_others_bit_identical(tmp_path):
    """The reset went through sigmoid and back: sigmoid(o) underflows to 0 below o = -88.7, whose logit is -inf, and
    the next save() refused the model."""
    model = random_model("lite", count=4000)
    generator = torch.Generator().manual_seed(3)
    with torch.no_grad():
        model.params["opacity"][:, 0] = torch.randn(4000, generator=generator) * 8.0  # about -30 to 30
        model.params["opacity"][:4, 0] = torch.tensor([-120.0, -90.0, -88.8, -1e30])
    before = model.params["opacity"].detach().clone()
    with torch.no_grad():  # what the reset computed before, which is right wherever sigmoid does not underflow
        capped = torch.clamp(torch.sigmoid(before), max=0.01)
        round_trip = torch.log(capped / (1.0 - capped))
    model.reset_opacity(0.01)
    after = model.params["opacity"].detach()
    assert torch.equal(after[:4], before[:4])
    assert torch.equal(after[4:], round_trip[4:])  # bit-identical, capped rows and the others
    assert bool((before[4:] < -4.6).any() and (before[4:] > -4.5).any())  # both kinds of rows were there
    model.save(tmp_path)


def test_topology_edits_validate_their_input_and_work_without_an_optimizer():
    model = random_model("lite", count=6)
    model.prune(torch.tensor([True, False, True, True, True, True]))
    model.extend(model.gather(torch.tensor([True, False, False, False, False])))
    assert model.num_gaussians == 6
    with pytest.raises(ValueError, match="bool"):
        model.prune(torch.tensor([0, 1]))
    with pytest.raises(ValueError, match="extend"):
        model.extend({key: torch.zeros(1, 1) for key in model.params})
    with pytest.raises(ValueError, match="shape"):
        model.replace_param("omega", torch.zeros(3, 4))
