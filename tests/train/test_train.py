"""The training loop on a tiny real scene: it learns, and a killed run resumes to the same result."""

from __future__ import annotations

import json
import os

import pytest
import torch

from stgc.compaction import CompactionConfig
from stgc.eval.evaluate import RunEvaluator, evaluate
from stgc.train import TrainConfig, train
from stgc.train.config import DensifyConfig, EMSConfig
from stgc.train.loop import Trainer, blending_weights


class Killed(Exception):
    pass


def _short_config(**over) -> TrainConfig:
    # Every mechanism fires within 40 iterations: 3 clone/split rounds (10, 15, 20), opacity pruning (25-35),
    # an opacity reset (30), a PLY save (20) and checkpoints every 10.
    base = dict(
        iterations=40,
        densify=DensifyConfig(start=5, interval=5, rounds=3, prune_until=36, opacity_reset_interval=30,
                              opacity_reset_until=36, grad_threshold=1e-5),
        save_iterations=(20,),
        checkpoint_every=10,
        log_every=5,
        progress=False,
        tensorboard=False,
        seed=3,
    )
    base.update(over)
    return TrainConfig(**base)


def _test_psnr(model, dataset) -> float:
    def render(cam):
        with torch.no_grad():
            return model.render(cam, t=cam.time).rgb

    return evaluate(render, dataset.test, dataset.load_image).psnr


def test_killed_run_resumes_to_the_uninterrupted_result(tiny_toys, make_model, tmp_path):
    # Error-guided sampling from iteration 2, so its camera bookkeeping and insertions cross the kill too (with this
    # seed its candidates are picked before the kill and are the last view of a batch at 31 and later).
    cfg = _short_config(seed=4, ems=EMSConfig(enabled=True, start=2, min_gap=3, select_ssim=0.99, trigger_ssim=0.99))
    # Compaction prunes every 2 iterations from 22 to 34, so the kill at 27 interrupts its window.
    compaction = CompactionConfig(case=0, window_start=0.55, window_end=0.875, interval=2)
    straight = Trainer(tiny_toys, None, None, cfg, compaction, tmp_path / "a", model=make_model(tiny_toys, 200),
                       evaluator=RunEvaluator())
    summary_a = straight.run()

    def kill_at_27(iteration, numbers):
        if iteration == 27:
            raise Killed

    with pytest.raises(Killed):
        train(tiny_toys, None, None, cfg, compaction, tmp_path / "b", model=make_model(tiny_toys, 200),
              callback=kill_at_27)
    assert json.loads((tmp_path / "b" / "config.json").read_text())["train"]["iterations"] == 40
    assert not (tmp_path / "b" / "train_summary.json").exists()
    resumed = Trainer(tiny_toys, None, None, cfg, compaction, tmp_path / "b", resume=True, evaluator=RunEvaluator())
    assert resumed.start_iteration == 20  # the last checkpoint before the kill
    summary_b = resumed.run()

    assert summary_a["finished"] and summary_b["finished"]
    assert summary_b["num_gaussians"] == summary_a["num_gaussians"] != 600  # densification did change N
    assert abs(summary_b["test_psnr"] - summary_a["test_psnr"]) <= 0.05
    # Per-iteration random streams make the resumed run bit-identical.
    for key, p in straight.model.params.items():
        assert torch.equal(p, resumed.model.params[key]), key
    # The log holds each iteration once, with the same training numbers.
    rows_a = [(r["iteration"], r["loss"], r["num_gaussians"]) for r in straight.metrics_log.read()]
    rows_b = [(r["iteration"], r["loss"], r["num_gaussians"]) for r in resumed.metrics_log.read()]
    assert rows_a == rows_b and [r[0] for r in rows_a] == list(range(5, 41, 5))
    assert straight.ems.state["events"] >= 1  # it did insert Gaussians
    # (as JSON: a camera whose render showed no depth has NaN, which equals nothing)
    assert json.dumps(resumed.ems.state, sort_keys=True) == json.dumps(straight.ems.state, sort_keys=True)
    events_a = [(e["iteration"], e["removed"]) for e in straight.compaction_log.read()]
    events_b = [(e["iteration"], e["removed"]) for e in resumed.compaction_log.read()]
    assert events_a == events_b and len(events_a) >= 5 and sum(r for _, r in events_a) > 0
    # Density control saw every compaction removal: its statistics keep one row per Gaussian, and what compaction
    # removed lowers its growth cap (unseen, the rounds cloned the removals back: session 30).
    for run in (straight, resumed):
        assert run.density.removed_by_others == sum(r for _, r in events_a)
        assert run.density.stats.grad_sum.shape[0] == run.model.num_gaussians
    # In the trainer's use, Adam's state follows every topology change: one state entry per live parameter.
    opt = resumed.optimizer
    for key, p in resumed.model.params.items():
        assert p in opt.state and opt.state[p]["exp_avg"].shape == p.shape, key
    # Outputs of a finished run.
    run = tmp_path / "b"
    for name in ("eval.json", "eval_per_view.csv", "train_summary.json", "checkpoint.pt",
                 "point_cloud/iteration_20/point_cloud.ply", "point_cloud/iteration_40/point_cloud.pt"):
        assert (run / name).exists(), name
    assert json.loads((run / "eval.json").read_text())["num_views"] == len(tiny_toys.test)
    assert summary_b["test_psnr"] == pytest.approx(_test_psnr(resumed.model, tiny_toys), abs=1e-4)


def test_without_an_evaluator_training_scores_no_test_view(tiny_toys, make_model, tmp_path):
    cfg = _short_config(iterations=3, save_iterations=(3,), checkpoint_every=0, eval_every=1)
    summary = train(tiny_toys, None, None, cfg, None, tmp_path / "run", model=make_model(tiny_toys, 100))
    assert summary["finished"] and "test_psnr" not in summary
    # Its times come with what they were measured on.
    saved = json.loads((tmp_path / "run" / "train_summary.json").read_text())
    assert saved["threads"] == torch.get_num_threads() and saved["machine"]["cpus"] == os.cpu_count()
    assert not (tmp_path / "run" / "eval.json").exists()
    assert (tmp_path / "run" / "point_cloud" / "iteration_3" / "point_cloud.ply").exists()


def test_training_improves_test_psnr(tiny_toys, make_model, tmp_path):
    model = make_model(tiny_toys, 500)
    before = _test_psnr(model, tiny_toys)
    cfg = _short_config(
        iterations=200,
        densify=DensifyConfig(start=30, interval=15, rounds=4, prune_until=180, opacity_reset_interval=0),
        save_iterations=(),
        checkpoint_every=0,
        log_every=50,
    )
    summary = train(tiny_toys, None, None, cfg, None, tmp_path / "run", model=model, evaluator=RunEvaluator())
    after = summary["test_psnr"]
    print(f"test PSNR {before:.2f} -> {after:.2f} dB, {summary['num_gaussians']} Gaussians, "
          f"{summary['it_per_s']:.1f} it/s")
    assert after >= before + 4.0  # measured: 14.9 -> 20.6 dB


def test_importance_sums_blending_weights_over_every_camera_and_frame(tiny_toys, make_model, tmp_path):
    trainer = Trainer(tiny_toys, None, None, _short_config(), None, tmp_path / "imp", model=make_model(tiny_toys, 200))
    views = trainer.importance_views()
    assert sorted(str(v.name) for v in views) == sorted(tiny_toys.train_views)
    assert len({v.frame for v in views}) == len(tiny_toys.frames)  # the frames are spread over the segment
    weights = trainer.importance()
    assert weights.shape == (trainer.model.num_gaussians,) and torch.all(weights >= 0)
    # Sum over Gaussians of alpha_i * T_i is each pixel's alpha, so the total is the summed alpha of the views.
    with torch.no_grad():
        total_alpha = sum(float(trainer.model.render(v, t=v.time).alpha.sum()) for v in views)
    assert float(weights.sum()) == pytest.approx(total_alpha, rel=1e-4)


def test_blending_weights_land_on_their_gaussians_rows_when_some_are_culled_at_the_views_times(tiny_toys, make_model):
    """The render culls Gaussians invisible at its time, so its weights come for a subset of the rows (out.index):
    each must be added to its own row. Half the rows live far outside the segment: they get 0, and the others get
    what a model of them alone gives (the culled rows render nothing)."""
    model = make_model(tiny_toys, 200)
    far = torch.arange(model.num_gaussians) % 2 == 1
    with torch.no_grad():
        model.params["trbf_center"][far] = 50.0
    views = tiny_toys.train[:3]
    background = torch.zeros(3)
    assert model.render(views[0], t=float(views[0].time), background=background).index.numel() < model.num_gaussians
    weights = blending_weights(model, views, background)
    model.prune(~far)
    alone = blending_weights(model, views, background)
    assert float(alone.sum()) > 0 and torch.all(weights[far] == 0)
    torch.testing.assert_close(weights[~far], alone, rtol=1e-6, atol=1e-9)


def test_importance_covers_every_frame_when_there_are_more_frames_than_cameras(tmp_path):
    """With one view per camera, two training cameras of a five-frame video saw two frames: a Gaussian living
    between them scored 0 and lost every pair it was in. Every frame is covered now, the cameras taking turns."""
    from scenes import scene_model, write_panoptic_scene

    from stgc.data import open_dataset

    scene = write_panoptic_scene(tmp_path / "scene", views=3, frames=5, width=16, height=12)
    dataset = open_dataset(scene.root)
    trainer = Trainer(dataset, None, None, _short_config(), None, tmp_path / "imp", model=scene_model())
    views = trainer.importance_views()
    assert sorted(v.frame for v in views) == [0, 1, 2, 3, 4]
    assert {str(v.name) for v in views} == set(dataset.train_views)
    assert len(trainer.probe_views()) <= 2  # the probe set keeps its one view per camera


def test_a_gaussian_made_non_finite_between_rounds_is_removed_and_a_non_finite_loss_stops_the_run(
        tiny_toys, make_model, tmp_path):
    """One Gaussian an optimizer step made non-finite stopped the next render (or, culled, the next save) until the
    next densification round removed it; it goes at the step now. A non-finite loss would make every Gaussian it
    reached non-finite, and that pruning would remove them all silently: it stops the run, named."""
    from stgc.errors import StgcError

    cfg = _short_config(iterations=20, save_iterations=(), checkpoint_every=0, eval_at_end=False,
                        densify=DensifyConfig(enabled=False, opacity_reset_interval=0))
    trainer = Trainer(tiny_toys, None, None, cfg, None, tmp_path / "run", model=make_model(tiny_toys, 100))
    count = trainer.model.num_gaussians
    with torch.no_grad():
        trainer.model.params["xyz"][3, 1] = float("nan")
    report = trainer.density.step(7, trainer.model, torch.Generator().manual_seed(0))
    assert report == {"pruned_nonfinite": 1} and trainer.model.num_gaussians == count - 1
    assert trainer.density.step(8, trainer.model, torch.Generator().manual_seed(0)) == {}
    # While the learned mask keeps one logit per row, no row goes between rounds (the mask would lose count).
    trainer.density.rows_fixed = True
    with torch.no_grad():
        trainer.model.params["xyz"][5, 0] = float("inf")
    assert trainer.density.step(8, trainer.model, torch.Generator().manual_seed(0)) == {}
    trainer.density.rows_fixed = False
    assert trainer.density.step(8, trainer.model, torch.Generator().manual_seed(0)) == {"pruned_nonfinite": 1}
    with torch.no_grad():  # the decoder's weights are no Gaussian's rows: nothing prunes them
        for weight in trainer.model.decoder.parameters():
            weight.fill_(float("nan"))
    with pytest.raises(StgcError, match="training diverged at iteration 9: the loss is nan"):
        trainer.train_step(9)


def test_a_model_handed_to_the_trainer_trains_at_the_data_s_extent_and_is_recorded_as_it_is(tiny_toys, make_model,
                                                                                            tmp_path):
    """A model loaded or built elsewhere carries extent 1.0 (STGModel.load's default): the learning rates and the
    clone/split sizes were scaled by it. And config.json recorded the default options, not the model: a 'clamp'
    decoder was recorded as 'sigmoid' and every later load of the run decoded with the wrong activation."""
    from stgc.config import ConfigError
    from stgc.model import ModelConfig

    model = make_model(tiny_toys, 100)
    model.scene_extent, model.decoder.activation = 1.0, "clamp"
    trainer = Trainer(tiny_toys, None, None, _short_config(), None, tmp_path / "run", model=model)
    assert trainer.extent == pytest.approx(tiny_toys.scene_extent()) and trainer.extent != 1.0
    recorded = json.loads((tmp_path / "run" / "config.json").read_text())["model"]
    assert (recorded["variant"], recorded["decoder_activation"]) == ("full", "clamp")
    with pytest.raises(ConfigError, match="model.decoder_activation='sigmoid', the model's is 'clamp'"):
        Trainer(tiny_toys, None, ModelConfig(decoder_activation="sigmoid"), _short_config(), None,
                tmp_path / "other", model=model)
    assert not (tmp_path / "other").exists()
    # ModelConfig's default variant ('full') is no request: a lite model trains and is recorded as lite.
    lite = make_model(tiny_toys, 100, variant="lite")
    Trainer(tiny_toys, None, ModelConfig(), _short_config(), None, tmp_path / "lite", model=lite)
    assert json.loads((tmp_path / "lite" / "config.json").read_text())["model"]["variant"] == "lite"


def test_training_cameras_at_one_place_are_refused_before_anything_is_written(tmp_path):
    from scenes import scene_model, write_panoptic_scene

    from stgc.data import open_dataset
    from stgc.errors import DataError

    scene = write_panoptic_scene(tmp_path / "scene", views=2, frames=1, width=16, height=12)  # one camera held out
    with pytest.raises(DataError, match="scene extent .* is 0: .* training cameras at two or more places"):
        Trainer(open_dataset(scene.root), None, None, _short_config(), None, tmp_path / "run", model=scene_model())
    assert not (tmp_path / "run").exists()


def test_lite_variant_trains_and_densifies(tiny_toys, make_model, tmp_path):
    # Lite has no features_t: its optimizer must get exactly its own parameter groups.
    cfg = _short_config(iterations=12, save_iterations=(), checkpoint_every=0, eval_at_end=False)
    trainer = Trainer(tiny_toys, None, None, cfg, None, tmp_path, model=make_model(tiny_toys, 100, variant="lite"))
    summary = trainer.run()
    assert {g["name"] for g in trainer.optimizer.param_groups} == set(trainer.model.params)
    assert "features_t" not in trainer.model.params and summary["iterations"] == 12


def test_the_test_views_are_scored_every_eval_every_iterations_whatever_log_every(tiny_toys, make_model, tmp_path):
    cfg = _short_config(iterations=12, save_iterations=(), checkpoint_every=0, log_every=5, eval_every=3)
    train(tiny_toys, None, None, cfg, None, tmp_path / "run", model=make_model(tiny_toys, 100),
          evaluator=RunEvaluator())
    rows = [json.loads(line) for line in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    # 3, 6 and 9 (12 is the end, scored once by eval_at_end); rows at 5 and 10 are logging ones.
    assert [r["iteration"] for r in rows if "test_psnr" in r] == [3, 6, 9]
    assert [r["iteration"] for r in rows] == [3, 5, 6, 9, 10, 12]


def test_error_guided_sampling_acts_without_the_ssim_loss(tiny_toys, make_model, tmp_path):
    from stgc.train.checkpoint import load_checkpoint

    # Every view is a candidate and triggers: with lambda_dssim = 0 the views once had no SSIM (NaN) and none did.
    ems = EMSConfig(enabled=True, start=1, min_gap=1, select_ssim=1.0, trigger_ssim=1.0, max_events=1)
    cfg = _short_config(iterations=40, seed=4, save_iterations=(), checkpoint_every=0, lambda_dssim=0.0, ems=ems)
    inserted = []
    train(tiny_toys, None, None, cfg, None, tmp_path / "run", model=make_model(tiny_toys, 100),
          callback=lambda iteration, numbers: inserted.append(iteration) if "ems_added" in numbers else None)
    assert load_checkpoint(tmp_path / "run")["ems"]["events"] == 1
    assert len(inserted) == 1  # the event's SSIM was below the trigger (a NaN would count an event, insert nothing)


def test_the_trainer_keeps_no_images_beside_the_datasets_bounded_cache(tiny_toys, make_model, tmp_path, caplog):
    """data.image_cache_mb bounds the decoded images: the trainer kept a second, unbounded copy of every one. With
    a cache of 0 MB, every use of a ground-truth image decodes it again (the trainer's copy served repeats)."""
    from stgc.data import open_dataset
    from stgc.train import TrainConfig, train

    dataset = open_dataset(tiny_toys.root, downscale=2, start=0, duration=3, image_cache_mb=0)
    cfg = TrainConfig(iterations=30, progress=False, tensorboard=False, eval_at_end=False, save_iterations=())
    with caplog.at_level("WARNING"):
        train(dataset, None, None, cfg, None, tmp_path / "run", model=make_model(dataset, 100))
    assert "more than data.image_cache_mb (0)" in caplog.text
    uses = cfg.iterations * cfg.batch
    assert uses > len(dataset.train)  # some views drawn twice: a private copy would have served them
    assert dataset._cache.misses >= uses and len(dataset._cache._items) == 0


@pytest.mark.parametrize("stats_views", ["all", "last"])
def test_one_backward_per_batch_gives_the_gradients_and_densification_statistics_of_one_backward_per_view(
        tiny_toys, make_model, tmp_path, stats_views):
    """train_step backpropagates the batch's summed loss once. Worked out the other way, as the official code does
    (each view rendered and backpropagated on its own, its loss divided by the batch size): the same parameter
    gradients and the same screen-space statistics for densification."""
    import copy

    cfg = _short_config(batch=3, densify=DensifyConfig(start=1, interval=50, rounds=1, stats_views=stats_views,
                                                       grad_threshold=1e-5))
    trainer = Trainer(tiny_toys, None, None, cfg, None, tmp_path / "run", model=make_model(tiny_toys, 200))
    assert trainer.density.collecting and trainer.colour is None
    before = copy.deepcopy(trainer.model)
    drawn, grads = [], {}
    render_views = trainer.model.render_views
    trainer.model.render_views = lambda views, t, **kw: drawn.append((list(views), t)) or render_views(views, t, **kw)
    optimizer_step = trainer.optimizer.step

    def step_keeping_the_gradients(*args, **kwargs):
        grads.update({k: p.grad.clone() for k, p in trainer.model.params.items() if p.grad is not None})
        grads.update({f"decoder.{k}": p.grad.clone() for k, p in trainer.model.decoder.named_parameters()})
        return optimizer_step(*args, **kwargs)

    trainer.optimizer.step = step_keeping_the_gradients
    trainer.train_step(1)
    trainer.close()
    [(views, t)] = drawn
    assert len(views) == 3 and len({cam.name for cam in views}) > 1

    grad_sum = torch.zeros(before.num_gaussians, dtype=torch.float64)
    count = torch.zeros(before.num_gaussians, dtype=torch.int64)
    for k, cam in enumerate(views):
        out = before.render(cam, t=t, background=trainer.background, backend=cfg.backend)
        (trainer.view_loss(out.rgb, trainer.images.get(cam), cam)[0] / len(views)).backward()
        if stats_views == "all" or k == len(views) - 1:
            rows = out.index[out.raster.visible]
            grad_sum.index_add_(0, rows, (out.raster.means2d_grad_ndc_norm() * len(views))[out.raster.visible]
                                .to(torch.float64))
            count.index_add_(0, rows, torch.ones_like(rows))
    assert count.sum() > 0 and grad_sum.max() > 0
    assert torch.equal(trainer.density.stats.count, count)
    torch.testing.assert_close(trainer.density.stats.grad_sum, grad_sum, rtol=1e-5, atol=1e-12)
    expected = {k: p.grad for k, p in before.params.items() if p.grad is not None}
    expected.update({f"decoder.{k}": p.grad for k, p in before.decoder.named_parameters()})
    assert grads.keys() == expected.keys() and "decoder.mlp2.weight" in grads and "xyz" in grads
    for key, grad in grads.items():
        assert grad.abs().max() > 0, key
        torch.testing.assert_close(grad, expected[key], rtol=1e-4, atol=1e-7, msg=key)
