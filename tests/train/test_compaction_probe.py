"""The compaction controller's probe signal (compaction.loss_signal 'probe'), wired through the trainer."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch
from scenes import write_panoptic_scene

from stgc import machine
from stgc.compaction import CompactionConfig
from stgc.data import open_dataset
from stgc.errors import DataError
from stgc.metrics import psnr
from stgc.model import STGModel
from stgc.train import TrainConfig
from stgc.train.config import DensifyConfig
from stgc.train.loop import Trainer


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return write_panoptic_scene(tmp_path_factory.mktemp("probe"), views=8, frames=2, width=48, height=36)


def _config(iterations: int) -> TrainConfig:
    return TrainConfig(iterations=iterations, densify=DensifyConfig(enabled=False, opacity_reset_interval=0),
                       colour_correction="off", save_iterations=(), checkpoint_every=0, log_every=10,
                       progress=False, tensorboard=False, seed=1, eval_at_end=False)


def test_the_compaction_probe_is_a_fixed_spread_set_of_training_views_and_steers_the_ratio(scene, tmp_path):
    """compaction.loss_signal 'probe': the controller's signal is the model's loss on fixed training views, read at
    every pruning step (the wiring through the trainer; the controller's rule: tests/compaction)."""
    dataset = open_dataset(scene.root)
    start = STGModel.from_ply_arrays(scene.model.to_ply_arrays(), "lite", None, scene_extent=3.3)
    compaction = CompactionConfig(case=0, window_start=0.25, window_end=0.75, interval=10, loss_signal="probe",
                                  probe_views=4)
    trainer = Trainer(dataset, None, None, _config(80), compaction, tmp_path / "run", model=start)
    views = trainer.probe_views()
    assert views == trainer.probe_views()  # fixed
    assert len(views) == 4 and len({c.name for c in views}) == 4 and len({c.frame for c in views}) == 2
    # More probe views than cameras (7 training cameras here): several frames of each, every view once.
    many = Trainer(dataset, None, None, _config(80), dataclasses.replace(compaction, probe_views=12),
                   tmp_path / "many", model=start).probe_views()
    assert len(many) == 12 and len({(c.name, c.frame) for c in many}) == 12 and len({c.name for c in many}) == 7
    everything = Trainer(dataset, None, None, _config(80), dataclasses.replace(compaction, probe_views=99),
                         tmp_path / "all", model=start).probe_views()
    assert sorted((c.name, c.frame) for c in everything) == sorted((c.name, c.frame) for c in dataset.train)
    read = []
    probe = trainer.probe
    trainer.strategies[-1].probe = lambda: read.append(probe()) or read[-1]
    trainer.run()
    events = [json.loads(line) for line in (tmp_path / "run" / "compaction.jsonl").read_text().splitlines()]
    assert [e["iteration"] for e in events] == [20, 30, 40, 50]
    assert [e["smoothed_loss"] for e in events] == pytest.approx([r.loss for r in read])
    # The probe's MSE is the mean PSNR's (geometric mean over the views), as evaluation scores a render: clamped.
    with torch.no_grad():
        scores = [float(psnr(trainer.model.render(cam, t=float(cam.time), background=trainer.background).rgb
                             .clamp(0, 1), trainer.images.get(cam))) for cam in views]
    assert trainer.probe().mse == pytest.approx(10.0 ** (-np.mean(scores) / 10.0), rel=1e-5)  # float32 PSNRs
    assert events[-1]["probe_psnr"] == pytest.approx(-10.0 * np.log10(read[-1].mse))



def test_prune_damage_reads_the_probe_right_before_and_right_after_each_prune(scene, tmp_path):
    """compaction.loss_signal 'prune_damage' through the trainer: a pruning step renders the probe, prunes, and
    renders it again with nothing trained between; the logged damage is the PSNR between the two renders."""
    dataset = open_dataset(scene.root)
    start = STGModel.from_ply_arrays(scene.model.to_ply_arrays(), "lite", None, scene_extent=3.3)
    compaction = CompactionConfig(case=0, window_start=0.25, window_end=0.75, interval=10, probe_views=4,
                                  loss_signal="prune_damage", loss_budget_db=0.5, ratio_init=0.1, ratio_max=0.2,
                                  ratio_increase="additive", removal_rate_max=0.0, prune_trials=0)
    trainer = Trainer(dataset, None, None, _config(80), compaction, tmp_path / "run", model=start)
    read = []  # (Gaussians, probe) in call order
    probe = trainer.probe
    trainer.strategies[-1].probe = lambda: read.append((trainer.model.num_gaussians, probe())) or read[-1][1]
    trainer.run()
    events = [json.loads(line) for line in (tmp_path / "run" / "compaction.jsonl").read_text().splitlines()]
    assert [e["iteration"] for e in events] == [20, 30, 40, 50] and all(e["removed"] for e in events)
    assert len(read) == 2 * len(events)
    for e, (before, after) in zip(events, zip(read[::2], read[1::2])):
        assert (before[0], after[0]) == (e["gaussians_before"], e["gaussians_left"])
        assert e["prune_damage_db"] == pytest.approx(10 * np.log10(after[1].mse / before[1].mse))
        assert e["probe_psnr"] == pytest.approx(-10.0 * np.log10(before[1].mse))
    assert sum(e["prune_damage_db"] for e in events) == pytest.approx(trainer.strategies[-1].compactor.prune_damage_db)

def test_a_budget_run_reads_its_unpruned_reference_run_at_the_same_iterations(scene, tmp_path):
    """compaction.method 'reference' trains as without compaction and logs the probe loss at each pruning iteration;
    a run of the same configuration with loss_reference holds its budget against those values. Until its first
    prune it is the same run, so the first probe losses agree exactly (the views drawn per iteration are seeded)."""
    dataset = open_dataset(scene.root)
    common = dict(case=0, window_start=0.25, window_end=0.75, interval=10, loss_signal="probe", probe_views=4)

    def start() -> STGModel:
        return STGModel.from_ply_arrays(scene.model.to_ply_arrays(), "lite", None, scene_extent=3.3)

    reference_trainer = Trainer(dataset, None, None, _config(80), CompactionConfig(method="reference", **common),
                                tmp_path / "ref", model=start())
    reference_trainer.run()
    reference = [json.loads(line) for line in (tmp_path / "ref" / "compaction.jsonl").read_text().splitlines()]
    assert [e["iteration"] for e in reference] == [20, 30, 40, 50]
    assert all(e["removed"] == 0 for e in reference)
    unpruned = Trainer(dataset, None, None, _config(80), CompactionConfig(method="none"), tmp_path / "plain",
                       model=start())
    unpruned.run()
    for key, value in unpruned.model.params.items():  # the probe renders change nothing in the training
        assert torch.equal(value, reference_trainer.model.params[key]), key

    budgeted = CompactionConfig(method="st-knn", loss_budget_db=0.3, loss_reference=str(tmp_path / "ref"),
                                ratio_init=0.02, ratio_max=0.05, **common)
    trainer = Trainer(dataset, None, None, _config(80), budgeted, tmp_path / "run", model=start())
    trainer.run()
    events = [json.loads(line) for line in (tmp_path / "run" / "compaction.jsonl").read_text().splitlines()]
    assert [e["reference_loss"] for e in events] == [e["smoothed_loss"] for e in reference]
    assert events[0]["smoothed_loss"] == reference[0]["smoothed_loss"]
    assert sum(e["removed"] for e in events) > 0
    # The same reference holds a probe_psnr run's MSE: the reference logs both signals.
    by_psnr = Trainer(dataset, None, None, _config(80), dataclasses.replace(budgeted, loss_signal="probe_psnr"),
                      tmp_path / "psnr", model=start())
    by_psnr.run()
    psnr_events = [json.loads(line) for line in (tmp_path / "psnr" / "compaction.jsonl").read_text().splitlines()]
    assert [e["reference_loss"] for e in psnr_events] == [e["probe_mse"] for e in reference]
    assert psnr_events[0]["smoothed_loss"] == reference[0]["probe_mse"]
    assert psnr_events[0]["loss_budget"] == pytest.approx(10 ** 0.03 - 1)
    with pytest.raises(DataError, match="probed 4 views, this run probes 8"):
        Trainer(dataset, None, None, _config(80), dataclasses.replace(budgeted, probe_views=8), tmp_path / "other",
                model=start())
    assert not (tmp_path / "other").exists()  # refused before the run's folder was made
    with pytest.raises(DataError, match="compaction.method is 'none'"):
        Trainer(dataset, None, None, _config(80), dataclasses.replace(budgeted, loss_reference=str(tmp_path / "plain")),
                tmp_path / "other", model=start())
    # A reference of another configuration: its losses would say nothing about this run's damage.
    with pytest.raises(DataError, match=r"train.seed: this run 2, the reference 1"):
        Trainer(dataset, None, None, dataclasses.replace(_config(80), seed=2), budgeted, tmp_path / "other",
                model=start())
    assert not (tmp_path / "other").exists()
    # Nor of another thread count or backend: the same options round differently and drift apart (the numba
    # rasterizer sums per-thread rows), so the budget would count the drift as damage.
    trained_with = json.loads((tmp_path / "ref" / "train_summary.json").read_text())["threads"]
    with pytest.raises(DataError, match=rf"train.threads: this run trains with {trained_with + 1}, the reference "
                                        rf"trained with {trained_with}"):
        Trainer(dataset, None, None, dataclasses.replace(_config(80), threads=trained_with + 1), budgeted,
                tmp_path / "other", model=start())
    with pytest.raises(DataError, match=r"train.backend: this run renders with 'torch', the reference with numba"):
        Trainer(dataset, None, None, dataclasses.replace(_config(80), backend="torch"), budgeted, tmp_path / "other",
                model=start())
    assert not (tmp_path / "other").exists()
    # A reference resumed with another thread count drifted between its sessions: the last session's count
    # (the summary's "threads", all that was checked before) does not describe it.
    ref_summary = json.loads((tmp_path / "ref" / "train_summary.json").read_text())
    assert ref_summary["executions"] == [{"from_iteration": 0, "threads": trained_with, "backend": "numba",
                                          "openmp_wait": machine.openmp_wait()}]
    resumed = {**ref_summary, "executions": [{"from_iteration": 0, "threads": trained_with + 1, "backend": "numba"},
                                             {"from_iteration": 40, "threads": trained_with, "backend": "numba"}]}
    (tmp_path / "ref" / "train_summary.json").write_text(json.dumps(resumed))
    with pytest.raises(DataError, match=rf"resumed with another thread count \({trained_with} and "
                                        rf"{trained_with + 1}: its losses drifted"):
        Trainer(dataset, None, None, _config(80), budgeted, tmp_path / "other", model=start())
    # A session from before the history was kept (threads unknown) trained with the config's count.
    saved_config = json.loads((tmp_path / "ref" / "config.json").read_text())
    unknown = {**ref_summary, "executions": [{"from_iteration": 0, "threads": None, "backend": None},
                                             {"from_iteration": 40, "threads": trained_with, "backend": "numba"}]}
    (tmp_path / "ref" / "train_summary.json").write_text(json.dumps(unknown))
    (tmp_path / "ref" / "config.json").write_text(json.dumps({**saved_config, "train": {
        **saved_config["train"], "threads": trained_with}}))
    Trainer(dataset, None, None, dataclasses.replace(_config(80), threads=trained_with), budgeted,
            tmp_path / "across-upgrade", model=start())
    (tmp_path / "ref" / "config.json").write_text(json.dumps(saved_config))
    (tmp_path / "ref" / "train_summary.json").write_text(json.dumps(ref_summary))
    Trainer(dataset, None, None, dataclasses.replace(_config(80), backend="numba", threads=trained_with), budgeted,
            tmp_path / "numba", model=start())  # what "auto" means on CPU, and the count it trained with
    # A reference saved before an option existed trained as its SAVED_BEFORE value says (here the densification
    # statistic's count): not a difference, unless this run asks for another value.
    saved = json.loads((tmp_path / "ref" / "config.json").read_text())
    del saved["train"]["densify"]["stats_count"]
    # remeasure_at_settle's SAVED_BEFORE (false) differs from today's default, but without a window it acts on
    # nothing in either run: no difference.
    del saved["train"]["quantization_aware"]["remeasure_at_settle"]
    (tmp_path / "ref" / "config.json").write_text(json.dumps(saved))
    Trainer(dataset, None, None, _config(80), budgeted, tmp_path / "old-ref", model=start())
    official_count = dataclasses.replace(_config(80), densify=DensifyConfig(enabled=False, opacity_reset_interval=0,
                                                                            stats_count="in_frustum"))
    with pytest.raises(DataError, match="train.densify.stats_count: this run 'in_frustum', the reference 'rendered'"):
        Trainer(dataset, None, None, official_count, budgeted, tmp_path / "other", model=start())
    # A continuation (stgc finetune) of the budgeted run prunes nothing: the loss reference it keeps is not checked.
    Trainer(dataset, None, None, _config(90), dataclasses.replace(budgeted, method="none"), tmp_path / "longer",
            model=start())


def test_the_trainer_tells_compaction_when_it_resets_the_opacities(scene, tmp_path):
    """compaction.reset_settle_steps through the trainer: the steps right after density control's opacity reset
    prune nothing (the reset itself: tests/train/test_densify; the rule: tests/compaction)."""
    dataset = open_dataset(scene.root)
    start = STGModel.from_ply_arrays(scene.model.to_ply_arrays(), "lite", None, scene_extent=3.3)
    config = dataclasses.replace(_config(80), densify=DensifyConfig(enabled=False, opacity_reset_interval=20,
                                                                   opacity_reset_until=21))
    compaction = CompactionConfig(case=0, window_start=0.25, window_end=0.75, interval=10, probe_views=4,
                                  loss_budget_db=0.5, ratio_init=0.1, ratio_max=0.2, reset_settle_steps=2)
    trainer = Trainer(dataset, None, None, config, compaction, tmp_path / "run", model=start)
    assert trainer.compactor is not None and trainer.compactor.opacity_resets == (20,)
    trainer.run()
    events = [json.loads(line) for line in (tmp_path / "run" / "compaction.jsonl").read_text().splitlines()]
    assert [(e["iteration"], bool(e.get("settling"))) for e in events] == [(20, True), (30, True), (40, False),
                                                                          (50, False)]


@pytest.mark.parametrize("backend", ["torch", "numba"])
def test_a_prune_trial_renders_exactly_what_the_pruned_model_renders(scene, tmp_path, backend):
    """compaction.prune_trials decides on the probe of the model with the selected Gaussians masked out
    (Trainer.probe(keep)) and then applies the prune without rendering again: the masked render must be the pruned
    model's, bit for bit, on both rasterizer backends; and a trial leaves the model as it was."""
    dataset = open_dataset(scene.root)
    start = STGModel.from_ply_arrays(scene.model.to_ply_arrays(), "lite", None, scene_extent=3.3)
    compaction = CompactionConfig(case=0, window_start=0.25, window_end=0.75, interval=10, probe_views=4,
                                  prune_trials=2)
    trainer = Trainer(dataset, None, None, dataclasses.replace(_config(80), backend=backend), compaction,
                      tmp_path / "run", model=start)
    n = trainer.model.num_gaussians
    keep = torch.from_numpy(np.random.default_rng(0).random(n) > 0.3)
    whole, trial = trainer.probe(), trainer.probe(keep)
    assert trainer.model.num_gaussians == n and trainer.probe() == whole
    assert trial.mse != whole.mse  # the mask took something the probe sees
    trainer.model.prune(keep)
    assert trainer.probe() == trial
