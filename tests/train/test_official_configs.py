"""Options a run leaves unset take the official STG per-dataset config of its data's family (stgc.official): the
sources say their family, the trainer resolves the options for it before anything trains, config.json records
what the run trained with, and an option the user gives is never replaced."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from scenes import write_n3dv_scene

from stgc.data import DataConfig, open_dataset
from stgc.data.colmap_io import ColmapCamera, ColmapImage, ColmapModel, write_model
from stgc.model import ModelConfig
from stgc.official import official_value
from stgc.train.config import LearningRates, TrainConfig
from stgc.train.loop import Trainer

W, H, FOCAL = 16, 12, 20.0
CAMERAS, FRAMES = 3, 2


def _image(path: Path, seed: int) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    pixels = np.random.default_rng(seed).integers(0, 256, size=(H, W, 3), dtype=np.uint8)
    Image.fromarray(pixels).save(path)


def _w2c(k: int) -> np.ndarray:
    w2c = np.eye(4)
    w2c[:3, 3] = [0.3 * k, 0.0, 4.0]
    return w2c


def make_technicolor(root: Path) -> Path:
    """cameras_parameters.txt (identity rotations) + <Scene>_undist_<frame>_<cam>.png."""
    rows = ["f cx cy a b qw qx qy qz tx ty tz"]
    for k in range(CAMERAS):
        rows.append(" ".join(str(v) for v in (FOCAL, W / 2, H / 2, 1.0, 0.0, 1.0, 0.0, 0.0, 0.0, *_w2c(k)[:3, 3])))
        for f in range(FRAMES):
            _image(root / f"Scene_undist_{f:05d}_{k:02d}.png", seed=10 * k + f)
    (root / "cameras_parameters.txt").write_text("\n".join(rows) + "\n")
    return root


def make_stg_colmap(root: Path, marker: str | None) -> Path:
    """STG's prepared layout (colmap_<t>/images + sparse/0 with points), with the file STG's preparation leaves
    beside it: `marker` (cameras_parameters.txt for Technicolor, poses_bounds.npy for Neural 3D Video) or none."""
    model = ColmapModel()
    for k in range(CAMERAS):
        model.cameras[k + 1] = ColmapCamera(k + 1, "PINHOLE", W, H, np.array([FOCAL, FOCAL, W / 2, H / 2]))
        model.images[k + 1] = ColmapImage(k + 1, np.array([1.0, 0, 0, 0]), _w2c(k)[:3, 3], k + 1, f"cam{k:02d}.png")
    rng = np.random.default_rng(0)
    for f in range(FRAMES):
        for k in range(CAMERAS):
            _image(root / f"colmap_{f}" / "images" / f"cam{k:02d}.png", seed=10 * k + f)
        model.xyz = rng.normal(scale=0.3, size=(40, 3))
        model.rgb = rng.integers(0, 256, size=(40, 3)).astype(np.uint8)
        model.error = np.zeros(40)
        write_model(root / f"colmap_{f}" / "sparse" / "0", model, "txt")
    if marker == "poses_bounds.npy":
        np.save(root / marker, np.zeros((CAMERAS, 17)))
    elif marker is not None:
        (root / marker).write_text("header\n")
    return root


def test_the_table_holds_the_official_configs_values() -> None:
    # ../shared/reference/stg_official_code.md: n3d scaling_lr 0.0015; techni desicnt 12, trbfslinit 2, sandwichnoact.
    assert official_value("train.lr.scaling", "n3dv") == 1.5e-3
    assert official_value("train.lr.scaling", "technicolor") == official_value("train.lr.scaling", None) == 5e-3
    assert official_value("model.trbf_scale_init", "technicolor") == -2.0
    assert official_value("model.trbf_scale_init", "n3dv") == 0.0
    assert official_value("model.decoder_activation", "technicolor") == "clamp"
    assert official_value("model.decoder_activation", None) == "sigmoid"
    assert official_value("train.densify.rounds", "technicolor") == 12
    assert official_value("train.densify.rounds", "n3dv") is None  # stgc's own schedule (the official 6)
    with pytest.raises(ValueError, match="unknown official config family"):
        official_value("train.lr.scaling", "immersive")


def test_every_source_names_its_family(tmp_path: Path) -> None:
    from scenes import write_panoptic_scene

    assert open_dataset(write_n3dv_scene(tmp_path / "n3dv")).official_config == "n3dv"
    assert open_dataset(make_technicolor(tmp_path / "techni")).official_config == "technicolor"
    assert open_dataset(write_panoptic_scene(tmp_path / "panoptic", views=4, frames=2).root).official_config is None
    prepared = {marker: open_dataset(make_stg_colmap(tmp_path / str(marker), marker))
                for marker in ("cameras_parameters.txt", "poses_bounds.npy", None)}
    assert {marker: data.format for marker, data in prepared.items()} == dict.fromkeys(prepared, "stg-colmap")
    assert {marker: data.official_config for marker, data in prepared.items()} == {
        "cameras_parameters.txt": "technicolor", "poses_bounds.npy": "n3dv", None: None}


def _started(data: Path, out: Path, model: ModelConfig, train: TrainConfig) -> tuple[Trainer, dict]:
    """A trainer set up on `data` (nothing trained) and the config.json it wrote."""
    dataset = open_dataset(data)
    data_cfg = DataConfig() if dataset.has_points else DataConfig(init_source="random", max_points_per_frame=50)
    trainer = Trainer(dataset, data_cfg, model, train, None, out)
    return trainer, json.loads((out / "config.json").read_text())


def test_a_run_trains_and_records_its_data_s_official_values(tmp_path: Path) -> None:
    train = TrainConfig(iterations=10, progress=False, tensorboard=False, eval_at_end=False)
    trainer, saved = _started(make_stg_colmap(tmp_path / "techni", "cameras_parameters.txt"), tmp_path / "t",
                              ModelConfig(), train)
    assert saved["model"]["trbf_scale_init"] == -2.0 and saved["model"]["decoder_activation"] == "clamp"
    assert saved["train"]["lr"]["scaling"] == 5e-3
    assert saved["train"]["densify"]["rounds"] == 12  # its dense COLMAP clouds ship
    assert saved["train"]["resolved_schedule"]["densify_rounds"] == 12
    # What the run trains with: the initial temporal scales, the decoder's output, the optimizer's rates.
    assert np.all(trainer.model.params["trbf_scale"].detach().numpy() == -2.0)
    assert trainer.model.decoder_activation == "clamp"
    assert trainer.ems.trbf_scale_init == -2.0
    trainer, saved = _started(write_n3dv_scene(tmp_path / "n3dv"), tmp_path / "n", ModelConfig(), train)
    assert saved["train"]["lr"]["scaling"] == 1.5e-3 and saved["model"]["trbf_scale_init"] == 0.0
    assert saved["train"]["densify"]["rounds"] == 20  # no points ship: stgc's sparse-cloud schedule
    assert {g["name"]: g["lr"] for g in trainer.optimizer.param_groups}["scaling"] == 1.5e-3
    # The source's own Technicolor reader ships no points: the sparse-cloud schedule, the family's model.
    _, saved = _started(make_technicolor(tmp_path / "raw"), tmp_path / "r", ModelConfig(), train)
    assert saved["train"]["densify"]["rounds"] == 20 and saved["model"]["decoder_activation"] == "clamp"


def test_the_user_s_values_are_never_replaced(tmp_path: Path) -> None:
    train = TrainConfig(iterations=10, progress=False, tensorboard=False, eval_at_end=False,
                        lr=LearningRates(scaling=5e-3))
    model = ModelConfig(trbf_scale_init=0.0, decoder_activation="sigmoid")
    train = train.resolved(sparse_cloud=False, family=None)  # every densification option given too
    trainer, saved = _started(make_stg_colmap(tmp_path / "techni", "cameras_parameters.txt"), tmp_path / "t",
                              model, train)
    assert saved["model"]["trbf_scale_init"] == 0.0 and saved["model"]["decoder_activation"] == "sigmoid"
    assert saved["train"]["densify"]["rounds"] == 6
    assert trainer.model.decoder_activation == "sigmoid"
    _, saved = _started(write_n3dv_scene(tmp_path / "n3dv"), tmp_path / "n", model, train)
    assert saved["train"]["lr"]["scaling"] == 5e-3


def test_a_resumed_run_keeps_what_it_recorded(tmp_path: Path) -> None:
    """config.json holds the resolved values, so a run resumed (or fine-tuned) trains on with them."""
    from stgc.options import configs_from_run

    data = write_n3dv_scene(tmp_path / "n3dv")
    train = TrainConfig(iterations=10, progress=False, tensorboard=False, eval_at_end=False)
    _started(data, tmp_path / "run", ModelConfig(), train)
    back = configs_from_run(tmp_path / "run")
    assert back["train"].lr.scaling == 1.5e-3 and back["model"].decoder_activation == "sigmoid"
    assert back["train"].densify.is_resolved and back["model"].is_resolved
    # The same options on Technicolor data are the run's (n3dv's), not Technicolor's.
    shutil.rmtree(data)
    techni = make_stg_colmap(tmp_path / "techni", "cameras_parameters.txt")
    _, saved = _started(techni, tmp_path / "again", back["model"], back["train"])
    assert saved["train"]["lr"]["scaling"] == 1.5e-3 and saved["model"]["trbf_scale_init"] == 0.0
