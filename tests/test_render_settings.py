"""What every render of a run is drawn with (near plane, background) comes from the data, and reaches the trainer,
the evaluator and the codec alike."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from scenes import add_blender_transforms, write_panoptic_scene

from stgc.cli import main
from stgc.data import open_dataset
from stgc.data.cameras import DEFAULT_NEAR_PLANE
from stgc.data.readers.panoptic import PANOPTIC_NEAR_PLANE
from stgc.eval.evaluate import open_run_dataset
from stgc.model import STGModel


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    scene = write_panoptic_scene(tmp_path_factory.mktemp("scene"), views=5, frames=2, width=32, height=24)
    add_blender_transforms(scene)
    return scene


def test_the_near_plane_follows_the_format_and_an_override_wins(scene):
    panoptic = open_dataset(scene.root, format="panoptic")
    blender = open_dataset(scene.root, format="blender")
    assert PANOPTIC_NEAR_PLANE == 1.0 and DEFAULT_NEAR_PLANE == 0.2
    assert {c.near for c in panoptic.cameras} == {1.0} and panoptic.near_plane == 1.0
    assert {c.near for c in blender.cameras} == {0.2}
    # Panoptic's reference (Dynamic 3D Gaussians) keeps one colour per Gaussian; STG's sources are view-dependent.
    assert not panoptic.view_dependent_colour and blender.view_dependent_colour
    for fmt in ("panoptic", "blender"):
        override = open_dataset(scene.root, format=fmt, near_plane=0.5)
        assert {c.near for c in override.cameras} == {0.5}
        assert override.segment(1, 1).near_plane == 0.5  # a segment keeps the choice


def test_a_run_records_its_near_plane_and_old_runs_keep_the_official_one(scene, tmp_path):
    run = tmp_path / "run"
    assert main(["train", str(scene.root), "--out", str(run), "--set", "data.format=panoptic",
                 "--set", "data.near_plane=0.7", *_tiny()]) == 0
    saved = json.loads((run / "config.json").read_text())
    assert saved["data"]["near_plane"] == 0.7
    assert open_run_dataset(run).near_plane == 0.7
    del saved["data"]["near_plane"]  # as written before the near plane was recorded
    (run / "config.json").write_text(json.dumps(saved))
    assert open_run_dataset(run).near_plane == DEFAULT_NEAR_PLANE


def _tiny(iterations: int = 6) -> list[str]:
    return ["--set", f"train.iterations={iterations}", "--set", "train.schedule_scale=1", "--set",
            "data.init_source=random", "--set", "train.progress=false", "--set", "train.tensorboard=false",
            "--set", f"train.save_iterations=[{iterations}]"]


def test_the_background_reaches_the_trainer_the_evaluator_and_the_codec(scene, tmp_path, monkeypatch):
    seen: list[tuple[str, tuple]] = []
    original = STGModel.render_views  # what render() calls too, and what a training step calls

    def recording_render(self, cameras, t, background=None, *args, **kwargs):
        if background is not None:
            seen.append((stage, tuple(round(float(v), 3) for v in torch.as_tensor(background).reshape(-1))))
        return original(self, cameras, t, background, *args, **kwargs)

    monkeypatch.setattr(STGModel, "render_views", recording_render)
    run = tmp_path / "run"
    stage = "train"  # the training steps alone: no evaluation at the end, which would render with it too
    assert main(["train", str(scene.root), "--out", str(run), "--set", "data.format=blender",
                 "--set", "data.background=white", "--set", "train.eval_at_end=false", *_tiny()]) == 0
    stage = "eval"
    assert main(["eval", str(run), "--no-fps"]) == 0
    stage = "codec"
    assert main(["compress", str(run), "--out", str(run / "m.stgc"), "--set", "codec.allocation=optimised",
                 "--set", "codec.allocation_views=2"]) == 0
    by_stage = {s: {bg for st, bg in seen if st == s} for s in ("train", "eval", "codec")}
    assert by_stage == {s: {(1.0, 1.0, 1.0)} for s in by_stage}, by_stage


def test_real_captures_train_without_the_decoders_ray_origin_and_with_colour_correction(scene, tmp_path):
    from stgc.model import ModelConfig
    from stgc.train import TrainConfig
    from stgc.train.loop import Trainer

    def trainer(fmt, **model):
        dataset = open_dataset(scene.root, format=fmt)
        model_cfg = ModelConfig(**model)
        xyz = scene.model.params["xyz"].detach().numpy()
        cloud = SimpleNamespace(xyz=xyz, rgb=np.full_like(xyz, 0.5), time=np.full(len(xyz), 0.5, np.float32))
        start = STGModel.from_points(cloud, variant="full", scene_extent=3.3)
        return Trainer(dataset, None, model_cfg, TrainConfig(iterations=1, progress=False, tensorboard=False),
                       None, tmp_path / "-".join([fmt, *(f"{k}={v}" for k, v in model.items())]), model=start)

    real, synthetic = trainer("panoptic"), trainer("blender")
    assert not real.decoder_ray_origin and not real.model.decoder.uses_ray_origin and real.colour is not None
    assert synthetic.decoder_ray_origin and synthetic.model.decoder.uses_ray_origin and synthetic.colour is None
    forced = trainer("panoptic", decoder_ray_origin="on")
    assert forced.model.decoder.uses_ray_origin
    # The viewing direction follows the source's reference by default (Panoptic's has none, Blender's STG has it);
    # each setting reaches the decoder.
    assert not real.model.decoder.uses_ray_direction and synthetic.model.decoder.uses_ray_direction
    assert trainer("panoptic", decoder_ray_direction="on").model.decoder.uses_ray_direction
    assert not trainer("blender", decoder_ray_direction="off").model.decoder.uses_ray_direction
