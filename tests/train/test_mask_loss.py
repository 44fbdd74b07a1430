"""The mask term of the loss: L1 over a view's foreground pixels, only where the view has a mask, said once."""

from __future__ import annotations

import logging

import numpy as np
import pytest
import torch
from PIL import Image
from scenes import write_panoptic_scene

from stgc.data import open_dataset
from stgc.train import TrainConfig
from stgc.train.config import DensifyConfig
from stgc.train.loop import Trainer


@pytest.fixture(scope="module")
def masked_scene(tmp_path_factory):
    return write_panoptic_scene(tmp_path_factory.mktemp("masked"), views=6, frames=1, width=48, height=36,
                                masks=True)


def _config(**over) -> TrainConfig:
    base = dict(iterations=2, densify=DensifyConfig(enabled=False, opacity_reset_interval=0), eval_at_end=False,
                progress=False, tensorboard=False, checkpoint_every=0, log_every=0)
    base.update(over)
    return TrainConfig(**base)


def _trainer(scene, tmp_path, **over) -> Trainer:
    return Trainer(open_dataset(scene.root), None, None, _config(**over), None, tmp_path, model=scene_model_copy(scene))


def scene_model_copy(scene):
    from stgc.model import STGModel

    return STGModel.from_state_dict(scene.model.state_dict())


def test_mask_term_adds_the_weighted_mean_error_over_the_mask_files_foreground(masked_scene, tmp_path):
    weight = 0.7
    plain = _trainer(masked_scene, tmp_path / "plain")
    masked = _trainer(masked_scene, tmp_path / "masked", mask_loss=weight)
    camera = masked.dataset.train[0]
    gt = masked.images.get(camera)
    render = torch.rand(gt.shape, generator=torch.Generator().manual_seed(0))
    base, _ = plain.view_loss(render, gt, camera)
    total, _ = masked.view_loss(render, gt, camera)
    # Independent of the reader: the mask PNG itself, 255 on the ball.
    foreground = np.asarray(Image.open(masked_scene.root / "seg" / f"{camera.name}/{camera.frame:06d}.png")) > 127
    assert 10 < foreground.sum() < foreground.size / 2
    expected = np.abs(render.numpy() - gt.numpy())[foreground].mean()
    assert float(total - base) == pytest.approx(weight * expected, rel=1e-5)


def test_mask_term_gradient_reaches_only_foreground_pixels(masked_scene, tmp_path):
    masked = _trainer(masked_scene, tmp_path / "masked", mask_loss=1.0, lambda_dssim=0.0)
    plain = _trainer(masked_scene, tmp_path / "plain", lambda_dssim=0.0)
    camera = masked.dataset.train[1]
    gt = masked.images.get(camera)
    grads = []
    for trainer in (masked, plain):
        render = torch.full(gt.shape, 0.5, requires_grad=True)
        trainer.view_loss(render, gt, camera)[0].backward()
        grads.append(render.grad)
    extra = (grads[0] - grads[1]).abs().sum(-1)
    foreground = masked.masks.get(camera)
    assert extra[~foreground].max() == 0
    assert extra[foreground].min() > 0


def test_views_without_masks_train_without_the_term_and_it_is_said_once(tmp_path, caplog):
    scene = write_panoptic_scene(tmp_path / "scene", views=5, frames=2, width=32, height=24, masks=True)
    for png in (scene.root / "seg" / "2").glob("*.png"):
        png.unlink()
    with caplog.at_level(logging.WARNING, logger="stgc"):
        trainer = _trainer(scene, tmp_path / "run", mask_loss=0.5)
        trainer.run()
    said = [r.getMessage() for r in caplog.records if "mask term" in r.getMessage()]
    assert len(said) == 1 and "2" in said[0]
    camera = next(c for c in trainer.dataset.train if c.name == "2")
    gt = trainer.images.get(camera)
    render = torch.rand(gt.shape, generator=torch.Generator().manual_seed(1))
    plain = _trainer(scene, tmp_path / "plain")
    assert float(trainer.view_loss(render, gt, camera)[0]) == pytest.approx(float(plain.view_loss(render, gt, camera)[0]))


def test_data_without_masks_says_once_that_the_term_is_off(tmp_path, caplog):
    scene = write_panoptic_scene(tmp_path / "scene", views=5, frames=1, width=32, height=24, masks=False)
    with caplog.at_level(logging.WARNING, logger="stgc"):
        trainer = _trainer(scene, tmp_path / "run", mask_loss=0.5)
    said = [r.getMessage() for r in caplog.records if "mask term" in r.getMessage()]
    assert len(said) == 1 and "no foreground masks" in said[0]
    assert trainer.masks is None


def test_mask_loss_must_be_a_non_negative_weight():
    from stgc.config import ConfigError, validate_config

    with pytest.raises(ConfigError, match="mask_loss"):
        validate_config(TrainConfig(mask_loss=-1.0), "train")
