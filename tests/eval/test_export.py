"""`stgc export --format ply-frames`: static 3DGS per frame, read back with plyfile and rendered as a static splat."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from plyfile import PlyData
from scenes import write_panoptic_scene

from stgc.cli import main
from stgc.data import open_dataset
from stgc.eval.export import (
    INRIA_FIELDS,
    SH_C0,
    export_ply_frames,
    gaussians_at,
    read_inria_ply,
    static_render_inputs,
    training_view_origin,
)
from stgc.eval.metrics import psnr
from stgc.model import STGModel
from stgc.render import rasterize


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return write_panoptic_scene(tmp_path_factory.mktemp("export"), views=5, frames=3, width=40, height=30)


def _moving(model: STGModel) -> STGModel:
    """The scene's model with motion, rotation speed and a short temporal life, so time matters."""
    moving = STGModel.from_state_dict(model.state_dict())
    rng = np.random.default_rng(0)
    with torch.no_grad():
        moving.params["motion"][:, 0:3] = torch.from_numpy(rng.normal(0, 0.3, (moving.num_gaussians, 3))).float()
        moving.params["omega"].normal_(0, 0.5, generator=torch.Generator().manual_seed(1))
        moving.params["trbf_scale"].fill_(float(np.log(0.15)))
        moving.params["trbf_center"].uniform_(0, 1, generator=torch.Generator().manual_seed(2))
    return moving


def test_exported_frames_render_as_the_model_does_at_that_time(scene, tmp_path):
    dataset = open_dataset(scene.root)
    model = _moving(scene.model)  # lite: its colour is exact as degree-0 SH
    written = export_ply_frames(model, tmp_path / "frames", frames="0:3", dataset=dataset)
    assert [p.name for p in written] == ["frame_000000.ply", "frame_000001.ply", "frame_000002.ply"]
    for frame, path in zip(range(3), written):
        ply = PlyData.read(str(path))["vertex"]  # plyfile, as any 3DGS tool reads it
        assert [p.name for p in ply.properties] == INRIA_FIELDS
        static = read_inria_ply(path)
        camera = next(c for c in dataset.test if c.frame == frame)
        expected = model.render(camera, t=camera.time, background=torch.zeros(3), backend="torch").rgb
        inputs = static_render_inputs(static)
        got = rasterize(**inputs, K=torch.tensor(camera.K, dtype=torch.float32),
                        viewmat=torch.tensor(camera.w2c, dtype=torch.float32), width=camera.width,
                        height=camera.height, background=torch.zeros(3), backend="torch",
                        near_plane=camera.near).image
        assert float(psnr(got.detach(), expected.detach())) > 60  # float32 PLY round trip only
        # Gaussians invisible at that time are left out, the others all kept.
        visible = int((model.temporal_opacity(camera.time) >= 1 / 255).sum())
        assert len(static) == visible < model.num_gaussians
    record = json.loads((tmp_path / "frames" / "export.json").read_text())
    assert [f["frame"] for f in record["frames"]] == [0, 1, 2] and "exact" in record["colour"]


def test_full_model_colour_is_its_decoder_per_gaussian_along_the_mean_training_view(scene):
    dataset = open_dataset(scene.root)
    rng = np.random.default_rng(4)
    cloud = SimpleNamespace(xyz=rng.normal(0, 0.5, (50, 3)), rgb=rng.uniform(0, 1, (50, 3)), time=rng.uniform(0, 1, 50))
    model = STGModel.from_points(cloud, variant="full")
    with torch.no_grad():
        model.params["features_t"].normal_(0, 0.3, generator=torch.Generator().manual_seed(5))
        model.params["trbf_scale"].fill_(3.0)
    t = 0.4
    origin = training_view_origin(dataset)
    got = gaussians_at(model, t, origin)
    # Written out here from the decoder's definition (docs/model.md): sigmoid(albedo + W2 relu(W1 [spec, tfeat,
    # origin, direction])), features at t = [features_dc(6), (t - mu_t) features_t].
    p = {k: v.detach().double().numpy() for k, v in model.params.items()}
    w1 = model.decoder.mlp1.weight.detach().double().numpy()[:, :, 0, 0]
    w2 = model.decoder.mlp2.weight.detach().double().numpy()[:, :, 0, 0]
    d = t - p["trbf_center"]
    means = p["xyz"] + p["motion"][:, 0:3] * d + p["motion"][:, 3:6] * d**2 + p["motion"][:, 6:9] * d**3
    direction = (means - origin) / np.linalg.norm(means - origin, axis=1, keepdims=True)
    x = np.concatenate([p["features_dc"][:, 3:6], d * p["features_t"], np.broadcast_to(origin, means.shape), direction], 1)
    rgb = 1 / (1 + np.exp(-(p["features_dc"][:, 0:3] + np.maximum(x @ w1.T, 0) @ w2.T)))
    np.testing.assert_allclose(got.rgb, rgb, atol=1e-5)
    np.testing.assert_allclose(got.means, means, atol=1e-5)


def test_sh_dc_round_trip_and_the_cli(scene, tmp_path, capsys):
    static = gaussians_at(scene.model, 0.5, np.zeros(3))
    assert SH_C0 == pytest.approx(0.5 / np.sqrt(np.pi))
    run = tmp_path / "run"
    (run / "point_cloud" / "iteration_1").mkdir(parents=True)
    scene.model.save(run / "point_cloud" / "iteration_1")
    (run / "config.json").write_text(json.dumps({"data": {"path": str(scene.root)}, "model": {}, "train": {},
                                                 "compaction": None}))
    assert main(["export", str(run), "--out", str(tmp_path / "out"), "--frames", "1:2"]) == 0
    assert "1 static 3DGS PLY" in capsys.readouterr().out
    back = read_inria_ply(tmp_path / "out" / "frame_000001.ply")
    assert len(back) == len(gaussians_at(scene.model, 1 / 3, np.zeros(3)))
    np.testing.assert_allclose(back.rgb[:5], gaussians_at(scene.model, 1 / 3, np.zeros(3)).rgb[:5], atol=1e-5)
    assert static.rgb.shape[1] == 3
    # A selection outside the data is a clear error (exit status 2, the frames named), and nothing is written.
    assert main(["export", str(run), "--out", str(tmp_path / "bad"), "--frames", "7:9"]) == 2
    assert "frames 7:9" in capsys.readouterr().err and not (tmp_path / "bad").exists()
