"""Error-guided sampling: which pixels get new Gaussians, where on their rays, and when it triggers."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from stgc.data import Camera
from stgc.train.config import EMSConfig
from stgc.train.ems import ErrorGuidedSampler, error_pixels, ray_points


def test_error_pixels_are_three_quarters_of_the_fully_wrong_patches():
    render = torch.full((128, 128, 3), 0.5)
    gt = render.clone()
    gt[48:80, 48:80] = 1.0  # exactly the 2x2 patches (3..4, 3..4) of the 16-pixel grid are wrong
    pixels = error_pixels(render, gt, EMSConfig(enabled=True))
    assert len(pixels) == 4 * 16 * 16 * 3 // 4
    assert pixels[:, 0].min() == 48 and pixels[:, 0].max() == 79 and pixels[:, 1].min() == 48
    assert not np.any((pixels[:, 0] % 2 == 0) & (pixels[:, 1] % 2 == 0))
    # The same error in the border ring of patches is ignored.
    gt2 = render.clone()
    gt2[0:16, 0:32] = 1.0
    assert len(error_pixels(render, gt2, EMSConfig(enabled=True))) == 0


def test_ray_points_project_back_to_their_pixels_at_the_sampled_depths():
    R = Rotation.from_euler("xyz", [0.2, -0.4, 0.1]).as_matrix()
    w2c = np.eye(4)
    w2c[:3, :3], w2c[:3, 3] = R, [0.3, -0.2, 2.0]
    K = np.array([[100.0, 0, 64.0], [0, 110.0, 48.0], [0, 0, 1]])
    cam = Camera("c", 0, 0.0, K, w2c, 128, 96)
    pixels = np.array([[10, 20], [64, 48], [127, 95]])
    cfg = EMSConfig(enabled=True)
    xyz, which = ray_points(cam, pixels, 3.0, cfg, torch.Generator().manual_seed(0))
    uv, depth = cam.project(xyz)
    assert np.allclose(uv, pixels[which] + 0.5, atol=1e-6)
    near, far = depth[:3], depth[3:]
    assert np.all(np.abs(near / (3.0 * 0.7) - 1) <= 0.05 + 1e-9)
    assert np.allclose(far / near, 7.5 / 0.7)


def test_sampler_picks_two_worst_cameras_after_seeing_all():
    cfg = EMSConfig(enabled=True, max_events=2)
    ems = ErrorGuidedSampler(cfg, start=10, min_gap=5, train_names=["a", "b", "c"], trbf_scale_init=0.0)
    cam = {n: SimpleNamespace(name=n) for n in "abc"}
    assert not ems.observe(9, cam["a"], 0.1)  # before start: not even recorded
    assert not ems.observe(10, cam["a"], 0.80)
    assert not ems.observe(11, cam["b"], 0.95)
    assert not ems.observe(12, cam["c"], 0.85)  # all seen now: candidates a and c
    assert ems.state["candidates"] == ["a", "c"]
    assert not ems.observe(13, cam["b"], 0.5)  # not a candidate
    assert not ems.observe(13, cam["c"], 0.5, last_of_batch=False)  # only the batch's last view may trigger
    assert ems.state["candidates"] == ["a", "c"]
    # A candidate's render makes an event whatever its SSIM: above the trigger 0.88 it inserts nothing, and the
    # event still counts and opens the gap.
    assert not ems.observe(13, cam["a"], 0.90)
    assert ems.state["events"] == 1 and ems.state["last"] == 13
    assert not ems.observe(18, cam["c"], 0.87)  # within min_gap of the last event: no event
    # The official loop never removes a candidate (its `selectviews` stays as picked), so the camera that made
    # the first event may make the second too.
    assert ems.state["candidates"] == ["a", "c"]
    assert ems.observe(19, cam["a"], 0.87)
    assert ems.state["events"] == 2 and not ems.listening(20)


def test_new_gaussians_start_as_the_official_code_adds_them():
    from stgc.model import STGModel
    from stgc.train.ems import new_gaussians

    rng = np.random.default_rng(0)
    cloud = SimpleNamespace(xyz=rng.normal(size=(200, 3)).astype(np.float32),
                            rgb=rng.uniform(size=(200, 3)).astype(np.float32),
                            time=rng.uniform(size=200).astype(np.float32))
    model = STGModel.from_points(cloud, variant="full")
    xyz = np.array([[0.0, 0, 0], [0.5, 0, 0], [0, 0.5, 0], [0, 0, 0.5]])  # 0.5 apart; the cloud is denser
    rgb = np.array([[0.9, 0.2, 0.1]] * 4)
    new = new_gaussians(model, xyz, rgb, 0.0, torch.Generator().manual_seed(0))
    # The colour and a zero specular feature (full variant).
    assert np.allclose(new["features_dc"].numpy(), [[0.9, 0.2, 0.1, 0.0, 0.0, 0.0]] * 4)
    # The scale is the 3-NN distance among the new and the existing points, computed independently here.
    everything = np.concatenate([xyz, cloud.xyz])
    squared = ((everything[:4, None, :] - everything[None, :, :]) ** 2).sum(-1)
    nearest = np.sort(squared, axis=1)[:, 1:4]
    expected = np.log(np.sqrt(nearest.mean(axis=1)))
    assert np.allclose(new["scaling"][:, 0].numpy(), expected, atol=1e-5)
    assert (new["scaling"][:, 0].numpy() < np.log(0.5)).all()  # closer than the new points' own spacing


def test_the_depth_it_reads_is_rendered_with_the_training_s_backend():
    """train.backend reaches the sampler's depth render, so that it rounds as the training renders do."""
    asked = []

    class Model:
        def render(self, camera, t=None, backend="auto", return_depth=False, **options):
            asked.append(backend)
            return SimpleNamespace(depth=torch.tensor([[0.0, 2.0], [3.0, 1.0]]))

    ems = ErrorGuidedSampler(EMSConfig(enabled=True), start=1, min_gap=1, train_names=["a"], trbf_scale_init=0.0,
                             backend="torch")
    assert ems.camera_depth(Model(), SimpleNamespace(name="a", time=0.5)) == 3.0
    assert asked == ["torch"]
