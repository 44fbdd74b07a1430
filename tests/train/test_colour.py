"""Per-training-camera colour correction: it recovers a rig's colour disagreement and never touches other views."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from scenes import write_panoptic_scene

from stgc.data import open_dataset
from stgc.model import STGModel
from stgc.train import TrainConfig
from stgc.train.colour import ColourCorrection
from stgc.train.config import DensifyConfig, LearningRates
from stgc.train.colour import COLOUR_CORRECTION_NAME
from stgc.train.loop import Trainer

# Log gains and offsets that average to zero over the six training cameras (views 1-6; view 0 is the test view),
# the gauge the correction fixes: the model keeps the average camera's colour.
LOG_GAINS = np.array([[0.10, -0.05, 0.02], [-0.08, 0.04, 0.06], [0.03, 0.09, -0.07],
                      [-0.06, -0.02, 0.05], [0.05, -0.10, -0.03], [-0.04, 0.04, -0.03]])
OFFSETS = np.array([[0.02, -0.01, 0.00], [-0.03, 0.02, 0.01], [0.01, 0.00, -0.02],
                    [0.00, 0.01, 0.02], [-0.01, -0.03, 0.01], [0.01, 0.01, -0.02]])


@pytest.fixture(scope="module")
def tinted_scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("tinted")
    gains = {v + 1: tuple(np.exp(g)) for v, g in enumerate(LOG_GAINS)}
    offsets = {v + 1: tuple(c) for v, c in enumerate(OFFSETS)}
    return write_panoptic_scene(root, views=7, frames=2, gains=gains, offsets=offsets)


# The model starts at the scene that rendered the images and stays there (zero learning rates), so whatever the
# loss still sees is the tint, and only the correction can remove it.
FROZEN_MODEL = LearningRates(xyz_init=1e-12, xyz_final=1e-12, motion=0, features_dc=0, features_t=0, opacity=0,
                             scaling=0, rotation=0, omega=0, trbf_center=0, trbf_scale=0, decoder=0,
                             colour_correction=5e-3)


def _config(**over) -> TrainConfig:
    base = dict(iterations=400, densify=DensifyConfig(enabled=False, opacity_reset_interval=0), lr=FROZEN_MODEL,
                eval_at_end=False, progress=False, tensorboard=False, checkpoint_every=0, log_every=0)
    base.update(over)
    return TrainConfig(**base)


def test_recovers_known_gain_and_offset_of_each_training_camera_within_one_percent(tinted_scene, tmp_path):
    dataset = open_dataset(tinted_scene.root)
    assert not dataset.synthetic  # Panoptic layout: a real rig, so `auto` turns the correction on
    model = STGModel.from_state_dict(tinted_scene.model.state_dict())
    trainer = Trainer(dataset, None, None, _config(), None, tmp_path / "run", model=model)
    assert trainer.colour is not None and "0" not in trainer.colour  # the test view has no correction
    trainer.run()
    names = trainer.colour.names
    gains, offsets = trainer.colour.gains().numpy(), trainer.colour.offsets().numpy()
    for i, name in enumerate(names):
        true_gain, true_offset = tinted_scene.gains[name], tinted_scene.offsets[name]
        np.testing.assert_allclose(gains[i], true_gain, rtol=0.01, err_msg=f"camera {name} gain")
        np.testing.assert_allclose(offsets[i], true_offset, atol=0.01, err_msg=f"camera {name} offset")
    saved = json.loads((tmp_path / "run" / "point_cloud" / "iteration_400" / COLOUR_CORRECTION_NAME).read_text())
    assert set(saved["cameras"]) == set(names)


def test_correction_off_when_asked(tinted_scene, tmp_path):
    dataset = open_dataset(tinted_scene.root)
    off = Trainer(dataset, None, None, _config(iterations=1, colour_correction="off"), None, tmp_path / "a",
                  model=STGModel.from_state_dict(tinted_scene.model.state_dict()))
    assert off.colour is None


def test_only_the_cameras_in_the_batch_move_and_the_gauge_stays_centred():
    cc = ColourCorrection(["a", "b", "c"], lr=0.1)
    rgb = torch.full((4, 4, 3), 0.5)
    loss = (cc.apply(rgb, "a") - 0.8).abs().mean()
    loss.backward()
    cc.step()
    table = cc.table.weight.detach()
    torch.testing.assert_close(table.mean(0), torch.zeros(6), atol=1e-7, rtol=0)
    # "a" was pushed brighter; "b" and "c" only take the re-centring share, identically.
    assert (table[0, :3] > 0).all() and torch.equal(table[1], table[2])
