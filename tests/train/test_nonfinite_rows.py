"""Rows an optimizer step makes non-finite: a culled row's temporal opacity may not make its gradient NaN, removing
such rows is never silent, too many of them at once stop the run as diverged, and inside the learned mask's window
none is removed (the run stops, naming them)."""

from __future__ import annotations

import logging

import pytest
import torch

from stgc.errors import StgcError
from stgc.model.stg import _temporal_opacity
from stgc.train import TrainConfig
from stgc.train.config import DensifyConfig, QuantizationAwareConfig
from stgc.train.loop import Trainer
from stgc.train.quantization import QuantizationSimulation


def _formula(params: dict[str, torch.Tensor], t: float) -> torch.Tensor:
    """The temporal opacity as written before the guard (and in the official code)."""
    delta = t - params["trbf_center"]
    return (torch.sigmoid(params["opacity"]) * torch.exp(-torch.square(delta / torch.exp(params["trbf_scale"]))))[:, 0]


def _rows(dtype: torch.dtype = torch.float32) -> dict[str, torch.Tensor]:
    """Rows from the ordinary to the degenerate; at t = 0.5: visible, faint, culled, far outside their lifetime with
    trbf_scale -44 .. -200 (exp(s)^2 underflows; exp(s) itself below -103), long-lived, at their centre."""
    scale = [-0.5, -1.0, -2.0, -3.0, -3.0, -5.0, -20.0, -44.0, -50.0, -90.0, -110.0, -200.0, 3.0, 40.0, -50.0, -120.0]
    center = [0.5, 0.2, 0.45, 0.4, 0.1, 0.3, 0.1, 0.1, 0.8, 0.0, 0.0, 1.0, 0.9, 0.3, 0.5, 0.5]
    n = len(scale)
    gen = torch.Generator().manual_seed(0)
    return {"trbf_scale": torch.tensor(scale, dtype=dtype)[:, None],
            "trbf_center": torch.tensor(center, dtype=dtype)[:, None],
            "opacity": torch.randn(n, 1, generator=gen, dtype=dtype)}


def _leaves(params: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    return {k: v.detach().clone().requires_grad_(True) for k, v in params.items()}


def test_a_row_far_outside_its_lifetime_gets_a_finite_gradient_and_every_value_stays_bit_identical():
    rows = _rows()
    guarded, formula = _leaves(rows), _leaves(rows)
    value = _temporal_opacity(guarded, 0.5)
    reference = _formula(formula, 0.5)
    finite = torch.isfinite(reference)
    assert torch.equal(value[finite], reference[finite])  # bit for bit, the zeros of the far rows included
    assert bool(torch.isfinite(value).all())
    # (Only the rows at their centre whose exp(s) underflowed to 0 were NaN: 0/0; they get the limit, sigmoid(o).)
    assert torch.equal(value[~finite], torch.sigmoid(rows["opacity"][:, 0][~finite]))

    # As a render does: the culled rows' opacity reaches the loss with weight 0 (index_select's backward).
    weight = torch.linspace(0.5, 2.0, len(value))
    culled = (value.detach() < 1.0 / 255.0) | ~finite
    weight[culled] = 0.0
    (value * weight).sum().backward()
    (reference[~culled] * weight[~culled]).sum().backward()
    for key in rows:
        assert bool(torch.isfinite(guarded[key].grad).all()), key  # the formula's trbf_scale gradient: NaN here
        visible = ~culled
        assert torch.equal(guarded[key].grad[visible], formula[key].grad[visible]), key
        assert bool((guarded[key].grad[culled] == 0).all()), key


def test_the_formula_s_nan_gradient_for_a_culled_short_lived_row_is_what_the_guard_removes():
    """The reviewer's case in a real render: trbf_scale -50, culled at the rendered time, loss finite."""
    rows = _rows()
    formula = _leaves(rows)
    value = _formula(formula, 0.5)
    (value * torch.where(value.detach() >= 1 / 255, 1.0, 0.0)).sum().backward()
    assert not bool(torch.isfinite(formula["trbf_scale"].grad).all())  # what the guard is for


def test_the_culled_row_of_a_render_gets_a_finite_gradient(tiny_toys, make_model):
    model = make_model(tiny_toys, 30)
    with torch.no_grad():
        model.params["trbf_scale"][0] = -50.0
        model.params["trbf_scale"][1] = -3.0
    cam = tiny_toys.train[0]
    out = model.render(cam, t=cam.time + 0.3, background=torch.zeros(3))
    assert len(out.index) < model.num_gaussians
    out.rgb.mean().backward()
    for key, p in model.params.items():
        assert bool(torch.isfinite(p.grad).all()), key


def test_the_guarded_temporal_opacity_passes_a_finite_difference_gradient_check():
    """float64: the cutoff is that dtype's (28.3), rows beyond it are the constant 0 they were."""
    rows = _rows(torch.float64)
    rows["trbf_scale"] = rows["trbf_scale"].clamp(min=-6.0)  # finite differences of exp(s) need a step it resolves
    rows["trbf_center"][5] = 0.5 - 29.0 * float(torch.exp(rows["trbf_scale"][5]))  # just beyond the cutoff
    keys = list(rows)

    def f(*tensors: torch.Tensor) -> torch.Tensor:
        return _temporal_opacity(dict(zip(keys, tensors)), 0.5)

    assert torch.autograd.gradcheck(f, tuple(_leaves(rows).values()), eps=1e-7, atol=1e-9)
    assert float(f(*rows.values())[5]) == 0.0


def _config(**over) -> TrainConfig:
    base = dict(iterations=20, save_iterations=(), checkpoint_every=0, eval_at_end=False, progress=False,
                tensorboard=False, seed=3, log_every=5,
                densify=DensifyConfig(start=5, interval=5, rounds=1, prune_until=0, opacity_reset_interval=0,
                                      grad_threshold=1e-5))
    base.update(over)
    return TrainConfig(**base)


def test_removing_a_non_finite_row_is_logged_and_counted(tiny_toys, make_model, tmp_path, caplog):
    trainer = Trainer(tiny_toys, None, None, _config(), None, tmp_path / "run", model=make_model(tiny_toys, 100))
    count = trainer.model.num_gaussians
    with torch.no_grad():
        trainer.model.params["trbf_scale"][4, 0] = float("nan")
    with caplog.at_level(logging.WARNING, logger="stgc.train.densify"):
        assert trainer.density.step(7, trainer.model, torch.Generator().manual_seed(0)) == {"pruned_nonfinite": 1}
    assert trainer.model.num_gaussians == count - 1
    [record] = [r for r in caplog.records if r.name == "stgc.train.densify"]
    assert record.levelno == logging.WARNING
    assert "iteration 7: removed 1 of" in record.getMessage() and "row 4;" in record.getMessage()
    assert "trbf_scale: 1" in record.getMessage() and "1 removed so far" in record.getMessage()
    # At a densification step (10) too, and the run's total goes into the checkpoint and comes back from it.
    with torch.no_grad():
        trainer.model.params["xyz"][9, 2] = float("inf")
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="stgc.train.densify"):
        report = trainer.density.step(10, trainer.model, torch.Generator().manual_seed(0))
    assert report["pruned_nonfinite"] == 1
    assert any("iteration 10: removed 1 of" in r.getMessage() and "2 removed so far" in r.getMessage()
               for r in caplog.records)
    state = trainer.density.state_dict()
    assert state["densify_pruned_nonfinite"] == 2
    trainer.density.pruned_nonfinite = 0
    trainer.density.load_state_dict(state)
    assert trainer.density.pruned_nonfinite == 2
    trainer.density.load_state_dict({k: v for k, v in state.items() if k != "densify_pruned_nonfinite"})
    assert trainer.density.pruned_nonfinite == 0  # a checkpoint from before the count


@pytest.mark.parametrize("iteration", [7, 10])  # between rounds, and a densification step
def test_more_than_one_percent_of_the_rows_non_finite_at_once_stops_the_run_as_diverged(tiny_toys, make_model,
                                                                                        tmp_path, iteration):
    trainer = Trainer(tiny_toys, None, None, _config(), None, tmp_path / "run", model=make_model(tiny_toys, 100))
    count = trainer.model.num_gaussians
    bad = count // 100 + 1  # just over 1 %
    with torch.no_grad():
        trainer.model.params["xyz"][:bad, 0] = float("nan")
        trainer.model.params["trbf_scale"][0, 0] = float("-inf")
    with pytest.raises(StgcError, match=rf"training diverged at iteration {iteration}: the optimizer step made "
                                        rf"{bad} of {count} Gaussians \(rows 0, 1, .*non-finite in xyz: {bad}, "
                                        r"trbf_scale: 1\).*lower the learning rates"):
        trainer.density.step(iteration, trainer.model, torch.Generator().manual_seed(0))
    assert trainer.model.num_gaussians == count  # nothing was removed


def test_nan_gradients_on_every_row_stop_the_training_instead_of_emptying_the_model(tiny_toys, make_model, tmp_path):
    """The reviewer's run: the loss finite, every xyz gradient NaN for one step; the model went 450 -> 0 Gaussians
    and the run 'finished'."""
    cfg = _config(iterations=6, batch=1)
    trainer = Trainer(tiny_toys, None, None, cfg, None, tmp_path / "run", model=make_model(tiny_toys, 50, "lite"))
    count = trainer.model.num_gaussians

    def nan_once(grad: torch.Tensor) -> torch.Tensor:
        handle.remove()
        return torch.full_like(grad, float("nan"))

    handle = trainer.model.params["xyz"].register_hook(nan_once)
    with pytest.raises(StgcError, match=rf"training diverged at iteration 1: the optimizer step made {count} of "
                                        rf"{count} Gaussians .*non-finite in xyz: {count}\)"):
        trainer.run()
    assert trainer.model.num_gaussians == count


def test_inside_the_learned_mask_s_window_a_non_finite_row_stops_the_run_named(tiny_toys, make_model, tmp_path):
    """The reviewer's run: a NaN row at a densification step inside the mask's window was removed, and the next step
    said the mask had more rows than the model, blaming density control, EMS or compaction."""
    cfg = _config(iterations=14, densify=DensifyConfig(start=5, interval=5, rounds=0, prune_until=0,
                                                       opacity_reset_interval=0),
                  quantization_aware=QuantizationAwareConfig(iterations=8, mask=True, rate_weight=0.01,
                                                             allocation="ladder"))
    trainer = Trainer(tiny_toys, None, None, cfg, None, tmp_path / "run", model=make_model(tiny_toys, 60))
    count = trainer.model.num_gaussians
    hooks = []

    def callback(iteration, numbers):
        if iteration == 9:  # the next step (10) is a densification step in the window
            def nan_rows(grad: torch.Tensor) -> torch.Tensor:
                grad = grad.clone()
                grad[:3] = float("nan")
                return grad
            hooks.append(trainer.model.params["xyz"].register_hook(nan_rows))
        elif iteration == 10:
            hooks.pop().remove()

    trainer.callback = callback
    with pytest.raises(StgcError, match=rf"training diverged at iteration 10, inside the rate-aware window's learned "
                                        rf"mask: the optimizer step made 3 of {count} Gaussians \(rows 0, 1, 2; "
                                        r"non-finite in xyz: 3\)"):
        trainer.run()
    assert trainer.model.num_gaussians == count


def test_inside_the_mask_window_a_non_finite_row_stays_between_rounds_and_the_quantization_names_it(
        tiny_toys, make_model, tmp_path):
    trainer = Trainer(tiny_toys, None, None, _config(), None, tmp_path / "run", model=make_model(tiny_toys, 40))
    trainer.density.rows_fixed = True
    with torch.no_grad():
        trainer.model.params["rotation"][2, 1] = float("nan")
    assert trainer.density.step(7, trainer.model, torch.Generator().manual_seed(0)) == {}
    with pytest.raises(StgcError, match=r"training diverged at iteration 10, inside the rate-aware window's learned "
                                        r"mask: .*\(row 2; non-finite in rotation: 1\)"):
        trainer.density.step(10, trainer.model, torch.Generator().manual_seed(0))
    simulation = QuantizationSimulation(QuantizationAwareConfig(iterations=8, mask=True, rate_weight=0.01,
                                                                allocation="ladder"))
    with pytest.raises(StgcError, match=r"training diverged in the rate-aware window: the last optimizer step made 1 "
                                        r"of \d+ Gaussians \(row 2; non-finite in rotation: 1\)"):
        simulation.quantized_params(trainer.model)


def test_a_run_logs_every_removal_of_non_finite_rows_and_totals_them_in_its_summary(tiny_toys, make_model, tmp_path):
    """metrics.jsonl carries the removal at the iteration it happened (7, no logging iteration of log_every 5), and
    train_summary.json the run's total."""
    import json

    def poison(iteration: int, values: dict) -> None:
        if iteration == 6:  # after its step: the density control of iteration 7 finds the row
            with torch.no_grad():
                trainer.model.params["trbf_scale"][3, 0] = float("nan")

    trainer = Trainer(tiny_toys, None, None, _config(), None, tmp_path / "run", model=make_model(tiny_toys, 100),
                      callback=poison)
    summary = trainer.run()
    rows = [json.loads(line) for line in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    assert [row["iteration"] for row in rows if row.get("pruned_nonfinite")] == [7]
    assert summary["pruned_nonfinite"] == 1
    assert json.loads((tmp_path / "run" / "train_summary.json").read_text())["pruned_nonfinite"] == 1
