"""Renders of a synthetic model before and after the codec (through stgc.model and stgc.render)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from stgc.codec import DEFAULT_QUALITY, decode, encode
from stgc.codec.synthetic import synthetic_model
from stgc.data.cameras import Camera
from stgc.model import STGModel

from .helpers import psnr


def _cameras() -> list[Camera]:
    # Close enough that a pixel (2.5 cm at 6 units with f = 240) is about a typical Gaussian (3 cm): errors show.
    K = np.array([[240.0, 0.0, 48.0], [0.0, 240.0, 36.0], [0.0, 0.0, 1.0]])
    w2c = np.eye(4)
    w2c[2, 3] = 6.0
    return [Camera("front", 0, t, K, w2c, 96, 72) for t in (0.15, 0.8)]


def _render(arrays, variant, decoder) -> list[np.ndarray]:
    model = STGModel.from_ply_arrays(arrays, variant, decoder)
    with torch.no_grad():
        return [model.render(cam, backend="torch").rgb.clamp(0, 1).numpy() for cam in _cameras()]


@pytest.mark.parametrize("variant", ["full", "lite"])
def test_default_quality_renders_are_nearly_identical(variant):
    arrays, decoder = synthetic_model(3000, variant, seed=11)
    before = _render(arrays, variant, decoder)
    assert min(float(img.std()) for img in before) > 0.05  # the views see actual structure
    decoded = decode(encode(arrays, variant, decoder, DEFAULT_QUALITY))
    after = _render(decoded.arrays, variant, decoded.decoder_state)
    scores = [psnr(a, b) for a, b in zip(before, after)]
    assert min(scores) > 45.0, scores
    if variant == "lite":
        return
    # And the codec is not a no-op the renderer cannot see: the coarsest level costs visible quality.
    coarse = decode(encode(arrays, variant, decoder, 1))
    assert np.mean([psnr(a, b) for a, b in zip(before, _render(coarse.arrays, variant, coarse.decoder_state))]) < np.mean(scores)


def test_a_model_on_real_scene_geometry_renders_the_same_from_the_held_out_camera(blender_toys):
    """Positions, colours and scales from the blender_toys point cloud (as initialisation makes them), seen
    through the dataset's real test camera: the precision argument of docs/stgc-format.md on real geometry."""
    from stgc.data import initial_points, open_dataset

    dataset = open_dataset(blender_toys)
    cloud = initial_points(dataset, source="data", frames=[0, 15], max_points_per_frame=4000)
    model = STGModel.from_points(cloud, "lite", scene_extent=dataset.scene_extent())
    arrays = model.to_ply_arrays()
    rng = np.random.default_rng(0)  # trained opacities are bimodal, not the initial 0.1: make the splats visible
    n = len(arrays["x"])
    arrays["opacity"] = np.where(rng.random(n) < 0.6, rng.normal(3, 1.5, n), rng.normal(-2, 1.5, n)).astype(np.float32)
    camera = dataset.test[0]

    def render(a):
        with torch.no_grad():
            m = STGModel.from_ply_arrays(a, "lite", None)
            return m.render(camera, t=camera.time, backend="torch").rgb.clamp(0, 1).numpy()

    before = render(arrays)
    assert float(before.std()) > 0.05
    after = render(decode(encode(arrays, "lite", None)).arrays)
    assert psnr(before, after) > 50.0
