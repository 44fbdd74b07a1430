"""The compaction controller's probe signal (compaction.loss_signal 'probe'), wired through the trainer."""

from __future__ import annotations

import json

import pytest
from scenes import write_panoptic_scene

from stgc.compaction import CompactionConfig
from stgc.data import open_dataset
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
    read = []
    probe = trainer.probe_loss
    trainer.strategies[-1].probe = lambda: read.append(probe()) or read[-1]
    trainer.run()
    events = [json.loads(line) for line in (tmp_path / "run" / "compaction.jsonl").read_text().splitlines()]
    assert [e["iteration"] for e in events] == [20, 30, 40, 50]
    assert [e["smoothed_loss"] for e in events] == pytest.approx(read)
