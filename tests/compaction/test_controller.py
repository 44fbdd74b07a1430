"""Adaptive ratio, loss smoothing, schedule and resume of the compactor, with scripted losses."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch

from stgc.compaction import (
    PAPER_RULE,
    ProbeResult,
    AdaptiveRatio,
    CompactionConfig,
    LossSmoother,
    STKNNCompactor,
    budget_for_psnr_drop,
    match_spatiotemporal_pairs,
    resolve_schedule,
)
from stgc.compaction.config import idle_compaction_options
from stgc.config import ConfigError
from stgc.options import resolve_configs

from .compaction_helpers import make_model, paper_rule, random_params


def test_ratio_follows_a_scripted_loss_sequence_and_its_bounds():
    ctrl = AdaptiveRatio(initial=0.03, step=0.01, minimum=0.01, maximum=0.05)
    losses = [1.0, 0.9, 0.8, 0.7, 0.6, 0.65, 0.7, 0.8, 0.9, 1.0, 0.95, 0.95]
    # First step: nothing to compare. Then down-loss -> +step, up-loss -> -step, equal -> 0, clamped to [.01, .05].
    expected_dir = [0, 1, 1, 1, 1, -1, -1, -1, -1, -1, 1, 0]
    expected_ratio = [0.03, 0.04, 0.05, 0.05, 0.05, 0.04, 0.03, 0.02, 0.01, 0.01, 0.02, 0.02]
    got = [(ctrl.update(loss), ctrl.ratio) for loss in losses]
    assert [d for d, _ in got] == expected_dir
    assert [r for _, r in got] == expected_ratio  # exact: ratios stay on the step grid


def test_tolerance_dead_band():
    ctrl = AdaptiveRatio(0.02, 0.01, 0.0, 0.1, tolerance=0.05)
    assert [ctrl.update(x) for x in (1.0, 1.04, 1.2, 1.19, 1.0)] == [0, 0, -1, 0, 1]
    # Relative to the previous loss: at a loss of 0.01 a rise of 0.0004 (4 %) is inside 5 %, one of 0.0012 is not.
    small = AdaptiveRatio(0.02, 0.01, 0.0, 0.1, tolerance=0.05)
    assert [small.update(x) for x in (0.01, 0.0104, 0.0116)] == [0, 0, -1]


def test_window_mean_and_ema_smoothing():
    sm = LossSmoother("window_mean", window=3)
    for x in (10.0, 1.0, 2.0, float("nan"), 3.0):
        sm.add(x)
    assert sm.value() == pytest.approx(2.0) and sm.ignored == 1
    ema = LossSmoother("ema", window=3, ema_decay=0.5)
    for x in (4.0, 2.0, 1.0):
        ema.add(x)
    assert ema.value() == pytest.approx(0.5 * (0.5 * 4 + 0.5 * 2) + 0.5 * 1)


def test_case_windows_scale_with_the_total():
    s = resolve_schedule(paper_rule(case=1), 30_000)
    assert (s.start, s.end, s.interval, s.num_steps) == (6000, 12000, 100, 60)
    s = resolve_schedule(paper_rule(case=4), 4500)
    assert (s.start, s.end, s.interval, s.num_steps) == (900, 3600, 15, 180)
    steps = [it for it in range(1, 4501) if s.is_pruning_iteration(it)]
    assert steps[0] == 900 and steps[-1] == 3585 and len(steps) == 180
    s = resolve_schedule(paper_rule(case=0, window_start=0.5, window_end=0.6, interval=7), 100)
    assert [it for it in range(101) if s.is_pruning_iteration(it)] == [50, 57]
    with pytest.raises(ValueError, match="ratio_init"):
        STKNNCompactor(paper_rule(ratio_init=0.5, ratio_max=0.2), 100)
    with pytest.raises(ValueError, match="case"):
        STKNNCompactor(paper_rule(case=7), 100)


def _scripted_run(compactor, model, losses, first=1, events=None):
    events = [] if events is None else events
    for it in range(first, len(losses) + 1):
        event = compactor.step(it, (it % 10) / 10, model, losses[it - 1])
        if event is not None:
            events.append(event)
    return events


def _loss_script(total: int, interval: int, window_means: list[float]) -> list[float]:
    """Losses whose mean over each window between pruning steps is scripted (noise that averages out inside)."""
    rng = np.random.default_rng(0)
    losses = []
    for it in range(1, total + 1):
        k = min(len(window_means) - 1, max(0, (it - 1) // interval))
        losses.append(window_means[k])
    for s in range(0, total - 1, 2):  # +-e on consecutive iterations: window means unchanged (even interval)
        e = rng.uniform(0, 0.01)
        losses[s] += e
        losses[s + 1] -= e
    return losses


def test_compactor_follows_scripted_losses_and_prunes_at_the_schedule():
    cfg = paper_rule(case=0, window_start=0.2, window_end=0.8, interval=10, ratio_init=0.1, ratio_step=0.05,
                           ratio_min=0.05, ratio_max=0.2, criterion="timestamp")
    total = 100
    model = make_model(random_params(600, 3, motion_scale=0.02), scene_extent=1.0)
    compactor = STKNNCompactor(cfg, total)
    # Window k covers iterations 10k+1 .. 10k+10; pruning steps at 20, 30, ..., 70 see windows 1..6.
    window_means = [9.0, 5.0, 4.0, 3.0, 3.5, 4.0, 2.0, 1.0, 1.0, 1.0]
    events = _scripted_run(compactor, model, _loss_script(total, 10, window_means))
    assert [e["iteration"] for e in events] == [20, 30, 40, 50, 60, 70]
    np.testing.assert_allclose([e["smoothed_loss"] for e in events], window_means[1:7], rtol=1e-12)
    assert [e["ratio_direction"] for e in events] == [0, 1, 1, -1, -1, 1]
    assert [e["ratio"] for e in events] == [0.1, 0.15, 0.2, 0.15, 0.1, 0.15]
    n = 600
    for e in events:
        assert e["gaussians_before"] == n and e["gaussians_left"] == n - e["removed"]
        assert e["selected_pairs"] == int(np.floor(e["ratio"] * e["matched_pairs"] + 0.5))
        assert 0 < e["removed"] <= e["selected_pairs"]
        n = e["gaussians_left"]
    assert model.params["xyz"].shape[0] == n
    assert {"t", "matched_pairs", "smoothed_loss", "removed", "gaussians_left", "ratio"} <= set(events[0])
    json.dumps(events)  # the trainer appends these to RUN/compaction.jsonl


def test_resume_gives_identical_events():
    cfg = paper_rule(case=0, window_start=0.1, window_end=0.9, interval=8, ratio_init=0.1, ratio_step=0.02,
                           ratio_min=0.02, ratio_max=0.3)
    total = 80
    losses = list(np.random.default_rng(1).uniform(0.5, 1.0, total))
    params = random_params(500, 4, motion_scale=0.02)
    straight = _scripted_run(STKNNCompactor(cfg, total), make_model(params), losses)

    model = make_model(params)
    first = STKNNCompactor(cfg, total)
    events = _scripted_run(first, model, losses[:43])
    state = json.loads(json.dumps(first.state_dict()))
    second = STKNNCompactor(cfg, total)
    second.load_state_dict(state)
    _scripted_run(second, model, losses, first=44, events=events)
    strip = lambda es: [{k: v for k, v in e.items() if not k.endswith("seconds")} for e in es]
    assert strip(events) == strip(straight)
    with pytest.raises(ValueError, match="different CompactionConfig"):
        STKNNCompactor(paper_rule(), total).load_state_dict(state)
    # A state saved before an option existed resumes when the run leaves that option at its default.
    older = json.loads(json.dumps(state))
    del older["config"]["loss_budget_db"], older["config"]["keeper_time_coverage"]
    STKNNCompactor(cfg, total).load_state_dict(older)
    with pytest.raises(ValueError, match="different CompactionConfig"):
        STKNNCompactor(dataclasses.replace(cfg, keeper_time_coverage=0.5), total).load_state_dict(older)


def test_method_none_and_min_gaussians():
    model = make_model(random_params(300, 5, motion_scale=0.0))
    off = STKNNCompactor(paper_rule(method="none"), 100)
    assert all(off.step(it, 0.5, model, 1.0) is None for it in range(1, 101))
    floor = STKNNCompactor(
        paper_rule(case=0, window_start=0.0, window_end=1.0, interval=1, ratio_init=1.0, ratio_max=1.0,
                         ratio_min=1.0, min_gaussians=280),
        20,
    )
    events = [floor.step(it, 0.5, model, 1.0) for it in range(20)]
    assert model.params["xyz"].shape[0] == 280
    assert sum(e["removed"] for e in events if e) == 20


def test_optimizer_state_stays_aligned_after_pruning_with_a_real_adam():
    params = random_params(400, 6, motion_scale=0.02)
    model = make_model(params)
    lrs = {k: 1e-3 for k in params}
    opt = model.make_optimizer(lrs, 1e-4)
    # Two Adam steps on a per-row loss so every row gets distinct moments.
    for _ in range(2):
        opt.zero_grad()
        loss = sum((p * torch.arange(1, p.shape[0] + 1, dtype=p.dtype)[:, None]).square().sum() for p in model.params.values())
        loss.backward()
        opt.step()
    tag = model.params["xyz"].detach()[:, 0].clone()  # row identity: positions are distinct
    before = {k: {s: opt.state[p][s].clone() for s in ("exp_avg", "exp_avg_sq")} for k, p in model.params.items()}
    values = {k: p.detach().clone() for k, p in model.params.items()}
    cfg = paper_rule(case=0, window_start=0.0, window_end=1.0, interval=1, ratio_init=0.5, ratio_min=0.5,
                           ratio_max=0.5)
    event = STKNNCompactor(cfg, 10).step(1, 0.4, model, 1.0)
    assert event["removed"] > 0
    survivors = torch.nonzero(torch.isin(tag, model.params["xyz"].detach()[:, 0])).squeeze(1)
    assert survivors.numel() == 400 - event["removed"]
    for key, param in model.params.items():
        assert opt.state[param]["exp_avg"].shape == param.shape
        torch.testing.assert_close(param.detach(), values[key][survivors])
        for s in ("exp_avg", "exp_avg_sq"):
            torch.testing.assert_close(opt.state[param][s], before[key][s][survivors])
        assert any(param is g["params"][0] for g in opt.param_groups)
    opt.zero_grad()
    sum(p.square().sum() for p in model.params.values()).backward()
    opt.step()  # still a consistent optimizer


def test_importance_criterion_through_the_compactor():
    cfg = paper_rule(case=0, window_start=0.0, window_end=1.0, interval=1, criterion="importance",
                           ratio_init=0.2, ratio_min=0.2, ratio_max=0.2)
    params = random_params(200, 8, motion_scale=0.0)
    model = make_model(params)
    with pytest.raises(ValueError, match="importance_fn"):
        STKNNCompactor(cfg, 10).step(1, 0.5, model, 1.0)
    pairs = match_spatiotemporal_pairs(make_model(params), 0.5, cfg.rotation_weight)
    weight = torch.arange(200, dtype=torch.float64)  # the lower index is always the less important one
    event = STKNNCompactor(cfg, 10).step(1, 0.5, model, 1.0, importance_fn=lambda: weight)
    survivors = torch.isin(params["xyz"][:, 0], model.params["xyz"].detach()[:, 0]).numpy()
    removed = np.flatnonzero(~survivors)
    assert removed.size == event["removed"] > 0
    # Every removed Gaussian is the lower index of a matched pair whose other member survived.
    for r in removed:
        partners = pairs.partner[pairs.reference == r].tolist() + pairs.reference[pairs.partner == r].tolist()
        assert any(p > r and survivors[p] for p in partners)


def test_on_prune_sees_each_removal_mask_aligned_with_the_model():
    """The trainer keeps per-Gaussian statistics of its own; on_prune hands it the exact rows model.prune kept."""
    cfg = paper_rule(case=0, window_start=0.2, window_end=0.8, interval=10, ratio_init=0.2, ratio_min=0.1,
                           ratio_max=0.3)
    model = make_model(random_params(400, 3, motion_scale=0.02), scene_extent=1.0)
    compactor = STKNNCompactor(cfg, 100)
    side = {"xyz": model.params["xyz"].detach().clone()}  # a per-Gaussian array that must follow the rows
    events = 0
    for it in range(1, 101):
        event = compactor.step(it, 0.5, model, 1.0 / it, on_prune=lambda keep: side.update(xyz=side["xyz"][keep]))
        if event:
            events += 1
            assert event["removed"] > 0
            assert torch.equal(side["xyz"], model.params["xyz"].detach())
    assert events == 6


def test_a_probe_signal_steers_the_ratio_instead_of_the_training_losses():
    """loss_signal 'probe': the controller compares the probe's values (read once per pruning step), whatever the
    training losses drawn in between; the paper's rule stays the default."""
    assert paper_rule().loss_signal == "training"
    total = 100
    cfg = paper_rule(case=0, window_start=0.2, window_end=0.7, interval=10, ratio_init=0.1, ratio_step=0.05,
                           ratio_min=0.05, ratio_max=0.3, loss_signal="probe")
    probe_values = iter([5.0, 4.0, 4.5, 4.5, 3.0, 3.5])
    calls = []

    def probe() -> ProbeResult:
        calls.append(1)
        return ProbeResult(loss=next(probe_values), mse=1.0)

    compactor = STKNNCompactor(cfg, total)
    model = make_model(random_params(600, seed=1))
    noisy = list(np.random.default_rng(0).uniform(0, 100, total))  # training losses: noise the probe ignores
    events = []
    for it in range(1, total + 1):
        event = compactor.step(it, (it % 10) / 10, model, noisy[it - 1], probe_fn=probe)
        if event is not None:
            events.append(event)
    assert len(calls) == len(events) == 5  # only at pruning steps (20..60)
    assert [e["smoothed_loss"] for e in events] == [5.0, 4.0, 4.5, 4.5, 3.0]
    assert [e["ratio_direction"] for e in events] == [0, 1, -1, 0, 1]
    assert all(e["loss_signal"] == "probe" for e in events)
    with pytest.raises(ValueError, match="probe_fn"):
        STKNNCompactor(cfg, total).step(20, 0.0, make_model(random_params(600, seed=1)), 1.0)
    with pytest.raises(ValueError, match="loss_signal"):
        paper_rule(loss_signal="psnr").validate()


def test_a_damage_budget_holds_the_accumulated_rise_not_the_step_to_step_change():
    """With a budget the ratio rises while the loss stays within budget of the best seen, even when it rose since
    the previous step (the paper's rule would step down), and falls while it is beyond it, even when it fell since
    the previous step (the paper's rule would step up)."""
    budget = 0.10
    ctrl = AdaptiveRatio(initial=0.03, step=0.01, minimum=0.01, maximum=0.06, budget=budget)
    losses = [1.0, 0.9, 0.95, 0.98, 1.2, 1.1, 1.0, 0.99, 0.5]
    # best:       -   1.0  0.9   0.9   0.9  0.9  0.9  0.9   0.9 ; bound = best x 1.1 = 0.99
    expected_dir = [0, 1, 1, 1, -1, -1, -1, 1, 1]
    expected_ratio = [0.03, 0.04, 0.05, 0.06, 0.03, 0.015, 0.01, 0.02, 0.03]  # up a step, down by half, clamped
    got = [(ctrl.update(loss), ctrl.ratio) for loss in losses]
    assert [d for d, _ in got] == expected_dir
    assert [r for _, r in got] == expected_ratio
    assert ctrl.best_loss == 0.5
    paper = AdaptiveRatio(initial=0.03, step=0.01, minimum=0.01, maximum=0.06)
    assert [paper.update(loss) for loss in losses] == [0, 1, -1, -1, -1, 1, 1, 1, 1]  # the same losses, step to step
    # The state carries the best; a checkpoint from before the budget existed falls back to the last loss.
    restored = AdaptiveRatio(initial=0.03, step=0.01, minimum=0.01, maximum=0.06, budget=budget)
    restored.load_state_dict(json.loads(json.dumps(ctrl.state_dict())))
    assert restored.best_loss == 0.5 and restored.update(0.56) == -1
    restored.load_state_dict({"ratio": 0.03, "previous_loss": 0.8})
    assert restored.best_loss == 0.8
    with pytest.raises(ValueError, match="budget"):
        AdaptiveRatio(0.03, 0.01, 0.01, 0.06, budget=-0.1)


def _probe(loss: float, mse: float = 1e-3) -> ProbeResult:
    return ProbeResult(loss=loss, mse=mse)


def test_the_budget_is_a_psnr_drop_in_the_config():
    # An L1-like loss grows with the RMS error: a 0.3 dB drop is 10^(0.3/20) - 1 = 3.5 % more loss.
    assert budget_for_psnr_drop(0.3) == pytest.approx(0.03514, abs=1e-5)
    assert budget_for_psnr_drop(20.0) == pytest.approx(9.0)
    cfg = paper_rule(case=0, window_start=0.2, window_end=0.7, interval=10, loss_signal="probe",
                           loss_budget_db=0.3)
    compactor = STKNNCompactor(cfg, 100)
    assert compactor.controller.budget == pytest.approx(budget_for_psnr_drop(0.3))
    assert STKNNCompactor(paper_rule(), 100).controller.budget == 0.0  # the paper's rule: no budget
    # stgc's defaults (sessions 37 and 42): the prunes' own damage held within 0.3 dB, the least-seen losers first,
    # slow start paced by the removal rate, a wait after the opacity reset, each prune tried before it is applied.
    default = CompactionConfig()
    assert (default.loss_signal, default.loss_budget_db, default.pair_order, default.ratio_max,
            default.ratio_increase, default.removal_rate_max, default.reset_settle_steps,
            default.prune_trials) == ("prune_damage", 0.3, "weight", 0.5, "slow_start", 0.002, 10, 3)
    assert {k: getattr(paper_rule(), k) for k in PAPER_RULE} == PAPER_RULE
    model = make_model(random_params(600, seed=1))
    probe_values = iter([1.0, 1.02, 1.05, 1.0, 0.9])
    events = [e for it in range(1, 101)
              if (e := compactor.step(it, 0.5, model, 1.0, probe_fn=lambda: _probe(next(probe_values)))) is not None]
    assert [e["ratio_direction"] for e in events] == [0, 1, -1, 1, 1]  # 1.05 > 1.0 x 1.035; 1.02 is within
    assert [e["best_smoothed_loss"] for e in events] == [None, 1.0, 1.0, 1.0, 1.0]
    for bad in (-0.1, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="loss_budget_db"):
            paper_rule(loss_budget_db=bad).validate()
    # The tolerance's refusal names every option the step-to-step rule needs (the defaults hold a budget and probe).
    for asked in (paper_rule(loss_budget_db=0.3, loss_tolerance=0.01), CompactionConfig(loss_tolerance=0.01)):
        with pytest.raises(ValueError, match="loss_tolerance .*loss_budget_db=0 .*loss_signal training, probe or probe_psnr"):
            asked.validate()
    CompactionConfig(loss_tolerance=0.01, loss_budget_db=0.0, loss_signal="probe").validate()
    # A new run asking for the paper's signal alone would keep the default budget, the probe signals': refused where
    # options are given; a run saved with the pair (allowed until session 39) still validates, so it reads back.
    with pytest.raises(ConfigError, match="loss_signal training compares .* step to step.*loss_budget_db=0"):
        resolve_configs("cpu", {}, {}, {"compaction.method": "st-knn", "compaction.loss_signal": "training"})
    resolve_configs("cpu", {}, {}, {"compaction.method": "st-knn", "compaction.loss_signal": "training",
                                    "compaction.loss_budget_db": "0"})
    CompactionConfig(loss_signal="training").validate()


def test_a_reference_loss_holds_the_budget_against_the_unpruned_run_not_the_best_seen():
    """With a reference (the unpruned run's loss at each step) the ratio halves once the loss is more than the budget
    above it, even while the loss is the lowest this run has seen: the unpruned model kept improving."""
    budget = 0.10
    losses = [1.0, 0.9, 0.85, 0.8, 0.78, 0.77]
    references = [1.0, 0.88, 0.8, 0.7, 0.66, 0.72]
    # bound = reference x 1.1:   1.1  0.968 0.88  0.77  0.726 0.792
    ctrl = AdaptiveRatio(initial=0.04, step=0.01, minimum=0.01, maximum=0.06, budget=budget)
    got = [(ctrl.update(loss, reference), ctrl.ratio) for loss, reference in zip(losses, references)]
    assert [d for d, _ in got] == [1, 1, 1, -1, -1, 1]
    assert [r for _, r in got] == [0.05, 0.06, 0.06, 0.03, 0.015, 0.025]
    best_seen = AdaptiveRatio(initial=0.04, step=0.01, minimum=0.01, maximum=0.06, budget=budget)
    assert [best_seen.update(loss) for loss in losses] == [0, 1, 1, 1, 1, 1]  # every loss a new best: always up


def _reference_log(path, iterations, losses, **extra):
    path.mkdir(parents=True, exist_ok=True)
    with open(path / "compaction.jsonl", "w") as f:
        for it, loss in zip(iterations, losses):
            f.write(json.dumps({"iteration": it, "smoothed_loss": loss, "loss_signal": "probe", "removed": 0,
                                **extra}) + "\n")
    return path


def test_a_reference_run_prunes_nothing_and_its_log_steers_another_runs_budget(tmp_path):
    total = 100
    common = dict(case=0, window_start=0.2, window_end=0.7, interval=10, loss_signal="probe")
    reference = STKNNCompactor(paper_rule(method="reference", **common), total)
    model = make_model(random_params(600, seed=1))
    probe_values = iter([1.0, 0.9, 0.8, 0.7, 0.6])
    events = [e for it in range(1, total + 1)
              if (e := reference.step(it, 0.5, model, 3.0, probe_fn=lambda: _probe(next(probe_values)))) is not None]
    assert model.num_gaussians == 600 and [e["removed"] for e in events] == [0] * 5
    assert [e["iteration"] for e in events] == list(resolve_schedule(paper_rule(**common), total).iterations())
    log = tmp_path / "ref"
    log.mkdir()
    (log / "compaction.jsonl").write_text("".join(json.dumps(e) + "\n" for e in events))

    budgeted = paper_rule(method="st-knn", loss_budget_db=0.3, loss_reference=str(log), **common)
    compactor = STKNNCompactor(budgeted, total)
    pruned = make_model(random_params(600, seed=1))
    mine = iter([1.0, 0.92, 0.85, 0.69, 0.7])  # 0.85 > 0.8 x 1.035; 0.7 > 0.6 x 1.035
    steps = [e for it in range(1, total + 1)
             if (e := compactor.step(it, 0.5, pruned, 3.0, probe_fn=lambda: _probe(next(mine)))) is not None]
    assert [e["reference_loss"] for e in steps] == [1.0, 0.9, 0.8, 0.7, 0.6]
    assert [e["ratio_direction"] for e in steps] == [1, 1, -1, 1, -1]


def test_a_reference_that_is_not_one_or_misses_iterations_is_refused_naming_its_log(tmp_path):
    from stgc.errors import DataError

    common = dict(case=0, window_start=0.2, window_end=0.7, interval=10, loss_signal="probe", loss_budget_db=0.3)
    short = _reference_log(tmp_path / "short", [20, 30, 40], [1.0, 0.9, 0.8])
    with pytest.raises(DataError, match=r"short/compaction.jsonl.*no probe loss at iteration 50"):
        STKNNCompactor(paper_rule(loss_reference=str(short), **common), 100)
    pruned = _reference_log(tmp_path / "pruned", [20, 30, 40, 50, 60], [1.0] * 5)
    lines = (pruned / "compaction.jsonl").read_text().splitlines()
    lines[1] = lines[1].replace('"removed": 0', '"removed": 7')
    (pruned / "compaction.jsonl").write_text("\n".join(lines) + "\n")
    with pytest.raises(DataError, match="iteration 30: not a reference run"):
        STKNNCompactor(paper_rule(loss_reference=str(pruned), **common), 100)
    with pytest.raises(DataError, match="no compaction log"):
        STKNNCompactor(paper_rule(loss_reference=str(tmp_path / "absent"), **common), 100)
    for bad in (dict(loss_budget_db=0.0), dict(loss_signal="training", loss_budget_db=0.0), dict(method="reference")):
        with pytest.raises(ValueError, match="loss_reference"):
            paper_rule(**{**common, "loss_reference": "x", **bad}).validate()
    # With method none it acts on nothing, as every other option (a fine-tuning carries its source's section so).
    paper_rule(**{**common, "loss_reference": "x", "method": "none"}).validate()


def test_a_non_finite_probe_or_reference_is_no_signal():
    # NaN compared False, so it read as 'no damage' and raised the ratio; a first NaN stuck as the best for ever.
    ctrl = AdaptiveRatio(0.005, 0.002, 0.001, 0.05, budget=0.035)
    assert ctrl.update(float("nan")) == 0 and ctrl.ratio == 0.005 and ctrl.best_loss is None
    assert ctrl.update(1.0) == 0 and ctrl.best_loss == 1.0  # the first signal: nothing to compare with
    assert ctrl.update(10.0) == -1 and ctrl.ratio == 0.0025  # damage: halved
    assert ctrl.update(float("inf")) == 0 and ctrl.ratio == 0.0025
    assert ctrl.update(5.0, reference=float("nan")) == 0 and ctrl.ratio == 0.0025 and ctrl.previous_loss == 10.0
    paper = AdaptiveRatio(0.02, 0.01, 0.0, 0.1)
    assert [paper.update(x) for x in (1.0, float("nan"), 1.2)] == [0, 0, -1]


def test_a_window_opening_at_zero_prunes_first_at_iteration_one_and_bad_numbers_are_refused():
    s = resolve_schedule(paper_rule(case=0, window_start=0.0, window_end=0.5, interval=10), 100)
    assert (s.start, s.num_steps) == (1, 5) and list(s.iterations()) == [1, 11, 21, 31, 41]
    for name in ("loss_tolerance", "ratio_step", "rotation_weight"):
        for bad in (float("nan"), float("inf"), -1.0):
            with pytest.raises(ValueError, match=f"compaction.{name}"):
                paper_rule(**{name: bad}).validate()


def test_the_probe_psnr_signal_holds_the_budget_in_the_psnr_it_names(tmp_path):
    """loss_signal probe_psnr: the controller compares the probe's MSE (geometric mean over the views), so a budget
    of 0.3 dB is exactly 0.3 dB of the probe views' mean PSNR, 10^(0.3/10) - 1 = 7.2 % more MSE, where the L1-like
    loss's 3.5 % is an approximation. The reference run logs both signals; one from before logged only the loss."""
    from stgc.errors import DataError

    assert budget_for_psnr_drop(0.3, squared_error=True) == pytest.approx(10 ** 0.03 - 1)
    assert budget_for_psnr_drop(10.0, squared_error=True) == pytest.approx(9.0)
    total = 100
    common = dict(case=0, window_start=0.2, window_end=0.7, interval=10)
    reference = STKNNCompactor(paper_rule(method="reference", loss_signal="probe", **common), total)
    model = make_model(random_params(600, seed=1))
    reference_mse = [1e-3, 9e-4, 8e-4, 7e-4, 6e-4]
    probes = iter([_probe(1.0 - k / 10, mse) for k, mse in enumerate(reference_mse)])
    events = [e for it in range(1, total + 1)
              if (e := reference.step(it, 0.5, model, 3.0, probe_fn=lambda: next(probes))) is not None]
    assert [e["probe_mse"] for e in events] == reference_mse
    assert [e["smoothed_loss"] for e in events] == pytest.approx([1.0, 0.9, 0.8, 0.7, 0.6])  # the loss, as before
    log = tmp_path / "ref"
    log.mkdir()
    (log / "compaction.jsonl").write_text("".join(json.dumps(e) + "\n" for e in events))

    budgeted = paper_rule(method="st-knn", loss_signal="probe_psnr", loss_budget_db=0.3,
                                loss_reference=str(log), **common)
    compactor = STKNNCompactor(budgeted, total)
    assert compactor.controller.budget == pytest.approx(10 ** 0.03 - 1)
    # PSNR drops against the reference: 0, 0.25, 0.35, 0.29, 0.31 dB (the loss says nothing here: it is flat).
    drops = [0.0, 0.25, 0.35, 0.29, 0.31]
    mine = iter([_probe(0.5, mse * 10 ** (drop / 10)) for mse, drop in zip(reference_mse, drops)])
    steps = [e for it in range(1, total + 1)
             if (e := compactor.step(it, 0.5, make_model(random_params(600, seed=1)), 3.0,
                                     probe_fn=lambda: next(mine))) is not None]
    assert [e["reference_loss"] for e in steps] == reference_mse
    assert [e["ratio_direction"] for e in steps] == [1, 1, -1, 1, -1]
    assert [e["probe_psnr"] for e in steps] == pytest.approx([30 - drop - 10 * np.log10(mse / 1e-3)
                                                             for mse, drop in zip(reference_mse, drops)])
    # A reference from before the MSE was logged: refused for probe_psnr, naming the log; still good for probe.
    old = _reference_log(tmp_path / "old", [20, 30, 40, 50, 60], [1.0] * 5)
    with pytest.raises(DataError, match=r"old/compaction.jsonl.*logged no probe_mse.*train the reference again"):
        STKNNCompactor(dataclasses.replace(budgeted, loss_reference=str(old)), total)
    STKNNCompactor(dataclasses.replace(budgeted, loss_signal="probe", loss_reference=str(old)), total)


def test_prune_damage_holds_the_prunes_own_psnr_cost_against_the_budget_spread_over_the_steps():
    """loss_signal prune_damage: each step's damage is the probe's PSNR right before its prune minus right after it,
    so training's progress between steps (here the probe MSE falling 20 % per interval) is no part of it; the
    controller halves the ratio while the damage summed so far exceeds the budget's share of the steps so far and
    rises one step otherwise."""
    ctrl = AdaptiveRatio(initial=0.04, step=0.01, minimum=0.01, maximum=0.06)
    assert [(ctrl.hold(spent, allowed), ctrl.ratio) for spent, allowed in
            [(0.0, 0.0), (0.2, 0.1), (0.25, 0.2), (0.3, 0.3), (float("nan"), 0.4)]] == \
        [(1, 0.05), (-1, 0.025), (-1, 0.0125), (1, 0.0225), (0, 0.0225)]

    budget_db, total = 0.6, 100
    cfg = paper_rule(case=0, window_start=0.2, window_end=0.8, interval=10, ratio_init=0.1, ratio_step=0.05,
                           ratio_min=0.02, ratio_max=0.3, loss_signal="prune_damage", loss_budget_db=budget_db,
                           prune_trials=0)  # measured after the prune: the scripted probe reads the renders in turn
    compactor = STKNNCompactor(cfg, total)
    model = make_model(random_params(600, 3, motion_scale=0.02))
    clock = {"iteration": 0}
    calls: list[int] = []

    def probe() -> ProbeResult:  # the error grows as the model loses Gaussians and falls as it trains
        n = model.params["xyz"].shape[0]
        calls.append(clock["iteration"])
        return _probe(1.0, 1e-3 * 0.8 ** (clock["iteration"] / 10) * (600 / n) ** 2)

    events = []
    for it in range(1, total + 1):
        clock["iteration"] = it
        if (e := compactor.step(it, 0.5, model, float(it), probe_fn=probe)) is not None:
            events.append(e)
    steps = len(events)
    assert steps == compactor.schedule.num_steps == 6
    spent = 0.0
    for k, e in enumerate(events):
        assert e["damage_allowed_db"] == pytest.approx(budget_db * k / steps)
        assert e["smoothed_loss"] == pytest.approx(spent)
        assert e["ratio_direction"] == (-1 if spent > budget_db * k / steps else 1)
        assert e["prune_damage_db"] == pytest.approx(20 * np.log10(e["gaussians_before"] / e["gaussians_left"]))
        assert calls.count(e["iteration"]) == (2 if e["removed"] else 1)  # before and after the prune
        spent += e["prune_damage_db"]
    assert {e["ratio_direction"] for e in events} == {-1, 1}  # the budget both let the ratio rise and held it
    assert compactor.prune_damage_db == pytest.approx(spent)
    restored = STKNNCompactor(cfg, total)
    restored.load_state_dict(json.loads(json.dumps(compactor.state_dict())))
    assert restored.prune_damage_db == pytest.approx(spent)
    with pytest.raises(ValueError, match="loss_budget_db"):
        paper_rule(loss_signal="prune_damage").validate()
    with pytest.raises(ValueError, match="loss_reference"):
        dataclasses.replace(cfg, loss_reference="runs/stg").validate()


def test_slow_start_doubles_the_ratio_until_the_budget_first_holds_it_then_steps():
    """ratio_increase slow_start: within the budget the ratio doubles (at least one step) until the first halving,
    and from then on rises one step at a time (additive increase, multiplicative decrease); additive steps from the
    start. The state round-trips mid-window, and one saved before slow start existed resumes additive."""
    schedule = [(0.0, 0.0), (0.0, 0.1), (0.0, 0.2), (0.5, 0.3), (0.5, 0.6), (0.5, 0.7)]
    slow = AdaptiveRatio(initial=0.01, step=0.01, minimum=0.0, maximum=0.2, budget=0.0, slow_start=True)
    assert [(slow.hold(s, a), slow.ratio) for s, a in schedule[:3]] == [(1, 0.02), (1, 0.04), (1, 0.08)]
    resumed = AdaptiveRatio(initial=0.01, step=0.01, minimum=0.0, maximum=0.2, slow_start=True)
    resumed.load_state_dict(json.loads(json.dumps(slow.state_dict())))
    assert [(resumed.hold(s, a), resumed.ratio) for s, a in schedule[3:]] == [(-1, 0.04), (1, 0.05), (1, 0.06)]
    additive = AdaptiveRatio(initial=0.01, step=0.01, minimum=0.0, maximum=0.2)
    assert [additive.hold(s, a) and additive.ratio for s, a in schedule[:3]] == [0.02, 0.03, 0.04]
    zero = AdaptiveRatio(initial=0.0, step=0.01, minimum=0.0, maximum=0.2, slow_start=True)
    assert [zero.hold(0.0, 0.0) and zero.ratio for _ in range(3)] == [0.01, 0.02, 0.04]  # at least one step
    capped = AdaptiveRatio(initial=0.15, step=0.01, minimum=0.0, maximum=0.2, slow_start=True)
    assert capped.hold(0.0, 0.0) == 1 and capped.ratio == 0.2
    # After a back-off (a run of halvings) the ratio doubles again up to half the ratio the back-off started from
    # (TCP's threshold), then steps; the next back-off sets the threshold again. The state keeps both.
    over, within = (0.5, 0.1), (0.0, 0.1)
    tcp = AdaptiveRatio(initial=0.16, step=0.01, minimum=0.0, maximum=0.2, slow_start=True)
    assert [(tcp.hold(*over), tcp.ratio) for _ in range(3)] == [(-1, 0.08), (-1, 0.04), (-1, 0.02)]
    assert tcp.threshold == 0.08
    resumed_tcp = AdaptiveRatio(initial=0.16, step=0.01, minimum=0.0, maximum=0.2, slow_start=True)
    resumed_tcp.load_state_dict(json.loads(json.dumps(tcp.state_dict())))
    assert [resumed_tcp.hold(*within) and resumed_tcp.ratio for _ in range(4)] == pytest.approx([0.04, 0.08, 0.09, 0.1])
    assert resumed_tcp.hold(*over) == -1 and resumed_tcp.threshold == pytest.approx(0.05)
    assert [resumed_tcp.hold(*within) and resumed_tcp.ratio for _ in range(2)] == pytest.approx([0.06, 0.07])
    # Session 39's slow start ended for good at the first halving: its states resume so.
    ended = {"ratio": 0.02, "previous_loss": None, "best_loss": None, "slow_start": False}
    resumed_ended = AdaptiveRatio(initial=0.01, step=0.01, minimum=0.0, maximum=0.2, slow_start=True)
    resumed_ended.load_state_dict(ended)
    assert resumed_ended.hold(*within) == 1 and resumed_ended.ratio == pytest.approx(0.03)
    old = {"ratio": 0.05, "previous_loss": None, "best_loss": None}  # a checkpoint from before session 39
    resumed_old = AdaptiveRatio(initial=0.01, step=0.01, minimum=0.0, maximum=0.2, slow_start=True)
    resumed_old.load_state_dict(old)
    assert resumed_old.hold(0.0, 0.0) == 1 and resumed_old.ratio == pytest.approx(0.06)

    # A compactor state saved before ratio_increase existed (read as additive) resumes under the paper's rule, where
    # the option acts on nothing, whatever its value there; with a budget it is a difference.
    paper = STKNNCompactor(paper_rule(case=0, window_start=0.2, window_end=0.8, interval=10), 100)
    saved = json.loads(json.dumps(paper.state_dict()))
    del saved["config"]["ratio_increase"]
    STKNNCompactor(paper_rule(case=0, window_start=0.2, window_end=0.8, interval=10), 100).load_state_dict(saved)
    slow = CompactionConfig(ratio_increase="slow_start")
    with_budget = json.loads(json.dumps(STKNNCompactor(slow, 100).state_dict()))
    del with_budget["config"]["ratio_increase"]
    with pytest.raises(ValueError, match="different CompactionConfig"):
        STKNNCompactor(slow, 100).load_state_dict(with_budget)
    STKNNCompactor(CompactionConfig(ratio_increase="additive"), 100).load_state_dict(with_budget)

    # The compactor: slow start only with a budget (the paper's rule steps), idle (refused) without one.
    budgeted = CompactionConfig(case=0, window_start=0.2, window_end=0.8, interval=10)
    assert STKNNCompactor(dataclasses.replace(budgeted, ratio_increase="slow_start"), 100).controller.slow_start
    assert not STKNNCompactor(dataclasses.replace(budgeted, ratio_increase="additive"), 100).controller.slow_start
    with pytest.raises(ValueError, match="ratio_increase 'slowstart'"):  # the API has no Literal parsing
        CompactionConfig(ratio_increase="slowstart").validate()  # type: ignore[arg-type]
    assert "compaction.ratio_increase" in idle_compaction_options(paper_rule())
    assert "compaction.ratio_increase" not in idle_compaction_options(budgeted)


def test_an_unmeasured_prune_damage_backs_the_ratio_off_instead_of_reading_as_free():
    """A non-finite probe render after a prune leaves its damage unknown: the next step halves the ratio (as over
    budget) rather than counting the prune as costing nothing, and the flag survives a resume between the steps."""
    cfg = CompactionConfig(case=0, window_start=0.2, window_end=0.8, interval=10, ratio_init=0.2, ratio_max=0.4,
                           ratio_increase="additive", ratio_step=0.01, pair_order="distance", removal_rate_max=0.0,
                           prune_trials=0)
    compactor = STKNNCompactor(cfg, 100)
    model = make_model(random_params(600, 3, motion_scale=0.02))
    renders = iter([1e-3, float("nan"), 1e-3, 1e-3, 1e-3, 1e-3, 1e-3, 1e-3])
    events = []
    for it in range(1, 100 + 1):
        if it == 21:  # between the first pruning step (20), whose damage is unknown, and the second
            resumed = STKNNCompactor(cfg, 100)
            resumed.load_state_dict(json.loads(json.dumps(compactor.state_dict())))
            compactor = resumed
        if (e := compactor.step(it, 0.5, model, 1.0, probe_fn=lambda: _probe(1.0, next(renders)))) is not None:
            events.append(e)
        if len(events) == 3:
            break
    assert events[0]["prune_damage_db"] is None and events[0]["removed"] > 0
    assert [e["ratio_direction"] for e in events] == [1, -1, 1]
    assert [e["ratio"] for e in events] == pytest.approx([0.21, 0.105, 0.115])
    assert [e["backed_off_unmeasured"] for e in events] == [False, True, False]  # the log says why it halved


def test_a_removal_rate_cap_bounds_each_step_and_the_ratio_goes_on_from_what_was_used():
    """removal_rate_max: a step removes at most that share of the model per training iteration since the previous
    step (x the interval). Where the cap binds, the controller's ratio becomes the one the step used, so that a
    halving halves what is removed (a ratio left above the cap would halve and still be capped: no back-off)."""
    rate, interval = 0.002, 10
    cfg = CompactionConfig(case=0, window_start=0.1, window_end=0.9, interval=interval, ratio_init=0.2, ratio_max=0.8,
                           ratio_increase="slow_start", removal_rate_max=rate, loss_budget_db=0.05,
                           pair_order="distance", prune_trials=0)
    compactor = STKNNCompactor(cfg, 100)
    model = make_model(random_params(600, 3, motion_scale=0.02))
    clock = {"iteration": 0}

    def probe() -> ProbeResult:  # free prunes until iteration 50, then each costs its share of the model
        n = model.params["xyz"].shape[0]
        return _probe(1.0, 1e-3 * ((600 / n) ** 2 if clock["iteration"] >= 50 else 1.0))

    events = []
    for it in range(1, 101):
        clock["iteration"] = it
        if (e := compactor.step(it, 0.5, model, 1.0, probe_fn=probe)) is not None:
            events.append(e)
    assert len(events) == 8
    for e in events:
        cap = int(rate * interval * e["gaussians_before"])
        assert e["removed"] <= cap
        if e["rate_capped"]:
            assert e["ratio"] == pytest.approx(cap / e["matched_pairs"])
    assert events[0]["rate_capped"] and events[0]["removed"] == int(rate * interval * 600)
    halvings = [(before, after) for before, after in zip(events, events[1:]) if after["ratio_direction"] == -1]
    assert halvings and any(before["rate_capped"] for before, _ in halvings)
    for before, after in halvings:  # half of what the step before used, whatever ratio it had asked for
        assert after["ratio"] <= before["ratio"] / 2 + 1e-12
        assert not after["rate_capped"] and after["removed"] < before["removed"]

    # Off (0, the paper's) by default and in PAPER_RULE; a state saved before the option existed resumes uncapped.
    assert paper_rule().removal_rate_max == 0.0
    saved = json.loads(json.dumps(STKNNCompactor(dataclasses.replace(cfg, removal_rate_max=0.0), 100).state_dict()))
    del saved["config"]["removal_rate_max"]
    STKNNCompactor(dataclasses.replace(cfg, removal_rate_max=0.0), 100).load_state_dict(saved)
    with pytest.raises(ValueError, match="different CompactionConfig"):
        STKNNCompactor(cfg, 100).load_state_dict(saved)
    for bad in (-0.1, 1.5, float("nan")):
        with pytest.raises(ValueError, match="removal_rate_max"):
            dataclasses.replace(cfg, removal_rate_max=bad).validate()


def test_the_steps_after_an_opacity_reset_prune_nothing_and_the_ratio_waits():
    """reset_settle_steps: right after an opacity reset every opacity is at most opacity_reset_value, so blending
    weights rank Gaussians by size and the probe cannot see what a prune takes; the steps within that many after a
    reset (at or before them) remove nothing, leave the controller as it was, and count toward the budget's spread."""
    cfg = CompactionConfig(case=0, window_start=0.1, window_end=0.9, interval=10, ratio_init=0.05, ratio_max=0.2,
                           loss_budget_db=0.3, pair_order="distance", reset_settle_steps=2, prune_trials=0)

    def run(config: CompactionConfig, resets: tuple[int, ...]) -> list[dict]:
        compactor = STKNNCompactor(config, 100, opacity_resets=resets)
        model = make_model(random_params(600, 3, motion_scale=0.02))
        events = []
        for it in range(1, 101):
            n = model.params["xyz"].shape[0]
            if (e := compactor.step(it, 0.5, model, 1.0, probe_fn=lambda: _probe(1.0, 1e-3))) is not None:
                assert e["gaussians_before"] == n and model.params["xyz"].shape[0] == n - e["removed"]
                events.append(e)
        return events

    events = run(cfg, (10, 50))
    assert [e["iteration"] for e in events] == [10, 20, 30, 40, 50, 60, 70, 80]
    settling = [e["iteration"] for e in events if e.get("settling")]
    assert settling == [10, 20, 50, 60]
    assert all(e["removed"] == 0 for e in events if e.get("settling"))
    assert all(e["removed"] > 0 for e in events if not e.get("settling"))
    # The ratio waits: the first prune after the settling uses the ratio a first prune uses; the steps counted.
    unsettled = run(cfg, ())
    first = events[2]
    assert first["ratio"] == pytest.approx(unsettled[0]["ratio"]) and first["step"] == 3
    assert all(e["ratio"] == pytest.approx(cfg.ratio_init) for e in events[:2])
    assert first["damage_allowed_db"] == pytest.approx(0.3 * 2 / 8)
    # A reset shortly before the window: the steps within the wait of it still wait.
    assert [e["iteration"] for e in run(cfg, (5,)) if e.get("settling")] == [10, 20]
    # No reset, none until after the last step, or the option off (the paper's): every step prunes.
    for config, resets in ((cfg, ()), (cfg, (90,)), (dataclasses.replace(cfg, reset_settle_steps=0), (10, 50))):
        assert not any(e.get("settling") for e in run(config, resets))
    assert paper_rule().reset_settle_steps == 0 and CompactionConfig.SAVED_BEFORE["reset_settle_steps"] == 0
    with pytest.raises(ValueError, match="reset_settle_steps"):
        dataclasses.replace(cfg, reset_settle_steps=-1).validate()


def _costly_scene_probe(model, costs_of):
    """A probe whose PSNR drops by the summed cost (dB) of the Gaussians missing from the model it started with, a
    cost read from each row's own position (rows keep their values through prunes); `keep` masks rows as a trial."""
    start_cost = float(costs_of(model.params["xyz"]).sum())

    def probe(keep: torch.Tensor | None = None) -> ProbeResult:
        present = costs_of(model.params["xyz"])
        missing = start_cost - float(present.sum() if keep is None else present[keep].sum())
        return _probe(1.0, 1e-3 * 10.0 ** (missing / 10.0))

    return probe, start_cost


def test_prune_trials_keep_the_summed_damage_within_the_allowance_and_measure_what_they_apply():
    """prune_trials: a prune is rendered (its Gaussians masked out) before it is applied; one that would take the summed
    damage over the allowance is not applied, the ratio halves and a smaller selection is tried. A few costly
    Gaussians among cheap ones: without trials the summed damage overshoots the allowance; with them it never does,
    and what the log says the prunes cost is what the model lost."""
    cfg = CompactionConfig(case=0, window_start=0.1, window_end=0.9, interval=10, ratio_init=0.1, ratio_max=0.4,
                           ratio_increase="slow_start", loss_budget_db=1.0, pair_order="distance", prune_trials=3,
                           removal_rate_max=0.0, reset_settle_steps=0)

    def costs_of(xyz: torch.Tensor) -> torch.Tensor:  # 1 in 20 costs 0.2 dB, the others 0.002 dB
        return torch.where(xyz[:, 0] < 0.05, 0.2, 0.002).double()

    def run(config: CompactionConfig) -> tuple[list[dict], float, int]:
        model = make_model(random_params(600, 3, motion_scale=0.02))
        probe, start_cost = _costly_scene_probe(model, costs_of)
        calls = {"n": 0}

        def counted(keep: torch.Tensor | None = None) -> ProbeResult:
            calls["n"] += 1
            return probe(keep)

        compactor = STKNNCompactor(config, 100)
        events = [e for it in range(1, 101) if (e := compactor.step(it, 0.5, model, 1.0, probe_fn=counted)) is not None]
        lost = start_cost - float(costs_of(model.params["xyz"]).sum())
        return events, lost, calls["n"]

    events, lost, calls = run(cfg)
    spent = np.cumsum([e["prune_damage_db"] for e in events])
    allowance = [cfg.loss_budget_db * e["step"] / len(events) for e in events]
    assert all(s <= a + 1e-9 for s, a in zip(spent, allowance))
    assert spent[-1] == pytest.approx(lost, abs=1e-9)  # the trials' damage is the applied prunes' damage
    assert calls == sum(1 + e["prune_trials"] for e in events)  # one probe before each step, no render after
    rejected = [e for e in events if e["trials_rejected"]]
    assert rejected and all(e["ratio_direction"] == -1 for e in rejected)
    assert sum(e["removed"] for e in events) > 0

    # Without trials the same scene overshoots the allowance (and pays back by backing off after the fact).
    untried, untried_lost, untried_calls = run(dataclasses.replace(cfg, prune_trials=0))
    untried_spent = np.cumsum([e["prune_damage_db"] for e in untried])
    assert any(s > cfg.loss_budget_db * e["step"] / len(untried) + 1e-9 for s, e in zip(untried_spent, untried))
    assert untried_spent[-1] == pytest.approx(untried_lost, abs=1e-9)
    assert all(e["prune_trials"] == 0 for e in untried)

    # Under a removal-rate cap, a step whose capped selection was rejected applies less than the cap's share: the
    # log does not call it capped.
    capped_cfg = dataclasses.replace(cfg, removal_rate_max=0.002)  # at most 12 a step
    assert run(dataclasses.replace(capped_cfg, prune_trials=0))[0][0]["rate_capped"]  # the cap binds at once
    backed_off = [e for e in run(capped_cfg)[0] if e["trials_rejected"] and e["removed"]]
    assert backed_off and not any(e["rate_capped"] for e in backed_off)
    assert all(e["removed"] < 12 for e in backed_off)

    # One trial: a prune that does not fit removes nothing that step.
    single, _, _ = run(dataclasses.replace(cfg, prune_trials=1))
    assert any(e["trials_rejected"] == 1 and e["removed"] == 0 for e in single)

    # Off (0) in states saved before it (and in the paper's rule, where it is idle: refused), on by default.
    assert CompactionConfig().prune_trials == 3 and CompactionConfig.SAVED_BEFORE["prune_trials"] == 0
    assert "compaction.prune_trials" in idle_compaction_options(paper_rule())
    assert "compaction.prune_trials" not in idle_compaction_options(cfg)
    with pytest.raises(ValueError, match="prune_trials"):
        dataclasses.replace(cfg, prune_trials=-1).validate()


def test_a_prune_trial_with_merged_opacity_renders_the_keepers_merged_and_leaves_the_model_as_it_was():
    """With merge_opacity the trial renders the keepers' merged opacity (what applying the prune would leave) through
    the model's params_replaced, and a rejected trial leaves every opacity as it was."""
    cfg = CompactionConfig(case=0, window_start=0.1, window_end=0.9, interval=10, ratio_init=0.1, ratio_max=0.4,
                           loss_budget_db=1e-6, pair_order="distance", prune_trials=1, merge_opacity=True)
    model = make_model(random_params(600, 3, motion_scale=0.02))
    before = model.params["opacity"].detach().clone()
    seen: list[torch.Tensor] = []

    def probe(keep: torch.Tensor | None = None) -> ProbeResult:
        if keep is not None:
            seen.append(model.params["opacity"].detach().clone())
            return _probe(1.0, 2e-3)  # 3 dB: over any allowance
        return _probe(1.0, 1e-3)

    compactor = STKNNCompactor(cfg, 100)
    event = next(e for it in range(1, 101) if (e := compactor.step(it, 0.5, model, 1.0, probe_fn=probe)) is not None)
    assert event["trials_rejected"] == 1 and event["removed"] == 0
    assert len(seen) == 1 and (seen[0] > before).any() and (seen[0] >= before).all()  # keepers merged in the trial
    assert torch.equal(model.params["opacity"].detach(), before)  # and nothing of it left behind


def test_prune_trials_skip_a_probe_that_is_not_finite_and_leave_the_prune_unmeasured():
    """A non-finite probe before the prune cannot say what a trial costs: the step does not try N renders in vain but
    prunes and measures after it as without trials, and the unknown damage backs the next step off."""
    cfg = CompactionConfig(case=0, window_start=0.2, window_end=0.8, interval=10, ratio_init=0.2, ratio_max=0.4,
                           ratio_increase="additive", ratio_step=0.01, pair_order="distance", removal_rate_max=0.0,
                           prune_trials=3)
    model = make_model(random_params(600, 3, motion_scale=0.02))
    calls: list[bool] = []  # whether each probe call was a trial

    def probe(keep: torch.Tensor | None = None) -> ProbeResult:
        calls.append(keep is not None)
        return _probe(1.0, float("nan") if len(calls) == 1 else 1e-3)

    compactor = STKNNCompactor(cfg, 100)
    events = []
    for it in range(1, 101):
        if (e := compactor.step(it, 0.5, model, 1.0, probe_fn=probe)) is not None:
            events.append(e)
        if len(events) == 2:
            break
    assert events[0]["prune_trials"] == 0 and events[0]["removed"] > 0 and events[0]["prune_damage_db"] is None
    assert calls[:2] == [False, False]  # the probe before and the render after, no trial
    assert events[1]["backed_off_unmeasured"] and events[1]["prune_trials"] >= 1
